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
from pathlib import Path

import numpy as np
import zenoh

from redistro.ddm import record as wire
from redistro.ddm import zenoh_transport as zt
from redistro.localdata.layout import FEEDBACK
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


def _publish_as(user: str, users: Path, endpoint: str, key: str, records: list[bytes]) -> None:
    """A zenoh session of ``user`` at ``endpoint`` putting ``records`` on ``key``."""
    passwords = zt.read_users(users)
    session = zt.open_session(
        {
            "mode": "client",
            "connect/endpoints": [endpoint],
            "scouting/multicast/enabled": False,
            "scouting/gossip/enabled": False,
            "transport/shared_memory/enabled": False,
            "transport/auth/usrpwd": {
                "user": user,
                "password": passwords[user],
                "dictionary_file": str(users),
            },
        }
    )
    try:
        time.sleep(1.0)  # the session's routes, before the puts (no sync exists for this)
        for r in records:
            session.put(key, r)
        time.sleep(0.5)  # the puts leave before the close
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
    base = 36000 + os.getpid() % 3000
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

        def met(group: str) -> bool:
            """The group's SSC session is up (its door opens at the ddm's
            first receive) and both its nodes' tokens are seen through it."""
            door = f"tcp/127.0.0.1:{port[group]}"
            try:
                seen = zt.look(door, str(users), seconds=0.2)["groups"].get(group, [])
            except zenoh.ZError:  # the door is not open yet
                return False
            return {n["node"] for n in seen if n["alive"]} >= {"ssc", f"esc.{ROBOT[group]}"}

        # the nodes meet (the tasks then run ~12 s)
        wait_for(lambda: met("lab-a") and met("lab-b"), 120, "both groups' nodes to meet")
        b_feedback = zt.feedback_key("lab-b", "r2")
        # lab-a's credentials on lab-b's keys: refused by lab-b's SSC
        _publish_as(zt.user_of("esc.r1", "lab-a"), users, b_door, b_feedback, _forged(SENT))
        # lab-b's own ESC's credentials: let in, and dropped by the ddm as forged
        _publish_as(zt.user_of("esc.r2", "lab-b"), users, b_door, b_feedback, _forged(SENT))
        seen = run_cli(
            "--set", f"ddm.zenoh.users_file={users}", "top", "--once", "--json",
            "--zenoh", f"tcp/127.0.0.1:{port['lab-a']}", "--zenoh", b_door,
            timeout=60,
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
