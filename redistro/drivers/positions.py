"""The positions file: final joint positions, kept between sessions.

Written at the end of a session (temporary file, fsync, rename, fsync of the
folder), read at the next start to preset the encoder counters. The file is
JSON: format version, session id, time, per robot the joint angles [rad], a
clean-shutdown mark, and a SHA-256 checksum of the rest. A missing, corrupt
or unclean file means the arm's configuration is unknown: :func:`read`
raises :class:`PositionsUnknown` saying why; motion then needs a
self-calibration, or an explicit override.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from redistro.errors import RedistroError

FORMAT = 1


class PositionsUnknown(RedistroError):
    """The positions file cannot be trusted; ``reason`` is missing, corrupt or unclean."""

    def __init__(self, path: Path, reason: str, detail: str) -> None:
        super().__init__(f"{path}: positions unknown ({reason}): {detail}")
        self.reason = reason


@dataclass(frozen=True)
class Positions:
    session: str
    written: float  # UNIX time
    clean: bool
    q_rad: dict[str, list[float]]


def _digest(body: dict[str, Any]) -> str:
    text = json.dumps(body, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def write(path: Path | str, session: str, q_rad: dict[str, Any], clean: bool) -> None:
    """Write atomically: a reader sees the old file or the new one, never a mix."""
    path = Path(path)
    body = {
        "format": FORMAT,
        "session": session,
        "written": time.time(),
        "clean": bool(clean),
        "q_rad": {r: [float(v) for v in q] for r, q in q_rad.items()},
    }
    doc = {**body, "sha256": _digest(body)}
    path.parent.mkdir(parents=True, exist_ok=True)
    from redistro import files

    tmp = files.temp_name(path)
    with files.open_new(tmp) as f:
        json.dump(doc, f, indent=2)
        f.write("\n")
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def read(path: Path | str, robots: list[str] | None = None) -> Positions:
    """The recorded positions, or PositionsUnknown (missing, corrupt, unclean)."""
    from redistro.config.inputs import load_json, read_text
    from redistro.errors import ConfigError

    path = Path(path)
    if not path.exists() and not path.is_symlink():
        raise PositionsUnknown(path, "missing", "no positions file")
    try:
        text = read_text(path, "positions file", limit=64 * 1024)
    except ConfigError as exc:
        detail = str(exc).split(": ", 1)[-1]
        raise PositionsUnknown(path, "corrupt", detail) from None
    try:
        doc = load_json(text)
        if not isinstance(doc, dict):
            raise ValueError("not a JSON object")
        digest = doc.pop("sha256")
        if digest != _digest(doc):
            raise ValueError("checksum does not match")
        if doc.get("format") != FORMAT:
            raise ValueError(f"format {doc.get('format')!r}, expected {FORMAT}")
        q = doc["q_rad"]
        if not isinstance(q, dict):
            raise ValueError("q_rad is not a mapping")
        for r, values in q.items():
            if not (
                isinstance(values, list)
                and len(values) == 7
                and all(isinstance(v, int | float) and math.isfinite(v) for v in values)
            ):
                raise ValueError(f"q_rad.{r}: expected 7 finite numbers")
        pos = Positions(str(doc["session"]), float(doc["written"]), bool(doc["clean"]), q)
    except (ValueError, KeyError, TypeError) as exc:
        raise PositionsUnknown(path, "corrupt", str(exc)) from None
    if not pos.clean:
        raise PositionsUnknown(path, "unclean", f"session {pos.session} did not shut down cleanly")
    for r in robots or []:
        if r not in pos.q_rad:
            raise PositionsUnknown(path, "corrupt", f"no positions for robot {r}")
    return pos
