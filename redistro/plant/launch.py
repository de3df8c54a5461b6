"""Start and stop the plant process from a session owner (or a test)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

from redistro import files
from redistro.config.hardware import RobotHardware, load_hardware
from redistro.config.loader import resolved
from redistro.config.model import Config
from redistro.drivers.io.bank import PlantState, RegisterBank
from redistro.errors import IPCError, LayoutError, RedistroError
from redistro.ipc.session import Session
from redistro.process.spawn import spawn


class PlantProcess:
    """The plant process: ``start()`` returns once its bank says RUNNING;
    ``launch()`` at once (``started()`` then tells)."""

    def __init__(self, proc: subprocess.Popen[bytes], session_id: str, result_path: Path) -> None:
        self.proc = proc
        self.session_id = session_id
        self.result_path = result_path
        self.bank: RegisterBank | None = None
        self.up = False
        self.deadline = float("inf")
        self.timeout_s = 0.0

    @property
    def pid(self) -> int:
        return self.proc.pid

    @classmethod
    def start(
        cls,
        session: Session,
        run_dir: Path,
        cfg: Config,
        *,
        gui: bool = False,
        timeout_s: float = 30.0,
        hardware: dict[str, RobotHardware] | None = None,
    ) -> PlantProcess:
        """The plant launched, once it is running (see ``launch``)."""
        plant = cls.launch(session, run_dir, cfg, gui=gui, timeout_s=timeout_s, hardware=hardware)
        try:
            while not plant.started():
                time.sleep(0.005)  # polling a condition, with a deadline (started's)
        except BaseException:
            plant.stop()
            raise
        return plant

    @classmethod
    def launch(
        cls,
        session: Session,
        run_dir: Path,
        cfg: Config,
        *,
        gui: bool = False,
        timeout_s: float = 30.0,
        hardware: dict[str, RobotHardware] | None = None,
    ) -> PlantProcess:
        """The plant process started, not waited for: ``started()`` says when
        it is running. cfg: the plant's config, loaded and checked by the
        caller, and the robots' hardware (read and checked here unless the
        caller did): handed down resolved (``plant.config.json`` in
        ``run_dir``), never re-read from their files."""
        files.make_folder(run_dir, "run folder")
        result = run_dir / "plant.json"
        resolved_path = run_dir / "plant.config.json"
        hw = hardware if hardware is not None else load_hardware(cfg)
        doc = {"config": resolved(cfg), "hardware": {r: resolved(h) for r, h in hw.items()}}
        files.replace(resolved_path, json.dumps(doc))
        args = ["plant", "--session", session.id, "--result", str(result)]
        args += ["--resolved", str(resolved_path)]
        if gui:
            args.append("--gui")
        proc = spawn(args, pass_fds=[session.lock_fd], env=session.child_env())
        plant = cls(proc, session.id, result)
        plant.deadline = time.monotonic() + timeout_s
        plant.timeout_s = timeout_s
        return plant

    def started(self) -> bool:
        """True once the plant's bank says RUNNING; False while it starts.
        Raises RedistroError when it ended, or did not come up in time."""
        if self.up:
            return True
        if self.proc.poll() is not None:
            why = self.result().get("error", f"exit code {self.proc.returncode}")
            raise RedistroError(f"plant failed to start: {why}")
        if self.bank is None:
            try:
                self.bank = RegisterBank.attach(self.session_id)
            except (IPCError, LayoutError):
                self.bank = None  # not created yet
        if self.bank is not None and int(self.bank.status.read()["state"]) == PlantState.RUNNING:
            self.up = True
            return True
        if time.monotonic() > self.deadline:
            raise RedistroError(f"plant not running after {self.timeout_s:g} s")
        return False

    def status(self) -> dict[str, Any]:
        assert self.bank is not None
        s = self.bank.status.read()
        return {name: s[name].item() for name in s.dtype.names or ()}

    def clock_s(self) -> float | None:
        """The plant's simulated time [s]; None when it cannot be read."""
        if self.bank is None:
            return None
        try:
            return int(self.bank.status.read()["sim_time_ns"]) * 1e-9
        except RedistroError:
            return None

    def stop(self, timeout_s: float = 10.0) -> int:
        """SIGTERM (and SIGCONT: a stopped plant takes it too), wait; SIGKILL
        if it does not end in time. Returns the exit code."""
        if self.bank is not None:
            self.bank.close()
            self.bank = None
        if self.proc.poll() is None:
            os.kill(self.proc.pid, signal.SIGTERM)
            os.kill(self.proc.pid, signal.SIGCONT)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        return int(self.proc.returncode)

    def result(self) -> dict[str, Any]:
        try:
            return dict(json.loads(self.result_path.read_text()))
        except (OSError, ValueError):
            return {}
