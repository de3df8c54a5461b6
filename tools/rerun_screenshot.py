"""A picture of a session log as Rerun shows it, for the README.

    python tools/rerun_screenshot.py RUN_DIR OUT.png [--at-s SECONDS]

Converts ``RUN_DIR/session.mcap`` with Rerun's own MCAP importer (``rerun
mcap convert``), serves it with Rerun's web viewer (``rerun --web-viewer``,
WebGL) on loopback and takes a screenshot with headless Chromium (Debian's
``chromium``, software GL). Nothing here is drawn by redistro: what shows
is what Rerun made of the file.
"""

from __future__ import annotations

import argparse
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RERUN = ROOT / ".venv" / "bin" / "rerun"


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _up(port: int, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.1)  # polling a port, with a deadline
    raise SystemExit(f"rerun's web viewer did not come up on port {port}")


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("run", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--wait-ms", type=int, default=30000, help="Chromium's virtual time budget")
    ap.add_argument("--size", default="1600,1000")
    args = ap.parse_args()
    chromium = shutil.which("chromium")
    if chromium is None:
        raise SystemExit("no chromium (apt-get install chromium)")
    with tempfile.TemporaryDirectory(prefix="redistro-rerun-") as tmp:
        rrd = Path(tmp) / "session.rrd"
        subprocess.run(
            [str(RERUN), "mcap", "convert", str(args.run / "session.mcap"), "-o", str(rrd)],
            check=True,
            capture_output=True,
        )
        web, grpc = _port(), _port()
        serve = ["--web-viewer", "--web-viewer-port", str(web), "--port", str(grpc)]
        viewer = subprocess.Popen(
            [str(RERUN), *serve, "--bind", "127.0.0.1", "--renderer", "webgl", str(rrd)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            _up(web, 60)
            url = f"http://127.0.0.1:{web}/?url=rerun%2Bhttp://127.0.0.1:{grpc}/proxy"
            flags = [
                "--headless",
                "--no-sandbox",
                "--disable-gpu-sandbox",
                "--use-gl=angle",
                "--use-angle=swiftshader",
                "--enable-unsafe-swiftshader",
                "--no-first-run",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-sync",
                "--hide-scrollbars",
                f"--user-data-dir={tmp}/chromium",
                f"--window-size={args.size}",
                f"--virtual-time-budget={args.wait_ms}",
                f"--screenshot={args.out}",
            ]
            subprocess.run(
                [chromium, *flags, url],
                check=True,
                capture_output=True,
                timeout=300,
            )
        finally:
            viewer.terminate()
            viewer.wait(10)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
