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
from redistro.config.hardware import RobotHardware
from redistro.config.model import Config
from redistro.drivers.io import registers as R
from redistro.drivers.io.bank import TRUTH
from redistro.drivers.io.image import RegisterImage
from redistro.drivers.io.registers import BOARD_NAMES, BoardType
from redistro.plant import chassis_layout
from redistro.plant.devices import Encoders, HomeSwitches, Motors, WristSensors
from redistro.plant.disturbance import Disturbance
from redistro.plant.world import BRAKE_STOPPED_RAD_S, Arm, World

DOF = 7
_AMPS_PER_CODE = R.DAC_FULL_SCALE_V / 2048  # volts per DAC code
_ADC_CODES_PER_V = 32768 / R.ADC_FULL_SCALE_V
count = np.count_nonzero  # on the hot path: a third of what ndarray.any() costs
HOME_AS_SWITCH, HOME_STUCK_OFF, HOME_STUCK_ON = 0, 1, 2


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


class Chassis:
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
        self.boards: dict[int, BoardType] = {}
        for hw in hardware.values():
            for b in hw.io.boards.values():
                self.boards[b.address] = BOARD_NAMES[b.type]
        self.banks = banks = RegisterImage(self.boards)
        self.image = banks.image
        self.inp = banks.rec_in  # address -> the board's in bank (0-d record)
        names = list(hardware)
        n = DOF * len(names)
        self.n = n
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
        # the chassis' state: one buffer (the truth is copied out of it in one call)
        st = self.state = kernels.Arena(64 * n + 1024 + 160 * len(wrists))
        self.step_rec = st.take("step", chassis_layout.STEP, ())  # the plant's step
        self.step_now = self.step_rec["step"]
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
        self.wrenches = st.take("wrenches", np.float64, (len(wrists), 6))
        self.tool_xyz = st.take("tool_xyz", np.float64, (len(wrists), 3))
        self.tool_rot = st.take("tool_rot", np.float64, (len(wrists), 3, 3))
        self.brake_torque_nm = np.concatenate(
            [np.asarray(s.brake_torque_nm, dtype=np.float64) for s in sensors]
        )
        self._last_home = np.zeros(n, dtype=bool)
        self._home_force = np.zeros(n, dtype=np.uint8)  # HOME_AS_SWITCH, or a stuck switch
        enc, dac, home, brake, torque, tach = ([] for _ in range(6))
        ft = banks.inp[BoardType.FORCE]
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
            enc += banks.wires([w.encoder for w in js], first)
            dac += banks.wires([w.dac for w in js], first)
            home += banks.wires([w.home for w in js], first)
            brake += banks.wires([w.brake for w in js], first)
            torque += banks.wires([w.torque for w in js], first)
            tach += banks.wires([w.tach for w in js], first)
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
        # the wrist sensors, one row each
        self.wrists = WristSensors(
            np.array([w[2] for w in wrists]).reshape(-1, 6, 6),
            np.array([cfg.plant.ft_bias.get(w[3], [0.0] * 6) for w in wrists]).reshape(-1, 6),
            cfg.plant.ft_noise_n,
            cfg.plant.ft_noise_nm,
            cfg.plant.seed,
        )
        self.ft_rows = np.array([w[1] for w in wrists], dtype=np.int64)
        self._wrist_rigs: list[tuple[RobotRig, int]] = []
        self._rot9 = []
        for k, (i, row, cal, _) in enumerate(wrists):
            rig = self.rigs[i]
            rig.ft_row, rig.wrench = row, self.wrenches[k]
            rig.tool_xyz, rig.tool_rot = self.tool_xyz[k], self.tool_rot[k]
            self._rot9.append(self.tool_rot[k].reshape(9))  # a view: filled in place each step
            ft[row]["calibration"] = np.asarray(cal)
            self._wrist_rigs.append((rig, k))
        self._strain = np.zeros((len(wrists), 6), dtype=np.int32)
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
        # field views (made once: a field lookup per step costs as much as the op)
        i_enc, o_enc = banks.inp[BoardType.ENCODER], banks.out[BoardType.ENCODER]
        self.enc_counter, self.enc_home = i_enc["counter"], i_enc["home"]
        self.enc_latch, self.enc_latch_count = i_enc["latch"], i_enc["latch_count"]
        self.enc_latch_edge, self.enc_preset_ack = i_enc["latch_edge"], i_enc["preset_ack"]
        self.enc_preset_value, self.enc_latch_mode = o_enc["preset_value"], o_enc["latch_mode"]
        # preset_req and latch_req lie side by side: one (boards, 8) view of both
        fields = o_enc.dtype.fields
        assert fields is not None
        off = int(fields["preset_req"][1])
        assert int(fields["latch_req"][1]) == off + 4 * R.ENC_AXES
        self.enc_requests = np.ndarray(
            (len(o_enc), 2 * R.ENC_AXES),
            dtype="<u4",
            buffer=self.image,
            offset=banks.base[(BoardType.ENCODER, "out")] + off,
            strides=(o_enc.dtype.itemsize, 4),
        )
        self._requests_seen = np.zeros(self.enc_requests.shape, dtype="<u4")
        self._req_changed = np.zeros(self.enc_requests.shape, dtype=bool)
        i_dac, o_dac = banks.inp[BoardType.DAC], banks.out[BoardType.DAC]
        self.dac_code, self.dac_watchdog = o_dac["code"], o_dac["watchdog"]
        self.dac_readback = i_dac["readback"]
        self.dio_outputs = banks.out[BoardType.DIO]["outputs"]
        self.dio_readback = banks.inp[BoardType.DIO]["outputs_readback"]
        self.dio_inputs = banks.inp[BoardType.DIO]["inputs"]
        self.adc_code = banks.inp[BoardType.ADC]["code"]
        self.ft_strain, self.ft_sample = ft["strain"], ft["sample"]
        self.ft_calibration = ft["calibration"]
        self.steps_in = [banks.inp[t]["step"] for t in banks.inp if len(banks.inp[t])]
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
        n_dac = len(o_dac)
        self._wd_values = [0] * n_dac  # each DAC board's watchdog register, last seen
        self._wd_ns = [0] * n_dac  # when it last moved
        self._dac_rows = [np.unique(self.dac.rows[rig.sl]).tolist() for rig in self.rigs]
        self._joint_cut = np.zeros(n, dtype=bool)
        self._wd_due = 0  # when the earliest armed board's watchdog runs out (0: none armed)
        self._any_cut = False
        self.watchdog_tripped = [False] * len(self.rigs)
        self.watchdog_trips: list[dict[str, Any]] = []  # robot, monotonic_ns, step
        # every time an arm becomes fully braked (a freeze): robot, step, time
        self.freezes: list[dict[str, Any]] = []
        self._all_braked = [True] * len(self.rigs)
        # the simulation's ground truth per robot (the bank publishes it; no driver reads it)
        self.truth = np.zeros(len(self.rigs), dtype=TRUTH)
        self.truth_image = self.truth.view(np.uint8)
        self._truth_copy = self._truth_table()
        self._contact = [
            (rig, self.truth[self.rigs.index(rig)]["contact_world"]) for rig, _ in self._wrist_rigs
        ]
        self.disturbance = disturbance
        if self.kernels:
            self._plans()
        for rig in self.rigs:  # brakes on at power-up: the arms hold until released
            world.set_brakes(rig.arm, np.ones(DOF, dtype=bool), rig.brake_torque_nm)
        self.sample()

    # -- the kernels' plans --

    def _plans(self) -> None:
        b = self.banks
        enc, dac, adc, dio, force = (
            BoardType.ENCODER,
            BoardType.DAC,
            BoardType.ADC,
            BoardType.DIO,
            BoardType.FORCE,
        )
        e, d, h, br = self.enc, self.dac, self.home_w, self.brake_w

        at = b.offsets

        def every(t: BoardType) -> range:
            return range(len(b.inp[t]))

        copy = [  # the readbacks: what the DAC and DIO boards drive
            (
                b.offset(dac, "out", r, "code"),
                b.offset(dac, "in", r, "readback"),
                2 * R.DAC_CHANNELS,
                0,
            )
            for r in every(dac)
        ] + [
            (
                b.offset(dio, "out", r, "outputs"),
                b.offset(dio, "in", r, "outputs_readback"),
                4,
                R.DIO_MASK,
            )
            for r in every(dio)
        ]
        self._apply_plan = kernels.plan(
            "chassis_apply",
            image=self.image,
            brake_off=at(dio, "out", "outputs", br.rows),
            brake_bit=br.ch.astype(np.int64),
            dac_off=at(dac, "out", "code", d.rows, d.ch, 2),
            cut=self._joint_cut,
            amps_per_code=_AMPS_PER_CODE * self.motors.amps_per_volt,
            max_current=self.motors.max_current_a,
            nm_per_amp=self.motors.nm_per_amp,
            motor_tau=self.motor_tau,
            brake=self._brake,
            braked=self.braked,
            copy=kernels.table("chassis_apply", "copy", copy),
            req_off=at(enc, "out", "preset_req", every(enc)),
            req_seen=self._requests_seen.view(np.uint8).reshape(-1),
        )
        self._sample_plan = kernels.plan(
            "chassis_sample",
            image=self.image,
            q=self.q,
            qd=self.qd,
            tau=self.tau,
            applied=self.applied,
            motor_tau=self.motor_tau,
            braked=self.braked,
            held=self.held,
            stopped=self._stopped,
            counts_per_rad=self.encoders.counts_per_rad,
            enc_offset=self.encoders.offset,
            counts=self.counts,
            counter_off=at(enc, "in", "counter", e.rows, e.ch, 4),
            home_center=self.homes.center,
            home_on=self.homes.on_within,
            home_off=self.homes.off_beyond,
            switch=self.homes.state,
            force=self._home_force,
            home=self.home,
            last_home=self._last_home,
            edges=self._edges,
            home_reg_off=at(enc, "in", "home", e.rows, e.ch, 1),
            dio_clear=at(dio, "in", "inputs", every(dio)),
            home_word=at(dio, "in", "inputs", h.rows),
            home_bit=h.ch.astype(np.int64),
            adc_src=self.adc_src.astype(np.int64),
            adc_scale=np.ascontiguousarray(self.adc_scale),
            adc_off=at(adc, "in", "code", self.adc_rows, self.adc_ch, 2),
            wrench=self.wrenches,
            inverse=self.wrists.inverse,
            noise=self.wrists.noise,
            noise_at=self.wrists.noise_at,
            strain_off=at(force, "in", "strain", self.ft_rows),
            sample_off=at(force, "in", "sample", self.ft_rows),
            step_off=np.concatenate([at(t, "in", "step", every(t)) for t in b.inp]),
            step=self.step_rec,
        )
        self._truth_plan = kernels.plan(
            "copy", src=self.state.buffer, dst=self.truth_image, table=self._truth_copy
        )

    def _truth_table(self) -> np.ndarray[Any, Any]:
        """What the truth records copy from the state: (src, dst, size) rows."""
        st, f = self.state, TRUTH.fields
        assert f is not None
        rows: list[tuple[int, int, int]] = []
        wrist_of = {rig.name: k for rig, k in self._wrist_rigs}
        for i, rig in enumerate(self.rigs):
            at = i * TRUTH.itemsize
            rows.append((st.offset("step"), at + int(f["step"][1]), 8))
            for name, src, size in (
                ("q_rad", "q", 8),
                ("qd_rad_s", "qd", 8),
                ("tau_nm", "tau", 8),
                ("braked", "braked", 1),
                ("home", "switch", 1),
                ("encoder_offset_counts", "enc_offset", 8),
            ):
                rows.append((st.offset(src) + size * DOF * i, at + int(f[name][1]), size * DOF))
            k = wrist_of.get(rig.name)
            if k is not None:
                rows.append((st.offset("wrenches") + 48 * k, at + int(f["wrench_sensor"][1]), 48))
                rows.append((st.offset("tool_xyz") + 24 * k, at + int(f["tool_xyz_m"][1]), 24))
                rows.append((st.offset("tool_rot") + 72 * k, at + int(f["tool_rot"][1]), 72))
        return kernels.copy_table(rows)

    # -- controller -> boards --

    def _watchdog(self, now_ns: int) -> bool:
        """Cut the amplifiers of every robot whose DAC boards' watchdog
        registers (when armed, non-zero) have not moved for the watchdog time;
        True while any robot is cut (``self._joint_cut`` says which joints).
        Per step it only looks for moved registers (a chassis has a few DAC
        boards: plain ints); the rest runs when the earliest armed board's
        time is up, or while a robot is cut."""
        values = self.dac_watchdog.tolist()
        if values != self._wd_values:
            moved = self._wd_ns
            for b, (v, old) in enumerate(zip(values, self._wd_values, strict=True)):
                if v != old:
                    moved[b] = now_ns
            self._wd_values = values
            armed = [t for t, v in zip(moved, values, strict=True) if v]
            self._wd_due = min(armed) + self.watchdog_ns if armed else 0
        if not (self._wd_due and now_ns > self._wd_due) and not self._any_cut:
            return False
        cut = [
            bool(v) and now_ns - t > self.watchdog_ns
            for t, v in zip(self._wd_ns, values, strict=True)
        ]
        self._joint_cut[:] = False
        for i, rig in enumerate(self.rigs):
            tripped = any(cut[b] for b in self._dac_rows[i])
            if tripped and not self.watchdog_tripped[i] and len(self.watchdog_trips) < 1000:
                self.watchdog_trips.append(
                    {"robot": rig.name, "step": self.step_count + 1, "monotonic_ns": now_ns}
                )
            self.watchdog_tripped[i] = tripped
            self._joint_cut[rig.sl] = tripped
        self._any_cut = any(self.watchdog_tripped)
        return self._any_cut

    @property
    def step_count(self) -> int:
        return int(self.step_now)

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
            self._watchdog(now_ns)
        if self.kernels:
            flags = kernels.KERNELS.chassis_apply(self._apply_plan)
            if flags & 2:
                np.not_equal(self.enc_requests, self._requests_seen, out=self._req_changed)
                self._encoder_commands()
            if flags & 1:
                np.not_equal(self._brake, self.braked, out=self._changed)
                self._brakes_changed(self._brake, now_ns)
        else:
            self._apply_numpy(now_ns)
        for rig in self.rigs:
            self.world.apply_motor_torques(rig.arm)

    def _apply_numpy(self, now_ns: int) -> None:
        # fail-safe brakes: engaged unless their release output is on
        brake = self._brake
        word = self._word
        self.dio_outputs.take(self.brake_w.rows, out=word)
        np.right_shift(word, self._brake_bits, out=word)
        np.bitwise_and(word, 1, out=word)
        np.equal(word, 0, out=brake)
        np.logical_or(brake, self._joint_cut, out=brake)  # the watchdog's relay drops them too
        # the amplifiers: DAC code -> current (saturated) -> joint torque;
        # inhibited while the joint's brake is on (interlock)
        d = self.dac
        cur = self._cur
        cur[...] = self.dac_code[d.rows, d.ch]
        np.multiply(cur, _AMPS_PER_CODE * self.motors.amps_per_volt, out=cur)
        m = self.motors
        np.minimum(cur, m.max_current_a, out=cur)
        np.maximum(cur, m.min_current_a, out=cur)
        np.multiply(cur, m.nm_per_amp, out=self.motor_tau)
        np.copyto(self.motor_tau, 0.0, where=brake)
        # what the boards say they drive
        self.dac_readback[...] = self.dac_code
        np.bitwise_and(self.dio_outputs, R.DIO_MASK, out=self.dio_readback)
        # encoder commands (presets, software latches): rare
        np.not_equal(self.enc_requests, self._requests_seen, out=self._req_changed)
        if count(self._req_changed):
            self._encoder_commands()
        np.not_equal(brake, self.braked, out=self._changed)
        if count(self._changed):
            self._brakes_changed(brake, now_ns)

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
        for row, k in zip(*np.nonzero(self._req_changed), strict=True):
            row, k = int(row), int(k)
            req = int(self.enc_requests[row, k])
            self._requests_seen[row, k] = req
            axis = k % R.ENC_AXES
            j = self._enc_joint.get((row, axis))
            if j is None:
                continue  # an axis wired to no joint
            if k < R.ENC_AXES:  # preset: load the value now
                self.encoders.preset(j, float(self.q[j]), int(self.enc_preset_value[row, axis]))
                self.enc_preset_ack[row, axis] = req
                self.enc_counter[row, axis] = int(self.encoders.counts(self.q)[j])
            elif int(self.enc_latch_mode[row, axis]) == R.LATCH_SOFTWARE:
                self.enc_latch[row, axis] = self.enc_counter[row, axis]
                self.enc_latch_count[row, axis] += 1

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
            self.ft_calibration[row, 0, 0] = np.nan

    def step_physics(self) -> None:
        """PyBullet's step alone (a disturbance acting on the devices first)."""
        if self.disturbance is not None:
            self.disturbance.before_physics(self)
        self.world.step()
        self.step_now += 1

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
            self._sample_numpy()
        if self.disturbance is not None:
            self.disturbance.after_sample(self)

    def _settle(self) -> None:
        """Braked joints that have stopped are held at their angle from now on."""
        for rig in self.rigs:
            if count(self._stopped[rig.sl]):
                self.world.settle_brakes(rig.arm, rig.q, rig.qd)

    def _sample_numpy(self) -> None:
        q, qd, n = self.q, self.qd, self.n
        # PyBullet reports a braked joint's torque (its brake motor's), not a
        # torque-controlled one's: there the motor's is the joint's
        np.copyto(self.tau, self.motor_tau)
        np.copyto(self.tau, self.applied, where=self.braked)
        # braked joints that have stopped: their brakes hold the angle from now
        # on (looked for only while a braked joint is not held yet)
        if self._loose_any:
            np.abs(qd, out=self._slow)
            np.less(self._slow, BRAKE_STOPPED_RAD_S, out=self._stopped)
            np.greater(self.braked, self.held, out=self._loose)  # braked, not yet held
            np.logical_and(self._stopped, self._loose, out=self._stopped)
            if count(self._stopped):
                self._settle()
            self._loose_any = bool(count(np.greater(self.braked, self.held, out=self._loose)))
        counts = self.encoders.counts(q)
        self.counts[...] = counts
        home = self.home
        np.copyto(home, self.homes.update(q))
        stuck = self._home_force != HOME_AS_SWITCH
        if count(stuck):
            home[stuck] = self._home_force[stuck] == HOME_STUCK_ON
        e = self.enc
        self.enc_counter[e.rows, e.ch] = counts
        np.not_equal(home, self._last_home, out=self._edges)
        if count(self._edges):  # a home input changed: its registers, its latches
            self._home_edges(counts, registers=True)
        # torque sensors and tachometers -> ADC codes (rounded, saturated)
        src = self._adc_in
        src[:n] = self.tau
        src[n:] = qd
        v = self._adc_v
        src.take(self.adc_src, out=v)
        np.multiply(v, self.adc_scale, out=v)
        np.rint(v, out=v)
        np.minimum(v, 32767, out=v)
        np.maximum(v, -32768, out=v)
        self.adc_code[self.adc_rows, self.adc_ch] = v
        if self._wrist_rigs:
            self.wrists.gauges_into(self.wrenches, self._strain)
            self.ft_strain[self.ft_rows] = self._strain
            self.ft_sample[self.ft_rows] += 1
        for steps in self.steps_in:
            steps[...] = self.step_count

    def _home_edges(self, counts: np.ndarray[Any, Any], registers: bool) -> None:
        """Home inputs that changed (rare: a switch edge): the encoder boards'
        home levels and the DIO input words (unless the kernel wrote them), and
        the counters of the axes that latch on home edges."""
        e, home = self.enc, self.home
        if registers:
            self.enc_home[e.rows, e.ch] = home
            # each DIO word is the sum of its wired bits
            np.copyto(self._homef, home)
            np.matmul(self._home_weights, self._homef, out=self._dio_word)
            self.dio_inputs[...] = self._dio_word
        for j in np.flatnonzero(self._edges).tolist():
            row, axis = int(e.rows[j]), int(e.ch[j])
            if int(self.enc_latch_mode[row, axis]) == R.LATCH_HOME_EDGES:
                self.enc_latch[row, axis] = counts[j]
                self.enc_latch_count[row, axis] += 1
                self.enc_latch_edge[row, axis] = R.EDGE_RISING if home[j] else R.EDGE_FALLING
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
