"""Checks before a release, beyond ``make test``.

    python tools/release_check.py

- the working tree is clean and the version is the same in pyproject.toml
  and ``redistro.__version__``;
- every relative link and image in README.md and docs/*.md names a file
  that exists;
- ``redistro --help`` and every subcommand's ``--help`` exit 0;
- the package builds as a wheel (``pip wheel --no-deps``) and the wheel
  holds the compiled kernels.

Prints one line per check and exits 1 when any failed.
"""

from __future__ import annotations

import re
import subprocess
import sys
import tempfile
import tomllib
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")
SUBCOMMANDS = ("session", "node", "check", "plant", "bench", "log", "faults", "top", "bridge")


def _run(*cmd: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, check=False)


def clean_tree() -> str:
    out = _run("git", "status", "--porcelain").stdout.strip()
    return "" if not out else f"uncommitted changes: {len(out.splitlines())} paths"


def versions() -> str:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    text = (ROOT / "redistro" / "__init__.py").read_text()
    m = re.search(r'__version__ = "([^"]+)"', text)
    package = m.group(1) if m else "?"
    return "" if project == package else f"pyproject {project} != redistro {package}"


def links() -> str:
    bad = []
    for md in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for target in LINK.findall(md.read_text()):
            if "://" in target or target.startswith("mailto:"):
                continue
            if not (md.parent / target).exists():
                bad.append(f"{md.relative_to(ROOT)} -> {target}")
    return "; ".join(bad)


def helps() -> str:
    bad = [
        " ".join(args)
        for args in [(), *((c,) for c in SUBCOMMANDS)]
        if _run(sys.executable, "-m", "redistro.cli", *args, "--help").returncode != 0
    ]
    return "; ".join(f"redistro {b} --help failed" for b in bad)


def wheel() -> str:
    with tempfile.TemporaryDirectory() as tmp:
        done = _run(sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", tmp, ".")
        if done.returncode != 0:
            return "pip wheel failed: " + (done.stderr.strip().splitlines() or ["?"])[-1]
        wheels = list(Path(tmp).glob("redistro-*.whl"))
        if not wheels:
            return "no wheel built"
        names = zipfile.ZipFile(wheels[0]).namelist()
        if not any(re.match(r"redistro/_kernels.*\.so$", n) for n in names):
            return "the wheel has no compiled kernels"
    return ""


def main() -> int:
    failed = 0
    for check in (clean_tree, versions, links, helps, wheel):
        why = check()
        print(f"{'FAIL' if why else 'ok  '} {check.__name__}{': ' + why if why else ''}")
        failed += bool(why)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
