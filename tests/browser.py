"""A page opened in a real browser: Debian's chromium, headless, driven by
Playwright (no browser download), with software WebGL."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from tests.helpers import REDISTRO, ROOT

CHROMIUM = "/usr/bin/chromium"
FLAGS = [
    "--no-sandbox",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--disable-background-networking",
]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


@contextlib.contextmanager
def served(args: list[str], port: int, timeout_s: float = 60.0) -> Iterator[None]:
    """``redistro ARGS`` serving a page on ``port`` while the block runs;
    ended with SIGTERM (then killed) and waited for."""
    from redistro.view import wait_served

    proc = subprocess.Popen(
        [*REDISTRO, *args], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
    )
    try:
        if not wait_served(port, timeout_s):
            proc.kill()
            _, err = proc.communicate()
            raise AssertionError(f"nothing served on port {port}: {err[-2000:]}")
        yield
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.communicate(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.communicate()


def screenshot(url: str, out: Path, settle_ms: int = 4000) -> str:
    """Open ``url``, wait for its 3D canvas and ``settle_ms``, save a
    picture; the page's text."""
    with page(url) as tab:
        tab.wait_for_function("document.body.innerText.includes('cycle')", timeout=60_000)
        tab.wait_for_timeout(settle_ms)  # (the renderer's first frames, in software)
        tab.screenshot(path=str(out), timeout=90_000)  # (software rendering on a loaded host)
        text: str = tab.inner_text("body")
    return text


def bluish_pixels(png: Path, box: tuple[float, float, float, float]) -> int:
    """Pixels in ``box`` (fractions of the width and height) whose blue
    exceeds their red by 6 or more: the arms' blue-grey, which neither the
    white background, the grey grid nor the table has."""
    import numpy as np
    from PIL import Image

    img = np.asarray(Image.open(png).convert("RGB")).astype(int)
    h, w = img.shape[:2]
    x0, y0, x1, y1 = int(box[0] * w), int(box[1] * h), int(box[2] * w), int(box[3] * h)
    part = img[y0:y1, x0:x1]
    return int(((part[..., 2] - part[..., 0]) >= 6).sum())


def keep_for_readme(shot: Path, dest: str) -> None:
    """The picture into the docs, when asked (REDISTRO_README_FIGURES=1)."""
    if os.environ.get("REDISTRO_README_FIGURES") == "1":
        shutil.copyfile(shot, ROOT / dest)


@contextlib.contextmanager
def page(url: str) -> Iterator[Any]:
    """``url`` open in headless Chromium, its 3D canvas up: a Playwright page
    to click on (``page.get_by_role("button", name="Pause")``)."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=FLAGS)
        try:
            tab = browser.new_page(viewport={"width": 1280, "height": 800})
            tab.goto(url)
            tab.wait_for_selector("canvas", timeout=60_000)
            yield tab
        finally:
            browser.close()


def wait_text(tab: Any, text: str, timeout_s: float = 60.0) -> str:
    """The page's text, once it shows ``text`` (Playwright waits, with a
    deadline; past it, an AssertionError that shows what the page said)."""
    from playwright.sync_api import TimeoutError as PageTimeout

    try:
        tab.wait_for_function(
            "t => document.body.innerText.includes(t)", arg=text, timeout=int(timeout_s * 1000)
        )
    except PageTimeout:
        raise AssertionError(
            f"the page never showed {text!r} in {timeout_s} s; it shows: "
            + tab.inner_text("body")[:3000]
        ) from None
    body: str = tab.inner_text("body")
    return body


@contextlib.contextmanager
def host_address() -> Iterator[str | None]:
    """An address of this host that is not loopback, on a veth pair whose
    other end sits alone in a network namespace (traffic to it stays on
    this host); None when that cannot be made here (not root, no ``ip``)."""
    if os.geteuid() != 0 or shutil.which("ip") is None:
        yield None
        return
    tag = f"{os.getpid() % 100000}"
    ns, host_end, ns_end = f"rdV{tag}", f"rdvh{tag}", f"rdvn{tag}"
    addr = f"10.214.{os.getpid() % 250}.1"

    def ip(*args: str) -> None:
        subprocess.run(["ip", *args], check=True, capture_output=True, timeout=10)

    made = False
    try:
        ip("netns", "add", ns)
        made = True
        ip("link", "add", host_end, "type", "veth", "peer", "name", ns_end)
        ip("link", "set", ns_end, "netns", ns)
        ip("addr", "add", f"{addr}/24", "dev", host_end)
        ip("link", "set", host_end, "up")
        yield addr
    finally:
        if made:  # (deleting the namespace deletes its end of the pair, and so both)
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=10)
