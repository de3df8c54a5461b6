"""Follow: where a held object's point went, from the holding hand's
measured pose against its planned one, on random poses."""

from __future__ import annotations

import numpy as np

from redistro.control.cartesian import rotvec_to_matrix
from redistro.ssc.follow import Follow


def test_the_point_goes_where_the_measured_hand_takes_it() -> None:
    rng = np.random.default_rng(7)
    for _ in range(200):
        goal = np.concatenate([rng.uniform(-0.5, 0.5, 3), rng.uniform(-2.0, 2.0, 3)])
        point = goal[:3] + rng.uniform(-0.2, 0.2, 3)
        f = Follow(goal, point)
        R_goal = rotvec_to_matrix(goal[3:])
        assert np.allclose(f.delta(goal[:3], R_goal), 0.0, atol=1e-12)  # (where planned)
        shift = rng.uniform(-0.01, 0.01, 3)
        assert np.allclose(f.delta(goal[:3] + shift, R_goal), shift, atol=1e-12)
        turn = rotvec_to_matrix(rng.uniform(-0.1, 0.1, 3))  # about the hand's TCP, world
        got = f.delta(goal[:3], turn @ R_goal)
        assert np.allclose(got, turn @ (point - goal[:3]) - (point - goal[:3]), atol=1e-12)


def test_the_cycles_update_is_the_reference_at_the_holders_measured_tcp() -> None:
    """update (in place, each cycle) against delta, with a real arm model
    at random postures: the holder's TCP from Pinocchio, the base added."""
    from types import SimpleNamespace

    from redistro.control.dynamics import ArmModel

    rng = np.random.default_rng(3)
    base = np.array([0.0, 0.45, 0.0])
    holder = SimpleNamespace(
        model=ArmModel(None, base.tolist()), views={"q": np.zeros(7)}, base=base, tcp_offset_m=0.01
    )
    goal = np.array([0.4, 0.1, 0.3, 0.0, np.pi, 0.0])
    f = Follow(goal, np.array([0.5, 0.1, 0.3]))
    for _ in range(50):
        holder.views["q"][...] = rng.uniform(-1.0, 1.0, 7)
        k = holder.model.kinematics(holder.views["q"])
        assert np.allclose(f.update(holder), f.delta(k.p, k.R), atol=1e-12)
