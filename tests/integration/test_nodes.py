"""Nodes started alone (`redistro node`): the ESCs beside the plant on one
host, the SSC on another, over the socket and the zenoh transports.

As root the two hosts are two network namespaces joined by a veth pair (the
SSC reaches the ESCs only through the pair); otherwise both sit on loopback.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from redistro.config import load_config
from tests.helpers import ROOT, load_json, read_session_id, run_cli, wait_for

TASK = str(ROOT / "tests/data/two_moves.yaml")
LIMIT = load_config(ROOT / "config/redistro.yaml").ddm.starving_limit_cycles


@dataclass
class Hosts:
    """Command prefixes that run a program on host A or B, and A's address as B sees it."""

    a: list[str]
    b: list[str]
    a_addr: str
    namespaces: bool
    b_addr: str = "127.0.0.1"


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, timeout=10)


@contextlib.contextmanager
def two_hosts() -> Iterator[Hosts]:
    if os.geteuid() != 0 or shutil.which("ip") is None:
        yield Hosts([], [], "127.0.0.1", namespaces=False)
        return
    tag = f"{os.getpid() % 100000}"
    ns_a, ns_b = f"rdA{tag}", f"rdB{tag}"
    veth_a, veth_b = f"rdva{tag}", f"rdvb{tag}"
    net = f"10.213.{os.getpid() % 250}"
    made: list[str] = []
    try:
        for ns in (ns_a, ns_b):
            _ip("netns", "add", ns)
            made.append(ns)
        _ip("link", "add", veth_a, "type", "veth", "peer", "name", veth_b)
        for ns, veth, host in ((ns_a, veth_a, 1), (ns_b, veth_b, 2)):
            _ip("link", "set", veth, "netns", ns)
            _ip("-n", ns, "addr", "add", f"{net}.{host}/24", "dev", veth)
            _ip("-n", ns, "link", "set", veth, "up")
            _ip("-n", ns, "link", "set", "lo", "up")
        yield Hosts(
            ["ip", "netns", "exec", ns_a],
            ["ip", "netns", "exec", ns_b],
            f"{net}.1",
            True,
            f"{net}.2",
        )
    finally:
        for ns in made:  # deleting a namespace deletes its end of the pair, and so both
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=10)


def _start(prefix: list[str], *args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [*prefix, sys.executable, "-m", "redistro.cli", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )


def _end(proc: subprocess.Popen[str], timeout: float) -> tuple[int, str]:
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.terminate()
        out, err = proc.communicate(timeout=30)
    return proc.returncode, out[-3000:] + err[-3000:]


@pytest.mark.parametrize("transport", ["socket", "zenoh"])
def test_the_ssc_and_the_escs_run_as_nodes_on_two_hosts(
    calibrated: Path, tmp_path: Path, transport: str
) -> None:
    """Over sockets the SSC connects to each ESC; over zenoh each ESC's
    session connects to the SSC's, authenticated (user and password from
    the shared users file) and under the SSC's access rules."""
    runs = tmp_path / "runs"
    shutil.copytree(calibrated, runs)
    from redistro.ddm.record import new_key

    key = tmp_path / "link.key"  # the link's key, shared by the nodes (one filesystem here)
    new_key(key)
    common = ["--set", f"session.runs_dir={runs}", "--set", f"ddm.transport={transport}"]
    common += ["--set", f"ddm.key_file={key}"]
    link = f"test-nodes-{os.getpid()}"
    esc_sets: list[str] = []
    ssc_sets: list[str] = []
    if transport == "zenoh":
        from redistro.ddm import zenoh_transport as zt

        users = tmp_path / "zenoh.users"  # shared like the key
        zt.new_users_file(users, link, ["ssc", "esc.r1", "esc.r2"])
        port = 26000 + os.getpid() % 3000  # below the ephemeral ports (32768-)
        common += ["--set", f"ddm.zenoh.users_file={users}"]
    with two_hosts() as hosts:
        if transport == "zenoh":
            esc_sets = ["--set", f'ddm.zenoh.connect=["tcp/{hosts.b_addr}:{port}"]']
            listen = "0.0.0.0" if hosts.namespaces else "127.0.0.1"
            ssc_sets = ["--set", f'ddm.zenoh.listen=["tcp/{listen}:{port}"]']
        plant = _start([], *common, "plant")
        procs: list[subprocess.Popen[str]] = [plant]
        try:
            plant_sid = read_session_id(plant)
            bank = Path(f"/dev/shm/redistro.{plant_sid}.plant.bank")
            wait_for(bank.exists, 60, "the plant's register bank")
            escs = {
                r: _start(
                    hosts.a,
                    *common,
                    "--set",
                    f"ddm.listen_host={'0.0.0.0' if hosts.namespaces else '127.0.0.1'}",
                    *esc_sets,
                    "node",
                    "esc",
                    r,
                    TASK,
                    "--plant",
                    plant_sid,
                    "--link",
                    link,
                    "--out",
                    str(tmp_path / f"esc.{r}"),
                )
                for r in ("r1", "r2")
            }
            procs += escs.values()
            ssc = _start(
                hosts.b,
                *common,
                "--set",
                f"ddm.esc_hosts.r1={hosts.a_addr}",
                "--set",
                f"ddm.esc_hosts.r2={hosts.a_addr}",
                *ssc_sets,
                "node",
                "ssc",
                TASK,
                "--link",
                link,
                "--out",
                str(tmp_path / "ssc"),
            )
            procs.append(ssc)
            ssc_rc, ssc_out = _end(ssc, 300)
            esc_ends = {r: _end(p, 120) for r, p in escs.items()}
        finally:
            for p in procs:
                if p.poll() is None:
                    p.terminate()
                    p.communicate(timeout=60)
    outputs = "\n".join([f"ssc: {ssc_out}", *(f"esc.{r}: {o}" for r, (_, o) in esc_ends.items())])
    assert ssc_rc == 0 and all(rc == 0 for rc, _ in esc_ends.values()), outputs
    summary = load_json(tmp_path / "ssc" / "summary.json")
    assert summary["result"] == "ok" and summary["node"] == "ssc"
    segs = {s["name"]: s for s in summary["segments"]}
    assert list(segs) == ["approach", "home"]
    assert segs["approach"]["final_pose_error"]["position_m"] <= 0.002, segs["approach"]
    for r in ("r1", "r2"):
        ddm = summary["ddm"]["ssc"][r]
        assert ddm["updates"] > 100 and ddm["malformed"] == 0, ddm
        esc = load_json(tmp_path / f"esc.{r}" / "summary.json")
        assert esc["result"] == "ok" and esc["plant_session"] == plant_sid, esc["reason"]
        d = esc["ddm"][f"esc.{r}"]
        assert d["updates"] > 100 and d["command_latency_us"]["p50"] > 0, d
        assert d["starving_index_max"] <= LIMIT, d
    print(f"{transport}, namespaces: {hosts.namespaces}")


def test_a_node_alone_refuses_bad_input(tmp_path: Path) -> None:
    bad = [
        (["node", "esc", "r9", TASK, "--plant", "x"], "robot 'r9': not in the task's robots"),
        (["node", "esc", "r2", TASK, "--plant", "nosuch"], "--plant nosuch: no running plant"),
        (["node", "ssc", "tasks/self_calibration.yaml"], "runs alone only in a strategy task"),
        (["node", "esc", "r2", TASK], "the following arguments are required: --plant"),
        (["node", "ssc", TASK, "--link", ""], "--link: expected a non-empty id"),
        (["node", "ssc", TASK, "--link", "l"], "ddm.key_file: nodes started alone need a shared"),
        (
            ["--set", f"ddm.key_file={tmp_path / 'open.key'}", "node", "ssc", TASK, "--link", "l"],
            "open.key: the key file has mode 0644, expected 0600",
        ),
    ]
    (tmp_path / "open.key").write_text("00" * 32)
    os.chmod(tmp_path / "open.key", 0o644)
    for args, message in bad:
        done = run_cli(*args, timeout=60)
        assert done.returncode == 2, (args, done.stderr)
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and message in lines[0], (args, done.stderr)


@pytest.fixture(autouse=True)
def _no_namespaces_left() -> Iterator[None]:
    yield
    if shutil.which("ip") is None:
        return
    listed = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True, check=False)
    assert f"rdA{os.getpid() % 100000}" not in listed.stdout
