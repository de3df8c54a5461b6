"""The config model: frozen dataclasses with constraints in field metadata.

Constraints understood by the validator (redistro.config.validate):
``gt``, ``ge``, ``lt``, ``le`` for numbers, ``min_len`` and ``len`` for lists, and
``keys`` (allowed keys) for dicts. Units are in the field names.

Past the house's ~400 lines: it is declarations only, one dataclass per
section of the config file, each documented where it is declared.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Literal

# Paper Table 5.I: relative priorities of the controller processes
# (acquisition 19 > sender 18 = SSC worker > calibration 17 > pid 16 > manager 15).
# One deliberate change: the manager runs *above* its workers (20). It is the
# node's timer and watchdog; below its workers, their wake-ups preempt it while
# it dispatches the cycle and a spinning worker could starve the heartbeat check
# (docs/PERFORMANCE.md measures both orders).
PAPER_PRIORITIES: dict[str, int] = {
    "acquisition": 19,
    "sender": 18,
    "worker": 18,
    "calibration": 17,
    "pid": 16,
    "manager": 20,
    "ddm": 19,
    "logger": 15,
    "recorder": 15,
    "busy": 16,
    # The simulated plant: the lowest real-time priority, below every
    # controller process (nice -10 where real time is refused). Its step costs
    # ~80-150 us of its 1 ms; a plant that needs more than half the wall clock
    # leaves real time (plant.process.DUTY_LIMIT). Above the controller it
    # delayed the nodes' cycles at 1 kHz (docs/PERFORMANCE.md).
    "plant": 1,
}


@dataclass(frozen=True)
class SessionConfig:
    """Where runs go, how long the session owner waits for its nodes, and
    what paces them."""

    runs_dir: str = "runs"
    # Kept between sessions, under runs_dir: the final joint positions (one
    # file per robot) and the simulated arms' pose while powered off.
    positions_dir: str = "positions"
    plant_pose_file: str = "plant-pose.json"
    startup_timeout_s: float = field(default=10.0, metadata={"gt": 0, "le": 600})
    shutdown_timeout_s: float = field(default=3.0, metadata={"gt": 0, "le": 60})
    # realtime: every node ticks on its interval timer and the plant on the
    # wall clock; lockstep: the plant paces the nodes (redistro.plant.lockstep)
    clock: Literal["realtime", "lockstep"] = "realtime"
    # lockstep's pace: 0, as fast as the CPUs allow; x > 0, at most x times
    # real time (a run watched live, e.g. in redistro view --live)
    lockstep_pace: float = field(default=0.0, metadata={"ge": 0, "le": 1000})


@dataclass(frozen=True)
class SchedulingConfig:
    """How processes ask the OS for real-time service.

    policy: ``auto`` tries SCHED_RR and falls back to nice values; ``rr`` and
    ``nice`` ask for that one only (and report a refusal); ``none`` leaves the
    default scheduler alone; ``batch`` puts every process of the session at
    SCHED_BATCH, no real-time service: for lockstep runs (a process that
    wakes does not preempt the one running; the short main job in lockstep
    took 7 % less CPU than at ``none``, docs/PERFORMANCE.md).
    lock_memory: mlockall in every process. Off by default: a locked process
    takes 10-17 ms (instead of about 2 ms) to die on this machine, which delays
    the manager's detection of a dead worker (docs/PERFORMANCE.md).
    cpu_latency_us: the CPU wake-up latency every node's manager asks of the
        kernel's power management while it runs (a PM QoS request through
        /dev/cpu_dma_latency, as cyclictest makes): 0 keeps idle CPUs out of
        halt, so a process woken by its timer, a semaphore or a socket runs
        at once. On this virtual machine a halted vCPU costs every wake-up
        a trip through the hypervisor (the DDM's command path: 200 µs p50
        halted, 40 µs polling). The price is power: idle CPUs poll. null
        leaves the kernel's choice alone; refused (not root), it is reported.
    """

    policy: Literal["auto", "rr", "nice", "none", "batch"] = "auto"
    priorities: dict[str, int] = field(
        default_factory=lambda: dict(PAPER_PRIORITIES),
        metadata={"ge": 1, "le": 99, "keys": tuple(PAPER_PRIORITIES)},
    )
    lock_memory: bool = False
    cpu_latency_us: int | None = field(default=0, metadata={"ge": 0, "le": 1_000_000})


@dataclass(frozen=True)
class NodeConfig:
    """One node's runtime parameters.

    rate_hz: cycle rate of the node's interval timer [Hz].
    heartbeat_limit_cycles: a worker that has not signed its heartbeat for this
        many consecutive manager cycles is deemed hung (session ends abnormal).
    cpus: CPUs the node's processes may run on (empty: all).
    """

    rate_hz: float = field(default=200.0, metadata={"gt": 0, "le": 10000})
    heartbeat_limit_cycles: int = field(default=25, metadata={"ge": 2, "le": 100000})
    cpus: list[int] = field(default_factory=list, metadata={"ge": 0})


def _seven(*values: float) -> list[float]:
    return list(values)


def _six(*values: float) -> list[float]:
    return list(values)


@dataclass(frozen=True)
class SafetyConfig:
    """Limits the sender's safety guard checks before every command.

    qd_max_rad_s: joint speed limits [rad/s], shape (7,).
    tau_max_nm: joint torque limits [N m], commanded and measured, shape (7,).
    force_max_n: limit on the wrist force's magnitude [N].
    moment_max_nm: limit on the wrist moment's magnitude [N m].
    encoder_jump_rad_s: the acquisition's plausibility check: a counter that
        moved more between two samples than this speed allows is a glitch
        (an I/O fault), not motion [rad/s].
    q_min_rad, q_max_rad: joint position limits [rad], shape (7,) or empty
        (empty: the arm model's). They may narrow the model's limits, never
        widen them (redistro/config/limits.py).
    q_margin_rad: the guard keeps every joint this far inside its limits [rad].
    decel_rad_s2: per joint, the deceleration a braking joint can count on
        [rad/s^2]: a joint that cannot stop before its limit less the margin
        at this deceleration is a fault while it still can.
    recovery_qd_rad_s: a joint resting outside its limits less the margin
        (or past them) may be moved back toward them at this speed at most
        [rad/s]; moving further out is a fault. 0: never (a robot left
        there stays there).
    Every limit is bounded by the hardware's rating (torque: current limit x
    torque constant x gear; speed: the model's; force and moment: the wrist
    sensor's range): a value above it is refused at load.
    """

    qd_max_rad_s: list[float] = field(
        default_factory=lambda: [1.0] * 7, metadata={"len": 7, "gt": 0}
    )
    tau_max_nm: list[float] = field(
        default_factory=lambda: _seven(200, 200, 120, 120, 60, 60, 30),
        metadata={"len": 7, "gt": 0},
    )
    force_max_n: float = field(default=120.0, metadata={"gt": 0})
    moment_max_nm: float = field(default=15.0, metadata={"gt": 0})
    encoder_jump_rad_s: float = field(default=20.0, metadata={"gt": 0})
    q_min_rad: list[float] = field(default_factory=list, metadata={"len": 7, "optional": True})
    q_max_rad: list[float] = field(default_factory=list, metadata={"len": 7, "optional": True})
    q_margin_rad: float = field(default=0.05, metadata={"ge": 0, "le": 0.5})
    decel_rad_s2: list[float] = field(
        default_factory=lambda: [5.0] * 7, metadata={"len": 7, "gt": 0}
    )
    recovery_qd_rad_s: float = field(default=0.5, metadata={"ge": 0, "le": 10})


@dataclass(frozen=True)
class PidConfig:
    """Joint PID gains, per joint (7 values): kp [N m/rad], ki [N m/(rad s)],
    kd [N m s/rad]; i_max_nm bounds the integral term [N m].

    Chosen for robustness, not stiffness: joints 1 and 3 move in a coupled
    mode of small inertia, and with twice these gains that mode went
    unstable when the controller was held off for 20-35 ms at a time (a
    loaded 2-vCPU host); with these, tracking errors stay within 0.5 mrad on
    the big joints and 4.4 mrad on the wrist during a 12 deg sweep in 10 s.
    """

    kp: list[float] = field(
        default_factory=lambda: _seven(150, 250, 50, 50, 5, 5, 2.5),
        metadata={"len": 7, "ge": 0},
    )
    ki: list[float] = field(
        default_factory=lambda: _seven(150, 250, 50, 50, 5, 5, 2.5),
        metadata={"len": 7, "ge": 0},
    )
    kd: list[float] = field(
        default_factory=lambda: _seven(5, 10, 1.2, 1.2, 0.05, 0.05, 0.03),
        metadata={"len": 7, "ge": 0},
    )
    i_max_nm: list[float] = field(default_factory=lambda: [20.0] * 7, metadata={"len": 7, "ge": 0})


@dataclass(frozen=True)
class EscConfig:
    """The Execution-Stage Controller of each robot.

    rate_hz: cycle rate [Hz] (paper: 200).
    heartbeat_limit_cycles: missed heartbeats that make a worker hung.
    cpus: CPUs the ESC's processes may run on (empty: all).
    """

    rate_hz: float = field(default=200.0, metadata={"gt": 0, "le": 10000})
    heartbeat_limit_cycles: int = field(default=25, metadata={"ge": 2, "le": 100000})
    cpus: list[int] = field(default_factory=list, metadata={"ge": 0})
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    pid: PidConfig = field(default_factory=PidConfig)


@dataclass(frozen=True)
class ImpedanceConfig:
    """Cartesian impedance of the TCP (world axes x, y, z, rx, ry, rz) and the
    joint terms under it. Chosen for robustness to delay: the SSC closes this
    loop through two DDMs and two node cycles (10-15 ms at 200 Hz), and the
    host can hold a node off for 20-35 ms; with these gains the peg insertion
    stays stable with 30 ms of constant delay in simulation.

    k: stiffness [N/m, N m/rad]; d: damping [N s/m, N m s/rad] (the
    translational part only when zeta is 0); zeta: damping ratio of the
    translation along each direction of the arm's own inertia (0: the fixed
    d instead; the TCP's inertia differs tenfold between directions, and a
    fixed d left the heavy one ringing at 1-2 Hz with zeta 0.15); ki: integral
    gain [N/(m s), N m/(rad s)]; i_max: bound on the integral force [N, N m];
    k_null: posture stiffness in the Jacobian's null space [N m/rad] (7);
    d_joint: joint damping [N m s/rad] (7).
    """

    k: list[float] = field(
        default_factory=lambda: _six(300, 300, 300, 8, 8, 8), metadata={"len": 6, "ge": 0}
    )
    d: list[float] = field(
        default_factory=lambda: _six(10, 10, 10, 0.05, 0.05, 0.05), metadata={"len": 6, "ge": 0}
    )
    ki: list[float] = field(
        default_factory=lambda: _six(300, 300, 300, 20, 20, 20), metadata={"len": 6, "ge": 0}
    )
    i_max: list[float] = field(
        default_factory=lambda: _six(10, 10, 10, 2, 2, 2), metadata={"len": 6, "ge": 0}
    )
    zeta: float = field(default=0.5, metadata={"ge": 0, "le": 2})
    k_null: list[float] = field(
        default_factory=lambda: _seven(10, 10, 10, 10, 1, 1, 0.5), metadata={"len": 7, "ge": 0}
    )
    d_joint: list[float] = field(
        default_factory=lambda: _seven(2, 2, 1, 1, 0.05, 0.05, 0.02), metadata={"len": 7, "ge": 0}
    )


@dataclass(frozen=True)
class ForceControlConfig:
    """Force-controlled axes: admittance k_adm [m/(N s)] and k_adm_rot
    [rad/(N m s)] move the reference; v_max [m/s] and w_max [rad/s] bound its
    speed (the approach speed in free space), a_max [m/s^2] and alpha_max
    [rad/s^2] its acceleration; contact_n: force that means contact [N];
    ramp_s: time to feed the goal wrench in after contact [s]."""

    k_adm: float = field(default=0.002, metadata={"gt": 0, "le": 1})
    k_adm_rot: float = field(default=0.05, metadata={"gt": 0, "le": 10})
    v_max: float = field(default=0.01, metadata={"gt": 0, "le": 0.2})
    w_max: float = field(default=0.05, metadata={"gt": 0, "le": 1})
    a_max: float = field(default=0.02, metadata={"gt": 0, "le": 10})
    alpha_max: float = field(default=0.1, metadata={"gt": 0, "le": 100})
    contact_n: float = field(default=3.0, metadata={"gt": 0, "le": 100})
    ramp_s: float = field(default=0.1, metadata={"gt": 0, "le": 10})


@dataclass(frozen=True)
class SscConfig:
    """The Strategy-Stage Controller of the robot group.

    rate_hz: cycle rate [Hz] (paper: 200); heartbeat_limit_cycles: missed
    heartbeats that make a worker hung; cpus: CPUs for its processes;
    impedance, force: the Cartesian control laws; pid: joint PID of joint
    segments and of robots that hold their pose (defaults: the ESC's);
    parallel_arms: each robot's law in a worker of its own, all of them in
    one stage that runs in parallel, the task's clock in a worker after
    them (paper 000's parallel stages; ``redistro bench group`` measures
    whether it pays: docs/PERFORMANCE.md).
    """

    rate_hz: float = field(default=200.0, metadata={"gt": 0, "le": 10000})
    heartbeat_limit_cycles: int = field(default=25, metadata={"ge": 2, "le": 100000})
    cpus: list[int] = field(default_factory=list, metadata={"ge": 0})
    parallel_arms: bool = False
    impedance: ImpedanceConfig = field(default_factory=ImpedanceConfig)
    force: ForceControlConfig = field(default_factory=ForceControlConfig)
    pid: PidConfig = field(default_factory=PidConfig)


@dataclass(frozen=True)
class ZenohTlsConfig:
    """TLS for zenoh's ``tls/HOST:PORT`` endpoints: every file PEM, a file
    of this user (the key mode 0600).

    ca_file: the certificate authority every node's certificate is checked
        against (the group's own CA; no system roots).
    cert_file, key_file: this node's certificate (signed by that CA) and
        its private key: presented when listening and, with ``mtls``, when
        connecting.
    mtls: the listening side asks every connecting node for its
        certificate and refuses a connection without one from the CA.
    verify_name: a connecting node checks that the listening node's
        certificate names the host it connects to.
    """

    ca_file: str = ""
    cert_file: str = ""
    key_file: str = ""
    mtls: bool = True
    verify_name: bool = True


@dataclass(frozen=True)
class ZenohConfig:
    """The DDM over Eclipse Zenoh (``ddm.transport: zenoh``).

    group: the robot group's name in the key expressions
        (``redistro/<group>/<robot>/command``, ``.../feedback``); empty: the
        link id (a session's id; ``redistro node --link``).
    mode: the ESCs' sessions: ``client`` (through the SSC's session, which
        is a peer and routes for the group's clients and its viewers) or
        ``peer``.
    listen, connect: zenoh endpoints (``tcp/host:port``, ``tls/host:port``).
        Both empty (the default): the SSC's ddm listens on
        ``tcp/<ddm.listen_host>:<port>`` (``tls/...`` when ``tls`` names a
        certificate) and each ESC's ddm connects to ``tcp/127.0.0.1:<port>``
        (on other hosts: the SSC's host in ``connect``).
    port: that port (0: derived from the group).
    scouting: multicast scouting (off: only the endpoints above).
    users_file: user/password lines (``name:password``, a file of this user,
        mode 0600) that authenticate every node's session; each node's user
        is ``<node>@<group>`` (``esc.r1@lab1``). Empty: a session makes one
        in its runtime folder; nodes started alone need this file, the same
        on every host.
    access_control: every node's session refuses what its peers may not
        send: the SSC takes only each ESC's own robot's feedback, an ESC
        only its robot's commands from its group's SSC.
    tls: certificates for ``tls/`` endpoints (:class:`ZenohTlsConfig`).
    """

    group: str = ""
    mode: Literal["peer", "client"] = "client"
    listen: list[str] = field(default_factory=list)
    connect: list[str] = field(default_factory=list)
    port: int = field(default=0, metadata={"ge": 0, "le": 65535})
    scouting: bool = False
    users_file: str = ""
    access_control: bool = True
    tls: ZenohTlsConfig = field(default_factory=ZenohTlsConfig)


@dataclass(frozen=True)
class DdmConfig:
    """The Distributed Data Managers: how nodes exchange Robot Group Shared Data.

    transport: ``socket`` (TCP send/receive/reply: the SSC's ddm connects to
        each ESC's ddm), ``reflective`` (simulated reflective memory: a
        SysV memory card per node, writes broadcast by UDP multicast) or
        ``zenoh`` (Eclipse Zenoh pub/sub, :class:`ZenohConfig`).
    rate_hz: 0 (the default): each ddm moves data when there is data (woken
        by its transport, its node's producer, its manager's e-stop; at
        least once a node period); > 0: it polls on a timer of its own at
        this rate [Hz] instead (paper: 1000), for comparison.
    starving_limit_cycles: an ESC whose sender has sent this many commands
        since the last fresh one ends ``starving`` (the SSC likewise, counted
        in its own cycles without fresh feedback from a robot).
    connect_timeout_s: how long a node waits for its peer's first record.
    listen_host: where an ESC's ddm listens (socket transport).
    esc_hosts, esc_ports: per robot, where the SSC finds that ESC's ddm;
        port 0: derived from the session id, or from the link id of nodes
        started alone (``redistro node --link``).
    group, port: the reflective network's multicast group and UDP port
        (0: derived like the ESC ports); peers: host:port of nodes on other
        hosts that also get every write.
    key_file: the link's key (hex, a file of this user, mode 0600) that
        authenticates every record (HMAC-SHA256). Empty: a session makes a
        fresh key in its runtime directory; nodes started alone
        (``redistro node``) need this file, the same on every node.
    zenoh: the zenoh transport's settings.
    encrypt: every command's and feedback's payload encrypted (ChaCha20 with
        a key derived from the run's key; the record's tag covers the
        ciphertext): what multicast on loopback or a network shows of the
        robots' state is then only its headers. The records then take the
        ddm's Python path, not the compiled one (docs/PERFORMANCE.md
        gives the cost per record).
    """

    transport: Literal["socket", "reflective", "zenoh"] = "socket"
    rate_hz: float = field(default=0.0, metadata={"ge": 0, "le": 10000})
    starving_limit_cycles: int = field(default=40, metadata={"ge": 2, "le": 100000})
    connect_timeout_s: float = field(default=30.0, metadata={"gt": 0, "le": 3600})
    listen_host: str = "127.0.0.1"
    esc_hosts: dict[str, str] = field(default_factory=dict)
    esc_ports: dict[str, int] = field(default_factory=dict, metadata={"ge": 0, "le": 65535})
    group: str = "239.255.68.68"
    port: int = field(default=0, metadata={"ge": 0, "le": 65535})
    peers: list[str] = field(default_factory=list)
    key_file: str = ""
    zenoh: ZenohConfig = field(default_factory=ZenohConfig)
    encrypt: bool = False


@dataclass(frozen=True)
class RobotConfig:
    """One robot of the group: its hardware files and where it stands.

    io: I/O interface config (boards, channel map), a YAML file; relative paths
        are taken from the main config file's folder (``config/`` by default).
    sensors: sensor/actuator config (gears, motor constants, scalings), a YAML file.
    base_xyz_m: the base position in the world frame [m]; the base is not rotated.
    initial_q_rad: joint angles at power-on [rad], shape (7,).
    peg: whether the peg is fixed to this robot's flange.
    """

    io: str = ""
    sensors: str = ""
    base_xyz_m: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0], metadata={"len": 3})
    initial_q_rad: list[float] = field(
        default_factory=lambda: [0.0, 0.5, 0.0, -1.2, 0.0, 1.0, 0.0], metadata={"len": 7}
    )
    peg: bool = False


def _default_robots() -> dict[str, RobotConfig]:
    return {
        "r1": RobotConfig(
            io="robots/r1.io.yaml", sensors="robots/r1.sensors.yaml", base_xyz_m=[0.0, 0.45, 0.0]
        ),
        "r2": RobotConfig(
            io="robots/r2.io.yaml",
            sensors="robots/r2.sensors.yaml",
            base_xyz_m=[0.0, -0.45, 0.0],
            peg=True,
        ),
    }


@dataclass(frozen=True)
class HoleConfig:
    """The hole fixture on the table, as drawn: what the controller believes.

    xyz_m: nominal centre of the hole's mouth (top face of the fixture),
        world frame [m]; the hole's axis is the world's z.
    clearance_m: the hole's side is the peg's side plus this [m].
    depth_m, wall_m: the hole's depth and the fixture's wall [m].
    """

    xyz_m: list[float] = field(default_factory=lambda: [0.55, -0.35, 0.15], metadata={"len": 3})
    clearance_m: float = field(default=0.001, metadata={"gt": 0, "le": 0.001})
    depth_m: float = field(default=0.04, metadata={"ge": 0.03, "le": 0.2})
    wall_m: float = field(default=0.03, metadata={"gt": 0, "le": 0.2})


@dataclass(frozen=True)
class HoleTruth:
    """Where the plant's hole really is: the drawn pose (``workcell.hole``)
    moved by a fixed offset and, when ``offset_radius_m`` or ``yaw_range_deg``
    is above 0, by a random one drawn from ``seed``. The controller never
    sees it.

    offset_xyz_m: fixed offset of the mouth's centre [m];
    yaw_deg: fixed rotation about the hole's axis [deg];
    tilt_xy_deg: fixed tilt of the fixture about the world's x and y [deg];
    offset_radius_m: a random lateral offset, uniform over the disc of this
        radius [m] (over the ring outside ``offset_min_radius_m``, when set);
    yaw_range_deg: a random yaw, uniform within plus or minus this [deg];
    seed: the seed of both draws.
    """

    offset_xyz_m: list[float] = field(
        default_factory=lambda: [0.0, 0.0, 0.0], metadata={"len": 3, "ge": -0.02, "le": 0.02}
    )
    yaw_deg: float = field(default=0.0, metadata={"ge": -10, "le": 10})
    tilt_xy_deg: list[float] = field(
        default_factory=lambda: [0.0, 0.0], metadata={"len": 2, "ge": -3, "le": 3}
    )
    offset_radius_m: float = field(default=0.0, metadata={"ge": 0, "le": 0.02})
    offset_min_radius_m: float = field(default=0.0, metadata={"ge": 0, "le": 0.02})
    yaw_range_deg: float = field(default=0.0, metadata={"ge": 0, "le": 10})
    seed: int = field(default=0, metadata={"ge": 0, "le": 2**32 - 1})


@dataclass(frozen=True)
class PegConfig:
    """The square peg fixed to a flange: side [m], length [m], mass [kg]."""

    side_m: float = field(default=0.02, metadata={"gt": 0.002, "le": 0.1})
    length_m: float = field(default=0.1, metadata={"gt": 0.01, "le": 0.5})
    mass_kg: float = field(default=0.1, metadata={"gt": 0, "le": 5})


@dataclass(frozen=True)
class ObjectConfig:
    """An object on the table, as drawn: a box resting on the table top
    (the table's, as ``workcell.hole`` draws it), what a gripper picks up.

    size_xyz_m: its edges along its own x, y and z [m];
    xy_m: its centre on the table, world [m]; yaw_deg: about the world's z;
    mass_kg: its mass;
    hole_side_m, hole_depth_m, hole_at_xy_m: a square hole in its top face
    (0: none), its depth, and its centre on the top face in the object's
    own x and y [m] (what a peg goes into when a hand holds the object).
    """

    size_xyz_m: list[float] = field(metadata={"len": 3, "gt": 0.005, "le": 0.6})
    xy_m: list[float] = field(metadata={"len": 2, "ge": -2, "le": 2})
    yaw_deg: float = field(default=0.0, metadata={"ge": -180, "le": 180})
    mass_kg: float = field(default=0.2, metadata={"gt": 0, "le": 5})
    hole_side_m: float = field(default=0.0, metadata={"ge": 0, "le": 0.2})
    hole_depth_m: float = field(default=0.0, metadata={"ge": 0, "le": 0.5})
    hole_at_xy_m: list[float] = field(
        default_factory=lambda: [0.0, 0.0], metadata={"len": 2, "ge": -0.3, "le": 0.3}
    )

    def hole_problem(self) -> str:
        """Why the hole cannot be made in this box ('' when it can): walls
        and floor of at least OBJECT_WALL_M around and under it."""
        side, depth = self.hole_side_m, self.hole_depth_m
        if side == 0:
            return "hole_depth_m without hole_side_m" if depth else ""
        for i, axis in enumerate("xy"):
            room = self.size_xyz_m[i] / 2 - abs(self.hole_at_xy_m[i]) - side / 2
            if room < OBJECT_WALL_M:
                return (
                    f"the hole's wall along {axis} is {room * 1e3:.1f} mm, at least "
                    f"{OBJECT_WALL_M * 1e3:.0f} mm (size_xyz_m, hole_at_xy_m, hole_side_m)"
                )
        if not 0 < depth <= self.size_xyz_m[2] - OBJECT_WALL_M:
            return (
                f"hole_depth_m {depth} m: more than 0 and at most the height less "
                f"{OBJECT_WALL_M * 1e3:.0f} mm of floor"
            )
        return ""


@dataclass(frozen=True)
class ObjectTruth:
    """Where the plant really puts an object of ``workcell.objects``: its
    drawn place moved by ``offset_xy_m`` [m] and turned by ``yaw_deg``."""

    offset_xy_m: list[float] = field(
        default_factory=lambda: [0.0, 0.0], metadata={"len": 2, "ge": -0.02, "le": 0.02}
    )
    yaw_deg: float = field(default=0.0, metadata={"ge": -10, "le": 10})


OBJECT_WALL_M = 0.003  # the thinnest wall or floor around a hole in an object

# The work-cell's drawing around the hole (both the controller's belief,
# from workcell.hole, and the plant's build, where plant.hole moves it)
FIXTURE_FLOOR_M = 0.01  # thickness of the fixture below the hole
TABLE_HALF_XY_M = (0.3, 0.6)  # the table's half extents; centred at (hole x, 0)
# the arms' clearance (ssc/clearance.py): at load, every planned sample at
# least this far; in each cycle, closer than the trip is the group's e-stop
MIN_CLEARANCE_M = 0.03
TRIP_M = 0.01


def table_top_m(hole: HoleConfig, dz_m: float = 0.0) -> float:
    """The table's top [m, world z]: under the fixture of ``hole`` (moved up
    by ``dz_m``: the plant's truth)."""
    return float(hole.xyz_m[2]) + dz_m - hole.depth_m - FIXTURE_FLOOR_M


@dataclass(frozen=True)
class WorkcellConfig:
    """The work-cell as the controller knows it (the paper's Work-cell
    Configuration): the hole fixture as drawn, the tool on the flange and
    the objects on the table (``objects``, by name).
    The robots' base poses are ``robots.<name>.base_xyz_m``. The plant builds
    the same work-cell, with the hole where ``plant.hole`` moves it."""

    hole: HoleConfig = field(default_factory=HoleConfig)
    peg: PegConfig = field(default_factory=PegConfig)
    objects: dict[str, ObjectConfig] = field(default_factory=dict)


@dataclass(frozen=True)
class CanConfig:
    """The CAN backplane. interface: python-can interface; channel: its channel
    ('' picks the interface's default: a multicast group for udp_multicast,
    can0 for socketcan, a session-derived name for virtual)."""

    interface: Literal["virtual", "udp_multicast", "socketcan"] = "udp_multicast"
    channel: str = ""
    port: int = field(default=0, metadata={"ge": 0, "le": 65535})  # udp_multicast; 0: per session
    loopback_only: bool = True  # udp_multicast: join the group and send on loopback only


@dataclass(frozen=True)
class PlantConfig:
    """The simulated plant and its I/O chassis.

    backplane: how drivers reach the boards: ``shm`` (shared-memory register
        bank) or ``can`` (the same registers in CAN FD frames).
    physics_hz: physics steps per second, paced to the wall clock.
    real_time_factor: the pace: 1 is real time, 0.1 slow motion (ten wall
        seconds per simulated second: to watch, or to try the controller
        against a plant as slow as a loaded host makes it).
    io_timeout_ms: bound on every backplane send and receive; a board that has
        not answered (CAN) or not updated (shm) within it is an I/O fault.
    output_watchdog_ms: the amplifiers' watchdog: a robot whose DAC boards
        have not been written for this long (their watchdog register has not
        moved) is put in its safe state by the chassis: every DAC channel at
        zero, every brake on, until the controller writes again. 0: off.
    encoder_disturbance_rad: per robot, the error of the encoder counters at
        power-on (the arm was moved while powered off) [rad], shape (7,).
    ft_noise_n, ft_noise_nm: standard deviation of the wrist sensor noise.
    ft_bandwidth_hz: the wrist sensor's bandwidth: a first-order low-pass
        on the wrench it reads, stepped with the physics (0: none, every
        physics step's reaction as it is).
    ft_bias: per robot, the wrist sensor's bias [N, N, N, N m, N m, N m].
    seed: seed of the plant's noise.
    hole: where the hole really is (:class:`HoleTruth`).
    objects: where each object of ``workcell.objects`` really is
        (:class:`ObjectTruth`; one not named here: as drawn).

    The plant's section is the simulated world's truth, apart from what the
    I/O boards' datasheet tells a driver (``CONTROLLER_KEYS``): controller
    nodes get a config without the rest (:func:`controller_view`).
    """

    backplane: Literal["shm", "can"] = "shm"
    can: CanConfig = field(default_factory=CanConfig)
    physics_hz: float = field(default=1000.0, metadata={"ge": 100, "le": 10000})
    real_time_factor: float = field(default=1.0, metadata={"gt": 0, "le": 1})
    gui: bool = False
    # 500 ms: beside a whole robot group on a 2-vCPU VM the (non-real-time)
    # simulated plant was seen not to step for 250-330 ms at times
    io_timeout_ms: float = field(default=500.0, metadata={"gt": 0, "le": 10000})
    # 100 ms: 20 cycles at 200 Hz; a sender is seen held off up to ~35 ms
    output_watchdog_ms: float = field(default=100.0, metadata={"ge": 0, "le": 10000})
    hole: HoleTruth = field(default_factory=HoleTruth)
    objects: dict[str, ObjectTruth] = field(default_factory=dict)
    # within the self-calibration's reach (its sweep finds a home switch up
    # to 12 degrees away): an arm moved further while powered off is a
    # rebuild, not a disturbance
    encoder_disturbance_rad: dict[str, list[float]] = field(
        default_factory=lambda: {
            "r1": [0.031, -0.022, 0.045, -0.013, 0.027, -0.038, 0.019],
            "r2": [-0.024, 0.036, -0.017, 0.041, -0.029, 0.012, -0.033],
        },
        metadata={"len": 7, "ge": -0.2, "le": 0.2},
    )
    # bounded well inside the guard's wrist limits: noise that alone trips
    # the guard is a broken sensor, not one to control with
    ft_noise_n: float = field(default=0.05, metadata={"ge": 0, "le": 10})
    ft_noise_nm: float = field(default=0.005, metadata={"ge": 0, "le": 1})
    # 100 Hz: an impact the rigid physics resolves in one 1 ms step is read
    # at about half its height; the force loop's 200 Hz sees 1.6 ms of lag
    ft_bandwidth_hz: float = field(default=100.0, metadata={"ge": 0, "le": 100000})
    ft_bias: dict[str, list[float]] = field(
        default_factory=dict, metadata={"len": 6, "ge": -100, "le": 100}
    )
    seed: int = field(default=0, metadata={"ge": 0, "le": 2**32 - 1})
    # The arms' pose kept while powered off (JSON, per robot, rad): read at
    # power-on, written at power-off. Empty: start at initial_q_rad each time.
    pose_file: str = ""


@dataclass(frozen=True)
class LogConfig:
    """The session log's recorders: the SSC's logger and the ESC recorder.

    heartbeat_limit_cycles: missed heartbeats that make a recorder hung. They
        run at the lowest real-time priority, and a loaded host starves them
        for a while (a CI host: over 25 cycles at 200 Hz, which ended a peg
        insertion); they drop and count the cycles they miss. A starved
        recorder is no fault, a hung one is, after this many of its node's
        cycles (1 s at 200 Hz).
    heartbeat_limit_s: ... and never fewer cycles than this long at the
        node's rate (1 s: 1 000 cycles at 1 kHz, what the log ring holds,
        1 024 cycles; at 1 kHz a recorder held off 200 ms had ended a
        session ``abnormal`` with nothing lost).
    drain_hz: how often a recorder drains the log ring, off the cycle on its
        own timer (the manager captures every cycle into the ring at its
        tick; nothing in the cycle waits for a recorder). At 50 Hz a drain
        takes 4 cycles at 200 Hz, 20 at 1 kHz; at the bounds (20 Hz, a
        10 kHz node) 500, half of what the ring holds.
    """

    heartbeat_limit_cycles: int = field(default=200, metadata={"ge": 2, "le": 100000})
    heartbeat_limit_s: float = field(default=1.0, metadata={"ge": 0, "le": 60})
    drain_hz: float = field(default=50.0, metadata={"ge": 20, "le": 1000})


@dataclass(frozen=True)
class Ros2Config:
    """The running group's data as ROS 2 topics over Zenoh (``redistro bridge``).

    bridge: ``redistro session`` starts the bridge beside the nodes.
    listen: the bridge's zenoh endpoints, where a ROS 2 machine's zenoh
        router (rmw_zenoh's ``zenohd``) or a client connects (7447: the
        port rmw_zenoh's router listens on by default).
    rate_hz: how often it publishes at most (it reads the nodes' Local Data
        from outside, off every cycle).
    domain_id: the ROS domain in the key expressions (``ROS_DOMAIN_ID``).
    """

    bridge: bool = False
    listen: list[str] = field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    rate_hz: float = field(default=50.0, metadata={"gt": 0, "le": 100})
    domain_id: int = field(default=0, metadata={"ge": 0, "le": 232})


@dataclass(frozen=True)
class Config:
    """The whole config. Sections are added as capabilities land."""

    session: SessionConfig = field(default_factory=SessionConfig)
    scheduling: SchedulingConfig = field(default_factory=SchedulingConfig)
    # 100 cycles at 1 kHz: host stalls of one vCPU up to ~22 ms were measured here.
    bench: NodeConfig = field(
        default_factory=lambda: NodeConfig(rate_hz=1000.0, heartbeat_limit_cycles=100)
    )
    robots: dict[str, RobotConfig] = field(default_factory=_default_robots)
    workcell: WorkcellConfig = field(default_factory=WorkcellConfig)
    plant: PlantConfig = field(default_factory=PlantConfig)
    esc: EscConfig = field(default_factory=EscConfig)
    ssc: SscConfig = field(default_factory=SscConfig)
    ddm: DdmConfig = field(default_factory=DdmConfig)
    log: LogConfig = field(default_factory=LogConfig)
    ros2: Ros2Config = field(default_factory=Ros2Config)
    # The file this config was read from (relative hardware paths start from
    # its folder); set by the loader, never read from YAML.
    source: str = field(default="config/redistro.yaml", compare=False, metadata={"internal": True})
    # The dotted keys set by --set overrides; set by the loader.
    overridden: tuple[str, ...] = field(default=(), compare=False, metadata={"internal": True})

    def origin(self, dotted: str) -> str:
        """Where a value came from: ``--set`` when an override set it (or a
        section above it), else the config file."""
        for key in self.overridden:
            if dotted == key or dotted.startswith(key + ".") or dotted.startswith(key + "["):
                return "--set"
        return self.source


# What a controller node may know of the plant's section: what the I/O
# boards' datasheet tells its driver (how the boards are reached, their
# sample rate, their time-outs). The rest is the simulated world's truth.
CONTROLLER_KEYS = ("backplane", "can", "physics_hz", "io_timeout_ms", "output_watchdog_ms")


def controller_view(cfg: Config) -> Config:
    """The config a controller node (an ESC, the SSC, their ddms) is given:
    the plant's section cut to :data:`CONTROLLER_KEYS`, everything else in it
    empty (no hole offset, no encoder disturbance, no sensor bias or noise).
    What the controller knows of the work-cell is ``workcell`` and
    ``robots``; what it learns of the plant comes through its sensors."""
    keep = {k: getattr(cfg.plant, k) for k in CONTROLLER_KEYS}
    empty = PlantConfig(
        **keep,
        hole=HoleTruth(),
        encoder_disturbance_rad={},
        ft_noise_n=0.0,
        ft_noise_nm=0.0,
        ft_bandwidth_hz=0.0,
        ft_bias={},
        seed=0,
    )
    return dataclasses.replace(cfg, plant=empty)
