"""The one compiled part: redistro._kernels (C), built by the normal pip install.

Its sources sit beside their Python owners (redistro/kernels.h lists them).
Their buffer offsets come from one header generated here from the declared
layouts (redistro/kernel_layouts.py), into the build's own directory.
libcrypto (HMAC) and zlib (crc32) are linked.

Everything else about the package is in pyproject.toml.
"""

import os
import sys

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

HERE = os.path.dirname(os.path.abspath(__file__))
SOURCES = [
    "redistro/kernel_core.c",
    "redistro/plant/chassis_kernel.c",
    "redistro/drivers/driver_kernel.c",
    "redistro/esc/guard_kernel.c",
    "redistro/control/joint_kernel.c",
    "redistro/control/linalg.c",
    "redistro/control/cartesian_kernel.c",
    "redistro/ddm/wire_kernel.c",
    "redistro/ddm/step_kernel.c",
    "redistro/ddm/answer_kernel.c",
]


class BuildKernels(build_ext):
    """build_ext that first writes kernel_layouts.h from the layouts."""

    def run(self) -> None:
        sys.path.insert(0, HERE)
        try:
            from redistro import kernel_layouts
        finally:
            sys.path.remove(HERE)
        generated = os.path.join(os.path.abspath(self.build_temp), "generated")
        os.makedirs(generated, exist_ok=True)
        path = os.path.join(generated, "kernel_layouts.h")
        text = kernel_layouts.header()
        old = None
        if os.path.exists(path):
            with open(path) as f:
                old = f.read()
        if old != text:  # (an unchanged header rebuilds nothing)
            with open(path, "w") as f:
                f.write(text)
        for ext in self.extensions:
            ext.include_dirs.append(generated)
            ext.depends.append(path)
        super().run()


setup(
    cmdclass={"build_ext": BuildKernels},
    ext_modules=[
        Extension(
            "redistro._kernels",
            SOURCES,
            depends=[
                "redistro/kernels.h",
                "redistro/control/linalg.h",
                "redistro/ddm/wire.h",
                "redistro/ddm/step.h",
            ],
            libraries=["crypto", "z"],
            # one module from many files: only its init is exported, and the
            # link inlines across the files (-flto), as one file would
            extra_compile_args=[
                "-O2",
                "-std=c11",
                "-Wall",
                "-Wextra",
                "-Wno-unused-parameter",
                "-fvisibility=hidden",
                "-flto=auto",
            ],
            extra_link_args=["-O2", "-flto=auto"],
        )
    ],
)
