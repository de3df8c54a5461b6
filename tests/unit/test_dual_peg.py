"""The dual-arm peg insertion's plan (tasks/dual_peg.yaml under
config/dual_peg.yaml) and a move's own stiffness (the law's gains)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from redistro.bench.dual import target_object
from redistro.config.loader import load_config
from redistro.config.task import load_task
from redistro.control.cartesian import move_gains
from redistro.control.cartesian_layout import GAINS
from redistro.ssc.plan import segment_plans

ROOT = Path(__file__).parents[2]


def test_r2_inserts_into_the_hole_r1_presents_and_follows_r1s_hand() -> None:
    cfg = load_config(ROOT / "config/dual_peg.yaml")
    plans = {p.name: p for p in segment_plans(load_task(ROOT / "tasks/dual_peg.yaml", cfg), cfg)}
    present = plans["present"].move_of("r1")
    insert = plans["insert"].move_of("r2")
    holder = plans["insert"].move_of("r1")
    assert present is not None and insert is not None and holder is not None
    sock, peg = cfg.workcell.objects["socket"], cfg.workcell.objects["peg"]
    # the hole where r1's quarter turn takes it: 0.18 m from the grasp along
    # the block, which now lies along world x
    grasp_to_hole = 0.09 - sock.hole_at_xy_m[1]
    mouth = present.pose[:3] + np.array([grasp_to_hole, 0.0, -0.005])
    assert np.allclose([*insert.mouth_xy_m], mouth[:2], atol=1e-6), (insert.mouth_xy_m, mouth)
    # the TCP's height with the held peg's tip at the mouth
    assert abs(insert.mouth_z_m - (mouth[2] + peg.size_xyz_m[2] + 0.004)) < 1e-6
    assert insert.follows == "r1" and insert.search.pattern == "spiral"
    assert (insert.hole_depth_m, insert.hole_half_m) == (sock.hole_depth_m, sock.hole_side_m / 2)
    # r1 holds the block where it presented it, stiffer than the config's
    assert np.allclose(holder.pose, present.pose) and holder.scheme == "position"
    assert holder.stiffness == (1500, 1500, 1500, 40, 40, 30)
    assert cfg.ssc.impedance.k[3] < 40
    # bench dual --task peg draws the truth of the block the hole is in
    for name in ("dual_peg.yaml", "dual_peg_short.yaml"):
        assert target_object(load_task(ROOT / "tasks" / name, cfg), "peg") == "socket"


def test_a_moves_stiffness_replaces_the_configs_and_keeps_the_damping_ratio() -> None:
    rng = np.random.default_rng(7)
    for _ in range(50):
        config = np.zeros((), GAINS)
        for name in GAINS.names:
            config[name] = rng.uniform(0.1, 10.0, np.shape(config[name]))
        k = tuple(rng.uniform(1.0, 100.0, 6))
        got = np.zeros((), GAINS)
        move_gains(got, config, k)
        assert np.allclose(got["k"], k)
        ratio = got["d"][3:] / np.sqrt(got["k"][3:])  # damping ratio at the same inertia
        assert np.allclose(ratio, config["d"][3:] / np.sqrt(config["k"][3:]))
        assert np.array_equal(got["d"][:3], config["d"][:3])  # (translation: zeta's)
        for name in GAINS.names:
            if name not in ("k", "d"):
                assert np.array_equal(got[name], config[name]), name
        move_gains(got, config, ())  # no stiffness of its own: the config's, whole
        assert got.tobytes() == config.tobytes()
