"""The device kernel compiled by NVRTC, the compiler ``device="cuda"`` uses, from PyPI's
``nvidia-cuda-nvrtc`` wheel (no GPU needed): it compiles with the backend's options, and its
PTX has no fused multiply-add on doubles, the one contraction that would change the CPU
kernel's bits. The negative control compiles the same source with contraction allowed and
finds them, so the check can fail.
"""

from __future__ import annotations

import re

import pytest
from mcsm.core import emulation
from mcsm.core.device import NVRTC_OPTIONS

FUSED = re.compile(r"\b(fma|mad)\.[a-z.]*f64\b")
KERNELS = ["mk_d_joint_sums", "mk_d_joint_gain", "mk_d_joint_apply", "mk_d_transform",
           "mk_d_meanrot_lanes", "mk_d_meanrot_finish", "mk_d_canon_check"]


@pytest.fixture(scope="module")
def nvrtc() -> str:
    path = emulation.nvrtc_library()
    if path is None:
        pytest.skip("NVRTC is not installed here (pip install nvidia-cuda-nvrtc; the test "
                    "extra has it on Linux x86-64 and aarch64)")
    return path


def test_nvrtc_compiles_the_device_kernel_without_fused_multiply_adds(nvrtc: str) -> None:
    ptx = emulation.compile_ptx(NVRTC_OPTIONS, "compute_90", library=nvrtc)  # Hopper
    for k in KERNELS:
        assert f".entry {k}(" in ptx, k
    assert FUSED.findall(ptx) == []
    assert "div.rn.f64" in ptx and "sqrt.rn.f64" in ptx  # IEEE division and square root


def test_with_contraction_allowed_the_same_source_has_them(nvrtc: str) -> None:
    opts = tuple("--fmad=true" if o == "--fmad=false" else o for o in NVRTC_OPTIONS)
    assert len(FUSED.findall(emulation.compile_ptx(opts, library=nvrtc))) > 100


def test_ptxas_reports_what_each_kernel_needs_and_none_spills(nvrtc: str) -> None:
    """Registers per thread decide how many warps an SM holds (docs/kernel.md, "Measured on
    a GPU"); with the shipped options no kernel spills to local memory. Capped at 64
    registers the apply step does, so the check can fail."""
    info = emulation.ptxas_info(NVRTC_OPTIONS, library=nvrtc)
    assert set(KERNELS) <= set(info)
    assert all(info[k]["registers"] > 0 and info[k]["spill_stores"] == 0 for k in KERNELS)
    capped = emulation.ptxas_info((*NVRTC_OPTIONS, "--maxrregcount=64"), library=nvrtc)
    assert capped["mk_d_joint_apply"]["registers"] <= 64
    assert capped["mk_d_joint_apply"]["spill_stores"] > 0
