"""``mcsm-client`` commands that ask one served map or its fleet: ``info``, ``update``,
``query``, ``remove``, ``retract``/``reinstate``, ``relinearize``, ``audit``, ``servers``,
``verdict`` and ``watch`` (the parser and ``main``: :mod:`mcsm_client.cli`).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from mcsm.errors import McsmError, NoPermittedServer, NoServer, Timeout

from mcsm_client.cli_common import (
    EXIT_GATE_REJECTED,
    EXIT_OK,
    UsageError,
    _ack_dict,
    _ack_text,
    _client,
    _count,
    _noise_cov,
    _print,
)


def cmd_info(args: argparse.Namespace) -> int:
    """``info``: print the map's N, frames, components, sequence number and digest."""
    with _client(args) as c:
        info = c.info()
    obj = {"map": info.map, "n_samples": info.n_samples, "options": info.options,
           "seq": info.seq, "digest": info.digest, "n_frames": info.n_frames,
           "components": {k: list(v) for k, v in info.components.items()},
           "rejected": info.rejected, "requests_with_error": info.rejected,
           "errors": dict(info.rejected_by_error), "server_id": info.server_id,
           "recording": info.recording, "verdicts": dict(info.verdicts), "role": info.role,
           "standbys": dict(info.standbys), "replicas": info.replicas, "epoch": info.epoch}
    comps = ", ".join(f"{root} ({_count(len(frames), 'frame')})" for root, frames in
                      list(info.components.items())[:10])
    more = f" ... ({len(info.components) - 10} more)" if len(info.components) > 10 else ""
    refused = ", ".join(f"{k} {v}" for k, v in sorted(info.rejected_by_error.items()))
    text = (f"map {info.map!r}: N={info.n_samples}, {_count(info.n_frames, 'frame')} in "
            f"{_count(len(info.components), 'component')}"
            f"{': ' + comps + more if comps else ''}\n"
            f"seq {info.seq}, digest {info.digest}\n"
            f"requests answered with an error (any kind, queries too): {info.rejected}"
            f"{f' ({refused})' if refused else ''}; recording {info.recording or '-'}")
    if info.verdicts:
        text += "\nupdates by verdict: " + ", ".join(
            f"{k} {v}" for k, v in sorted(info.verdicts.items())) + (
            " (rejected: refused by the gate, recorded, map unchanged)"
            if info.verdicts.get("rejected") else "")
    text += f"\nserver {info.server_id} ({info.role})"
    if info.replicas:
        lag = ", ".join(f"{z} lag {info.seq - s}" for z, s in sorted(info.standbys.items()))
        text += (f"; log with {info.replicas} replicas, lease revision {info.epoch}; "
                 f"standbys: {lag or 'none'}")
    _print(args, obj, text)
    return EXIT_OK


def cmd_update(args: argparse.Namespace) -> int:
    """``update``: draw N samples from the given mean and noise and apply them."""
    from mcsm_client.sampling import sample_planar, sample_point, sample_pose

    as_sigma = args.sigma is not None
    noise = args.sigma if as_sigma else args.cov
    rng = np.random.default_rng(args.seed)
    if args.point is not None and len(args.point) not in (2, 3):
        raise UsageError("--point takes X Y or X Y Z")
    with _client(args) as c:
        n = c.info().n_samples
        try:
            if args.planar is not None:
                x = sample_planar(args.planar, _noise_cov(noise, 3, as_sigma), n_samples=n,
                                  rng=rng)
                ack = c.update(args.a, args.b, x, trusted=args.trusted)
            elif args.pose is not None:
                x = sample_pose(args.pose, _noise_cov(noise, 6, as_sigma), n_samples=n,
                                rng=rng)
                ack = c.update(args.a, args.b, x, trusted=args.trusted)
            else:
                d = len(args.point)
                p = sample_point(args.point, _noise_cov(noise, d, as_sigma), n_samples=n,
                                 rng=rng)
                ack = c.update_point(args.a, args.b, p, trusted=args.trusted)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
    _print(args, _ack_dict(ack), _ack_text(ack))
    if ack.verdict is not None and ack.verdict.status == "rejected":
        return EXIT_GATE_REJECTED  # the map is unchanged: a script must see it in $?
    return EXIT_OK


def cmd_query(args: argparse.Namespace) -> int:
    """``query``: print the marginal of A->B; optionally save its samples."""
    if args.samples_out is not None:
        if not str(args.samples_out).endswith(".npy"):
            args.samples_out = Path(f"{args.samples_out}.npy")  # what np.save writes
        if args.samples_out.exists() and not args.force:
            raise UsageError(f"--samples-out {args.samples_out}: exists (--force overwrites "
                             "it)")
    with _client(args) as c:
        mean, cov = c.marginal(args.a, args.b)
        if args.samples_out is not None:
            samples = c.query(args.a, args.b)
            args.samples_out.parent.mkdir(parents=True, exist_ok=True)
            np.save(args.samples_out, samples)
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    with np.printoptions(precision=5, suppress=True, linewidth=100):
        text = (f"{args.a} -> {args.b}\n"
                f"mean  x y z qw qx qy qz: {mean}\n"
                f"sigma tx ty tz rx ry rz: {sd}\n"
                f"covariance (6x6):\n{cov}")
    if args.samples_out is not None:
        text += f"\nsamples saved to {args.samples_out}"
    _print(args, {"a": args.a, "b": args.b, "mean": mean, "cov": cov}, text)
    return EXIT_OK


def cmd_remove(args: argparse.Namespace) -> int:
    """``remove``: remove one frame."""
    with _client(args) as c:
        ack = c.remove(args.frame)
    _print(args, _ack_dict(ack), _ack_text(ack))
    return EXIT_OK


def cmd_retract(args: argparse.Namespace) -> int:
    """``retract`` / ``reinstate``: take back an update, or put it back."""
    with _client(args) as c:
        fn = c.retract if args.command == "retract" else c.reinstate
        ack = fn(args.request_id)
    verdict = (f" verdict={ack.verdict.status}" if ack.verdict is not None
               and f"verdict={ack.verdict.status}" not in _ack_text(ack) else "")
    _print(args, _ack_dict(ack), f"{_ack_text(ack)} target={args.request_id}{verdict}")
    return EXIT_OK


def cmd_relinearize(args: argparse.Namespace) -> int:
    """``relinearize``: one component (or every one) back to its maximum a posteriori estimate."""
    with _client(args) as c:
        ack = c.relinearize(args.frame)
    rel = ack.relin or {}
    parts = [f"{d['root']}: " + (f"skipped ({d['skipped']})" if d["skipped"] else
                                 f"{d['frames']} frames, {d['variables']} variables, "
                                 f"{d['factors']} factors, {d['iterations']} iterations, "
                                 f"cost {d['cost_before']:.6g} -> {d['cost_after']:.6g}")
             for d in rel.get("components", [])]
    _print(args, _ack_dict(ack), _ack_text(ack) + f" time={rel.get('time_s', 0.0):.3f}s; "
           + ("; ".join(parts) or "no component"))
    return EXIT_OK


def cmd_audit(args: argparse.Namespace) -> int:
    """``audit``: GNC over the recorded inputs; print (and with --apply send) its decisions."""
    from mcsm.log.reader import RecordingReader
    from mcsm.log.replay import replay
    from mcsm.log.topics import TOPIC_OPS, decode_input

    from mcsm_client.audit import AuditInput, Auditor

    if not args.recording.is_file():
        raise UsageError(f"no such recording: {args.recording}")
    try:
        import gtsam  # noqa: F401
    except ImportError:
        raise UsageError("audit needs gtsam: pip install 'mcsm[eval]'") from None
    rep = replay(args.recording)
    st = rep.states.get(args.map)
    if st is None:
        raise UsageError(f"the recording has no map {args.map!r} "
                         f"(it has {', '.join(rep.states) or 'none'})")
    inputs: list[AuditInput] = []
    ids: list[str] = []
    for item in RecordingReader(args.recording):
        d = item.data
        if d.get("map") != args.map or TOPIC_OPS.get(item.topic) != "update":
            continue
        req = decode_input("update", bytes(d["request"]), st.n_samples)
        if req.samples.shape[1] != 7:
            continue  # the auditor takes full-frame constraints only
        try:
            verdict = st.verdict_of(req.request_id).verdict
        except McsmError:
            verdict = None  # forgotten (older than the id memory): as applied
        ids.append(req.request_id)
        inputs.append(AuditInput(len(ids) - 1, req.a, req.b, req.samples,
                                 verdict.status if verdict is not None else "accepted"))
    decisions = Auditor(gate=args.gate).decide(inputs) if inputs else []
    rows = [{"request_id": ids[dd.request_id], "action": dd.action, "weight": dd.weight,
             "residual_nis": dd.residual_nis, "threshold": dd.threshold, "dof": dd.dof}
            for dd in decisions]
    if args.apply and rows:
        with _client(args) as c:
            for r in rows:  # each one re-gates the later inputs: a later decision may be moot
                fn = c.retract if r["action"] == "retract" else c.reinstate
                try:
                    ack = fn(str(r["request_id"]))
                    r["verdict"] = ack.verdict.status if ack.verdict is not None else ""
                except McsmError as exc:
                    if isinstance(exc, (NoServer, NoPermittedServer, Timeout)):
                        raise
                    r["verdict"] = f"refused: {exc}"
    text = "\n".join(f"{r['action']:9s} {r['request_id']}  GNC weight {r['weight']:.2f}, "
                     f"residual {r['residual_nis']:.3g} (threshold {r['threshold']:.3g})"
                     + (f" -> {r['verdict']}" if "verdict" in r else "") for r in rows)
    _print(args, {"inputs": len(inputs), "decisions": rows},
           f"{len(inputs)} full-frame inputs audited; {len(rows)} decision(s)"
           + (" (not sent: add --apply)" if rows and not args.apply else "")
           + ("\n" + text if text else ""))
    return EXIT_OK


def cmd_servers(args: argparse.Namespace) -> int:
    """``servers``: the maps that live servers serve (liveliness tokens), with server ids,
    and each replicated map's standbys (from its primary's ``info``)."""
    rows: list[dict[str, str]] = []
    with _client(args) as c:
        for reply in c.session.liveliness().get(f"{args.prefix}/*/alive/*", timeout=2.0):
            if reply.ok is None:
                continue
            parts = str(reply.ok.key_expr).split("/")
            rows.append({"map": parts[-3], "server": parts[-1], "role": "primary"})
    for m in sorted({r["map"] for r in rows}):  # standbys: the log's consumers
        try:
            with _client(args, map=m) as mc:
                info = mc.info(timeout_s=2.0)
        except McsmError:
            continue
        rows += [{"map": m, "server": z, "role": "standby"} for z in info.standbys]
    rows.sort(key=lambda r: (r["map"], r["server"]))
    text = "\n".join(f"{r['map']:24s} {r['server']:34s} {r['role']}" for r in rows) \
        or "no live server"
    _print(args, {"servers": rows}, text)
    return EXIT_OK


def cmd_verdict(args: argparse.Namespace) -> int:
    """``verdict``: the current verdict of a past request."""
    with _client(args) as c:
        v = c.verdict(args.request_id)
    d = v.to_dict() if v is not None else None
    if v is None:
        text = f"{args.request_id}: no verdict (a remove or an import)"
    else:
        text = f"{args.request_id}: {v.status}"
        if v.nis is not None:
            text += f" nis={v.nis:.4g} dof={v.dof}"
        if v.threshold is not None:
            text += f" threshold={v.threshold:.4g}"
        if v.reason:
            text += f" ({v.reason})"
    _print(args, {"request_id": args.request_id, "verdict": d}, text)
    return EXIT_OK


def cmd_watch(args: argparse.Namespace) -> int:
    """``watch``: print events until ``--count``/``--duration-s`` or Ctrl-C."""
    deadline = None if args.duration_s is None else time.monotonic() + args.duration_s
    seen = 0
    with _client(args) as c, c.watch() as events:
        if not args.json:
            print(f"watching map {c.map!r} (Ctrl-C to stop)", file=sys.stderr, flush=True)
        while (args.count is None or seen < args.count) and \
                (deadline is None or time.monotonic() < deadline):
            ev = events.get(0.2)
            if ev is None:
                continue
            seen += 1
            v = ev.extra.get("verdict") if isinstance(ev.extra, dict) else None
            status = v.get("status") if isinstance(v, dict) else None
            obj = {"seq": ev.seq, "op": ev.op, "kind": ev.kind, "frames": list(ev.frames),
                   "component": ev.component, "time_ns": ev.time_ns, "digest": ev.digest,
                   "request_id": ev.request_id, "verdict": v}
            digest = f" digest={ev.digest[:16]}" if ev.digest else ""
            comp = f" component={ev.component}" if ev.component is not None else ""
            shown = f" verdict={status}" if status and status != ev.kind else ""
            _print(args, obj, f"seq {ev.seq:6d} {ev.op:<8} {ev.kind:<14} "
                              f"{','.join(ev.frames):<24} id={ev.request_id or '-'}"
                              f"{shown}{comp}{digest}")
    return EXIT_OK

