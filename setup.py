"""Builds mcsm's compiled kernel (``mcsm.core._kernel``), a plain C shared library loaded with
ctypes by ``mcsm.core.kernel``; everything else is declared in pyproject.toml.

The flags fix the arithmetic: no fast-math, no fused multiply-add (``-ffp-contract=off``): the
library gives the same bits on every CPU (README, "Portable arithmetic"). On x86-64 the same
source is built twice, for baseline x86-64 (``_kernel``) and with AVX2 (``_kernel_avx2``,
loaded when the CPU has it: same bits, its four lanes fit one register). A missing compiler or
a failed build stops the install with one line saying so: there is no fallback to another
implementation.
"""

import platform
import sys

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

KERNEL_FLAGS = ["-std=gnu11", "-O3", "-ffp-contract=off", "-fno-fast-math",
                "-fno-unsafe-math-optimizations", "-fno-math-errno", "-fexcess-precision=standard",
                "-Wall", "-Wno-unused-function", "-Wno-psabi"]


class BuildKernel(build_ext):
    def run(self) -> None:
        try:
            super().run()
        except Exception as exc:  # one clear line, then fail the install
            sys.stderr.write(
                f"\nmcsm: building the compiled kernel (service/mcsm/core/_*.c) failed: "
                f"{type(exc).__name__}: {exc}. mcsm needs a C compiler (gcc or clang) and the "
                f"Python headers at install time (Debian: apt-get install gcc python3-dev).\n")
            raise


# _kernel.c: the map's updates; _relin*.c: relinearisation (the same flags, linked into the
# same libraries).
SOURCE = ["service/mcsm/core/_kernel.c", "service/mcsm/core/_relin.c",
          "service/mcsm/core/_relin_order.c", "service/mcsm/core/_relin_chol.c",
          "service/mcsm/core/_relin_draw.c"]
# the per-sample and per-frame arithmetic shared with the device kernel (_kernel_cuda.cu)
DEPENDS = ["service/mcsm/core/kernel_common.h", "service/mcsm/core/_relin.h"]
KERNELS = [Extension("mcsm.core._kernel", SOURCE, depends=DEPENDS,
                     extra_compile_args=KERNEL_FLAGS)]
if platform.machine().lower() in ("x86_64", "amd64"):
    KERNELS.append(Extension("mcsm.core._kernel_avx2", SOURCE, depends=DEPENDS,
                             extra_compile_args=[*KERNEL_FLAGS, "-mavx2"]))

setup(ext_modules=KERNELS, cmdclass={"build_ext": BuildKernel})
