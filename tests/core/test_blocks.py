"""The joint update's frame pass: bit-identical whatever the thread count or frame split.

The server replays recordings on whatever machine it runs on, so a digest must not depend on
the number of cores: these tests run the same operations on one thread and on several with
frame ranges of every size, and compare state digests bit for bit.
"""

from __future__ import annotations

import numpy as np
import pytest
from mcsm import StochasticMap
from mcsm.core import joint
from mcsm.errors import InvalidOperation

from tests.helpers import random_at

N = 48


def _run(threads: int, **opts: object) -> StochasticMap:
    """A chain of 40 frames with point landmarks and a dozen loop closures of both kinds."""
    rng = np.random.default_rng(4242)
    m = StochasticMap(N, threads=threads, **opts)  # type: ignore[arg-type]
    for k in range(40):
        m.update(f"p{k}", f"p{k + 1}", random_at(rng, N, kind="cloud", t_sigma=0.1,
                                                  r_sigma=0.02))
        if k % 5 == 0:
            m.update(f"p{k}", f"l{k}", 2.0 + 0.1 * rng.standard_normal((N, 3)))
    for k in range(12):
        a, b = rng.choice(41, 2, replace=False)
        m.update(f"p{a}", f"p{b}", m.query(f"p{a}", f"p{b}")[rng.permutation(N)])
        if k % 3 == 0:
            m.update(f"p{b}", f"l{5 * (k % 8)}", 2.0 + 0.1 * rng.standard_normal((N, 3)))
    return m


@pytest.mark.parametrize("opts", [{}, {"space": "quaternion"}, {"inflation": 1.01},
                                  {"inflation": "adaptive", "shrink": None},
                                  {"gain": "endpoints"}, {"gain": "endpoints", "shrink": None}])
def test_digest_does_not_depend_on_threads(monkeypatch: pytest.MonkeyPatch,
                                           opts: dict[str, object]) -> None:
    one_thread = _run(1, **opts).state_digest()
    monkeypatch.setattr(joint, "_MIN_FRAMES_PER_TASK", 1)  # split even the smallest component
    for threads in (2, 3, 4):
        assert _run(threads, **opts).state_digest() == one_thread


def test_edges_is_a_copy_that_later_updates_do_not_touch() -> None:
    rng = np.random.default_rng(5)
    m = StochasticMap(N, threads=2, gate=None)  # random closures: the gate would refuse them
    for k in range(5):
        m.update(f"x{k}", f"x{k + 1}", random_at(rng, N, kind="cloud"))
    before = m.edges("x0")
    kept = before.copy()
    for _ in range(3):  # the replaced edge arrays are reused as scratch space
        m.update("x0", "x5", random_at(rng, N, kind="cloud"))
    np.testing.assert_array_equal(before, kept)
    assert not np.array_equal(m.edges("x0"), kept)


@pytest.mark.parametrize("threads", [0, -1, 1.5, True, "2"])
def test_bad_thread_counts_are_refused(threads: object) -> None:
    with pytest.raises(InvalidOperation):
        StochasticMap(N, threads=threads)  # type: ignore[arg-type]


def test_threads_are_not_an_option_of_the_state() -> None:
    assert "threads" not in StochasticMap(N, threads=3).options()
    assert StochasticMap(N, threads=1).state_digest() == StochasticMap(N, threads=4).state_digest()
