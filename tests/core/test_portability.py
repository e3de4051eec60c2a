"""One map history, one digest: on every BLAS kernel, numpy CPU feature set, thread count and
build of the compiled kernel.

Our own green CI cannot show a dependence on the CPU, so these tests change what varies
between machines inside one: OpenBLAS's kernels (``OPENBLAS_CORETYPE``), numpy's SIMD
dispatch (``NPY_DISABLE_CPU_FEATURES``), the thread count, and the kernel compiled for
baseline x86-64 (SSE2) and for this CPU (``-march=native``: AVX2, FMA where it exists). Each
runs the scripted history of :mod:`tests.core.portable_history` in a fresh interpreter, with
every option set of the joint update, and replays the shipped recordings.
"""

from __future__ import annotations

import ast
import importlib.util
import json
import os
import platform
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SOURCES = [ROOT / "service" / "mcsm" / "core" / f for f in (
    "_kernel.c", "_relin.c", "_relin_order.c", "_relin_chol.c", "_relin_draw.c")]
RECORDINGS = sorted(str(p) for p in (ROOT / "recordings").glob("*.mcap"))


def _kernel_flags() -> list[str]:
    """The flags setup.py builds the kernel with (read from its source, not executed)."""
    tree = ast.parse((ROOT / "setup.py").read_text())
    for node in tree.body:
        if isinstance(node, ast.Assign) and getattr(node.targets[0], "id", "") == "KERNEL_FLAGS":
            flags: list[str] = ast.literal_eval(node.value)
            return flags
    raise AssertionError("setup.py has no KERNEL_FLAGS")


CONFIGS: dict[str, dict[str, str]] = {
    "openblas-prescott": {"OPENBLAS_CORETYPE": "Prescott"},
    "openblas-sandybridge": {"OPENBLAS_CORETYPE": "Sandybridge"},
    "openblas-haswell": {"OPENBLAS_CORETYPE": "Haswell"},
    "numpy-no-avx2-fma": {"NPY_DISABLE_CPU_FEATURES": "AVX2 FMA3 AVX512F"},
}


def _run(env_extra: dict[str, str], threads: int) -> dict[str, object]:
    env = {**os.environ, **env_extra, "PYTHONPATH": str(ROOT)}
    out = subprocess.run(
        [sys.executable, "-m", "tests.core.portable_history", "--threads", str(threads),
         "--replay", *RECORDINGS],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=300, check=False)
    assert out.returncode == 0, out.stderr[-3000:]
    result: dict[str, object] = json.loads(out.stdout)
    return result


@pytest.fixture(scope="module")
def reference() -> dict[str, object]:
    return _run({}, 1)


@pytest.fixture(scope="module")
def kernel_builds(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    if platform.machine() not in ("x86_64", "AMD64"):
        pytest.fail("the build matrix of this test is written for x86-64")
    cc = shutil.which("gcc") or shutil.which("cc")
    assert cc is not None, "a C compiler is needed to build mcsm's kernel"
    out = tmp_path_factory.mktemp("kernels")
    builds = {}
    for name, march in (("baseline", "-march=x86-64"), ("native", "-march=native"),
                        ("plain-factor", "-DMR_PLAIN_FACTOR")):
        lib = out / f"kernel-{name}.so"
        subprocess.run([cc, *_kernel_flags(), march, "-shared", "-fPIC",
                        *(str(s) for s in SOURCES), "-o", str(lib)], check=True,
                       capture_output=True, timeout=120)
        builds[name] = lib
    return builds


def test_the_shipped_recordings_replay_identical(reference: dict[str, object]) -> None:
    for path in RECORDINGS:
        rep = reference[path]
        assert isinstance(rep, dict)
        assert rep["identical"], f"{path}: {rep['divergence']}"


@pytest.mark.parametrize("config", sorted(CONFIGS))
def test_same_digests_under_other_blas_and_simd(reference: dict[str, object],
                                                config: str) -> None:
    assert _run(CONFIGS[config], 2) == reference


@pytest.mark.parametrize("build", ["baseline", "native", "plain-factor"])
def test_same_digests_with_the_kernel_built_for_other_cpus(
        reference: dict[str, object], kernel_builds: dict[str, Path], build: str) -> None:
    """Also "plain-factor": the relinearisation's factorisation without its unrolled and
    paired-lane paths for 6- and 3-dimensional blocks (``MR_PLAIN_FACTOR``), the order of
    operations those paths must keep."""
    got = _run({"MCSM_KERNEL_LIBRARY": str(kernel_builds[build]),
                "OPENBLAS_CORETYPE": "Sandybridge"}, 2)
    assert got == reference


def test_same_digests_with_the_installed_baseline_build(reference: dict[str, object]) -> None:
    """pip installs a baseline and an AVX2 build; the reference ran on the one this CPU
    picks (the AVX2 one on x86-64 with AVX2): the other must agree."""
    spec = importlib.util.find_spec("mcsm.core._kernel")
    assert spec is not None and spec.origin is not None
    assert _run({"MCSM_KERNEL_LIBRARY": spec.origin}, 1) == reference


def test_every_option_set_changes_the_digest(reference: dict[str, object]) -> None:
    digests = [v for k, v in reference.items() if not k.endswith(".mcap")]
    assert len(set(digests)) == len(digests) == 10  # 9 option sets and the --gate-defer run
