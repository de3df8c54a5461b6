"""Two robot groups on one Zenoh network: group lab-a (r1 and its SSC) and
group lab-b (r2 and its SSC), every node started alone beside one plant.
The groups share nothing but the network (lab-b's SSC connects to lab-a's),
both end ``ok``; a session with lab-a's credentials that publishes on
lab-b's keys is refused by lab-b's access rules (its records never reach
lab-b's ddm), while the same records sent with lab-b's own credentials do
(and are dropped there as forged); ``redistro top --zenoh`` lists both
groups."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from redistro.ddm import record as wire
from redistro.ddm import zenoh_transport as zt
from redistro.localdata.layout import FEEDBACK
from redistro.localdata.view import NodeView
from tests.helpers import ROOT, load_json, read_session_id, run_cli, wait_for

TASKS = {
    "lab-a": str(ROOT / "tests/data/r1_alone.yaml"),
    "lab-b": str(ROOT / "tests/data/r2_alone.yaml"),
}
ROBOT = {"lab-a": "r1", "lab-b": "r2"}
SENT = 20  # forged records the control sends with lab-b's own credentials


def _start(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "redistro.cli", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )


def _forged(n: int) -> list[bytes]:
    fb = np.zeros((), FEEDBACK)
    return [wire.encode(wire.KIND_FEEDBACK, 1, "esc.r2", k, k, fb, key=bytes(32)) for k in range(n)]


def _publish_as(
    user: str,
    users: Path,
    endpoint: str,
    key: str,
    records: list[bytes],
    arrived: Callable[[], bool] | None = None,
) -> None:
    """A zenoh session of ``user`` at ``endpoint`` putting ``records`` on
    ``key``. Given ``arrived`` (records that must get through), it waits
    until a subscriber matches the key before the puts and until
    ``arrived()`` after them; else (records that must be refused, with no
    event to wait on) it gives the routes 1 s and the puts 0.5 s."""
    session = zt.open_session(zt.client_settings(endpoint, user, str(users)))
    try:
        pub = session.declare_publisher(key)
        if arrived is None:
            time.sleep(1.0)
        else:
            wait_for(lambda: pub.matching_status.matching, 30, f"a subscriber of {key}")
        for r in records:
            pub.put(r)
        if arrived is None:
            time.sleep(0.5)
        else:
            wait_for(arrived, 30, f"{user}'s records to arrive")
        pub.undeclare()
    finally:
        session.close()


def test_two_groups_share_one_network_and_nothing_else(calibrated: Path, tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    shutil.copytree(calibrated, runs)
    key = tmp_path / "link.key"
    wire.new_key(key)
    users = tmp_path / "zenoh.users"
    lines = [f"{zt.user_of(n, 'lab-a')}" for n in ("ssc", "esc.r1")]
    lines += [f"{zt.user_of(n, 'lab-b')}" for n in ("ssc", "esc.r2")]
    fd = os.open(users, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    os.write(
        fd,
        "".join(f"{u}:pw-{i}-{os.getpid()}\n" for i, u in enumerate([*lines, zt.VIEWER])).encode(),
    )
    os.close(fd)
    base = 29000 + 2 * (os.getpid() % 1500)  # below the ephemeral ports (32768-)
    port = {"lab-a": base, "lab-b": base + 1}
    common = ["--set", f"session.runs_dir={runs}", "--set", "ddm.transport=zenoh"]
    common += ["--set", f"ddm.key_file={key}", "--set", f"ddm.zenoh.users_file={users}"]
    plant = _start(*common, "plant")
    procs = [plant]
    try:
        plant_sid = read_session_id(plant)
        wait_for(Path(f"/dev/shm/redistro.{plant_sid}.plant.bank").exists, 60, "the plant's bank")
        nodes: dict[str, subprocess.Popen[str]] = {}
        for group, task in TASKS.items():
            r = ROBOT[group]
            endpoint = f"tcp/127.0.0.1:{port[group]}"
            nodes[f"esc.{r}"] = _start(
                *common,
                "--set",
                f'ddm.zenoh.connect=["{endpoint}"]',
                "node", "esc", r, task, "--plant", plant_sid, "--link", group,
                "--out", str(tmp_path / f"esc.{r}"),
            )  # fmt: skip
            ssc_sets = ["--set", f'ddm.zenoh.listen=["{endpoint}"]']
            if group == "lab-b":  # one network: lab-b's SSC also connects to lab-a's
                ssc_sets += ["--set", f'ddm.zenoh.connect=["tcp/127.0.0.1:{port["lab-a"]}"]']
            nodes[f"ssc.{group}"] = _start(
                *common, *ssc_sets, "node", "ssc", task, "--link", group,
                "--out", str(tmp_path / f"ssc.{group}"),
            )  # fmt: skip
        procs += nodes.values()
        b_door = f"tcp/127.0.0.1:{port['lab-b']}"

        sids = {name: read_session_id(p) for name, p in nodes.items()}

        def exchange(node: str, figure: str) -> int:
            """A count of the node's ddm (0 while its Local Data is not there)."""
            view = NodeView.open(sids[node], "ssc" if node.startswith("ssc.") else node)
            if view is None:
                return 0
            with view:
                return int(view.read("exchange", 0)[figure])

        def met() -> bool:
            """Every node is running and both groups' ddms hear their peers
            (a SSC's door opens at its ddm's first receive)."""
            ended = {n: p.returncode for n, p in nodes.items() if p.poll() is not None}
            assert not ended, f"a node ended before the groups met: {ended}"
            return all(exchange(n, "updates") > 0 for n in nodes)

        # the nodes meet (the tasks then run ~12 s)
        wait_for(met, 120, "both groups' nodes to meet")
        # one look over both doors while every node runs (once, taken after
        # the forgeries on a loaded host, it found lab-b's task over)
        seen = run_cli(
            "--set", f"ddm.zenoh.users_file={users}", "top", "--once", "--json",
            "--zenoh", f"tcp/127.0.0.1:{port['lab-a']}", "--zenoh", b_door,
            timeout=60,
        )  # fmt: skip
        b_feedback = zt.feedback_key("lab-b", "r2")
        # lab-a's credentials on lab-b's keys: refused by lab-b's SSC
        _publish_as(zt.user_of("esc.r1", "lab-a"), users, b_door, b_feedback, _forged(SENT))
        # lab-b's own ESC's credentials: let in, and dropped by the ddm as forged
        _publish_as(
            zt.user_of("esc.r2", "lab-b"), users, b_door, b_feedback, _forged(SENT),
            arrived=lambda: exchange("ssc.lab-b", "forged") >= SENT,
        )  # fmt: skip
        ends = {name: p.communicate(timeout=240) for name, p in nodes.items()}
    finally:
        for p in procs:
            if p.poll() is None:
                p.terminate()
                p.communicate(timeout=60)
    outputs = {n: (nodes[n].returncode, o[-2000:] + e[-2000:]) for n, (o, e) in ends.items()}
    assert all(rc == 0 for rc, _ in outputs.values()), outputs
    for group in TASKS:
        s = load_json(tmp_path / f"ssc.{group}" / "summary.json")
        assert s["result"] == "ok", s["reason"]
        d = s["ddm"]["ssc"][ROBOT[group]]
        assert d["updates"] > 100, d
        if group == "lab-a":
            assert d["forged"] == 0 and d["malformed"] == 0, d
        else:  # only the control's records reached lab-b's ddm
            assert d["forged"] == SENT, d
    assert seen.returncode == 0, seen.stdout[-2000:] + seen.stderr[-2000:]
    looks = json.loads(seen.stdout)["zenoh"]
    groups = {
        g: {n["node"] for n in ns if n["alive"]}
        for look in looks
        for g, ns in look["groups"].items()
    }
    assert groups.get("lab-a", set()) >= {"ssc", "esc.r1"}, groups
    assert groups.get("lab-b", set()) >= {"ssc", "esc.r2"}, groups
