"""The loop closures the device kernel is compared on, bit for bit, against the CPU kernel: every
option set of the joint update, point observations, three forced failures (the gain bound, a
NaN in one frame, a quaternion pushed to zero) and a sample the apply step rescues (one nearly
opposite its frame's centre, whose linear move crosses zero). Shared by
tests/core/test_device_emulation.py (the emulated device) and benchmarks/gpu_check.py (a real
GPU).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from mcsm import StochasticMap
from mcsm.core import joint, kernel
from mcsm.core.device import Backend, DeviceComponent
from mcsm.core.storage import to_rows

from tests.helpers import random_at


def component(n: int, rng: np.random.Generator) -> StochasticMap:
    """A 3-D chain of 24 frames with point landmarks, after a few loop closures."""
    m = StochasticMap(n, gate=None, threads=1)
    for k in range(24):
        m.update(f"p{k}", f"p{k + 1}", random_at(rng, n, kind="cloud", t_sigma=0.2,
                                                  r_sigma=0.05))
        if k % 5 == 0:
            m.update(f"p{k}", f"l{k}", 2.0 + 0.2 * rng.standard_normal((n, 3)))
    for a, b in ((2, 20), (7, 24), (0, 13)):
        m.update(f"p{a}", f"p{b}", m.query(f"p{a}", f"p{b}")[rng.permutation(n)])
    return m


def opposite_sample_map(n: int, om: float = 0.25) -> tuple[StochasticMap, np.ndarray]:
    """A planar edge a→b whose sample 0 points 3 rad (172°) away from the others, and a
    precise re-observation of it: the linear move in the quaternion's coordinates takes that
    sample's quaternion through zero (w10000's step 2445 in small, where one sample of 1000 had
    drifted 2.5-3.1 rad from its frames' means). The map and the observation."""
    from mcsm_client.sampling import sample_planar

    rng = np.random.default_rng(5)
    ab = np.zeros((n, 7))
    ab[:, 0] = 5.0 + 0.5 * rng.standard_normal(n)
    ab[:, 1] = 0.5 * rng.standard_normal(n)
    th = 0.3 * rng.standard_normal(n)
    th[0] = 3.0
    ab[:, 3], ab[:, 6] = np.cos(th / 2), np.sin(th / 2)
    obs = sample_planar(np.array([5.0, 0.0, om]), np.diag([0.05, 0.05, 0.02]) ** 2,
                        n_samples=n, rng=rng)
    m = StochasticMap(n, gate=None, relinearize=None, threads=1)
    m.update("a", "b", ab)
    return m, obs


FAILURES = ("wmax", "nan", "tiny-q")
"""The tamperings that make frames fail (the others must pass)."""

# name: (options of the pass, point observation, tampering)
CASES: dict[str, tuple[dict[str, Any], bool, str]] = {
    "default": (dict(space="tangent", gain="direct", shrink=4.0, inflation=1.0), False, ""),
    "quaternion": (dict(space="quaternion", gain="direct", shrink=4.0, inflation=1.0), False, ""),
    "endpoints": (dict(space="tangent", gain="endpoints", shrink=4.0, inflation=1.002), False,
                  ""),
    "endpoints-no-shrink": (dict(space="tangent", gain="endpoints", shrink=None,
                                 inflation=1.0), False, ""),
    "enkf-no-shrink-inflation": (dict(space="quaternion", gain="direct", shrink=None,
                                      inflation=1.01, rule="enkf"), False, ""),
    "denkf-point": (dict(space="tangent", gain="direct", shrink=4.0, inflation=1.0,
                         rule="denkf"), True, ""),
    "endpoints-point-denkf-inflation": (dict(space="tangent", gain="endpoints", shrink=4.0,
                                             inflation=1.01, rule="denkf"), True, ""),
    "gain-bound": (dict(space="tangent", gain="direct", shrink=4.0, inflation=1.0), False,
                   "wmax"),
    "nan-in-one-frame": (dict(space="tangent", gain="direct", shrink=4.0, inflation=1.0),
                         False, "nan"),
    "quaternion-to-zero": (dict(space="tangent", gain="direct", shrink=4.0, inflation=1.0),
                           False, "tiny-q"),
    "opposite-sample-rescued": (dict(space="tangent", gain="direct", shrink=4.0,
                                     inflation=1.0), False, "opposite"),
}


def frame_case(name: str, n: int) -> tuple[dict[str, Any], joint.Prepared]:
    """One loop closure's frame pass inputs for case ``name``."""
    opts, point, tamper = CASES[name]
    rng = np.random.default_rng(20261201 + n)
    if tamper == "opposite":
        m, x = opposite_sample_map(n)
        a, b = "a", "b"
    else:
        m = component(n, rng)
        a, b = ("p3", "l15") if point else ("p3", "p21")
        x = m.query(a, b)[rng.permutation(n)]
    c = m._comps[m._where[a]]
    x_rows = to_rows(x[:, :3] if point else x)
    rule = str(opts.get("rule", "ensrf"))
    prep = joint.prepare(c, c.index[a], c.index[b], x_rows, point, str(opts["space"]), rule)
    args, arrays = joint.frame_args(c, c.index[a], c.index[b], prep, space=str(opts["space"]),
                                    gain=str(opts["gain"]), shrink=opts["shrink"],
                                    inflation=float(opts["inflation"]))
    rows = c.rows.copy()
    if tamper == "wmax":
        args.wmax = 1e300
    elif tamper == "nan":
        rows[9, 1, 17] = np.nan
    elif tamper == "tiny-q":
        rows[11, 3:, 5] = [1e-3, 0.0, 0.0, 0.0]
    return {"args": args, "arrays": arrays, "rows": rows, "flags": c.point_list(),
            "frames": list(c.frames)}, prep


def cpu_pass(case: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame codes and outputs of the CPU kernel, one frame per call."""
    args, arrays, rows = case["args"], case["arrays"], case["rows"]
    assert isinstance(args, kernel.JointArgs) and isinstance(arrays, dict)
    assert isinstance(rows, np.ndarray)
    for name_, arr in arrays.items():
        setattr(args, name_, kernel.ptr(arr))
    flags = np.asarray(case["flags"], dtype=np.uint8)
    out = np.zeros_like(rows)
    codes = np.array([kernel.joint_frames(args, rows, out, flags, f, f + 1)
                      for f in range(rows.shape[0])])
    return codes, out


def device_pass(case: dict[str, Any], be: Backend) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame codes and outputs of the device kernel on backend ``be``."""
    args, arrays, rows = case["args"], case["arrays"], case["rows"]
    assert isinstance(args, kernel.JointArgs) and isinstance(arrays, dict)
    assert isinstance(rows, np.ndarray)
    dc = DeviceComponent.from_rows(be, list(case["frames"]), list(case["flags"]), rows)
    out = be.zeros(dc.buffer.shape)
    rc, fl = dc.frame_pass(args, arrays, out)
    xp = be.xp
    codes = xp.where(rc != 0, rc, xp.where(fl & 1, kernel.BAD_QUATERNION,
                                           xp.where(fl & 2, kernel.NONFINITE, 0)))
    host = be.download(out)[:, :, : rows.shape[0]]
    return (np.asarray(be.download(codes)),
            np.ascontiguousarray(np.transpose(host, (2, 0, 1))))


