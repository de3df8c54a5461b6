"""Per-cycle timing samples kept in a fixed ring (no allocation in Routine)."""

from __future__ import annotations

import numpy as np

RING = 1 << 20  # about 17 minutes of cycles at 1 kHz


class Samples:
    def __init__(self, size: int = RING) -> None:
        self._buf = np.zeros(size, dtype=np.int64)
        self.count = 0

    def add(self, value_ns: int) -> None:
        self._buf[self.count % self._buf.shape[0]] = value_ns
        self.count += 1

    def values_ns(self) -> np.ndarray:
        return self._buf[: min(self.count, self._buf.shape[0])]

    def summary_us(self) -> dict[str, float]:
        """{p50, p99, max} in microseconds (zeros when empty)."""
        v = self.values_ns()
        if v.size == 0:
            return {"p50": 0.0, "p99": 0.0, "max": 0.0}
        # linear interpolation between order statistics found by partition:
        # O(n), and no lazy import of numpy.ma (np.percentile's) at the end
        # of a session, on a fault
        n = v.size
        ranks = [(n - 1) * q for q in (0.5, 0.99)]
        kth = sorted({int(r) for r in ranks} | {min(n - 1, int(r) + 1) for r in ranks})
        part = np.partition(v, kth)
        p50, p99 = (
            part[int(r)] + (part[min(n - 1, int(r) + 1)] - part[int(r)]) * (r - int(r))
            for r in ranks
        )
        return {
            "p50": round(float(p50) / 1e3, 1),
            "p99": round(float(p99) / 1e3, 1),
            "max": round(float(v.max()) / 1e3, 1),
        }
