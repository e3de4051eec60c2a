"""The device kernel without a GPU: ``_kernel_cuda.cu`` compiled as host C++ with the CPU
kernel's flags and launched thread by thread (:mod:`mcsm.core.emulation`), against the CPU
kernel, bit for bit; and the device backend's Python code (:mod:`mcsm.core.device`) run end
to end on that emulated device.

What this shows: the device source computes the CPU kernel's bits (same arithmetic, same
summation order, same checks and codes) and the glue around it keeps the map's digests. What
it cannot show: that NVRTC compiles it to the same operations (tests/core/test_device_nvrtc.py
checks the PTX for fused multiply-adds) and that a real GPU runs it so
(``benchmarks/gpu_check.py``, on a machine with one).
"""

from __future__ import annotations

import ast
import json
import platform
import sys
from pathlib import Path

import numpy as np
import pytest
from mcsm import StochasticMap
from mcsm.core import emulation, kernel
from mcsm.core.device import HEADROOM_BYTES, DeviceComponent
from mcsm.errors import DeviceMemoryExceeded, InvalidOperation

from tests.core import device_cases, portable_history
from tests.helpers import random_at

ROOT = Path(__file__).resolve().parents[2]
RECORDINGS = sorted((ROOT / "recordings").glob("*.mcap"))


def _setup_flags() -> list[str]:
    tree = ast.parse((ROOT / "setup.py").read_text())
    for node in tree.body:
        if isinstance(node, ast.Assign) and getattr(node.targets[0], "id", "") == "KERNEL_FLAGS":
            flags: list[str] = ast.literal_eval(node.value)
            return flags
    raise AssertionError("setup.py has no KERNEL_FLAGS")


@pytest.fixture(scope="module")
def backend() -> emulation.EmulatedBackend:
    # the default cache (keyed by the sources and flags): gpu_check's rehearsal reuses it
    return emulation.EmulatedBackend(emulation.build())


def test_the_emulation_is_built_with_the_kernels_flags() -> None:
    c_only = {"-std=gnu11", "-fexcess-precision=standard"}
    assert [f for f in _setup_flags() if f not in c_only] == \
        [f for f in emulation.EMULATION_FLAGS if f != "-std=c++14"]


# ------------------------------------------------------------------ the frame pass, bit for bit

@pytest.mark.parametrize("n", [50, 1003])  # neither a multiple of 4: the lanes' tails count
@pytest.mark.parametrize("name", sorted(device_cases.CASES))
def test_the_device_frame_pass_gives_the_cpu_kernels_bits(
        backend: emulation.EmulatedBackend, name: str, n: int) -> None:
    case, _prep = device_cases.frame_case(name, n)
    cpu_codes, cpu_out = device_cases.cpu_pass(case)
    dev_codes, dev_out = device_cases.device_pass(case, backend)
    np.testing.assert_array_equal(dev_codes, cpu_codes)
    ok = cpu_codes == kernel.OK
    tamper = device_cases.CASES[name][2]
    if tamper in device_cases.FAILURES:
        assert not ok.all(), "the forced failure did not fail: the case tests nothing"
    else:
        assert ok.all()
    # the gain bound trips every frame with a gain (the codes are the comparison there); the
    # rescued sample's component has two frames
    assert ok.sum() >= {"wmax": 1, "opposite": 2}.get(tamper, 20)
    same = dev_out[ok].view(np.uint64) == cpu_out[ok].view(np.uint64)
    assert same.all(), f"{int((~same).sum())} of {same.size} values differ"


def test_a_contracting_build_of_the_same_source_differs(tmp_path: Path,
                                                         backend: emulation.EmulatedBackend
                                                         ) -> None:
    """The negative control: compiled with fused multiply-adds, the same source gives other
    bits, so the comparison above can fail."""
    flags = [f for f in emulation.EMULATION_FLAGS if f not in ("-ffp-contract=off", "-O3")]
    fma = ["-mfma"] if platform.machine() in ("x86_64", "AMD64") else []  # aarch64 has it
    lib = emulation.build(tmp_path, [*flags, "-O2", "-ffp-contract=fast", *fma])
    contracted = emulation.EmulatedBackend(lib)
    case, _ = device_cases.frame_case("default", 50)
    _, ref = device_cases.device_pass(case, backend)
    _, got = device_cases.device_pass(case, contracted)
    differ = int((ref.view(np.uint64) != got.view(np.uint64)).sum())
    assert differ > 100, differ


# ------------------------------------------------------------------ the backend's Python code

@pytest.mark.parametrize("option_set", [k for k in portable_history.OPTION_SETS if k != "paper"])
def test_the_scripted_history_has_the_cpus_digest_on_the_emulated_device(
        backend: emulation.EmulatedBackend, option_set: str) -> None:
    opts = portable_history.OPTION_SETS[option_set]
    before = dict(backend.launches)
    got = portable_history.history(1, device=backend, **opts)
    assert got == portable_history.history(1, **opts)
    for k in ("mk_d_joint_apply", "mk_d_transform", "mk_d_canon_check"):
        assert backend.launches.get(k, 0) > before.get(k, 0), f"{k} never ran"


def test_the_deferral_history_on_the_emulated_device(backend: emulation.EmulatedBackend) -> None:
    assert portable_history.deferral_history(1, device=backend) == \
        portable_history.deferral_history(1)


@pytest.mark.parametrize("path", RECORDINGS, ids=[p.name for p in RECORDINGS])
def test_the_shipped_recordings_replay_identical_on_the_emulated_device(
        backend: emulation.EmulatedBackend, path: Path) -> None:
    from mcsm.log.replay import replay

    rep = replay(path, device=backend)
    assert rep.identical, rep.divergence
    assert all(st.map.device == "emulated" for st in rep.states.values())


def _chain(be: emulation.EmulatedBackend, n: int = 24) -> StochasticMap:
    rng = np.random.default_rng(20261202)
    m = StochasticMap(n, gate=None, threads=1, device=be)
    for k in range(12):
        m.update(f"p{k}", f"p{k + 1}", random_at(rng, n, kind="cloud", t_sigma=0.1))
    for k in range(3):
        m.update(f"q{k}", f"q{k + 1}", random_at(rng, n, kind="cloud", t_sigma=0.1))
    return m


@pytest.mark.parametrize("what", ["loop closure", "join", "new frame", "remove root"])
def test_a_request_that_does_not_fit_is_refused_and_changes_nothing(
        backend: emulation.EmulatedBackend, what: str) -> None:
    n = 24
    m = _chain(backend, n)
    rng = np.random.default_rng(20261203)
    comp = m._comps[m._where["p0"]]
    k = 12
    while len(comp) < comp.capacity:  # fill p's capacity, so that a new frame must grow it
        m.update(f"p{k}", f"p{k + 1}", random_at(rng, n, kind="cloud", t_sigma=0.1))
        k += 1
    assert isinstance(comp, DeviceComponent) and len(comp) == comp.capacity == 16
    m._spare = None  # a loop closure must then allocate a whole component
    before = m.state_digest()
    mem = m.memory()
    assert mem["device"] == "emulated" and mem["bytes"] > 16 * 7 * n * 8
    op = {"loop closure": lambda: m.update("p1", "p9", m.query("p1", "p9")),
          "join": lambda: m.update("p3", "q0", random_at(rng, n, kind="cloud")),
          "new frame": lambda: m.update(f"p{k}", "new", random_at(rng, n, kind="cloud")),
          "remove root": lambda: m.remove("p0")}[what]
    old = backend.limit_bytes
    backend.limit_bytes = backend.in_use + HEADROOM_BYTES + 1024
    try:
        with pytest.raises(DeviceMemoryExceeded, match="device memory"):
            op()
        assert m.state_digest() == before
    finally:
        backend.limit_bytes = old
    op()
    assert m.state_digest() != before


def test_device_cuda_without_a_gpu_is_one_clear_error() -> None:
    try:
        import cupy

        if cupy.cuda.runtime.getDeviceCount() > 0:
            pytest.skip("a CUDA GPU is present: benchmarks/gpu_check.py covers it")
    except Exception:  # no CuPy, or CuPy without a driver: the case under test
        pass
    with pytest.raises(InvalidOperation, match="device='cuda'"):
        StochasticMap(50, device="cuda")


def test_the_paper_method_stays_on_the_cpu(backend: emulation.EmulatedBackend) -> None:
    with pytest.raises(InvalidOperation, match="CPU only"):
        StochasticMap(50, method="paper", device=backend)
    with pytest.raises(InvalidOperation, match="device must be"):
        StochasticMap(50, device="tpu")


def test_device_is_not_an_option_of_the_state(backend: emulation.EmulatedBackend) -> None:
    m = StochasticMap(24, device=backend)
    assert "device" not in m.options()
    assert m.state_digest() == StochasticMap(24).state_digest()
    assert m.device == "emulated" and StochasticMap(24).device == "cpu"


# ------------------------------------------------------------------ benchmarks/gpu_check.py

def _gpu_check(tmp_path: Path, *args: str) -> tuple[int, str]:
    import subprocess
    import sys

    res = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "gpu_check.py"),
                          "--out", str(tmp_path), *args], cwd=ROOT, capture_output=True,
                         text=True, timeout=300, check=False)
    return res.returncode, res.stdout + res.stderr


def test_gpu_check_rehearses_every_section_on_the_emulated_device(tmp_path: Path) -> None:
    """The script a GPU session runs once, unattended: every section runs and agrees here on
    the emulated device (small sizes), and its report files are written."""
    rc, out = _gpu_check(tmp_path, "--emulate", "--sizes", "40x50,24x1003", "--repeats", "2",
                         "--max-constraints", "150", "--dataset-samples", "16",
                         "--serve-frames", "40", "--serve-samples", "16",
                         "--serve-block-frames", "8", "--serve-seconds", "0.5",
                         "--tune-frames", "24", "--tune-blocks", "32,256", "--tune-spt", "4,8",
                         "--keep-tuned", "--dataset-every", "50")
    assert rc == 0, out[-3000:]
    # the tuning section: 4 launch shapes, each the default shape's bits, the default the
    # CPU kernel's; the fastest kept for the timing table
    assert out.count("| identical |") == 4 + 2, out[-3000:]  # and the 2 timing rows
    assert "default shapes vs the CPU kernel at M = 24: identical" in out
    assert "kept for the sections that follow: BLOCKS = {" in out
    # the datasets: four workers, digests compared after 50, 100, 150 updates and at the end
    assert out.count("3 checkpoints compared") == 2, out[-3000:]
    assert "FAILED" not in out and "DIFFERENT" not in out and "DIVERGED" not in out
    assert out.count("identical") >= 20 + len(RECORDINGS) + 2
    assert "| 40 | 50 |" in out and "| 24 | 1003 |" in out
    # the serve section: `mcsm serve --device cuda` built 40 frames from 5 imports and 4
    # joins over Zenoh, and every measured update was an acknowledged loop closure
    assert "built by 5 acknowledged imports" in out and "4 joins" in out
    assert "40 frames in one component" in out
    assert "info: 40 frames, 1 component(s), device emulated" in out
    report = (tmp_path / "gpu_check.txt").read_text()
    sections = [line for line in report.splitlines() if line.startswith("## ")]
    assert [line.split(":")[0] for line in sections] == \
        ["## bits", "## the shipped recordings replayed on the device", "## tuning",
         "## timings",
         "## serve", "## datasets"], sections  # the bits first, then the timings
    data = json.loads((tmp_path / "gpu_check.json").read_text())
    rates = data["serve"]["rates"]
    assert [r["clients"] for r in rates] == [1, 4]
    assert all(r["acked"] >= 1 and set(r["kinds"]) == {"loop_closure"} for r in rates)
    assert data["serve"]["server_exit"] == 0


def test_gpu_check_dataset_comparison_finds_a_different_checkpoint() -> None:
    """The dataset section's verdict: the same only where every common checkpoint and both
    ends agree; a differing checkpoint, a differing end or nothing in common is not."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        from gpu_datasets import compare
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))

    def ck(k: int, d: str, final: bool = False) -> dict[str, object]:
        return {"k": k, "digest": d, "outcomes": "o", "seconds": 1.0, "final": final}

    cpu = [ck(50, "a"), ck(100, "b"), ck(120, "c", True)]
    assert compare(cpu, [ck(50, "a"), ck(100, "b"), ck(120, "c", True)])["same"]
    assert compare(cpu, [ck(50, "a"), {"k": 70, "stopped": True}])["same"]  # a prefix
    res = compare(cpu, [ck(50, "a"), ck(100, "X"), ck(120, "c", True)])
    assert not res["same"] and res["checkpoints_differ"] == [100]
    assert not compare(cpu, [ck(50, "a"), ck(100, "b"), ck(120, "Y", True)])["same"]
    assert not compare(cpu, [{"k": 10, "stopped": True}])["same"]  # nothing compared


def test_gpu_check_without_a_gpu_says_so_and_exits_0(tmp_path: Path) -> None:
    try:
        import cupy

        if cupy.cuda.runtime.getDeviceCount() > 0:
            pytest.skip("a GPU is present")
    except Exception:  # no CuPy or no driver: the case under test
        pass
    rc, out = _gpu_check(tmp_path)
    assert rc == 0, out[-2000:]
    assert "no GPU here" in out


def test_a_retraction_rebuilds_the_map_on_its_device(backend: emulation.EmulatedBackend) -> None:
    """The retract window rebuilds a map from an in-memory snapshot: on the map's own device,
    with the CPU's digest."""
    from mcsm import wire
    from mcsm.map.state import MapState

    rng = np.random.default_rng(20261207)
    n = 24
    inputs = [(f"u{k}", f"p{k}", f"p{k + 1}", random_at(rng, n, kind="cloud", t_sigma=0.1))
              for k in range(9)]
    chain = StochasticMap(n)
    for _, a, b, x in inputs:
        chain.update(a, b, x)
    x_loop = chain.query("p1", "p8")[rng.permutation(n)]
    states = [MapState("default", StochasticMap(n, device=d), snapshot_every=3,
                       snapshots_kept=10) for d in ("cpu", backend)]
    for st in states:
        for rid, a, b, x in inputs:
            st.apply("update", wire.UpdateRequest(rid, a, b, x), time_ns=0)
        st.apply("update", wire.UpdateRequest("loop", "p1", "p8", x_loop), time_ns=0)
        before = st.digest()
        st.apply("retract", wire.RetractRequest("r1", "u4"), time_ns=0)
        assert st.digest() != before
    assert states[1].map.device == "emulated"
    assert states[1].digest() == states[0].digest()


def test_the_apply_step_takes_more_samples_per_thread_only_on_large_components() -> None:
    """32 samples a thread where that still leaves 2**21 threads (measured faster at
    M = 100,000, N = 1000), 8 elsewhere (the shape smaller maps were measured with)."""
    from mcsm.core import device

    assert device.apply_samples_per_thread(100_000, 1000) == 32
    assert device.apply_samples_per_thread(10_000, 10_000) == 32
    assert device.apply_samples_per_thread(40_000, 1000) == 8
    assert device.apply_samples_per_thread(400, 1000) == 8
