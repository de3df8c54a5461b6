"""``redistro bench ddm``: the DDM transports alone, without the plant.

N ESC ddms and their SSC ddm, each a process of its own running the real
:class:`~redistro.ddm.worker.Ddm` over the real transport
(``--transport socket|reflective|zenoh``) on its node's Local Data (in the
process's memory: nothing else of the node runs), at the ddm's priority and
policy of a node (``scheduling.*``: real time when granted). The SSC's process
publishes a command per robot at ``--rate`` (stamped, as the SSC's worker
does) and wakes its ddm; each ESC's process, woken by its transport, puts a
fresh feedback sample beside the command that came (as an acquisition
would) and steps its ddm, which admits the command and answers with the
sample. Per robot: command latency (the command's stamp to its admission
in the ESC's Local Data, the ddm's own figure) and feedback latency (the
sample's stamp to its admission in the SSC's); the records delivered each
way per second; every ddm's CPU (% of one vCPU); records dropped or never
delivered. While they run, the CPUs' wake-up latency is held as a node's
manager holds it (``scheduling.cpu_latency_us``): the ddms wake as they
would in a session.

The process entry (``python -m redistro.bench.ddm``) blocks the runtime
signals before anything that may start a thread is imported (zenoh's
threads among them).
"""

import os
import sys

if __name__ == "__main__":
    from redistro.ipc.signals import block_runtime_signals

    block_runtime_signals()
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import contextlib
import dataclasses
import json
import select
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

CONNECT_S = 20.0  # how long the SSC waits for every ESC's first feedback
TRANSPORTS = ("socket", "reflective", "zenoh")


def bench_config(cfg: Any, transport: str, robots: int, key: str, users: str) -> Any:
    """The config with ``robots`` robots (r1..rN) and the transport chosen."""
    from redistro.config.model import RobotConfig

    zenoh = dataclasses.replace(cfg.ddm.zenoh, users_file=users)
    ddm = dataclasses.replace(cfg.ddm, transport=transport, key_file=key, zenoh=zenoh)
    fleet = {f"r{i + 1}": RobotConfig() for i in range(robots)}
    return dataclasses.replace(cfg, robots=fleet, ddm=ddm)


def _spec(cfg: Any, sid: str, node: str, kind: str, robots: list[str], rate_hz: float) -> Any:
    from redistro.config.loader import resolved
    from redistro.process.spec import NodeParams, NodeSpec, WorkerSpec

    return NodeSpec(
        session_id=sid,
        node=node,
        kind=kind,
        rate_hz=rate_hz,
        heartbeat_limit_cycles=25,
        # the ddm's priority and policy as in a node (scheduling.*)
        workers=[
            WorkerSpec(
                name="ddm",
                role="ddm",
                stage=-1,
                priority=cfg.scheduling.priorities.get("ddm", WorkerSpec.priority),
            )
        ],
        sched_policy=cfg.scheduling.policy,
        robots=robots,
        config=resolved(cfg),
        node_params=NodeParams(link=sid),
    )


def run(cfg: Any, transport: str, robots: int, rate_hz: float, seconds: float) -> dict[str, Any]:
    """Spawn the ddms, wait for them, gather their figures."""
    from redistro.ddm import record as wire
    from redistro.ipc import sched
    from redistro.ipc import session as ipc_session

    procs: list[subprocess.Popen[bytes]] = []
    granted = sched.Granted()
    us = cfg.scheduling.cpu_latency_us
    held = None if us is None else sched.hold_cpu_latency(us, granted)
    with contextlib.ExitStack() as stack, ipc_session.Session.create() as session:
        if held is not None:  # as every node's manager holds it
            stack.callback(os.close, held)
        sid = session.id
        folder = session.directory
        try:
            key = folder / "link.key"
            wire.new_key(key)
            users = folder / "zenoh.users"
            names = [f"r{i + 1}" for i in range(robots)]
            if transport == "zenoh":
                from redistro.ddm import zenoh_transport as zt

                zt.new_users_file(users, sid, ["ssc", *(f"esc.{r}" for r in names)])
            bench = bench_config(cfg, transport, robots, str(key), str(users))
            end_by = time.monotonic() + CONNECT_S + seconds + 5.0
            sides = [("esc", f"esc.{r}", [r]) for r in names] + [("ssc", "ssc", names)]
            for kind, node, mine in sides:
                spec = _spec(bench, sid, node, kind, mine, rate_hz)
                path = folder / f"{node}.spec.json"
                spec.save(path)
                procs.append(
                    subprocess.Popen(
                        [
                            sys.executable,
                            "-m",
                            "redistro.bench.ddm",
                            kind,
                            str(path),
                            str(folder / f"{node}.json"),
                            repr(seconds),
                            repr(end_by),
                        ],
                        stdin=subprocess.DEVNULL,
                    )
                )
            for p in procs:
                p.wait(timeout=max(1.0, end_by - time.monotonic() + 10.0))
            found = {
                node: json.loads((folder / f"{node}.json").read_text())
                for _, node, _ in sides
                if (folder / f"{node}.json").exists()
            }
        finally:
            for p in procs:
                if p.poll() is None:
                    p.kill()
                    p.wait()
    out = _figures(transport, robots, rate_hz, seconds, found, names)
    out["cpu_latency_us"] = granted.cpu_latency_us  # the PM QoS held (None: none)
    return out


def _figures(
    transport: str,
    robots: int,
    rate_hz: float,
    seconds: float,
    found: dict[str, Any],
    names: list[str],
) -> dict[str, Any]:
    ssc = found.get("ssc", {})
    per_robot: dict[str, Any] = {}
    for r in names:
        esc = found.get(f"esc.{r}", {})
        per_robot[r] = {
            "command_latency_us": esc.get("command_latency_us"),
            "feedback_latency_us": (ssc.get("feedback_latency_us") or {}).get(r),
            "commands_sent": (ssc.get("sent") or {}).get(r, 0),
            "commands_taken": esc.get("taken", 0),
            "commands_superseded": esc.get("superseded", 0),
            "feedback_taken": (ssc.get("taken") or {}).get(r, 0),
            "feedback_seen": (ssc.get("seen") or {}).get(r, 0),
            "answered_in_transport": esc.get("answered", 0),
            "dropped": esc.get("dropped", 0) + (ssc.get("dropped") or {}).get(r, 0),
            "dropped_by_esc": esc.get("dropped_by", {}),
            "cpu_percent": esc.get("cpu_percent"),
            "step_cpu_us": esc.get("step_cpu_us"),
            # why its ESC side stopped: the SSC's last command ("finished"),
            # the link closed ("lost"), or its deadline ("deadline")
            "ended": esc.get("ended"),
        }
    measured = ssc.get("measured_s") or 0.0
    sent = sum(v["commands_sent"] for v in per_robot.values())
    taken = sum(v["commands_taken"] for v in per_robot.values())
    superseded = sum(v["commands_superseded"] for v in per_robot.values())
    lat = [v["command_latency_us"] for v in per_robot.values() if v["command_latency_us"]]
    fb = [v["feedback_latency_us"] for v in per_robot.values() if v["feedback_latency_us"]]
    esc_cpu = [v["cpu_percent"] for v in per_robot.values() if v["cpu_percent"] is not None]
    return {
        "transport": transport,
        "robots": robots,
        "rate_hz": rate_hz,
        "seconds": seconds,
        "connected": bool(ssc.get("connected")),
        "scheduling": ssc.get("scheduling"),  # the ddms' policy (SCHED_RR as in a node, if granted)
        "measured_s": measured,
        "error": ssc.get("error")
        or next((e["error"] for e in found.values() if e.get("error")), ""),
        "command_latency_us": {
            "p50": max((x["p50"] for x in lat), default=0.0),
            "p99": max((x["p99"] for x in lat), default=0.0),
            "max": max((x["max"] for x in lat), default=0.0),
        },
        "feedback_latency_us": {
            "p50": max((x["p50"] for x in fb), default=0.0),
            "p99": max((x["p99"] for x in fb), default=0.0),
            "max": max((x["max"] for x in fb), default=0.0),
        },
        "commands_per_s": round(taken / measured, 1) if measured else 0.0,
        "feedback_per_s": round(sum(v["feedback_taken"] for v in per_robot.values()) / measured, 1)
        if measured
        else 0.0,
        # (commands neither taken nor overwritten on a card by a newer one)
        "lost_commands": max(0, sent - taken - superseded),
        "superseded_commands": superseded,
        "dropped": sum(v["dropped"] for v in per_robot.values()),
        "ssc_answered_in_transport": ssc.get("answered", 0),
        "ssc_cpu_percent": ssc.get("cpu_percent"),
        "esc_cpu_percent_max": max(esc_cpu, default=None),
        # each ddm's step (its thread's CPU; the process's loop around it is not in it)
        "ssc_step_cpu_us": ssc.get("step_cpu_us"),
        "ssc_steps_per_s": ssc.get("steps_per_s"),
        "esc_step_cpu_us_p50_max": max(
            (v["step_cpu_us"]["p50"] for v in per_robot.values() if v["step_cpu_us"]),
            default=None,
        ),
        "per_robot": per_robot,
    }


# -- the processes --


class _Waits:
    """The ddm's fds in an epoll, asked again after every step (a transport's
    fds change: a connection accepted, a peer gone), as the worker runner does."""

    def __init__(self, ddm: Any) -> None:
        self.ddm = ddm
        self.poll = select.epoll()
        self.fds: list[int] = []
        self.refresh()

    def refresh(self) -> None:
        now = list(self.ddm.fds())
        if now == self.fds:
            return
        for fd in self.fds:  # a closed one has left the epoll already
            with contextlib.suppress(OSError):
                self.poll.unregister(fd)
        for fd in now:
            self.poll.register(fd, select.EPOLLIN)
        self.fds = now

    def wait(self, timeout_s: float) -> list[tuple[int, int]]:
        events: list[tuple[int, int]] = self.poll.poll(timeout_s)
        return events


def _cpu_s() -> float:
    t = os.times()
    return t.user + t.system


def _side(kind: str, spec_path: str, out_path: str, seconds: float, end_by: float) -> None:
    from redistro.ddm.record import KIND_COMMAND
    from redistro.ddm.worker import Ddm
    from redistro.localdata.block import Record
    from redistro.localdata.layout import COMMAND, FEEDBACK
    from redistro.process.spec import NodeSpec
    from redistro.process.stats import Samples
    from redistro.process.watch import node_local_data

    spec = NodeSpec.load(spec_path)
    period_ns = int(1e9 / spec.rate_hz)
    ld = node_local_data(spec, period_ns, None, memory=True)
    out: dict[str, Any] = {"node": spec.node}
    ddm = Ddm(spec, 0, ld)
    try:
        ddm.initialize()
        # then the node's real-time priority, as a worker takes it after its
        # initialization (zenoh's threads get it at the session's opening)
        from redistro.ipc import sched

        out["scheduling"] = sched.apply(spec.workers[0].priority, None, spec.sched_policy).policy
        poll = _Waits(ddm)
        robots = spec.robots
        if kind == "esc":
            out.update(_esc_loop(ddm, ld, poll, end_by, Record(FEEDBACK), Samples))
        else:
            out.update(
                _ssc_loop(
                    ddm, ld, poll, robots, period_ns, seconds, end_by, Record(COMMAND), Samples
                )
            )
    except Exception as exc:  # the figures say what went wrong, the parent goes on
        out["error"] = f"{type(exc).__name__}: {exc}"
    finally:
        # its measuring over, the process leaves real time, as a node's
        # workers do at their clean-up: an ESC that ends on the last command
        # and exits at the ddm's priority held the vCPUs from the ESCs that
        # had yet to take it (that command's latency: 20-220 ms at N = 4-16)
        from redistro.ipc import sched

        sched.leave_real_time()
        ddm.cleanup()
        ld.close()
        ld.unlink()
    ex = ddm.ex
    out["dropped"] = (
        int(sum(e["dropped"] for e in ex))
        if kind == "esc"
        else {r: int(e["dropped"]) for r, e in zip(spec.robots, ex, strict=True)}
    )
    reasons = ("malformed", "forged", "duplicate", "out_of_order", "stale")
    out["dropped_by"] = {why: int(sum(e[why] for e in ex)) for why in reasons}
    if kind == "esc":
        out["command_latency_us"] = ddm.latency.summary_us()
        out["taken"] = int(ex[0]["updates"])
        # this robot's commands a newer one overwrote on the card before this
        # ddm read it (reflective memory keeps the latest record of each
        # slot; the card holds the other robots' commands too, not counted)
        of = getattr(ddm.transport, "superseded_of", None)
        out["superseded"] = 0 if of is None else int(of(KIND_COMMAND, ddm.gid[spec.robots[0]]))
    # the records the ddm took whole in its transport's thread (zenoh's),
    # without a step of its own
    out["answered"] = ddm.answers.taken
    Path(out_path).write_text(json.dumps(out))


def _esc_loop(ddm: Any, ld: Any, poll: Any, end_by: float, fb: Any, samples: Any) -> dict[str, Any]:
    """Woken by the transport: a fresh sample beside each command that came,
    then the ddm. A replying ddm (sockets, zenoh) answers the command with
    it in the same step, so the sample goes first; otherwise (reflective
    memory, where every write wakes every node) the ddm takes the command,
    and only a new one brings a sample and a second step to send it. It
    ends with a command that says the session finished (or a lost link)."""
    from redistro.localdata.layout import SessionStatus

    commands = ld.block("command", 0)
    last_cmd = first_cmd = checked = commands.seq
    cpu0, t0 = _cpu_s(), time.monotonic()
    sample = _acquisition(ddm, ld, fb)
    next_datum = 0.0
    steps = samples()  # the CPU of each of the ddm's steps
    cycle = [0]

    def step() -> None:
        cycle[0] += 1
        c0 = time.thread_time_ns()
        ddm.step(cycle[0])
        steps.add(time.thread_time_ns() - c0)

    while time.monotonic() < end_by and not ddm.lost:
        # an answering ddm, once commanded, sleeps as a node's does (wait_s:
        # its heartbeat's pace, out of the commands' burst); else 50 ms
        answering = ddm.answers.on and ddm.commanded
        events = poll.wait(ddm.wait_s() if answering else 0.05)
        ddm.ready_fds = [fd for fd, _ in events] or None
        now = time.monotonic()
        # (an answering ddm's sample is made beside each command, in the
        # transport's thread, even for one it leaves to this step)
        if (ddm.replying and not answering) or (commands.seq == first_cmd and now >= next_datum):
            # (and the start-up datum, on its own, every 50 ms until a
            # command comes: on reflective memory the other robots' data
            # wake this process too, so silence cannot be waited for)
            sample()
            next_datum = now + 0.05
        step()
        if not ddm.replying and commands.seq != last_cmd:
            last_cmd = commands.seq
            sample()
            step()
        poll.refresh()
        if commands.seq != checked:
            checked = commands.seq
            if int(commands.read()["session_status"]) == SessionStatus.FINISHED:
                ended = "finished"  # the SSC's last command (its reply, if any, sent)
                break
    else:
        ended = "lost" if ddm.lost else "deadline"
    wall = max(1e-9, time.monotonic() - t0)
    return {
        "ended": ended,
        "cpu_percent": round(100 * (_cpu_s() - cpu0) / wall, 2),
        "step_cpu_us": steps.summary_us(),
    }


def _acquisition(ddm: Any, ld: Any, fb: Any) -> Any:
    """The acquisition's stand-in: a fresh feedback sample per call. A ddm
    that answers in its transport's thread takes one before each record
    there, as the ddm's own step takes one before its step."""
    writer = ld.writer("feedback", 0, role="acquisition")
    sampling = threading.Lock()
    seq = [0]
    # (the stand-in's own cost kept small: it runs in the answering thread,
    # on the way of every command it times)
    seq_word, stamp_word, step_word = fb.word("seq_src"), fb.word("stamp_ns"), fb.word("step")
    publish, record, stamp = writer.publish, fb.bytes, time.monotonic_ns

    def sample() -> None:
        with sampling:  # (the ddm's step, or zenoh's thread answering)
            seq[0] += 1
            seq_word[0] = step_word[0] = seq[0]
            stamp_word[0] = stamp()
            publish(record)

    if ddm.answers.on and ddm.answers.state is not None:
        # the compiled answer runs it first on every record
        ddm.answers.before = sample
    elif ddm.answers.on:
        answer = ddm.transport.answer

        def answered(raw: bytes) -> int:
            sample()
            result: int = answer(raw)
            return result

        ddm.transport.answer = answered
    return sample


def _ssc_loop(
    ddm: Any,
    ld: Any,
    poll: Any,
    robots: list[str],
    period_ns: int,
    seconds: float,
    end_by: float,
    cmd: Any,
    samples: Any,
) -> dict[str, Any]:
    """A command per robot every period (stamped), the ddm woken for it and
    for what comes; each robot's fresh feedback timed from its stamp to its
    admission (the exchange's ``last_update_ns``: a ddm that admits in its
    transport's thread is not woken for it, and this loop reads it later)."""
    b = _SscBench(ddm, ld, poll, robots, samples)
    # the meeting point: every ESC's start-up datum (its feedback on its own)
    connect_by = min(end_by, time.monotonic() + CONNECT_S)
    while not all(b.last) and time.monotonic() < connect_by and not ddm.lost:
        b.turn(0.05, False)
    if not all(b.last):
        silent = [r for r, s in zip(robots, b.last, strict=True) if not s]
        return {
            "connected": False,
            "error": f"not heard from within {CONNECT_S:g} s: {', '.join(silent)}",
        }
    cpu0, t0 = _cpu_s(), time.monotonic()
    # feedback taken: what the ddm admitted into Local Data from here on (two
    # that come within one of this process's reads leave one sample to see)
    admitted0 = [int(e["updates"]) for e in ddm.ex]
    steps = b.commands(cmd, period_ns, min(end_by - 2.0, t0 + seconds))
    wall = max(1e-9, time.monotonic() - t0)
    b.finish(cmd)
    taken = [int(e["updates"]) - a for e, a in zip(ddm.ex, admitted0, strict=True)]
    return {
        "connected": True,
        "measured_s": round(wall, 3),
        "cpu_percent": round(100 * (_cpu_s() - cpu0) / wall, 2),
        "step_cpu_us": steps.summary_us(),
        "steps_per_s": round(steps.count / wall, 1),
        "sent": dict(zip(robots, b.sent, strict=True)),
        "taken": dict(zip(robots, taken, strict=True)),
        "seen": dict(zip(robots, b.seen, strict=True)),
        "feedback_latency_us": {r: s.summary_us() for r, s in zip(robots, b.lat, strict=True)},
    }


class _SscBench:
    """The SSC's side of ``bench ddm``: a worker's stand-in publishing the
    commands, and each robot's feedback timed to its admission."""

    def __init__(self, ddm: Any, ld: Any, poll: Any, robots: list[str], samples: Any) -> None:
        from redistro.localdata.block import Record
        from redistro.localdata.layout import FEEDBACK

        n = len(robots)
        self.ddm, self.poll, self.samples = ddm, poll, samples
        self.writers = [ld.writer("command", i, role="worker") for i in range(n)]
        self.readers = [ld.block("feedback", i) for i in range(n)]
        self.fbs = [Record(FEEDBACK) for _ in robots]
        self.last = [0] * n
        self.lat = [samples() for _ in robots]
        self.seen = [0] * n
        self.sent = [0] * n
        self.cycle = 0
        self.period_s = 0.0  # (the commands' period, once sent)

    def take(self, measure: bool) -> None:
        """Each robot's newest feedback, timed by its admission."""
        ddm = self.ddm
        with ddm.answers.lock:  # (the sample and its admission's time together)
            for i, (rd, rec) in enumerate(zip(self.readers, self.fbs, strict=True)):
                rd.read_into(rec.bytes)
                s = int(rec["seq_src"])
                if s != self.last[i]:
                    self.last[i] = s
                    if measure:
                        self.seen[i] += 1
                        lat = int(ddm.ex[i]["last_update_ns"]) - int(rec["stamp_ns"])
                        self.lat[i].add(lat)

    def turn(self, timeout_s: float, measure: bool) -> None:
        events = self.poll.wait(timeout_s)
        self.ddm.ready_fds = [fd for fd, _ in events] or None
        self.cycle += 1
        self.ddm.step(self.cycle)
        self.poll.refresh()
        self.take(measure)

    def commands(self, cmd: Any, period_ns: int, stop: float) -> Any:
        """A command per robot every period until ``stop``: the CPU of each
        of the ddm's steps."""
        ddm, poll = self.ddm, self.poll
        due = time.monotonic_ns()
        seq = 0
        steps = self.samples()
        # (the worker's stand-in kept small: its commands are timed from their stamps)
        seq_word, stamp_word, record = cmd.word("seq_src"), cmd.word("stamp_ns"), cmd.bytes
        publishes, clock = [w.publish for w in self.writers], time.monotonic_ns
        while time.monotonic() < stop and not ddm.lost:
            now = time.monotonic_ns()
            if now >= due:
                # the last period's feedback, timed by its admission: read here,
                # before the commands, the reads stay out of the burst they time
                self.take(True)
                seq += 1
                seq_word[0] = seq
                for publish in publishes:  # (each stamped as it goes)
                    stamp_word[0] = clock()
                    publish(record)
                for i in range(len(self.sent)):
                    self.sent[i] += 1
                due += period_ns
                ddm.ready_fds = []  # woken by its worker's command (as by a node's wake event)
            else:
                events = poll.wait(max(0.0, (due - now) / 1e9))
                ddm.ready_fds = [fd for fd, _ in events]
                if not events:
                    continue
            self.cycle += 1
            c0 = time.thread_time_ns()
            ddm.step(self.cycle)
            steps.add(time.thread_time_ns() - c0)
            poll.refresh()
        self.seq = seq
        self.period_s = period_ns / 1e9
        return steps

    def finish(self, cmd: Any) -> None:
        """The last command says the session finished (as a session's last
        does): an ESC ends on it, where no closed link tells it (reflective
        memory); then the last replies."""
        from redistro.localdata.layout import SessionStatus

        ddm = self.ddm
        # the last command's replies taken first, for a period: once the
        # first ESC closes its link after the finished command, the exchange
        # stops on every link (a lost link is a fault), and a reply still on
        # its way would go untaken (r1 once two short of its commands)
        end = time.monotonic() + self.period_s
        while (left := end - time.monotonic()) > 0 and not ddm.lost:
            self.turn(left, True)
        seq = self.seq + 1
        cmd["session_status"] = SessionStatus.FINISHED
        for i, w in enumerate(self.writers):
            cmd["seq_src"] = seq
            cmd["stamp_ns"] = time.monotonic_ns()
            w.publish(cmd.bytes)
            self.sent[i] += 1
        ddm.ready_fds = []
        self.cycle += 1
        ddm.step(self.cycle)  # sent now (waiting first made its latency the wait's, 20 ms)
        self.poll.refresh()
        tail = time.monotonic() + 0.2
        while time.monotonic() < tail and not ddm.lost:
            self.turn(0.02, True)


def print_figures(out: dict[str, Any]) -> None:
    c, f = out["command_latency_us"], out["feedback_latency_us"]
    print(
        f"bench ddm {out['transport']}: {out['robots']} robots at {out['rate_hz']:g} Hz, "
        f"{out['measured_s']:.1f} s measured" + (f" ({out['error']})" if out["error"] else "")
    )
    print(
        f"  command latency us p50 {c['p50']} p99 {c['p99']} max {c['max']}; "
        f"feedback p50 {f['p50']} p99 {f['p99']} max {f['max']} (the worst robot's)"
    )
    print(
        f"  {out['commands_per_s']} commands/s, {out['feedback_per_s']} feedback/s; "
        f"lost {out['lost_commands']} (superseded {out['superseded_commands']}), "
        f"dropped {out['dropped']}; CPU: SSC ddm "
        f"{out['ssc_cpu_percent']} %, ESC ddm up to {out['esc_cpu_percent_max']} % of a vCPU"
    )
    step = out.get("ssc_step_cpu_us") or {}
    print(
        f"  step CPU us p50: SSC ddm {step.get('p50')} (p99 {step.get('p99')}, "
        f"{out.get('ssc_steps_per_s')} steps/s), ESC ddm up to {out['esc_step_cpu_us_p50_max']}"
    )
    fl = (out.get("socket_floor") or {}).get("reply_cpu_us") or {}
    if fl:
        lat = out["socket_floor"].get("latency_us") or {}
        print(
            f"  socket floor (receive + reply alone) CPU us p50 {fl['p50']} p99 {fl['p99']}; "
            f"latency p50 {lat.get('p50')} p99 {lat.get('p99')} (the worst robot's)"
        )
    zf = out.get("zenoh_floor") or {}
    if zf.get("latency_us"):
        lat, cpu = zf["latency_us"], zf.get("reply_cpu_us") or {}
        print(
            f"  zenoh floor (bare zenoh-python puts and replies) latency us p50 {lat['p50']} "
            f"p99 {lat['p99']}; reply CPU p50 {cpu.get('p50')}; "
            f"{zf.get('replies')}/{zf.get('commands')} replies"
        )
    elif zf:
        print(f"  zenoh floor: {zf.get('error')}")


if __name__ == "__main__":
    _side(sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4]), float(sys.argv[5]))
