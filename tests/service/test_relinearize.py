"""Relinearisation over the wire: the ``relinearize`` operation and a server's automatic
policy, through retract, replay, ``--restore`` from a recorded snapshot and a hot standby on
the map's NATS log (with its takeover after the primary's SIGKILL).

The map's relinearisation is deterministic kernel code driven by the recorded inputs, so each
of these paths recomputes it: the digests are compared with an in-process ``StochasticMap``
fed the same inputs (and, for the retraction, without the retracted one).
"""

from __future__ import annotations

import json
import signal
from pathlib import Path

import numpy as np
import pytest
from mcsm import StochasticMap
from mcsm.errors import McsmError
from mcsm.log.replay import replay
from mcsm.serve.natsrun import NatsCluster
from mcsm_client.cli import main as client_main
from mcsm_client.client import MapClient

from tests.service.daemon_util import Daemon, noisy_at, start_daemon, start_router, wait_for

N = 32
POLICY = {"nis": 0.95, "every": 6, "gap": 3, "regate": 1, "spread": 1.3, "recentre": False}
# OPTS leave --relinearize-spread at its default (the default policy's 1.3); the standby test
# names it
# the recording's one state snapshot comes at seq 25, after the retract and reinstate (a
# --restore from a snapshot taken between a retracted input and its retraction refuses the
# retraction: a limit of the retract window, not of relinearisation)
OPTS = ("--samples", str(N), "--snapshot-every", "4", "--snapshots-kept", "8",
        "--disk-snapshot-every", "25", "--relinearize-nis", "0.95", "--relinearize-every", "6",
        "--relinearize-gap", "3", "--relinearize-regate", "1", "--no-relinearize-recentre",
        "--relinearize-readmit", "none")

Op = tuple[str, str, str, str, "np.ndarray | None", bool]  # id, kind, a, b, samples, trusted


RECENTRE = {**POLICY, "recentre": True, "readmit": 300, "calibrate": 15}  # as the default


def _inputs(rng: np.random.Generator, policy: dict[str, object]) -> list[Op]:
    """A chain with landmarks, true closures, a wrong closure forced in, and relinearize
    requests (one of the whole map, one of a component) after it."""
    local = StochasticMap(N, relinearize=policy)
    ops: list[Op] = []

    def add(op: Op) -> None:
        ops.append(op)
        _apply(local, op)

    for k in range(10):
        add((f"odo{k}", "update", f"p{k}", f"p{k + 1}", noisy_at(rng, N, [1.0, 0, 0], yaw=0.2),
             False))
        if k % 3 == 0:
            p = np.array([1.0, 2.0, 0.0]) + 0.1 * rng.standard_normal((N, 3))
            add((f"pt{k}", "update", f"p{k}", "l0", p, False))
    wrong = local.query("p2", "p7")
    wrong[:, 1] += 2.0
    add(("wrong", "update", "p2", "p7", wrong, True))
    add(("rl-all", "relinearize", "", "", None, False))
    add(("close", "update", "p0", "p10", local.query("p0", "p10")[rng.permutation(N)], False))
    add(("rm", "remove", "p4", "", None, False))
    add(("rl-p1", "relinearize", "p1", "", None, False))
    for k in range(10, 13):
        add((f"odo{k}", "update", f"p{k}", f"p{k + 1}", noisy_at(rng, N, [1.0, 0, 0], yaw=0.2),
             False))
    return ops


def _apply(m: StochasticMap, op: Op) -> None:
    _, kind, a, b, x, trusted = op
    if kind == "update":
        assert x is not None
        m.update(a, b, x, trusted=trusted)
    elif kind == "remove":
        m.remove(a)
    else:
        m.relinearize(a or None)


def _send(c: MapClient, op: Op) -> None:
    rid, kind, a, b, x, trusted = op
    if kind == "update":
        if x is not None and x.shape[1] == 3:
            c.update_point(a, b, x, request_id=rid)
        else:
            c.update(a, b, x, request_id=rid, trusted=trusted)
    elif kind == "remove":
        c.remove(a, request_id=rid)
    else:
        ack = c.relinearize(a, request_id=rid)
        assert ack.op == ack.kind == "relinearize" and ack.relin is not None
        assert ack.relin["trigger"] == "request" and ack.relin["time_s"] >= 0.0
        assert all(d["skipped"] == "" and d["iterations"] >= 1 for d in ack.relin["components"])


def _fresh(ops: list[Op], skip: str = "", policy: dict[str, object] = POLICY) -> StochasticMap:
    m = StochasticMap(N, relinearize=policy)
    for op in ops:
        if op[0] != skip:
            _apply(m, op)
    return m


@pytest.mark.parametrize("policy", [POLICY, RECENTRE], ids=["policy", "recentre"])
def test_retract_replay_and_restore_through_relinearisations(
        tmp_path: Path, daemons: list[Daemon], capsys: pytest.CaptureFixture[str],
        policy: dict[str, object]) -> None:
    """With the policy (and with re-centring after every closure too): retract and reinstate
    across relinearisations, replay, replay from a snapshot and --restore all give the map
    that the same inputs give in process."""
    ops = _inputs(np.random.default_rng(20261210), policy)
    opts = (*OPTS, "--relinearize-recentre", "--relinearize-readmit", "300") \
        if policy.get("recentre") else OPTS
    d = start_daemon(tmp_path, *opts)
    daemons.append(d)
    rng = np.random.default_rng(5)
    with MapClient(connect=d.endpoint, timeout_s=20.0) as c:
        for op in ops:
            _send(c, op)
        with_wrong = c.info().digest
        assert with_wrong == _fresh(ops, policy=policy).state_digest()
        # retract an input from before both relinearize requests and several automatic
        # relinearisations: the map is the one that never had it
        assert c.retract("wrong").verdict.status == "retracted"  # type: ignore[union-attr]
        assert c.info().digest == _fresh(ops, "wrong", policy).state_digest() != with_wrong
        assert c.reinstate("wrong").verdict.status == "reinstated"  # type: ignore[union-attr]
        assert c.info().digest == with_wrong
        tail: list[Op] = [
            ("odo13", "update", "p13", "p14", noisy_at(rng, N, [1.0, 0, 0]), False),
            ("rl-late", "relinearize", "", "", None, False),  # after the disk snapshot
            ("odo14", "update", "p14", "p15", noisy_at(rng, N, [1.0, 0, 0]), False)]
        for op in tail:
            _send(c, op)
        final = c.info()
    local = _fresh(ops + tail, policy=policy)
    assert final.digest == local.state_digest()
    assert d.stop(signal.SIGKILL) != 0
    full, fast = replay(d.record), replay(d.record, from_snapshot=True)
    assert full.divergence is None and full.final_digests()["default"] == final.digest
    assert fast.divergence is None and fast.snapshots_loaded == 1 and fast.n_inputs == 2
    assert fast.states["default"].digest() == final.digest
    d2 = start_daemon(tmp_path, *opts, "--restore", str(d.record), name="d2",
                      listen_on=d.endpoint)
    daemons.append(d2)
    with MapClient(connect=d2.endpoint, timeout_s=20.0) as c:
        assert c.info().digest == final.digest
        # the command line: mcsm-client relinearize [FRAME] prints what the ack says
        assert client_main(["relinearize", "p1", "--json", "--connect", d2.endpoint]) == 0
        out = json.loads(capsys.readouterr().out)
        assert out["kind"] == "relinearize" and out["relin"]["components"][0]["frames"] >= 10
        local.relinearize("p1")
        assert c.info().digest == local.state_digest()
    assert d2.stop(signal.SIGINT) == 0, d2.log_text()
    assert replay(d2.record).identical


def test_a_standby_follows_relinearisations(tmp_path: Path, daemons: list[Daemon],
                                            nats: NatsCluster) -> None:
    """Whatever applies inputs through ``MapState.apply`` recomputes a relinearisation: a
    standby that joins late (catching up from the map's NATS log) and then follows live holds
    the primary's digest; after the primary's SIGKILL it takes over with that digest and
    relinearises on request itself. The daemons leave re-centring and readmission at their
    defaults (on)."""
    ops = _inputs(np.random.default_rng(20261211), RECENTRE)
    router, ep = start_router(tmp_path)
    repl = ("--samples", str(N), "--connect", ep, "--nats", ",".join(nats.urls),
            "--relinearize-nis", "0.95", "--relinearize-every", "6", "--relinearize-gap", "3",
            "--relinearize-regate", "1", "--relinearize-spread", "1.3")
    try:
        p = start_daemon(tmp_path, *repl, "--map", "m", name="p", endpoint="-")
        daemons.append(p)
        with MapClient(map="m", connect=ep, timeout_s=30.0) as c:
            half = len(ops) // 2
            for op in ops[:half]:
                _send(c, op)
            s = start_daemon(tmp_path, *repl, "--standby-of", "m", name="s", endpoint="-")
            daemons.append(s)
            for op in ops[half:]:  # both relinearize requests come after the standby joined
                _send(c, op)
            info = c.info()
            assert info.digest == _fresh(ops, policy=RECENTRE).state_digest()
            wait_for("the standby holds the head",
                     lambda: list(c.info().standbys.values()) == [info.seq])
            p.proc.send_signal(signal.SIGKILL)
            p.proc.wait(timeout=10)
            wait_for("the standby serves", lambda: c.info().server_id != info.server_id,
                     30.0)
            after = c.info()
            assert after.seq == info.seq and after.digest == info.digest
            last: Op = ("rl-after", "relinearize", "", "", None, False)
            _send(c, last)
            assert c.info().digest == _fresh([*ops, last], policy=RECENTRE).state_digest()
        assert s.stop() == 0
    finally:
        router.stop(signal.SIGKILL)
    rep = replay(s.record)
    assert rep.divergence is None
    assert rep.final_digests()["m"] == _fresh([*ops, last], policy=RECENTRE).state_digest()


def test_the_serve_flags_give_the_default_policy_and_refuse_a_bad_spread(
        capsys: pytest.CaptureFixture[str]) -> None:
    """``mcsm serve`` with no relinearisation flag gives the core's default policy; a spread
    outside [1, 2] is a usage error; with every trigger off a spread other than 1 is kept (for
    requested relinearisations), ``--history none`` turns the policy off, re-centring is on
    unless ``--no-relinearize-recentre``, and calibration goes with readmit."""
    from mcsm.cli import build_parser
    from mcsm.cli.serve_cmd import _policy
    from mcsm.core.relinearize import Policy
    from mcsm.core.smap import DEFAULT_POLICY

    def policy(*argv: str) -> dict[str, object] | None:
        return _policy(build_parser().parse_args(["serve", *argv]))

    default = policy()
    assert default is not None and Policy.from_plain(default) == DEFAULT_POLICY
    for bad in ("3", "0.5", "wide"):
        with pytest.raises(SystemExit) as exc:
            build_parser().parse_args(["serve", "--relinearize-spread", bad])
        assert exc.value.code == 2
        assert "expected a number in [1, 2]" in capsys.readouterr().err
    off = ("--relinearize-nis", "none", "--relinearize-regate", "none",
           "--no-relinearize-recentre")
    assert policy(*off, "--relinearize-spread", "1") is None
    kept = policy(*off, "--relinearize-spread", "1.5")
    assert kept is not None and Policy.from_plain(kept) == Policy(gap=25, spread=1.5,
                                                                  readmit=300, calibrate=15)
    assert policy("--history", "none") is None
    assert policy("--history", "none", "--no-relinearize-recentre") is None
    # re-centring alone keeps a policy; asked for with --history none it is refused
    rc = policy(*off, "--relinearize-spread", "1", "--relinearize-recentre")
    assert rc is not None and Policy.from_plain(rc) == Policy(gap=25, recentre=True,
                                                              readmit=300, calibrate=15)
    assert Policy.from_plain(policy("--relinearize-recentre") or {}) == DEFAULT_POLICY
    with pytest.raises(McsmError, match="needs a history"):
        policy("--history", "none", "--relinearize-recentre")
    with pytest.raises(McsmError, match="needs a history"):
        policy("--history", "none", "--relinearize-readmit", "50")
    alone = policy("--no-relinearize-recentre", "--relinearize-readmit", "none")
    assert Policy.from_plain(alone or {}) == Policy(nis=0.95, regate=1, gap=25, spread=1.3)
    assert (policy() or {}).get("readmit") == 300 and (policy() or {}).get("recentre") is True
    # calibration: on by default where readmit is, off with it or with "none"
    assert (policy() or {}).get("calibrate") == 15
    assert (policy("--relinearize-calibrate", "none") or {}).get("calibrate") is None
    assert (policy("--relinearize-calibrate", "5") or {}).get("calibrate") == 5
    assert (policy("--relinearize-readmit", "none") or {}).get("calibrate") is None
    assert policy("--history", "none", "--relinearize-calibrate", "none") is None
    with pytest.raises(McsmError, match="needs a history"):
        policy("--history", "none", "--relinearize-calibrate", "5")
