"""The skills a strategy segment's move is made of: each a motion generator
and a terminal condition (MRROC++'s Move instruction), stated here once.

A move names its skill (``skill``); without one it is the skill its scheme
has always meant (``joint``/``position``: move; ``force``: push, or
search_insert with a search). The task loader checks a move against its
skill (:func:`check_skill`); the SSC runs it (``ssc/worker.py``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from redistro.errors import ConfigError

if TYPE_CHECKING:
    from redistro.config.task import Move


@dataclass(frozen=True)
class Skill:
    name: str
    schemes: tuple[str, ...]  # the control schemes it runs under
    goal: str  # what its goal gives
    ends: str  # its terminal condition (besides the segment's duration_s)
    search: bool = False  # a spiral search for the hole
    contact: bool = False  # it ends at the first contact (end.contact_n)
    gripper: str = ""  # "close" or "open": the flange's gripper, as the move ends
    carry: bool = False  # the goal comes from the segment's carry (the held object's motion)


SKILLS: dict[str, Skill] = {
    s.name: s
    for s in (
        Skill(
            "move", ("joint", "position"), "a joint goal (joint) or a TCP pose (position)",
            "once end's pose tolerances have held for end.hold_s",
        ),
        Skill(
            "guarded_move", ("position",), "a TCP pose beyond the surface it should meet",
            "at the first contact: the wrist's force over end.contact_n; it holds there",
            contact=True,
        ),
        Skill(
            "push", ("force",), "a pose and a wrench on the force axes",
            "once end's force tolerance has held for end.hold_s",
        ),
        Skill(
            "search_insert", ("force",), "the hole's pose and a wrench pushing down world z",
            "in the hole, once end's force tolerance has held (a hole not found: failed)",
            search=True,
        ),
        Skill(
            "grasp", ("joint", "position"), "the grasp pose: the tool point on the object's top "
            "face (goal.relative_to: the object)",
            "as move; the gripper closes as the segment ends, and stays closed", gripper="close",
        ),
        Skill(
            "release", ("joint", "position"), "a joint goal or a TCP pose (where it lets go)",
            "as move; the gripper opens as the segment ends", gripper="open",
        ),
        Skill(
            "carry", ("position",), "none: the segment's carry moves the object both hands "
            "hold, and the squeeze between them",
            "with the segment", carry=True,
        ),
        Skill("hold", (), "nothing: the robot holds its pose", "with the segment"),
    )
}  # fmt: skip


# a move's rotational stiffness at most [N m/rad]
ROT_STIFFNESS_MAX = 100.0


def skill_of(m: Move) -> Skill:
    """The move's skill: named, or the one its scheme has always meant."""
    if m.skill:
        return SKILLS[m.skill]
    if m.scheme == "force":
        return SKILLS["search_insert" if m.search.pattern != "none" else "push"]
    return SKILLS["move"]


def check_skill(m: Move, at: str) -> Skill:
    """The move against its skill (else a ConfigError naming the field)."""
    s = skill_of(m)
    if s.name == "hold":
        if m.goal.q_rad or m.goal.pos_xyz_rot_xyz or m.goal.stiffness_xyz_rot_xyz:
            raise ConfigError(f"{at}.goal: a hold has no goal (it holds where it is)")
        return s
    k = m.goal.stiffness_xyz_rot_xyz
    if k and m.scheme == "joint":
        raise ConfigError(f"{at}.goal.stiffness_xyz_rot_xyz: a joint move has no Cartesian one")
    if k and max(k[3:]) > ROT_STIFFNESS_MAX:
        raise ConfigError(
            f"{at}.goal.stiffness_xyz_rot_xyz: {max(k[3:]):g} N m/rad is over "
            f"{ROT_STIFFNESS_MAX:g} (the loop closes through two ddms: a stiffer wrist rings)"
        )
    if s.carry and (m.goal.q_rad or m.goal.pos_xyz_rot_xyz):
        raise ConfigError(f"{at}.goal: a carry's goal is the segment's carry (give move_s only)")
    if m.scheme not in s.schemes:
        raise ConfigError(
            f"{at}.scheme: the skill {s.name} runs under {' or '.join(s.schemes)}, not {m.scheme}"
        )
    if s.contact != (m.end.contact_n > 0):
        raise ConfigError(
            f"{at}.end.contact_n: "
            + ("a guarded_move ends at contact: give the force [N] that is contact"
               if s.contact else f"only a guarded_move ends at contact, not a {s.name}")
        )  # fmt: skip
    if s.search != (m.search.pattern != "none"):
        raise ConfigError(
            f"{at}.search: "
            + ("a search_insert searches: give search.pattern: spiral"
               if s.search else f"a {s.name} does not search (skill: search_insert)")
        )  # fmt: skip
    return s
