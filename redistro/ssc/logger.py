"""The SSC logger (paper priority 15): off the cycle, on its own timer
(``log.drain_hz``), it drains the cycles the manager captured into the log
ring since its last run, and from each cycle's plan of each robot keeps the
figures of each segment: its duration, the final pose error against the
goal, and on force segments the force error after the first contact (mean
and RMS). It also follows the peg's tip: how deep it went inside the hole.
At Cleanup (after a last drain) it writes them to ``ssc-segments.json`` in
the run folder (the manager puts them in its result).

It also records the session log (:mod:`redistro.log.recorder`): every cycle,
per robot the feedback, the command and the plan (references, TCP pose,
wrench in task axes), the SSC's timing, and segment changes as events.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from redistro.control.cartesian import pose_error, rotvec_to_matrix
from redistro.control.search import Phase
from redistro.localdata.block import Record
from redistro.localdata.layout import OPERATOR, PLAN
from redistro.log.recorder import CycleRecorder, log_topics, robots_meta
from redistro.process.worker import Worker
from redistro.ssc.ctl import Command, Status
from redistro.ssc.plan import segment_plans
from redistro.ssc.worker import AFTER

BOTTOM_M = 0.002  # within this of the hole's depth, the peg is at the bottom


@dataclass
class SegmentFigures:
    name: str
    robot: str
    scheme: str
    samples: int = 0
    duration_s: float = 0.0
    final: dict[str, Any] = field(default_factory=dict)
    contact_t_s: float | None = None
    force_n: int = 0
    force_sum: np.ndarray[Any, Any] = field(default_factory=lambda: np.zeros(3))
    force_sq: float = 0.0
    force_max: float = 0.0
    carry: bool = False  # a carry's hand: its squeeze, on the line between the hands
    squeeze_n: int = 0
    squeeze_sq: float = 0.0
    squeeze_peak: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "name": self.name,
            "robot": self.robot,
            "scheme": self.scheme,
            "duration_s": round(self.duration_s, 4),
            "final_pose_error": self.final or None,
        }
        if self.scheme == "force":
            if self.force_n:
                mean = self.force_sum / self.force_n
                out["first_contact_s"] = round(self.contact_t_s or 0.0, 4)
                out["force_mean_error_n"] = round(float(np.linalg.norm(mean)), 4)
                out["force_rms_error_n"] = round(float(np.sqrt(self.force_sq / self.force_n)), 4)
                out["force_max_error_n"] = round(self.force_max, 4)
                out["force_samples"] = self.force_n
            else:
                out["first_contact_s"] = None
                out["force_mean_error_n"] = None
                out["force_rms_error_n"] = None
        if self.carry and self.squeeze_n:
            out["squeeze_rms_error_n"] = round(math.sqrt(self.squeeze_sq / self.squeeze_n), 4)
            out["squeeze_peak_n"] = round(self.squeeze_peak, 4)
        return out


class SscLogger(Worker):
    op_taken = (0, 0)  # the operator's commands accepted and refused, logged so far ...
    op_effect = (0, 0)  # ... and the (command, status) the plans last said

    def initialize(self) -> None:
        cfg = self.spec.cfg()
        task = self.spec.task()
        self.plans = segment_plans(task, cfg)
        self.robots = list(self.spec.robots)
        # one per robot's move, in the segments' order; per robot and
        # segment (1-based) the index of its move's figures (-1: it holds)
        moves = [mv for p in self.plans for mv in p.moves]
        self.figures = [
            SegmentFigures(mv.name, mv.robot, mv.scheme, carry=mv.skill == "carry") for mv in moves
        ]
        self.fig_of = [[-1] * (len(self.plans) + 1) for _ in self.robots]
        j = 0
        for k, p in enumerate(self.plans, 1):
            for mv in p.moves:
                self.fig_of[self.robots.index(mv.robot)][k] = j
                j += 1
        # per move: the plan of its robot at the segment's last cycle
        self.last_plan = [Record(PLAN) for _ in moves]
        # the insertion: the first force move's robot, at its hole (the
        # fixture's, or an object's where the plan has it); the tool's tip
        # is in the hole below its mouth, within the hole's half side and
        # the widest search of the believed centre
        reach = max(
            (mv.search.max_radius_m for mv in moves if mv.search.pattern != "none"), default=0.0
        )
        first = next((mv for mv in moves if mv.scheme == "force"), None)
        h = cfg.workcell.hole
        self.hole = [*first.mouth_xy_m, first.mouth_z_m] if first else [float(v) for v in h.xyz_m]
        self.hole_depth = first.hole_depth_m if first else h.depth_m
        self.hole_half = (first.hole_half_m if first else 0.0) + reach
        self.phase = 0  # the search's last phase and path
        self.search_m = 0.0
        self.contact_t: float | None = None
        self.bottom_t: float | None = None
        self.peak_f2 = 0.0  # the peak contact force, squared [N^2]
        self.peg_index = self.robots.index(first.robot) if first else -1
        # the depth counts from the first force segment on (1-based): a peg
        # left in the hole by an earlier session is pulled out by the approach
        forces = [
            k for k, p in enumerate(self.plans, 1) if any(mv.scheme == "force" for mv in p.moves)
        ]
        self.depth_from = forces[0] if forces else AFTER
        self.depth = 0.0
        self.depth_t: float | None = None
        run_dir = self.spec.node_params.run_dir
        self.out_path = os.path.join(run_dir, "ssc-segments.json") if run_dir else ""
        self.cycles = 0
        self.arms_min = (math.inf, 0.0)  # the two arms' nearest as the watch measured, and when
        self.cell_min = math.inf
        self.recorder: CycleRecorder | None = None
        self.segment = [0] * len(self.robots)
        self.recs: list[Record] = []
        if run_dir:
            meta = robots_meta(cfg, self.robots)
            meta["task"] = task.task
            meta["hole_xyz_m"] = self.hole  # believed: workcell.hole
            meta["segments"] = [
                {
                    "name": p.name,
                    "robots": p.robots,
                    "schemes": [mv.scheme for mv in p.moves],
                    "duration_s": p.duration_s,
                }
                for p in self.plans
            ]
            topics = log_topics(self.spec)  # the manager captures the same
            self.recorder = CycleRecorder(self.ld, self.spec, topics, run_dir, meta)
            plan_topics = [k for k, (_t, name, _i) in enumerate(topics) if name == "plan"]
            # the recorded cycle's plans, in place in the frame
            self.recs = [self.recorder.view(k, PLAN) for k in plan_topics]
            self.recorder.start()
        else:  # no session log: the plans straight from Local Data
            self.blocks = [self.ld.block("plan", i) for i in range(len(self.robots))]
            self.recs = [Record(PLAN) for _ in self.robots]
        self.tcp = [rec.array["tcp_xyz_m"] for rec in self.recs]
        self.wrench_task = [rec.array["wrench_task"] for rec in self.recs]
        self.wrench_goal = [rec.array["wrench_goal"] for rec in self.recs]
        self.sel3 = [mv.selection[:3].tolist() for mv in moves]
        self.op_block, self.op = self.ld.block("operator"), Record(OPERATOR)  # (the operator's)

    def step(self, cycle: int) -> None:
        if self.recorder is not None:
            self.recorder.drain(self._cycle)
            self._operator()
            return
        for block, rec in zip(self.blocks, self.recs, strict=True):
            block.read_into(rec.bytes)
        self._cycle(cycle)

    def _operator(self) -> None:
        """The operator's commands the manager took or refused, as events."""
        self.op_block.read_into(self.op.bytes)
        op, rec = self.op, self.recorder
        seq, refused = int(op["seq"]), int(op["refused"])
        if (seq, refused) == self.op_taken or rec is None:
            return
        if seq != self.op_taken[0]:
            step = [round(float(v), 6) for v in op.array["step"]]
            rec.event("operator", int(op["cycle"]), event="command", seq=seq,
                      command=Command(int(op["command"])).name.lower(),
                      robot=self.robots[int(op["robot"])] if int(op["robot"]) < len(self.robots)
                      else "", step=step)  # fmt: skip
        if refused != self.op_taken[1]:
            why = op.array["refused_why"].item().decode(errors="replace")
            rec.event("operator", int(op["cycle"]), event="refused", refused=refused, why=why)
        self.op_taken = (seq, refused)

    def _effect(self, cycle: int, pl: Record) -> None:
        """A command's effect, as the worker wrote it in the plans."""
        key = (int(pl["op_seq"]), int(pl["op_status"]))
        if key == self.op_effect or not key[0] or self.recorder is None:
            return
        self.op_effect = key
        self.recorder.event("operator", cycle, event="effect", seq=key[0],
                            command=Command(int(pl["op_command"])).name.lower(),
                            status=Status(key[1]).name.lower(), paused=bool(pl["paused"]),
                            t_s=round(float(pl["t_s"]), 4))  # fmt: skip

    def _cycle(self, cycle: int) -> None:
        """One cycle's plans: segment events, the segments' figures, the depth."""
        self.cycles += 1
        rec = self.recs[0] if self.recs else None
        if rec is not None and rec["op_seq"]:
            self._effect(cycle, rec)
        if rec is not None and rec["stamp_ns"]:  # (the watch's, in every robot's plan)
            arms, cell = float(rec["arms_clearance_m"]), float(rec["cell_clearance_m"])
            if arms < self.arms_min[0]:
                self.arms_min = (arms, float(rec["t_s"]))
            self.cell_min = min(self.cell_min, cell)
        for i, rec in enumerate(self.recs):
            k = rec["segment"]
            moving = rec["moving"]
            if k != self.segment[i] and (moving or k in (0, AFTER)):
                self.segment[i] = k
                if self.recorder is not None:
                    name = self.plans[k - 1].name if 1 <= k <= len(self.plans) else ""
                    self.recorder.event(
                        "segments",
                        cycle,
                        robot=self.robots[i],
                        segment=k,
                        name=name,
                        t_s=round(float(rec["t_s"]), 4),
                        done=bool(rec["done"]),
                    )
            if i == self.peg_index and self.depth_from <= k != 0:
                x, y, z = self.tcp[i].tolist()
                hx, hy, hz = self.hole
                d = hz - z
                if d > self.depth and max(abs(x - hx), abs(y - hy)) <= self.hole_half + 1e-4:
                    self.depth = d
                    self.depth_t = float(rec["t_s"])
                    if self.bottom_t is None and d >= self.hole_depth - BOTTOM_M:
                        self.bottom_t = self.depth_t
                if rec["contact"]:
                    if self.contact_t is None:
                        self.contact_t = float(rec["t_s"])
                    w = self.wrench_task[i]
                    f2 = float(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
                    if f2 > self.peak_f2:
                        self.peak_f2 = f2
                phase = rec["phase"]
                if phase:  # (the goal's offset is read once, at the end)
                    self.phase = phase
                    self.search_m = rec["search_m"]
            if not moving or k in (0, AFTER) or k > len(self.plans):
                continue
            j = self.fig_of[i][k]
            if j < 0:
                continue
            fig = self.figures[j]
            fig.samples += 1
            fig.duration_s = rec["segment_t_s"]
            self.last_plan[j].bytes[:] = rec.bytes  # (a numpy record's copy: 4 us)
            if fig.carry:
                _squeeze(fig, self.wrench_goal[i].tolist(), self.wrench_task[i].tolist())
            if fig.scheme == "force" and rec["contact"]:
                if fig.contact_t_s is None:
                    fig.contact_t_s = fig.duration_s
                w = self.wrench_task[i].tolist()
                g, s = self.wrench_goal[i].tolist(), self.sel3[j]
                e0, e1, e2 = (g[0] - w[0]) * s[0], (g[1] - w[1]) * s[1], (g[2] - w[2]) * s[2]
                fig.force_n += 1
                fig.force_sum += (e0, e1, e2)
                n2 = e0 * e0 + e1 * e1 + e2 * e2
                fig.force_sq += n2
                fig.force_max = max(fig.force_max, math.sqrt(n2))

    def _final_errors(self) -> None:
        """Each segment's final pose error, from its last plan (the goal pose of
        a joint segment is the TCP pose at the joint goal)."""
        for fig, last in zip(self.figures, self.last_plan, strict=True):
            if not fig.samples:
                continue
            pl = last.array
            e = pose_error(
                pl["tcp_xyz_m"],
                rotvec_to_matrix(pl["tcp_rot_xyz"]),
                pl["goal_xyz_m"],
                rotvec_to_matrix(pl["goal_rot_xyz"]),
            )
            fig.final = {
                "position_m": round(float(np.linalg.norm(e[:3])), 6),
                "orientation_rad": round(float(np.linalg.norm(e[3:])), 6),
                "position_xyz_m": [round(float(v), 6) for v in e[:3]],
                "orientation_xyz_rad": [round(float(v), 6) for v in e[3:]],
            }

    def _search_figures(self) -> dict[str, Any]:
        """The peg's way into the hole: the search's last phase, path and
        goal offset, the first contact, the bottom (within 2 mm of the
        hole's depth), the peak contact force."""
        phase = int(self.phase)
        offset = [0.0, 0.0]
        if phase and self.peg_index >= 0:
            with contextlib.suppress(Exception):  # the worker's last plan
                last = self.ld.block("plan", self.peg_index).read()
                offset = [round(float(v), 6) for v in last["search_xy_m"]]
        # a peg that meets nothing before the bottom touches first there
        touched = [t for t in (self.contact_t, self.bottom_t) if t is not None]
        contact = min(touched) if touched else None
        return {
            "phase": Phase(phase).name.lower() if phase else "none",
            "search_m": round(float(self.search_m), 6),
            "offset_xy_m": offset,
            "contact_t_s": contact,
            "bottom_t_s": self.bottom_t,
            "contact_to_bottom_s": (
                round(self.bottom_t - contact, 4)
                if self.bottom_t is not None and contact is not None
                else None
            ),
            "peak_force_n": round(math.sqrt(self.peak_f2), 3),
        }

    def cleanup(self) -> None:
        if self.recorder is not None:
            self.recorder.close(self._cycle)  # (the cycles since the last drain first)
        if not self.out_path:
            return
        self._final_errors()
        doc = {
            "cycles": self.cycles,
            "segments": [f.as_dict() for f in self.figures],
            "insertion_depth_m": round(self.depth, 6),
            "insertion_depth_t_s": self.depth_t,
            "hole_depth_m": self.hole_depth,
            "search": self._search_figures(),
            "clearance": {
                "arms_min_m": _finite(self.arms_min[0]),
                "arms_min_t_s": round(self.arms_min[1], 4)
                if math.isfinite(self.arms_min[0])
                else None,
                "cell_min_m": _finite(self.cell_min),
            },
        }
        from redistro import files

        files.replace(self.out_path, json.dumps(doc, indent=1))


def _squeeze(fig: SegmentFigures, g: list[float], w: list[float]) -> None:
    """A carry's hand: the squeeze it applies along its goal's line (the
    plan's wrench_goal: the squeeze times the line inward) against the goal."""
    goal = math.sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2])
    if goal <= 0:
        return
    f = (w[0] * g[0] + w[1] * g[1] + w[2] * g[2]) / goal
    fig.squeeze_n += 1
    fig.squeeze_sq += (goal - f) ** 2
    fig.squeeze_peak = max(fig.squeeze_peak, f)


def _finite(v: float) -> float | None:
    return round(v, 5) if math.isfinite(v) else None
