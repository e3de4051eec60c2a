"""``mcsm-client``: talk to an ``mcsm serve`` map from the shell.

Commands (each takes the connection flags ``--connect``, ``--map``, ``--prefix``,
``--namespace``, ``--zenoh-config`` and ``--timeout-s``, before or after the command name;
``ZENOH_CONFIG`` names a config file when ``--zenoh-config`` is not given)::

    mcsm-client info [--json]
    mcsm-client update A B --planar DX DY DTH --sigma SX SY STH     # AT a->b, N samples drawn
    mcsm-client update A B --pose X Y Z QW QX QY QZ --sigma S1..S6  # 3D, tangent [t, r] sigmas
    mcsm-client update A B --point X Y [Z] --sigma SX SY [SZ]       # point frame b seen from a
    mcsm-client query A B [--json] [--samples-out FILE.npy]
    mcsm-client remove FRAME
    mcsm-client watch [--count K] [--duration-s S]
    mcsm-client play FILE|gtsam:NAME [--bounded] [--order file|pose] [--max-constraints K]
    mcsm-client play-rosbag BAG [--constraint-topic T] [--landmark-topic T] [--odometry-topic T]
    mcsm-client sim [--iterations 340] [--sigma-theta-deg 0] [--csv F] [--png F]
    mcsm-client multirobot [--connect-b ENDPOINT | --map-b NAME]

``play``, ``sim`` and ``multirobot`` also run without a server with ``--in-process N`` (an
in-process map of N samples); they write only into a frame namespace that has no frames yet
(``--namespace NS``: frames ``NS/...``). ``--cov`` gives a full covariance (row-major) instead
of ``--sigma``. Exit codes: 0 success, 1 the server refused the request (its error is
printed), 2 bad command line or input file (a malformed ``--connect`` too), 3 no answer within
``--timeout-s`` (nothing to connect to, no live server, no permitted server for the key, or a
slow server: the message says which), 4 ``update`` of a constraint the server's gate rejected
(recorded and acknowledged, the map unchanged; the verdict says why), 130 interrupted.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from mcsm.connect import (
    add_connection_args,
    check_endpoint,
    client_kwargs,
    fill_connection_defaults,
)
from mcsm.errors import McsmError, NoPermittedServer, NoServer, Timeout, Unreachable

EXIT_OK, EXIT_REFUSED, EXIT_USAGE, EXIT_TIMEOUT, EXIT_INTERRUPTED = 0, 1, 2, 3, 130
EXIT_GATE_REJECTED = 4  # update: recorded and acknowledged, but the gate refused it


class UsageError(Exception):
    """A command-line value that argparse alone cannot check."""


def _add_common(p: argparse.ArgumentParser) -> None:
    add_connection_args(p, suppress=True)
    p.add_argument("--timeout-s", type=float, default=argparse.SUPPRESS,
                   help="how long one request waits for the server, seconds (default 10)")


def _add_in_process(p: argparse.ArgumentParser) -> None:
    p.add_argument("--in-process", type=int, default=None, metavar="N",
                   help="no server: use an in-process map with N samples per AT")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser (exposed for tests and docs)."""
    p = argparse.ArgumentParser(
        prog="mcsm-client",
        description="Client of the Monte Carlo stochastic map server (mcsm serve).",
        epilog="Exit codes: 0 ok, 1 refused by the server, 2 usage or input error, "
               "3 no answer in time (nothing to connect to, no server, access denied, or "
               "slow), 4 update rejected by the server's loop-closure gate (recorded, map "
               "unchanged), 130 interrupted. "
               "Connection flags go before or after the command.")
    _add_common(p)
    p.add_argument("--version", action="version", version=_version_text())
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    s = sub.add_parser("info", help="frames, components, N, sequence number and digest")
    s.add_argument("--json", action="store_true", help="one JSON object")
    _add_common(s)

    s = sub.add_parser("update", help="send one observation (samples drawn from mean + noise)",
                       description="Draw N samples (N = the map's) from a mean and a Gaussian "
                                   "noise model and apply them as the AT A->B (or the point B "
                                   "seen from A).")
    s.add_argument("a", help="source frame")
    s.add_argument("b", help="target frame")
    kind = s.add_mutually_exclusive_group(required=True)
    kind.add_argument("--planar", nargs=3, type=float, metavar=("DX", "DY", "DTHETA"),
                      help="planar AT: B in A's frame (m, m, rad)")
    kind.add_argument("--pose", nargs=7, type=float,
                      metavar=("X", "Y", "Z", "QW", "QX", "QY", "QZ"),
                      help="3D AT: B in A's frame, scalar-first quaternion")
    kind.add_argument("--point", nargs="+", type=float, metavar="X",
                      help="point B in A's frame: X Y [Z] (m)")
    noise = s.add_mutually_exclusive_group(required=True)
    noise.add_argument("--sigma", nargs="+", type=float, metavar="S",
                       help="standard deviations (planar: 3; pose: 6 as tx ty tz rx ry rz; "
                            "point: 2 or 3)")
    noise.add_argument("--cov", nargs="+", type=float, metavar="C",
                       help="full covariance, row-major (9, 36, 4 or 9 numbers)")
    s.add_argument("--seed", type=int, default=None, help="random seed (default: fresh)")
    s.add_argument("--trusted", action="store_true",
                   help="bypass the server's loop-closure gate for this observation")
    s.add_argument("--json", action="store_true")
    _add_common(s)

    s = sub.add_parser("query", help="the relation A->B: mean and covariance (or samples)")
    s.add_argument("a")
    s.add_argument("b")
    s.add_argument("--samples-out", type=Path, default=None, metavar="FILE.npy",
                   help="also save the (N, 7) samples as a .npy file")
    s.add_argument("--force", action="store_true", help="overwrite an existing --samples-out")
    s.add_argument("--json", action="store_true")
    _add_common(s)

    s = sub.add_parser("remove", help="remove a frame (other estimates unchanged)")
    s.add_argument("frame")
    s.add_argument("--json", action="store_true")
    _add_common(s)

    for name, text in (("retract", "take back an update by its request id (the map becomes "
                                   "what it would be without it)"),
                       ("reinstate", "put back a retracted update, or one the gate "
                                     "rejected (as trusted)")):
        s = sub.add_parser(name, help=text)
        s.add_argument("request_id", help="the update's request id (from its ack or events)")
        s.add_argument("--json", action="store_true")
        _add_common(s)

    s = sub.add_parser("relinearize", help="bring a component (or every component) back to the "
                       "maximum a posteriori estimate of its recorded inputs and redraw its "
                       "samples (admin)")
    s.add_argument("frame", nargs="?", default="",
                   help="a frame of the component (default: every component)")
    s.add_argument("--json", action="store_true")
    _add_common(s)

    s = sub.add_parser("audit", help="run GTSAM's GNC over a map's recorded inputs and retract "
                       "or reinstate where it disagrees with the map (eval extra)",
                       description="Read the recorded inputs of a map (the server's MCAP "
                                   "file), replay it for each update's current verdict, run "
                                   "the GNC auditor (mcsm_client.audit, hysteresis: marginal "
                                   "closures keep their state) and print its decisions; with "
                                   "--apply, ask the server to retract or reinstate them "
                                   "(admin rights under the shipped access control).")
    s.add_argument("recording", type=Path, help="the map server's recording (.mcap)")
    s.add_argument("--apply", action="store_true",
                   help="send the decisions to the server (default: print them only)")
    s.add_argument("--gate", type=float, default=0.99,
                   help="chi-square quantile the residuals are judged against (default 0.99)")
    s.add_argument("--json", action="store_true")
    _add_common(s)

    s = sub.add_parser("servers", help="every map with a live server, its server id and role "
                       "(all servers reachable from here, e.g. behind a router)")
    s.add_argument("--json", action="store_true")
    _add_common(s)

    s = sub.add_parser("verdict", help="what the map did with a past request (gate verdict)")
    s.add_argument("request_id")
    s.add_argument("--json", action="store_true")
    _add_common(s)

    s = sub.add_parser("watch", help="print the map's events as they happen (Ctrl-C stops)")
    s.add_argument("--count", type=int, default=None, help="stop after this many events")
    s.add_argument("--duration-s", type=float, default=None, help="stop after this long")
    s.add_argument("--json", action="store_true", help="one JSON object per event")
    _add_common(s)

    s = sub.add_parser("play", help="stream a dataset file into the map",
                       description="Read a g2o (2D/3D), TORO .graph or Victoria Park text "
                                   "file (or gtsam:NAME from the gtsam wheel's data) and send "
                                   "its constraints in order: odometry and loop closures as "
                                   "ATs, landmark sightings as point updates.")
    s.add_argument("file", help="dataset path, or gtsam:NAME (e.g. gtsam:victoria_park.txt)")
    s.add_argument("--bounded", action="store_true",
                   help="keep only the first pose, the current pose and the landmarks")
    s.add_argument("--order", choices=("file", "pose"), default="file",
                   help="file order, or each constraint once its newest pose exists")
    s.add_argument("--max-constraints", type=int, default=None, metavar="K")
    s.add_argument("--noise", choices=("auto", "information", "sqrt_information",
                                       "covariance"), default="auto",
                   help="how to read g2o noise numbers (default: auto-detect)")
    s.add_argument("--stop-on-error", action="store_true",
                   help="stop at the first refused update (default: count and go on)")
    s.add_argument("--no-progress", action="store_true")
    s.add_argument("--json", action="store_true", help="print the summary as JSON")
    _add_in_process(s)
    _add_common(s)

    s = sub.add_parser("play-rosbag", help="stream a ROS 2 bag (MCAP or sqlite3) into the map, "
                       "mapped as mcsm ros2 maps messages (ros extra: rosbags)",
                       description="Read a ROS 2 bag with rosbags (no ROS installation "
                                   "needed) and send its nav_msgs/Odometry messages of the "
                                   "input topics as mcsm ros2 would: in header-stamp order, "
                                   "samples and request ids from each message (a bag played "
                                   "twice is applied once). docs/ros2.md.")
    s.add_argument("bag", type=Path, help="the bag (its folder, or one .mcap/.db3 file)")
    s.add_argument("--odometry-topic", action="append", default=None, metavar="TOPIC",
                   help="a cumulative odometry topic, keyframed (repeatable; default /odom)")
    s.add_argument("--constraint-topic", action="append", default=None, metavar="TOPIC",
                   help="a relative-pose topic (repeatable; default /mcsm/constraints)")
    s.add_argument("--landmark-topic", action="append", default=None, metavar="TOPIC",
                   help="a point-landmark topic (repeatable; default /mcsm/landmarks)")
    s.add_argument("--frame-prefix", default="", metavar="NS",
                   help="prepended to every frame id (NS/base_link)")
    s.add_argument("--keyframe-distance-m", type=float, default=0.5)
    s.add_argument("--keyframe-angle-rad", type=float, default=0.5)
    s.add_argument("--no-progress", action="store_true")
    s.add_argument("--json", action="store_true", help="print the summary as JSON")
    _add_common(s)

    s = sub.add_parser("sim", help="the paper's §6 simulation: RMS and NEES vs ground truth")
    s.add_argument("--iterations", type=int, default=340, help="odometry steps (340: one lap)")
    s.add_argument("--sigma-theta-deg", type=float, default=0.0,
                   help="odometry heading noise, degrees (paper: 0 and 0.1)")
    s.add_argument("--landmarks", type=int, default=200)
    s.add_argument("--score-every", type=int, default=10)
    s.add_argument("--unbounded", action="store_true", help="keep every pose frame")
    s.add_argument("--csv", type=Path, default=None, help="write per-iteration scores here")
    s.add_argument("--png", type=Path, default=None, help="plot here (needs matplotlib)")
    s.add_argument("--force", action="store_true", help="overwrite existing --csv/--png files")
    s.add_argument("--json", action="store_true")
    _add_in_process(s)
    _add_common(s)

    s = sub.add_parser("multirobot", help="two robots' maps joined at a rendezvous, then a "
                                          "loop closed across them")
    s.add_argument("--connect-b", default=None, metavar="ENDPOINT",
                   help="robot B's own server (default: B's component in the same map)")
    s.add_argument("--map-b", default=None, metavar="NAME",
                   help="robot B's own map on the same server")
    s.add_argument("--landmarks", type=int, default=200, help="landmarks in the world")
    s.add_argument("--json", action="store_true")
    _add_in_process(s)
    _add_common(s)
    return p


# ----------------------------------------------------------------------------- helpers

def _client(args: argparse.Namespace, **over: Any) -> Any:
    from mcsm_client.client import MapClient

    kw = client_kwargs(args)
    kw.update(over)
    return MapClient(timeout_s=args.timeout_s, **kw)


def _noise_cov(values: list[float], dim: int, as_sigma: bool) -> np.ndarray:
    v = np.asarray(values, dtype=np.float64)
    if as_sigma:
        if v.shape != (dim,):
            raise UsageError(f"--sigma needs {dim} numbers here, got {v.size}")
        if np.any(v < 0) or not np.all(np.isfinite(v)):
            raise UsageError("--sigma values must be finite and >= 0")
        return np.diag(v**2)
    if v.size != dim * dim:
        raise UsageError(f"--cov needs {dim * dim} numbers here, got {v.size}")
    return v.reshape(dim, dim)


def _print(args: argparse.Namespace, obj: dict[str, Any], text: str) -> None:
    print(json.dumps(obj, default=_jsonable) if getattr(args, "json", False) else text,
          flush=True)


def _jsonable(x: Any) -> Any:
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    if isinstance(x, (tuple, set)):
        return list(x)
    return str(x)


def _ack_dict(ack: Any) -> dict[str, Any]:
    return {"request_id": ack.request_id, "seq": ack.seq, "op": ack.op, "kind": ack.kind,
            "component": ack.component,
            "frames_added": list(ack.frames_added), "frames_removed": list(ack.frames_removed),
            "duplicate": ack.duplicate,
            "verdict": ack.verdict.to_dict() if ack.verdict is not None else None,
            "relin": ack.relin}


def _ack_text(ack: Any) -> str:
    extra = ""
    if ack.frames_added:
        extra += f" added={','.join(ack.frames_added)}"
    if ack.frames_removed:
        extra += f" removed={','.join(ack.frames_removed)}"
    v = ack.verdict
    if v is not None and v.nis is not None:
        extra += f" verdict={v.status} nis={v.nis:.3g}/dof={v.dof}"
        if v.threshold is not None:
            extra += f" (threshold {v.threshold:.3g})"
        if v.reason:
            extra += f" [{v.reason}]"
    elif v is not None and v.status in ("pending", "rejected"):  # held or refused by deferral
        extra += f" verdict={v.status} [{v.reason}]"
    comp = f" component={ack.component}" if ack.component is not None else ""
    return f"ok seq={ack.seq} id={ack.request_id} {ack.kind}{comp}{extra}"


def _count(n: int, noun: str) -> str:
    """``1 frame``, ``2 frames``."""
    return f"{n} {noun}{'' if n == 1 else 's'}"


def _version_text() -> str:
    from mcsm import __version__
    from mcsm.core import ARITHMETIC_VERSION
    from mcsm.wire import VERSION

    return (f"mcsm-client {__version__} (core arithmetic version {ARITHMETIC_VERSION}, wire "
            f"protocol v{VERSION})")


def _check_output(path: Path | None, flag: str, force: bool = False) -> None:
    """Refuse an output file that cannot be written, or that exists without ``--force`` (as
    every writer of ``mcsm`` and ``mcsm-client`` does), before any long run starts."""
    if path is None:
        return
    if path.is_file() and not force:
        raise UsageError(f"{flag} {path}: exists (--force overwrites it)")
    parent = path.parent if str(path.parent) else Path(".")
    if path.is_dir():
        raise UsageError(f"{flag} {path}: is a directory")
    if not parent.is_dir():
        raise UsageError(f"{flag} {path}: directory {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK) or (path.exists()
                                                    and not os.access(path, os.W_OK)):
        raise UsageError(f"{flag} {path}: not writable")


class _Progress:
    """Progress over items: a tqdm bar on a terminal; otherwise (a log, a pipe) a plain line
    ``label: done/total (rate/s)`` every 10 s and at the end of a longer run, never ``\\r``."""

    def __init__(self, label: str, enabled: bool = True, every_s: float = 10.0) -> None:
        self.label = label
        self.enabled = enabled
        self.every_s = every_s
        self._tty = sys.stderr.isatty()
        self._bar: Any = None
        self._t0 = self._last = time.monotonic()
        self._lines = 0

    def __call__(self, done: int, total: int, *_: Any) -> None:
        if not self.enabled:
            return
        if self._tty:
            if self._bar is None:
                from tqdm import tqdm

                self._bar = tqdm(total=total, desc=self.label, file=sys.stderr,
                                 dynamic_ncols=True)
            self._bar.update(done - self._bar.n)
            if done >= total:
                self._bar.close()
                self.enabled = False
            return
        now = time.monotonic()
        if now - self._last >= self.every_s or (done >= total and self._lines):
            self._last = now
            self._lines += 1
            rate = done / max(now - self._t0, 1e-9)
            sys.stderr.write(f"{self.label}: {done}/{total} ({rate:.0f}/s)\n")
            sys.stderr.flush()


# ----------------------------------------------------------------------------- commands

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
    from mcsm.recording import TOPIC_OPS, RecordingReader, decode_input, replay

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


def _map_for(args: argparse.Namespace, **over: Any) -> tuple[Any, Any]:
    """(target, closer): an in-process map or a connected client, as a ``MapTarget`` whose
    frames live in ``--namespace`` (when given); refuses a namespace that has frames."""
    from mcsm_client.players import MapTarget

    prefix = _prefix(args)
    if args.in_process is not None:
        from mcsm import StochasticMap

        if args.in_process < 2:
            raise UsageError("--in-process N needs N >= 2")
        return MapTarget(StochasticMap(args.in_process), prefix), None
    c = _client(args, **over)
    try:
        target = MapTarget(c, prefix)
        taken = target.existing()
    except BaseException:
        c.close()
        raise
    if taken:
        c.close()
        where = f"namespace {prefix!r}" if prefix else "the root namespace (names without '/')"
        raise UsageError(
            f"map {c.map!r} already has {len(taken)} frames in {where} (e.g. {taken[0]!r}); "
            f"{args.command} writes only into an empty namespace, so it would merge into "
            "them: pass --namespace NAME (frames become NAME/...), or use another map")
    return target, c


def _prefix(args: argparse.Namespace) -> str:
    from mcsm.core.names import is_frame_name

    ns = args.namespace or ""
    if ns and not is_frame_name(ns + "/x"):
        raise UsageError(f"--namespace {ns!r}: expected frame-name segments joined by '/'")
    return str(ns)


def cmd_play(args: argparse.Namespace) -> int:
    """``play``: stream a dataset; exit 1 if the map refused any constraint."""
    from mcsm_client.datasets import DatasetError, read_dataset
    from mcsm_client.players import play

    try:
        ds = read_dataset(args.file, noise=args.noise)
    except (OSError, DatasetError, ValueError) as exc:
        raise UsageError(str(exc)) from None
    counts = ds.counts()
    print(f"{ds.name}: {len(ds.constraints)} constraints ({counts['odometry']} odometry, "
          f"{counts['loop_closure']} loop closures, {counts['landmark']} landmark sightings; "
          f"{counts['poses']} poses, {counts['landmarks']} landmarks; noise read as "
          f"{ds.noise})", file=sys.stderr, flush=True)
    target, closer = _map_for(args)
    try:
        stats = play(ds, target, rng=np.random.default_rng(args.seed), bounded=args.bounded,
                     order=args.order, max_constraints=args.max_constraints,
                     progress=_Progress("play", not args.no_progress),
                     stop_on_error=args.stop_on_error)
    finally:
        if closer is not None:
            closer.close()
    obj = {"file": ds.name, "total": stats.total, "applied": stats.applied,
           "results": stats.results, "skipped": stats.skipped, "rejected": stats.rejected,
           "removed": stats.removed, "elapsed_s": stats.elapsed_s,
           "first_error": stats.first_error}
    text = stats.summary() + (f"\nfirst refusal: {stats.first_error}" if stats.first_error
                              else "")
    _print(args, obj, text)
    return EXIT_REFUSED if stats.rejected else EXIT_OK


def cmd_play_rosbag(args: argparse.Namespace) -> int:
    """``play-rosbag``: a ROS 2 bag through the node's mapping; exit 1 if anything was refused
    or rejected, or a message was invalid."""
    if importlib.util.find_spec("rosbags") is None:
        raise UsageError("play-rosbag needs rosbags: pip install 'mcsm[ros]'")
    from mcsm_client.ros2.bag import BagError, play_rosbag
    from mcsm_client.ros2.mapping import MappingOptions

    d = MappingOptions()
    opts = MappingOptions(
        odometry_topics=tuple(args.odometry_topic or d.odometry_topics),
        constraint_topics=tuple(args.constraint_topic or d.constraint_topics),
        landmark_topics=tuple(args.landmark_topic or d.landmark_topics),
        frame_prefix=args.frame_prefix, keyframe_distance_m=args.keyframe_distance_m,
        keyframe_angle_rad=args.keyframe_angle_rad)
    bar = _Progress("play-rosbag", not args.no_progress)
    try:
        with _client(args) as c:
            stats = play_rosbag(args.bag, c, opts, progress=bar)
    except BagError as exc:
        raise UsageError(str(exc)) from None
    text = stats.summary() + (f"\nfirst problem: {stats.first_error}" if stats.first_error
                              else "")
    _print(args, {"bag": str(args.bag), **stats.as_dict()}, text)
    return EXIT_REFUSED if (stats.rejected or stats.n_refused or stats.invalid) else EXIT_OK


def cmd_sim(args: argparse.Namespace) -> int:
    """``sim``: the paper's §6 simulation with per-iteration scores."""
    from mcsm_client.sim import SimConfig, plot_results, run_sim

    if args.iterations < 1 or args.score_every < 1 or args.landmarks < 1:
        raise UsageError("--iterations, --score-every and --landmarks must be >= 1")
    _check_output(args.csv, "--csv", args.force)  # before the run, not after it
    _check_output(args.png, "--png", args.force)
    if args.png is not None and importlib.util.find_spec("matplotlib") is None:
        raise UsageError("--png needs matplotlib (pip install -e '.[eval]')")
    cfg = SimConfig(n_iterations=args.iterations, sigma_theta_deg=args.sigma_theta_deg,
                    n_landmarks=args.landmarks, score_every=args.score_every,
                    bounded=not args.unbounded)
    target, closer = _map_for(args)

    def show(row: Any) -> None:
        if not args.json:
            print(f"iteration {row.iteration:5d}: {row.n_landmarks:3d} landmarks, "
                  f"RMS {row.rms_m:.3f} m, NEES/dof {row.nees_per_dof:.2f}", flush=True)

    try:
        res = run_sim(cfg, target, rng=np.random.default_rng(args.seed), progress=show)
    finally:
        if closer is not None:
            closer.close()
    if args.csv is not None:
        res.write_csv(args.csv)
    if args.png is not None:
        try:
            plot_results({f"N={res.n_samples}": res}, args.png)
        except ImportError as exc:
            print(f"mcsm-client sim: {exc}", file=sys.stderr)
            return EXIT_USAGE
    _print(args, res.as_dict(), res.summary())
    return EXIT_OK


def cmd_multirobot(args: argparse.Namespace) -> int:
    """``multirobot``: the two-robot join and cross loop closure demo."""
    from mcsm_client.multirobot import MultiRobotConfig, run_multirobot

    if args.connect_b and args.map_b and args.in_process is not None:
        raise UsageError("--in-process cannot be combined with --connect-b/--map-b")
    if args.landmarks < 1:
        raise UsageError("--landmarks must be >= 1")
    rng = np.random.default_rng(args.seed)
    cfg = MultiRobotConfig(n_landmarks=args.landmarks)
    log = None if args.json else (lambda s: print(s, flush=True))
    if args.in_process is not None:
        from mcsm import StochasticMap

        from mcsm_client.players import MapTarget

        prefix = _prefix(args)
        a_map = MapTarget(StochasticMap(args.in_process), prefix)
        b_map = MapTarget(StochasticMap(args.in_process), prefix)
        res = run_multirobot(cfg, a_map, b_map, rng=rng, log=log)
    else:
        ca, closer_a = _map_for(args)
        try:
            if args.connect_b or args.map_b:
                over: dict[str, Any] = {}
                if args.connect_b:
                    over["connect"] = args.connect_b
                if args.map_b:
                    over["map"] = args.map_b
                cb, closer_b = _map_for(args, **over)
                try:
                    res = run_multirobot(cfg, ca, cb, rng=rng, log=log)
                finally:
                    closer_b.close()
            else:
                res = run_multirobot(cfg, ca, rng=rng, log=log)
        finally:
            closer_a.close()
    obj = {"scores": [vars(s) for s in res.scores], "join": res.join_kind,
           "import": res.import_kind, "cross_loop_closures": res.cross_loop_closures,
           "elapsed_s": res.elapsed_s}
    _print(args, obj, res.summary())
    return EXIT_OK


COMMANDS = {"info": cmd_info, "update": cmd_update, "query": cmd_query, "remove": cmd_remove,
            "retract": cmd_retract, "reinstate": cmd_retract, "verdict": cmd_verdict,
            "relinearize": cmd_relinearize,
            "servers": cmd_servers, "audit": cmd_audit,
            "watch": cmd_watch, "play": cmd_play, "play-rosbag": cmd_play_rosbag, "sim": cmd_sim,
            "multirobot": cmd_multirobot}


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``mcsm-client`` console script; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    fill_connection_defaults(args)
    if not hasattr(args, "timeout_s"):
        args.timeout_s = 10.0
    prog = f"mcsm-client {args.command}"
    try:
        if not args.timeout_s > 0:
            raise UsageError("--timeout-s must be > 0")
        if args.connect is not None:
            check_endpoint(args.connect)
        if getattr(args, "connect_b", None):
            check_endpoint(args.connect_b, "--connect-b")
        return COMMANDS[args.command](args)
    except UsageError as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except (NoServer, NoPermittedServer, Unreachable) as exc:
        print(f"{prog}: {exc.message}", file=sys.stderr)
        return EXIT_TIMEOUT
    except Timeout as exc:
        print(f"{prog}: no answer from the server: {exc.message} (is `mcsm serve` running, "
              f"and do --connect/--map/--prefix match it?)", file=sys.stderr)
        return EXIT_TIMEOUT
    except McsmError as exc:
        if exc.fields.get("field") in ("--connect", "--connect-b", "--zenoh-config",
                                       "namespace"):
            print(f"{prog}: {exc.message}", file=sys.stderr)  # a usage error, found early
            return EXIT_USAGE
        print(f"{prog}: refused: {type(exc).__name__}: {exc.message}", file=sys.stderr)
        return EXIT_REFUSED
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:  # the reader went away (`... | head`): not an error of ours
        _silence_stdout()
        return EXIT_OK


def _silence_stdout() -> None:
    """Point stdout at /dev/null so the interpreter's final flush does not fail again."""
    import os

    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())


if __name__ == "__main__":
    raise SystemExit(main())
