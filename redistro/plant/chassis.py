"""The simulated I/O chassis: boards wired to the arms' devices.

Each step: take the controller's ``out`` banks (DAC codes, brake bits,
encoder presets and latch requests), drive the motors and brakes, step the
world, then convert the new joint states into the ``in`` banks (counters,
home bits and latches, ADC codes, wrist gauges). Wiring comes from the I/O
interface configs; device constants from the sensor/actuator configs.

Layout for speed: every board's registers live in one byte buffer, the
*image* (per board type, one structured array with a row per board); every
joint of every robot in one vector; every kind of wire (the encoder axis,
DAC channel, home bit ... of each joint) is a pair of index arrays (board
row, channel) and a table of byte offsets, built once. A step is then two
calls of a compiled kernel (:mod:`redistro.kernels`: outputs -> joints,
joints -> boards) around PyBullet's own calls; only what rarely happens (an
encoder preset, a latch, a brake change, the amplifiers' watchdog) takes a
Python path. The same arithmetic is kept in numpy (``kernels=False``): the
reference the kernels are tested against.

Past the house's ~400 lines: every board's simulation, vectorised over the
banks, and its numpy reference, in one register image.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from redistro import kernels
from redistro.config.hardware import RobotHardware, SensorsConfig
from redistro.config.model import Config
from redistro.drivers.io import registers as R
from redistro.drivers.io.bank import TRUTH
from redistro.drivers.io.image import RegisterImage
from redistro.drivers.io.registers import BOARD_NAMES, BoardType
from redistro.plant import chassis_layout
from redistro.plant.chassis_plans import plan_kernels, truth_table
from redistro.plant.chassis_reference import apply_numpy, sample_numpy
from redistro.plant.devices import Encoders, HomeSwitches, Motors, WristSensors
from redistro.plant.disturbance import Disturbance
from redistro.plant.grippers import Grippers
from redistro.plant.watchdog import AmplifierWatchdog
from redistro.plant.world import Arm, World

DOF = 7
_AMPS_PER_CODE = R.DAC_FULL_SCALE_V / 2048  # volts per DAC code
_ADC_CODES_PER_V = 32768 / R.ADC_FULL_SCALE_V
count = np.count_nonzero  # on the hot path: a third of what ndarray.any() costs
HOME_AS_SWITCH, HOME_STUCK_OFF, HOME_STUCK_ON = 0, 1, 2
# the wires each joint has, by kind (fields of the hardware's joint wiring)
WIRE_KINDS = ("encoder", "dac", "home", "brake", "torque", "tach")


@dataclass(frozen=True)
class Wires:
    """One kind of channel of every joint wired to it, in joint order: the
    joint (index in the chassis' joint vector), and where the wire lands
    (the board's row in its type's array, the channel on the board)."""

    joints: np.ndarray
    rows: np.ndarray
    ch: np.ndarray


def _wires(parts: list[tuple[int, ...]]) -> Wires:
    a = np.array(parts, dtype=np.int64).reshape(-1, 3)
    return Wires(a[:, 0].copy(), a[:, 1].copy(), a[:, 2].copy())


@dataclass
class RobotRig:
    """One robot's place in the chassis: its arm, its slice of the joint vector
    (``q``, ``qd``, ``tau`` ... are views), its wrist sensor."""

    name: str
    arm: Arm
    hw: RobotHardware
    sl: slice
    q: np.ndarray
    qd: np.ndarray
    tau: np.ndarray
    home: np.ndarray  # the levels on the home inputs' wires (view)
    switch: np.ndarray  # the home switches' own state (view; a fault may force the wires)
    encoder_offset: np.ndarray  # counter reading at q = 0, before wrap (view)
    counts_per_rad: np.ndarray
    brake_torque_nm: np.ndarray
    wrist: bool  # it has a wrist sensor
    ft_row: int = -1  # the wrist receiver's row among the force boards
    wrench: np.ndarray = field(default_factory=lambda: np.zeros(6))
    tool_xyz: np.ndarray = field(default_factory=lambda: np.zeros(3))
    tool_rot: np.ndarray = field(default_factory=lambda: np.eye(3))


# The register fields each step reads or writes, by board type and bank
# (views made once: a field lookup per step costs as much as the operation).
REGISTERS: tuple[tuple[str, BoardType, str, str], ...] = (
    ("enc_counter", BoardType.ENCODER, "in", "counter"),
    ("enc_home", BoardType.ENCODER, "in", "home"),
    ("enc_latch", BoardType.ENCODER, "in", "latch"),
    ("enc_latch_count", BoardType.ENCODER, "in", "latch_count"),
    ("enc_latch_edge", BoardType.ENCODER, "in", "latch_edge"),
    ("enc_preset_ack", BoardType.ENCODER, "in", "preset_ack"),
    ("enc_preset_value", BoardType.ENCODER, "out", "preset_value"),
    ("enc_latch_mode", BoardType.ENCODER, "out", "latch_mode"),
    ("dac_code", BoardType.DAC, "out", "code"),
    ("dac_watchdog", BoardType.DAC, "out", "watchdog"),
    ("dac_readback", BoardType.DAC, "in", "readback"),
    ("dio_outputs", BoardType.DIO, "out", "outputs"),
    ("dio_readback", BoardType.DIO, "in", "outputs_readback"),
    ("dio_inputs", BoardType.DIO, "in", "inputs"),
    ("adc_code", BoardType.ADC, "in", "code"),
    ("ft_strain", BoardType.FORCE, "in", "strain"),
    ("ft_sample", BoardType.FORCE, "in", "sample"),
    ("ft_calibration", BoardType.FORCE, "in", "calibration"),
)


class Registers:
    """The chassis' view of its boards' registers (REGISTERS), and the
    encoder boards' request words: preset_req and latch_req lie side by
    side, one (boards, 8) view of both, with the requests last seen."""

    enc_counter: np.ndarray
    enc_home: np.ndarray
    enc_latch: np.ndarray
    enc_latch_count: np.ndarray
    enc_latch_edge: np.ndarray
    enc_preset_ack: np.ndarray
    enc_preset_value: np.ndarray
    enc_latch_mode: np.ndarray
    dac_code: np.ndarray
    dac_watchdog: np.ndarray
    dac_readback: np.ndarray
    dio_outputs: np.ndarray
    dio_readback: np.ndarray
    dio_inputs: np.ndarray
    adc_code: np.ndarray
    ft_strain: np.ndarray
    ft_sample: np.ndarray
    ft_calibration: np.ndarray

    def __init__(self, banks: RegisterImage) -> None:
        for attr, board, side, name in REGISTERS:
            setattr(self, attr, (banks.inp if side == "in" else banks.out)[board][name])
        o_enc = banks.out[BoardType.ENCODER]
        fields = o_enc.dtype.fields
        assert fields is not None
        off = int(fields["preset_req"][1])
        assert int(fields["latch_req"][1]) == off + 4 * R.ENC_AXES
        self.enc_requests = np.ndarray(
            (len(o_enc), 2 * R.ENC_AXES),
            dtype="<u4",
            buffer=banks.image,
            offset=banks.base[(BoardType.ENCODER, "out")] + off,
            strides=(o_enc.dtype.itemsize, 4),
        )
        self.requests_seen = np.zeros(self.enc_requests.shape, dtype="<u4")
        self.req_changed = np.zeros(self.enc_requests.shape, dtype=bool)
        self.steps_in = [banks.inp[t]["step"] for t in banks.inp if len(banks.inp[t])]


class Chassis:
    """The simulated I/O chassis (see the module's text)."""

    wrists: WristSensors
    ft_rows: np.ndarray
    _wrist_rigs: list[tuple[RobotRig, int]]
    _rot9: list[np.ndarray]
    _strain: np.ndarray

    def __init__(
        self,
        cfg: Config,
        world: World,
        hardware: dict[str, RobotHardware],
        *,
        use_kernels: bool | None = None,
        disturbance: Disturbance | None = None,
    ) -> None:
        """use_kernels: the compiled kernels (default: when built), or the numpy
        reference (False); disturbance: what acts on the plant from outside
        (:mod:`redistro.plant.disturbance`; none normally)."""
        self.world = world
        self.kernels = kernels.AVAILABLE if use_kernels is None else use_kernels
        self.disturbance = disturbance
        names = list(hardware)
        self.n = n = DOF * len(names)
        wrists = self._boards(cfg, hardware, names)
        self._state(n, len(wrists), [hardware[r].sensors for r in names])
        wires = self._robots(hardware, names, world)
        fit_wrist_sensors(self, cfg, wrists)
        self._wiring(wires, [hardware[r].sensors for r in names])
        self.reg = Registers(self.banks)
        self.grippers = Grippers(self.rigs, hardware, self.banks.row, world)
        self._step_buffers(cfg)
        plans: tuple[Any, Any, Any] = plan_kernels(self) if self.kernels else (None, None, None)
        self._apply_plan, self._sample_plan, self._truth_plan = plans
        for rig in self.rigs:  # brakes on at power-up: the arms hold until released
            world.set_brakes(rig.arm, np.ones(DOF, dtype=bool), rig.brake_torque_nm)
        self.sample()

    def _boards(
        self, cfg: Config, hardware: dict[str, RobotHardware], names: list[str]
    ) -> list[tuple[int, int, Any, str]]:
        """The boards' register image, the joints' devices; the wrists:
        (robot, force board row, calibration, name) each."""
        self.boards: dict[int, BoardType] = {}
        for hw in hardware.values():
            for b in hw.io.boards.values():
                self.boards[b.address] = BOARD_NAMES[b.type]
        self.banks = banks = RegisterImage(self.boards)
        self.image = banks.image
        self.inp = banks.rec_in  # address -> the board's in bank (0-d record)
        sensors = [hardware[r].sensors for r in names]
        q0 = np.concatenate(
            [np.asarray(cfg.robots[r].initial_q_rad, dtype=np.float64) for r in names]
        )
        enc_disturbance = np.concatenate(
            [np.asarray(cfg.plant.encoder_disturbance_rad.get(r, [0.0] * DOF)) for r in names]
        )
        self.motors = Motors(sensors)
        self.encoders = Encoders(sensors, q0, enc_disturbance)
        self.homes = HomeSwitches(sensors)
        wrists: list[tuple[int, int, Any, str]] = []  # robot, force board row, calibration
        for i, name in enumerate(names):
            w = hardware[name].wrist
            if w is not None:
                wrists.append(
                    (i, banks.row[w.address], hardware[name].sensors.ft_calibration, name)
                )
        return wrists

    def _state(self, n: int, n_wrists: int, sensors: list[SensorsConfig]) -> None:
        """The chassis' state: one buffer (the truth is copied out of it in one call)."""
        st = self.state = kernels.Arena(64 * n + 1024 + 160 * n_wrists)
        self.step_rec = st.take("step", chassis_layout.STEP, ())  # the plant's step
        # the step as a Python int, written through to the record per step
        # (an in-place add on a 0-d field costs numpy's ufunc machinery)
        self.steps = 0
        self.step_word = self.step_rec["step"].reshape(1)
        self.q = st.take("q", np.float64, n)
        self.qd = st.take("qd", np.float64, n)
        self.tau = st.take("tau", np.float64, n)  # at the joint: motor, or brake on a braked joint
        self.applied = st.take("applied", np.float64, n)  # PyBullet's applied torque (a brake's)
        self.motor_tau = st.take("motor_tau", np.float64, n)
        self.counts = st.take("counts", np.int64, n)
        enc_offset = st.take("enc_offset", np.int64, n)
        enc_offset[...] = self.encoders.offset
        self.encoders.offset = enc_offset
        self.braked = st.take("braked", np.bool_, n)
        self.braked[...] = True
        self.held = st.take("held", np.bool_, n)
        switch = st.take("switch", np.bool_, n)
        switch[...] = self.homes.state
        self.homes.state = switch
        self.home = st.take("home", np.bool_, n)  # the levels on the wires (faults may force them)
        self.wrenches = st.take("wrenches", np.float64, (n_wrists, 6))
        self.tool_xyz = st.take("tool_xyz", np.float64, (n_wrists, 3))
        self.tool_rot = st.take("tool_rot", np.float64, (n_wrists, 3, 3))
        self.brake_torque_nm = np.concatenate(
            [np.asarray(s.brake_torque_nm, dtype=np.float64) for s in sensors]
        )
        self._last_home = np.zeros(n, dtype=bool)
        self._home_force = np.zeros(n, dtype=np.uint8)  # HOME_AS_SWITCH, or a stuck switch

    def _robots(
        self, hardware: dict[str, RobotHardware], names: list[str], world: World
    ) -> dict[str, list[tuple[int, ...]]]:
        """Each robot's rig (its arm's state in the chassis' vectors), and
        every joint's wires of each kind (WIRE_KINDS), in joint order."""
        banks = self.banks
        wires: dict[str, list[tuple[int, ...]]] = {kind: [] for kind in WIRE_KINDS}
        self.rigs: list[RobotRig] = []
        for i, name in enumerate(names):
            hw = hardware[name]
            sl = slice(DOF * i, DOF * (i + 1))
            arm = world.arms[name]
            # the world's arm state lives in the chassis' vectors (views)
            for attr, vec in (("braked", self.braked), ("brake_held", self.held)):
                vec[sl] = getattr(arm, attr)
                setattr(arm, attr, vec[sl])
            arm.motor_tau = self.motor_tau[sl]
            arm.brake_torque_nm = self.brake_torque_nm[sl].copy()
            js = hw.joints
            first = DOF * i
            for kind, got in wires.items():
                got += banks.wires([getattr(w, kind) for w in js], first)
            self.rigs.append(
                RobotRig(
                    name=name,
                    arm=arm,
                    hw=hw,
                    sl=sl,
                    q=self.q[sl],
                    qd=self.qd[sl],
                    tau=self.tau[sl],
                    home=self.home[sl],
                    switch=self.homes.state[sl],
                    encoder_offset=self.encoders.offset[sl],
                    counts_per_rad=self.encoders.counts_per_rad[sl],
                    brake_torque_nm=self.brake_torque_nm[sl],
                    wrist=hw.wrist is not None,
                )
            )
        return wires

    def _wiring(
        self, wires: dict[str, list[tuple[int, ...]]], sensors: list[SensorsConfig]
    ) -> None:
        """The wires as index arrays; the ADC's sources and scales; the DIO
        boards' home words."""
        n, banks = self.n, self.banks
        enc, dac, home, brake = (wires[k] for k in ("encoder", "dac", "home", "brake"))
        torque, tach = wires["torque"], wires["tach"]
        # every joint has an encoder axis, a DAC channel, a home bit and a
        # brake bit (the config checks it): those wires are in joint order
        self.enc, self.dac, self.home_w, self.brake_w = (
            _wires(enc),
            _wires(dac),
            _wires(home),
            _wires(brake),
        )
        self._brake_bits = self.brake_w.ch.astype(np.uint32)
        self._enc_joint = {(int(r), int(c)): int(j) for j, r, c in enc}
        # the ADC carries the torque sensors, then the tachometers, of the
        # joints that have them: one gather from [tau, qd] for both
        t_w, h_w = _wires(torque), _wires(tach)
        self.adc_src = np.concatenate([t_w.joints, n + h_w.joints])
        self.adc_rows = np.concatenate([t_w.rows, h_w.rows])
        self.adc_ch = np.concatenate([t_w.ch, h_w.ch])
        torque_v = np.concatenate([np.asarray(s.torque_volts_per_nm, float) for s in sensors])
        tach_v = np.concatenate([np.asarray(s.tach_volts_per_rad_s, float) for s in sensors])
        self.adc_scale = _ADC_CODES_PER_V * np.concatenate(
            [torque_v[t_w.joints], tach_v[h_w.joints]]
        )
        self._adc_in = np.zeros(2 * n)
        self._adc_v = np.zeros(len(self.adc_src))
        # home inputs: each DIO board's word is the sum of its wired bits
        dio_n = len(banks.inp[BoardType.DIO])
        self._home_weights = np.zeros((dio_n, n))
        for j, r, c in home:
            self._home_weights[r, j] = float(1 << c)
        self._homef = np.zeros(n)
        self._dio_word = np.zeros(dio_n)

    def _step_buffers(self, cfg: Config) -> None:
        """Per-step work buffers, the amplifiers' watchdog, the freezes and
        the truth."""
        n, banks = self.n, self.banks
        # per-step buffers
        self._cur = np.zeros(n)
        self._word = np.zeros(n, dtype=np.uint32)
        self._brake = np.ones(n, dtype=bool)
        self._changed = np.zeros(n, dtype=bool)
        self._slow = np.zeros(n)
        self._stopped = np.zeros(n, dtype=bool)
        self._loose = np.zeros(n, dtype=bool)
        self._edges = np.zeros(n, dtype=bool)
        self._loose_any = True
        # the boards whose outputs do something (ADC and force boards have none)
        self.outputs_wanted = {
            a: b
            for a, b in banks.bytes_out.items()
            if self.boards[a] not in (BoardType.ADC, BoardType.FORCE)
        }
        # the amplifiers' watchdog: per DAC board, its last value and when it moved
        self.watchdog_ns = round(cfg.plant.output_watchdog_ms * 1e6)
        robot_boards = [np.unique(self.dac.rows[rig.sl]).tolist() for rig in self.rigs]
        n_dac = len(banks.out[BoardType.DAC])
        self.watchdog = AmplifierWatchdog(self.watchdog_ns, n_dac, robot_boards, n)
        self._joint_cut = self.watchdog.joint_cut
        self.watchdog_trips = self.watchdog.trips
        # every time an arm becomes fully braked (a freeze): robot, step, time
        self.freezes: list[dict[str, Any]] = []
        self._all_braked = [True] * len(self.rigs)
        # the simulation's ground truth per robot (the bank publishes it; no driver reads it)
        self.truth = np.zeros(len(self.rigs), dtype=TRUTH)
        self.truth_image = self.truth.view(np.uint8)
        self._truth_copy = truth_table(self)
        self._contact = [
            (rig, self.truth[self.rigs.index(rig)]["contact_world"]) for rig, _ in self._wrist_rigs
        ]

    @property
    def step_count(self) -> int:
        return self.steps

    def read_outputs(self, port: Any) -> None:
        """Take every board's latest ``out`` bank from the backplane's board side
        (one at a time; the plant loop takes them all at once through the port)."""
        for a, dst in self.outputs_wanted.items():
            port.outputs_into(a, memoryview(dst))  # type: ignore[arg-type]

    def apply_outputs(
        self, outputs: dict[int, np.ndarray[Any, Any]] | None = None, now_ns: int = 0
    ) -> None:
        """Act on the boards' ``out`` banks (``outputs``: address -> a bank to
        take first; None: as they are in the image). ``now_ns``:
        CLOCK_MONOTONIC, for the amplifiers' watchdog (0 reads the clock)."""
        if outputs is not None:
            for a, rec in outputs.items():
                self.banks.rec_out[a][...] = rec
        now_ns = now_ns or time.monotonic_ns()
        if self.watchdog_ns > 0:
            self.watchdog.check(self.reg.dac_watchdog, now_ns, self.rigs, self.step_count + 1)
        if self.kernels:
            flags = kernels.KERNELS.chassis_apply(self._apply_plan)
            if flags & 2:
                np.not_equal(
                    self.reg.enc_requests, self.reg.requests_seen, out=self.reg.req_changed
                )
                self._encoder_commands()
            if flags & 1:
                np.not_equal(self._brake, self.braked, out=self._changed)
                self._brakes_changed(self._brake, now_ns)
        else:
            apply_numpy(self, now_ns)
        for rig in self.rigs:
            self.world.apply_motor_torques(rig.arm)
        if self.grippers.fitted:
            self.grippers.apply(self.reg.dio_outputs, self.step_count + 1)

    def _brakes_changed(self, brake: np.ndarray[Any, Any], now_ns: int) -> None:
        self._loose_any = True  # newly braked joints are held once they stop
        for i, rig in enumerate(self.rigs):
            sl = rig.sl
            if not count(self._changed[sl]):
                continue
            self.world.set_brakes(rig.arm, brake[sl], rig.brake_torque_nm)
            all_braked = bool(brake[sl].all())
            if all_braked != self._all_braked[i]:
                self._all_braked[i] = all_braked
                if all_braked and len(self.freezes) < 1000:
                    self.freezes.append(
                        {"robot": rig.name, "step": self.step_count + 1, "monotonic_ns": now_ns}
                    )

    def _encoder_commands(self) -> None:
        """New preset or software-latch requests (sequence-numbered commands)."""
        for row, k in zip(*np.nonzero(self.reg.req_changed), strict=True):
            row, k = int(row), int(k)
            req = int(self.reg.enc_requests[row, k])
            self.reg.requests_seen[row, k] = req
            axis = k % R.ENC_AXES
            j = self._enc_joint.get((row, axis))
            if j is None:
                continue  # an axis wired to no joint
            if k < R.ENC_AXES:  # preset: load the value now
                self.encoders.preset(j, float(self.q[j]), int(self.reg.enc_preset_value[row, axis]))
                self.reg.enc_preset_ack[row, axis] = req
                self.reg.enc_counter[row, axis] = int(self.encoders.counts(self.q)[j])
            elif int(self.reg.enc_latch_mode[row, axis]) == R.LATCH_SOFTWARE:
                self.reg.enc_latch[row, axis] = self.reg.enc_counter[row, axis]
                self.reg.enc_latch_count[row, axis] += 1

    # -- physics --

    def step(self) -> None:
        """One physics step, then every board sampled."""
        self.step_physics()
        self.sample()

    # -- where a disturbance acts (robot: its index among the rigs) --

    def push_wrist(self, robot: int, force_xyz: np.ndarray[Any, Any]) -> None:
        """A force [N] on the robot's last link during the next step (world axes)."""
        self.world.push(self.rigs[robot].arm, force_xyz)

    def glitch_encoder(self, robot: int, joint: int, counts: int) -> None:
        """The joint's counter jumps by ``counts`` (and stays off by as much)."""
        self.rigs[robot].encoder_offset[joint] += counts

    def force_home_switches(self, robot: int, state: bool | None) -> None:
        """Every home switch of the robot stuck on (True) or off (False), or
        working again (None)."""
        mode = HOME_AS_SWITCH if state is None else HOME_STUCK_ON if state else HOME_STUCK_OFF
        self._home_force[self.rigs[robot].sl] = mode

    def corrupt_wrist_calibration(self, robot: int) -> None:
        """The wrist receiver's calibration memory gives NaN (from the next sample)."""
        row = self.rigs[robot].ft_row
        if row >= 0:
            self.reg.ft_calibration[row, 0, 0] = np.nan

    def step_physics(self) -> None:
        """PyBullet's step alone (a disturbance acting on the devices first)."""
        if self.disturbance is not None:
            self.disturbance.before_physics(self)
        self.world.step()
        self.steps += 1
        self.step_word[0] = self.steps

    def sample(self) -> None:
        """Joint states -> every board's ``in`` bank and the truth."""
        world = self.world
        if self.kernels:
            unpack = kernels.KERNELS.unpack_states
            for rig in self.rigs:
                unpack(world.joint_states_raw(rig.arm), self.q, self.qd, self.applied, rig.sl.start)
        else:
            for rig in self.rigs:
                world.read_joints(rig.arm, rig.q, rig.qd, self.applied[rig.sl])
        for rig, k in self._wrist_rigs:
            world.read_wrist(rig.arm, rig.tool_xyz, self._rot9[k], rig.wrench)
        if self.kernels:
            flags = kernels.KERNELS.chassis_sample(self._sample_plan)
            if flags & 1:
                self._settle()
            if flags & 2:
                self._home_edges(self.counts, registers=False)
            if flags & 4:
                self.wrists.refill()
        else:
            sample_numpy(self)
        if self.disturbance is not None:
            self.disturbance.after_sample(self)

    def _settle(self) -> None:
        """Braked joints that have stopped are held at their angle from now on."""
        for rig in self.rigs:
            if count(self._stopped[rig.sl]):
                self.world.settle_brakes(rig.arm, rig.q, rig.qd)

    def _home_edges(self, counts: np.ndarray[Any, Any], registers: bool) -> None:
        """Home inputs that changed (rare: a switch edge): the encoder boards'
        home levels and the DIO input words (unless the kernel wrote them), and
        the counters of the axes that latch on home edges."""
        e, home = self.enc, self.home
        if registers:
            self.reg.enc_home[e.rows, e.ch] = home
            # each DIO word is the sum of its wired bits
            np.copyto(self._homef, home)
            np.matmul(self._home_weights, self._homef, out=self._dio_word)
            self.reg.dio_inputs[...] = self._dio_word
        for j in np.flatnonzero(self._edges).tolist():
            row, axis = int(e.rows[j]), int(e.ch[j])
            if int(self.reg.enc_latch_mode[row, axis]) == R.LATCH_HOME_EDGES:
                self.reg.enc_latch[row, axis] = counts[j]
                self.reg.enc_latch_count[row, axis] += 1
                self.reg.enc_latch_edge[row, axis] = R.EDGE_RISING if home[j] else R.EDGE_FALLING
        self._last_home[...] = home

    # -- the simulation's truth --

    def fill_truth(self) -> None:
        """The truth records (``self.truth``) of this step."""
        if self.kernels:
            kernels.KERNELS.copy(self._truth_plan)
        else:
            kernels.copy_rows(self.state.buffer, self.truth_image, self._truth_copy)
        for rig, contact in self._contact:
            self.world.contact_wrench_world_into(rig.arm, rig.tool_xyz, contact)

    def brake_all(self) -> None:
        """Every brake on (the plant stops: the arms stay where they are)."""
        for rig in self.rigs:
            self.world.set_brakes(rig.arm, np.ones(DOF, dtype=bool), rig.brake_torque_nm)


def fit_wrist_sensors(ch: Chassis, cfg: Config, wrists: list[tuple[int, int, Any, str]]) -> None:
    """The wrist sensors, one row each, and their rigs' views."""
    ft = ch.banks.inp[BoardType.FORCE]
    ch.wrists = WristSensors(
        np.array([w[2] for w in wrists]).reshape(-1, 6, 6),
        np.array([cfg.plant.ft_bias.get(w[3], [0.0] * 6) for w in wrists]).reshape(-1, 6),
        cfg.plant.ft_noise_n,
        cfg.plant.ft_noise_nm,
        cfg.plant.seed,
    )
    ch.ft_rows = np.array([w[1] for w in wrists], dtype=np.int64)
    ch._wrist_rigs = []
    ch._rot9 = []
    for k, (i, row, cal, _) in enumerate(wrists):
        rig = ch.rigs[i]
        rig.ft_row, rig.wrench = row, ch.wrenches[k]
        rig.tool_xyz, rig.tool_rot = ch.tool_xyz[k], ch.tool_rot[k]
        ch._rot9.append(ch.tool_rot[k].reshape(9))  # a view: filled in place each step
        ft[row]["calibration"] = np.asarray(cal)
        ch._wrist_rigs.append((rig, k))
    ch._strain = np.zeros((len(wrists), 6), dtype=np.int32)
