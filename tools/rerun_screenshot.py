"""A picture of a session log as Rerun shows it, for the README.

    python tools/rerun_screenshot.py RUN_DIR OUT.png [--wait-ms MS] [--click X,Y ...]

Converts ``RUN_DIR/session.mcap`` with Rerun's own MCAP importer (``rerun
mcap convert``), serves it with Rerun's web viewer (``rerun --web-viewer``,
WebGL) on loopback and takes a screenshot with headless Chromium (Debian's
``chromium``, driven by Playwright: ``pip install playwright``, no browser
download; software GL). Nothing here is drawn by redistro: what shows
is what Rerun made of the file.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
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


def _picture(url: str, out: Path, size: str, wait_s: float, clicks: list[str]) -> None:
    """The page in headless Chromium (Debian's, driven by Playwright; software
    WebGL), photographed once it has drawn for ``wait_s``."""
    from playwright.sync_api import sync_playwright

    w, h = (int(v) for v in size.split(","))
    flags = [
        "--no-sandbox",
        "--use-angle=swiftshader",
        "--enable-unsafe-swiftshader",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
    ]
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=shutil.which("chromium"), args=flags)
        page = browser.new_page(viewport={"width": w, "height": h})
        page.goto(url)
        page.wait_for_timeout(wait_s * 1000)  # (the viewer loads and draws; nothing to wait on)
        for act in clicks:  # (the viewer is one canvas: a button is a place)
            x, y, *more = (float(v) for v in act.split(","))
            page.mouse.move(x, y)
            if len(more) == 2:  # a drag by (DX, DY) (the 3D view turns)
                page.mouse.down()
                page.mouse.move(x + more[0], y + more[1], steps=20)
                page.mouse.up()
            elif more:  # a turn of the wheel there (the 3D view zooms)
                page.mouse.wheel(0, more[0])
            else:
                page.mouse.click(x, y)
            page.wait_for_timeout(3000)
        page.mouse.move(w - 60, h // 2)  # (no tooltip in the picture)
        page.wait_for_timeout(1000)
        page.screenshot(path=str(out))
        browser.close()


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("run", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--wait-ms", type=int, default=25000, help="how long the page draws first")
    ap.add_argument("--size", default="1600,1000")
    ap.add_argument(
        "--click",
        action="append",
        default=[],
        metavar="X,Y",
        help="click there first (a view's button)",
    )
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
            start_new_session=True,  # (the script starts the viewer binary as its child)
        )
        try:
            _up(web, 60)
            url = (
                f"http://127.0.0.1:{web}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc}"
                "%2Fproxy&renderer=webgl"
            )
            _picture(url, args.out, args.size, args.wait_ms / 1000, args.click)
        finally:
            os.killpg(viewer.pid, signal.SIGTERM)  # the wrapper and the viewer it started
            viewer.wait(10)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
