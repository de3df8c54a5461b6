"""The SSC Manager: the strategy node's timer and watchdog.

It has no hardware: its safety duties are the e-stop (set on any fault; its
ddm carries it to every ESC) and the freshness of the robots' feedback:
a robot whose feedback stops coming for ``ddm.starving_limit_cycles`` SSC
cycles (or never comes within ``ddm.connect_timeout_s``) ends the session
``starving``. It ends the session ``ok`` once the worker's plan is done and
the finished status has gone out for a few cycles.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import time
from pathlib import Path
from typing import Any

from redistro.ddm.exchange import exchange_report
from redistro.errors import NodeFault
from redistro.localdata.block import Block, Record
from redistro.localdata.layout import EXCHANGE, PLAN
from redistro.process.manager import Manager
from redistro.process.result import SscResult
from redistro.process.spec import NodeSpec
from redistro.ssc.ctl import Command, Desk, Receiver

FINISH_CYCLES = 20  # cycles the finished status goes out before the node ends


class SscManager(Manager):
    def __init__(self, spec: NodeSpec, spec_path: str) -> None:
        super().__init__(spec, spec_path)
        self.plan_blocks: list[Block] = []
        self.ex_blocks: list[Block] = []

    def initialize(self) -> None:
        cfg = self.spec.cfg()
        self.limit = cfg.ddm.starving_limit_cycles
        self.wait_first_s = cfg.ddm.connect_timeout_s
        self.run_dir = self.spec.node_params.run_dir
        ld = self.ld
        assert ld is not None
        n = len(self.spec.robots)
        self.plan_blocks = [ld.block("plan", i) for i in range(n)]
        self.ex_blocks = [ld.block("exchange", i) for i in range(n)]
        self.plans = [Record(PLAN) for _ in range(n)]
        self.exs = [Record(EXCHANGE) for _ in range(n)]
        self.last_updates = [0] * n
        self.last_change = [0] * n
        self.done_cycles = 0
        self.starving_max = 0
        self.desk = _desk(self, cfg, n)
        self._message(
            "manager", logging.INFO, f"waiting for feedback from {', '.join(self.spec.robots)}"
        )

    def idle(self, deadline_ns: int) -> bool:
        if self.desk is not None:
            self.desk.idle(self.cycle)  # (one operator datagram a cycle at most)
        return False

    def on_tick(self, cycle: int) -> bool:
        desk = self.desk
        if desk is not None and desk.act != Command.NONE:
            self._operator(desk)
        for i, robot in enumerate(self.spec.robots):
            self.ex_blocks[i].read_into(self.exs[i].bytes)
            updates = int(self.exs[i]["updates"])
            if updates != self.last_updates[i]:
                self.last_updates[i] = updates
                self.last_change[i] = cycle
                continue
            if updates == 0:
                if cycle > self.wait_first_s * self.spec.rate_hz:
                    raise NodeFault(
                        "starving", f"no feedback from {robot} within {self.wait_first_s} s"
                    )
                continue
            age = cycle - self.last_change[i]
            self.starving_max = max(self.starving_max, age)
            if age > self.limit:
                raise NodeFault(
                    "starving",
                    f"no fresh feedback from {robot} for {age} cycles "
                    f"(limit {self.limit}) at cycle {cycle}",
                )
        for block, rec in zip(self.plan_blocks, self.plans, strict=True):
            block.read_into(rec.bytes)
        if desk is not None and desk.owed is not None:
            desk.answer(self.plans[0])
        if all(int(rec["done"]) for rec in self.plans):
            self.done_cycles += 1
        if self.done_cycles <= FINISH_CYCLES:
            return False
        if any(int(rec["failed"]) for rec in self.plans):
            # the task could not be done, and ends cleanly: every robot held
            # its pose and the ESCs were told the session finished (no e-stop)
            self._drain_messages()
            r = self.result
            r.result = "failed"
            errors = self.last_error  # (the worker's; in a parallel SSC, an arm's)
            arms = [v for k, v in errors.items() if k.startswith("arm.")]
            r.reason = errors.get("worker") or next(iter(arms), "the task could not be done")
            r.fault_monotonic_ns, r.fault_cycle = time.monotonic_ns(), cycle
        return True

    def _operator(self, desk: Desk) -> None:
        """An operator's stop (as Ctrl-C: the session owner ends every node
        in order) or e-stop (the group's, from this node)."""
        act, desk.act = desk.act, Command.NONE
        if act == Command.ESTOP:
            raise NodeFault("estop", "the operator's e-stop (redistro ctl)")
        with contextlib.suppress(ProcessLookupError):
            os.kill(os.getppid(), signal.SIGINT)  # (the owner: it started this manager)

    def cleanup(self) -> None:
        ssc = self.result.ssc = SscResult(robots=list(self.spec.robots))
        if self.desk is not None:
            ssc.operator = {"accepted": self.desk.accepted, "refused": self.desk.refused}
            self.desk.close()
        if self.ex_blocks:
            ssc.ddm = {
                r: exchange_report(b.read())
                for r, b in zip(self.spec.robots, self.ex_blocks, strict=True)
            }
            ssc.starving_cycles_max = self.starving_max
        if self.run_dir:
            path = Path(self.run_dir) / "ssc-segments.json"
            try:
                doc = json.loads(path.read_text())
                ssc.segments = list(doc["segments"])
                ssc.insertion_depth_m = float(doc["insertion_depth_m"])
                ssc.insertion_depth_t_s = doc.get("insertion_depth_t_s")
                ssc.hole_depth_m = float(doc["hole_depth_m"])
                ssc.search = dict(doc.get("search") or {})
                ssc.clearance = dict(doc.get("clearance") or {})
            except (OSError, ValueError, KeyError, TypeError) as exc:
                self._message("manager", logging.WARNING, f"segment figures unreadable: {exc}")


def _desk(m: SscManager, cfg: Any, n: int) -> Desk | None:
    """The operator's desk (``ssc/ctl.py``): its socket in the session's
    runtime folder, its commands checked with the link's key."""
    from redistro.ddm import record as wire
    from redistro.ipc.session import Manifest

    directory = Manifest.for_session(m.spec.session_id).directory
    key_path = cfg.ddm.key_file or str(directory / wire.SESSION_KEY)
    try:
        key = wire.load_key(key_path)
        rx = Receiver(directory, key, m.spec.session_id)
    except (OSError, ValueError) as exc:
        m._message("manager", logging.WARNING, f"no operator commands: {exc}")
        return None
    ld = m.ld
    assert ld is not None
    block = ld.writer("operator", role="manager")

    def say(text: str, warning: bool = False) -> None:
        m._message("manager", logging.WARNING if warning else logging.INFO, text)

    return Desk(rx, block, list(m.spec.robots)[:n], say, not cfg.ssc.parallel_arms)
