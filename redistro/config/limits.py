"""Joint limits and the hardware's ratings: the bounds the safety config lives in.

- **Joint position limits** come from the arm's model (the URDF's ``<limit
  lower upper>`` of each joint). ``esc.safety.q_min_rad`` / ``q_max_rad`` may
  narrow them, never widen them. The guard keeps ``q_margin_rad`` inside them,
  and a joint whose stopping point at ``decel_rad_s2`` (q + qd|qd| / 2a) lies
  beyond that is a fault while it can still stop.
- **Ratings** bound every safety limit from above: a joint torque limit is at
  most the amplifier's current limit x the motor's torque constant x the gear
  (sensor/actuator config), a joint speed limit at most the model's velocity
  limit, the wrist force and moment limits at most the force sensor's range
  (its 24-bit gauge counts through the calibration matrix's diagonal).

All of this is checked when the hardware files are loaded (``load_hardware``),
so a bad value is refused before anything starts, naming the rating.
"""

from __future__ import annotations

import functools
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from redistro.errors import ConfigError

if TYPE_CHECKING:
    from redistro.config.hardware import RobotHardware
    from redistro.config.model import Config

DOF = 7


@dataclass(frozen=True)
class ModelLimits:
    """Per joint, from the arm's URDF: position [rad], velocity [rad/s], effort [N m]."""

    lower: tuple[float, ...]
    upper: tuple[float, ...]
    velocity: tuple[float, ...]
    effort: tuple[float, ...]


@functools.lru_cache(maxsize=1)
def model_limits() -> ModelLimits:
    from redistro.robotmodel import JOINT_NAMES, arm_urdf

    root = ET.fromstring(arm_urdf(None))
    by_name = {j.get("name"): j for j in root.iter("joint")}
    lo, hi, vel, eff = [], [], [], []
    for name in JOINT_NAMES:
        lim = by_name[name].find("limit")
        assert lim is not None, f"the arm model's joint {name} has no limit"
        lo.append(float(lim.get("lower", "nan")))
        hi.append(float(lim.get("upper", "nan")))
        vel.append(float(lim.get("velocity", "inf")))
        eff.append(float(lim.get("effort", "inf")))
    return ModelLimits(tuple(lo), tuple(hi), tuple(vel), tuple(eff))


@dataclass(frozen=True)
class JointLimits:
    """The limits the guard and the load checks use, for every robot (one arm model).

    lower/upper: the hard limits (model, narrowed by config) [rad];
    margin: kept inside them [rad]; decel: the braking deceleration [rad/s^2]."""

    lower: np.ndarray
    upper: np.ndarray
    margin: float
    decel: np.ndarray

    @property
    def inner_lower(self) -> np.ndarray:
        return self.lower + self.margin

    @property
    def inner_upper(self) -> np.ndarray:
        return self.upper - self.margin

    def outside(self, q: np.ndarray | list[float], margin: bool = True, slack: float = 0.0) -> str:
        """'' when every joint of q is inside the limits (less the margin, or
        the hard limits with ``margin`` false, widened by ``slack``), else
        which joint is not."""
        q = np.asarray(q, dtype=np.float64)
        lower, upper = (self.inner_lower, self.inner_upper) if margin else (self.lower, self.upper)
        lower, upper = lower - slack, upper + slack
        note = f" (joint limits less {self.margin:g} rad margin)" if margin else ""
        if slack:
            note = f" (joint limits and {slack:g} rad beyond: as far as a joint can be pushed)"
        for j in range(DOF):
            lo, hi = float(lower[j]), float(upper[j])
            if not lo <= float(q[j]) <= hi:
                return (
                    f"joint {j + 1} at {float(q[j]):.4g} rad is outside its limits "
                    f"[{lo:.4g}, {hi:.4g}] rad{note}"
                )
        return ""


def joint_limits(cfg: Config) -> JointLimits:
    """The configured limits, checked against the model's (ConfigError naming the field)."""
    s = cfg.esc.safety
    m = model_limits()
    lower = np.array(m.lower, dtype=np.float64)
    upper = np.array(m.upper, dtype=np.float64)
    for key, given, model, narrower in (
        ("q_min_rad", s.q_min_rad, lower, np.greater_equal),
        ("q_max_rad", s.q_max_rad, upper, np.less_equal),
    ):
        if not given:
            continue
        for j, v in enumerate(given):
            if not narrower(v, model[j]):
                raise ConfigError(
                    f"{cfg.origin('esc.safety.' + key)}: esc.safety.{key}[{j}]: {v:g} rad is "
                    f"wider than the arm model's limit {model[j]:.4g} rad "
                    "(limits may be narrowed, not widened)"
                )
        model[...] = given
    for j in range(DOF):
        if upper[j] - lower[j] <= 2 * s.q_margin_rad:
            raise ConfigError(
                f"{cfg.origin('esc.safety.q_margin_rad')}: esc.safety.q_margin_rad: "
                f"{s.q_margin_rad:g} rad leaves joint {j + 1} no room between its limits "
                f"[{lower[j]:.4g}, {upper[j]:.4g}] rad"
            )
    return JointLimits(lower, upper, s.q_margin_rad, np.asarray(s.decel_rad_s2, dtype=np.float64))


def torque_rating(hw: RobotHardware) -> np.ndarray:
    """Per joint, the most torque the drive can give [N m, joint side]."""
    s = hw.sensors
    rating: np.ndarray = (
        np.asarray(s.max_current_a)
        * np.asarray(s.torque_constant_nm_a)
        * np.asarray(s.gear_ratio, dtype=np.float64)
    )
    return rating


def wrench_range(hw: RobotHardware) -> tuple[float, float]:
    """The wrist sensor's range: (force [N], moment [N m]), the smallest axis of each."""
    from redistro.drivers.io.registers import FT_STRAIN_MAX

    c = np.abs(np.diag(np.asarray(hw.sensors.ft_calibration, dtype=np.float64)))
    full = c * FT_STRAIN_MAX
    return float(full[:3].min()), float(full[3:].min())


def check_ratings(cfg: Config, hardware: dict[str, RobotHardware]) -> None:
    """Every limit of esc.safety within the model's and each robot's ratings."""
    s = cfg.esc.safety
    m = model_limits()
    for j, v in enumerate(s.qd_max_rad_s):
        if v > m.velocity[j]:
            raise ConfigError(
                f"{cfg.origin('esc.safety.qd_max_rad_s')}: esc.safety.qd_max_rad_s[{j}]: "
                f"{v:g} rad/s is over joint {j + 1}'s rated speed {m.velocity[j]:g} rad/s "
                "(the arm model's velocity limit)"
            )
    for name, hw in hardware.items():
        rating = torque_rating(hw)
        for j, v in enumerate(s.tau_max_nm):
            if v > rating[j]:
                raise ConfigError(
                    f"{cfg.origin('esc.safety.tau_max_nm')}: esc.safety.tau_max_nm[{j}]: "
                    f"{v:g} N m is over {name}'s joint {j + 1} rating {rating[j]:g} N m "
                    f"(max_current_a x torque_constant_nm_a x gear_ratio in {hw.sensors_path})"
                )
        if hw.wrist is None:
            continue
        f_range, m_range = wrench_range(hw)
        for key, v, rng, unit in (
            ("force_max_n", s.force_max_n, f_range, "N"),
            ("moment_max_nm", s.moment_max_nm, m_range, "N m"),
        ):
            if v > rng:
                raise ConfigError(
                    f"{cfg.origin('esc.safety.' + key)}: esc.safety.{key}: {v:g} {unit} is "
                    f"over {name}'s wrist sensor range {rng:.4g} {unit} "
                    f"(ft_calibration in {hw.sensors_path})"
                )
    joint_limits(cfg)


QUINTIC_PEAK = 1.875  # a quintic's peak speed over its mean speed (15/8)
# how far past its limit a joint can be found (pushed there with its brakes
# on, the arm moved while powered off): a recorded position that far out is
# still a position (the guard lets it move back); further out, it cannot be right
RECOVERY_BAND_RAD = 0.35


def task_motion_problems(
    cfg: Config,
    task: Any,
    start_q: dict[str, list[float]] | None = None,
    cartesian_q: dict[tuple[int, str], np.ndarray] | None = None,
) -> list[str]:
    """One line per joint goal outside the limits (less the margin), per
    joint move whose distance over its move time is above ``qd_max_rad_s``
    (the quintic's peak, 15/8 of that, is the guard's to judge at run time:
    a task may run close to the limit on purpose), and per goal wrench the
    guard would refuse (above ``force_max_n`` or ``moment_max_nm``, which
    the wrist sensor's range bounds). A move's start is the previous joint
    goal of its robot; after a Cartesian segment, the posture its goal puts
    the arm in (``cartesian_q``, by segment index and robot: the inverse
    kinematics of the load check); for the first, the robot's position in ``start_q``
    (unknown: the speed of that move is left to the guard)."""
    limits = joint_limits(cfg)
    qd_max = np.asarray(cfg.esc.safety.qd_max_rad_s, dtype=np.float64)
    where = task.source or "task"
    out: list[str] = []
    prev: dict[str, np.ndarray | None] = {
        r: (np.asarray(q, dtype=np.float64) if q is not None else None)
        for r, q in (start_q or {}).items()
    }

    def goal(robot: str, q: list[float], move_s: float, at: str) -> None:
        qv = np.asarray(q, dtype=np.float64)
        problem = limits.outside(qv)
        if problem:
            out.append(f"{where}: {at}: {problem}")
        start = prev.get(robot)
        if start is not None and move_s > 0:
            mean = np.abs(qv - start) / move_s
            j = int(np.argmax(mean / qd_max))
            if mean[j] > qd_max[j]:
                out.append(
                    f"{where}: {at}: joint {j + 1} would move {abs(qv[j] - start[j]):.3g} rad "
                    f"in {move_s:g} s, {mean[j]:.3g} rad/s on average, over "
                    f"esc.safety.qd_max_rad_s {qd_max[j]:g} (give it at least "
                    f"{abs(qv[j] - start[j]) / qd_max[j]:.3g} s; the quintic's peak is "
                    f"{QUINTIC_PEAK:g} times the average)"
                )
        prev[robot] = qv

    for r, q in task.calibration.final_q_rad.items():
        problem = limits.outside(q)
        if problem:
            out.append(f"{where}: calibration.final_q_rad.{r}: {problem}")
    if task.kind == "joint_move":
        for i, seg in enumerate(task.segments):
            for r, q in seg.q_rad.items():
                goal(r, q, seg.duration_s, f"segments[{i}].q_rad.{r}")
    elif task.kind == "strategy":
        from redistro.config.skills import skill_of
        from redistro.config.task import move_s, segment_moves

        for i, seg in enumerate(task.segments):
            for m in segment_moves(seg, i):
                if skill_of(m).name == "hold":
                    continue
                if m.scheme == "joint":
                    goal(m.robot, m.goal.q_rad, move_s(seg, m), f"{m.where}.goal.q_rad")
                    continue
                # a Cartesian move ends where its inverse kinematics says
                prev[m.robot] = (cartesian_q or {}).get((i, m.robot))
                out.extend(_wrench_problems(m, cfg.esc.safety, where))
    return out


def _wrench_problems(m: Any, s: Any, where: str) -> list[str]:
    """A move's goal wrench the guard would refuse (``esc.safety`` s)."""
    out = []
    w = np.asarray(m.goal.force_xyz_torque_xyz, dtype=np.float64)
    sel = np.asarray(m.goal.selection_vector, dtype=np.float64)
    f = float(np.linalg.norm(w[:3] * sel[:3]))
    mo = float(np.linalg.norm(w[3:] * sel[3:]))
    for what, value, limit, key, unit in (
        ("force", f, s.force_max_n, "force_max_n", "N"),
        ("moment", mo, s.moment_max_nm, "moment_max_nm", "N m"),
    ):
        if value > limit:
            out.append(
                f"{where}: {m.where}.goal.force_xyz_torque_xyz: a goal {what} of "
                f"{value:.4g} {unit}, over esc.safety.{key} {limit:g} {unit} (the "
                "guard would stop it; the wrist sensor's range bounds that limit)"
            )
    return out
