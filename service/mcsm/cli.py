"""``mcsm``: run the map server, replay and inspect its recordings.

::

    mcsm serve [--listen tcp/127.0.0.1:7457] [--map NAME]... [--samples N]
               [--method joint|paper] [--record PATH.mcap] [--restore PATH.mcap]
               [--zenoh-config FILE]
    mcsm replay FILE.mcap
    mcsm inspect FILE.mcap
    mcsm plot FILE.mcap -o map.png [--map NAME] [--at SEQ] [--samples] [--truth CSV]
              [--view auto|top|xz|yz|3d]
    mcsm export-foxglove FILE.mcap -o scene.mcap [--every K] [--map NAME]
    mcsm view [--connect ENDPOINT] [--map NAME] [--foxglove-port P]

``serve`` prints one line ``listening on <endpoint>`` on stdout when it is ready, and closes
the recording cleanly on SIGINT or SIGTERM. ``replay`` exits 0 when every checkpoint and the
final state match (a truncated file is replayed up to its last complete record), 1 on a
divergence, 2 when the file cannot be read.
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

from mcsm import wire
from mcsm.errors import McsmError

log = logging.getLogger("mcsm")


def _parser() -> argparse.ArgumentParser:
    from mcsm.connect import add_connection_args

    p = argparse.ArgumentParser(prog="mcsm", description=__doc__.split("\n")[0] if __doc__
                                else None)
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("serve", help="run the map server (embedded Zenoh peer)")
    add_connection_args(s, role="server")
    s.add_argument("--samples", type=int, default=1000, metavar="N",
                   help="samples per AT for new maps (default 1000)")
    s.add_argument("--method", choices=("joint", "paper"), default="joint",
                   help="case II update (default joint)")
    s.add_argument("--space", choices=("tangent", "quaternion"), default="tangent",
                   help="vector space of the merges (default tangent)")
    s.add_argument("--analysis", choices=("ensrf", "denkf", "enkf"), default="ensrf",
                   help="analysis rule of the joint update (default ensrf, square root)")
    s.add_argument("--shrink", type=_shrink, default=4.0, metavar="C|none",
                   help="correlation shrink constant of the joint update (default 4; 'none' "
                        "turns it off)")
    s.add_argument("--inflation", type=_inflation, default=1.0, metavar="F|adaptive",
                   help="anomaly inflation per loop closure: a factor in [1, 2) or 'adaptive' "
                        "(default 1, none)")
    s.add_argument("--gain", choices=("direct", "endpoints"), default="direct",
                   help="cross-covariance estimator of the joint update: 'direct' (default) or "
                        "'endpoints' (through the loop's two endpoint frames; better on pose "
                        "graphs, with --inflation 1.002 in 3-D; tangent space only)")
    s.add_argument("--gate", type=_gate, default=None, metavar="Q|none",
                   help="loop-closure gate: reject a loop closure whose normalised innovation "
                        "exceeds the chi-square quantile Q (e.g. 0.99) for its dof; the map is "
                        "unchanged and the ack's verdict says why (default none; a request "
                        "marked trusted bypasses it)")
    s.add_argument("--record", type=Path, default=None, metavar="PATH.mcap",
                   help="new recording file (default recordings/run-<UTC time>.mcap)")
    s.add_argument("--restore", type=Path, default=None, metavar="PATH.mcap",
                   help="rebuild the maps from this recording first, then go on; the new "
                        "recording (--record) repeats its inputs so it replays on its own")
    s.add_argument("--checkpoint-every", type=int, default=100, metavar="K",
                   help="record the state digest every K operations per map (default 100)")
    s.add_argument("--queue-size", type=int, default=1024,
                   help="requests waiting for the worker before 'busy' errors")
    s.add_argument("--fsync", action="store_true",
                   help="fsync the recording before each ack (survives power loss; slow)")
    s.add_argument("--snapshot-every", type=int, default=100, metavar="K",
                   help="keep an in-memory snapshot of each map every K operations "
                        "(default 100); retract/reinstate restore one and apply the later "
                        "inputs again")
    s.add_argument("--snapshots-kept", type=int, default=5, metavar="S",
                   help="snapshots kept per map (default 5): updates of the last (S-1)*K to "
                        "S*K operations can be retracted")
    s.add_argument("--id-ttl-s", type=float, default=600.0, metavar="S",
                   help="remember each applied request id this long, so a retry (also after "
                        "a --restore) is not applied twice (default 600)")
    s.add_argument("--id-memory", type=int, default=100_000, metavar="K",
                   help="remember at most this many request ids per map (default 100000)")
    s.add_argument("--log-level", default="INFO")

    r = sub.add_parser("replay", help="rebuild the maps of a recording and check its digests")
    r.add_argument("file", type=Path)
    r.add_argument("--json", action="store_true", help="print the result as one JSON line")
    r.add_argument("--no-progress", action="store_true")

    i = sub.add_parser("inspect", help="summarise a recording")
    i.add_argument("file", type=Path)
    i.add_argument("--json", action="store_true")

    from mcsm.viz.commands import add_parsers as add_viz_parsers

    add_viz_parsers(sub)  # plot, export-foxglove, view (docs/visualising.md)
    return p


def main(argv: list[str] | None = None) -> int:
    from mcsm.connect import flags_after_command

    # `mcsm --listen X serve` works like `mcsm serve --listen X`
    argv = flags_after_command(sys.argv[1:] if argv is None else list(argv), "serve")
    args = _parser().parse_args(argv)
    try:
        if args.command == "serve":
            return serve(args)
        if args.command == "replay":
            return replay_cmd(args)
        if args.command in ("plot", "export-foxglove", "view"):
            from mcsm.viz.commands import run as run_viz

            return run_viz(args)
        return inspect_cmd(args)
    except BrokenPipeError:  # `mcsm inspect FILE | head`: the reader went away
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


# ------------------------------------------------------------------------------------ serve
def _shrink(text: str) -> float | None:
    if text == "none":
        return None
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number >= 0 or 'none', got {text!r}") \
            from None


def _gate(text: str) -> float | None:
    if text == "none":
        return None
    try:
        q = float(text)
    except ValueError:
        q = -1.0
    if not 0.0 < q < 1.0:
        raise argparse.ArgumentTypeError(f"expected a quantile in (0, 1) or 'none', got {text!r}")
    return q


def _inflation(text: str) -> float | str:
    if text == "adaptive":
        return text
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a number in [1, 2) or 'adaptive', got {text!r}") from None


def serve(args: argparse.Namespace) -> int:
    import zenoh

    from mcsm.connect import listen_endpoints, security_warning, server_config
    from mcsm.recording import progress_bar
    from mcsm.server import Server, ServerOptions

    logging.basicConfig(level=getattr(logging, str(args.log_level).upper(), logging.INFO),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
                        stream=sys.stderr)
    record = args.record
    if record is None:
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        record = Path("recordings") / f"run-{stamp}.mcap"
        k = 1
        while record.exists() and k < 1000:
            record = Path("recordings") / f"run-{stamp}-{k}.mcap"
            k += 1
    # restoring without --map serves the recording's maps (or "default" if it has none)
    maps = args.map or ([] if args.restore else [wire.DEFAULT_MAP])
    opts = ServerOptions(
        maps=list(dict.fromkeys(maps)), prefix=args.prefix,
        map_options={"n_samples": args.samples, "method": args.method, "space": args.space,
                     "analysis": args.analysis, "shrink": args.shrink,
                     "inflation": args.inflation, "gain": args.gain,
                     **({"gate": args.gate} if args.gate is not None else {})},
        record=record, restore=args.restore, checkpoint_every=max(1, args.checkpoint_every),
        queue_size=args.queue_size, fsync=args.fsync, lru_size=max(1, args.id_memory),
        id_ttl_s=max(0.0, args.id_ttl_s), snapshot_every=max(1, args.snapshot_every),
        snapshots_kept=max(1, args.snapshots_kept))
    try:
        for name in opts.maps:
            wire.map_keys(name, opts.prefix)
        conf = server_config(args.listen, args.zenoh_config)
    except (McsmError, zenoh.ZError, OSError) as exc:
        print(f"mcsm serve: {exc}", file=sys.stderr)
        return 2
    warning = security_warning(conf)
    if warning is not None:
        log.warning("%s", warning)
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as exc:
        print(f"mcsm serve: cannot open the Zenoh session: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()

    def on_signal(signum: int, _frame: Any) -> None:
        log.info("signal %d: shutting down", signum)
        stop.set()

    old_handlers = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    server = Server(session, opts, progress=progress_bar() if args.restore else None)
    try:
        try:
            server.start()
        except (McsmError, OSError) as exc:
            print(f"\nmcsm serve: {exc}", file=sys.stderr)
            return 2
        if args.restore:
            sys.stderr.write("\n")
        log.info("recording to %s", opts.record)
        print(f"listening on {' '.join(listen_endpoints(conf))}", flush=True)
        while not stop.wait(0.5):
            if server.failed.is_set():
                log.critical("stopping after a recording failure")
                return 3
        return 0
    finally:
        server.close()
        session.close()
        for sig, handler in old_handlers.items():
            signal.signal(sig, handler)


# ------------------------------------------------------------------------------------ replay
def replay_cmd(args: argparse.Namespace) -> int:
    from mcsm.recording import RecordingError, progress_bar, replay

    try:
        rep = replay(args.file, progress=None if args.no_progress else progress_bar())
    except (RecordingError, OSError) as exc:
        if not args.no_progress:
            sys.stderr.write("\n")
        print(f"mcsm replay: cannot read {args.file}: {exc}", file=sys.stderr)
        return 2
    if not args.no_progress:
        sys.stderr.write("\n")
    digests = rep.final_digests()
    speed = rep.n_inputs / rep.elapsed_s if rep.elapsed_s > 0 else float("inf")
    if args.json:
        print(json.dumps({"file": str(args.file), "identical": rep.identical,
                          "divergence": rep.divergence, "inputs": rep.n_inputs,
                          "checkpoints": len(rep.checkpoints),
                          "checkpoints_ok": rep.checkpoints_ok, "complete": rep.complete,
                          "tail_error": rep.tail_error, "digests": digests,
                          "seq": {n: s.seq for n, s in rep.states.items()},
                          "elapsed_s": rep.elapsed_s, "ops_per_s": speed}))
    else:
        print(f"{args.file}: {rep.n_inputs} inputs replayed in {rep.elapsed_s:.3f} s "
              f"({speed:.0f} ops/s); {rep.checkpoints_ok}/{len(rep.checkpoints)} checkpoints "
              "match")
        if not rep.complete:
            print(f"warning: recording is truncated (no clean close): {rep.tail_error}; "
                  "replayed every complete record before the cut")
        for name, d in digests.items():
            print(f"map {name}: seq {rep.states[name].seq}, digest {d}")
        print("identical" if rep.identical else f"DIVERGED: {rep.divergence}")
    return 0 if rep.identical else 1


# ------------------------------------------------------------------------------------ inspect
def inspect_cmd(args: argparse.Namespace) -> int:
    from mcsm.recording import (
        TOPIC_CHECKPOINT,
        TOPIC_CONFIG,
        TOPIC_OPS,
        RecordingError,
        RecordingReader,
    )

    reader = RecordingReader(args.file)
    maps: dict[str, dict[str, Any]] = {}
    times: list[int] = []
    try:
        for item in reader:
            d = item.data
            name = str(d.get("map"))
            m = maps.setdefault(name, {"options": None, "ops": Counter(), "kinds": Counter(),
                                       "frames": set(), "checkpoints": [], "last_seq": 0,
                                       "senders": Counter()})
            times.append(item.log_time_ns)
            if item.topic == TOPIC_CONFIG:
                m["options"] = d.get("options")
                m["restored_from"] = d.get("restored_from")
            elif item.topic == TOPIC_CHECKPOINT:
                m["checkpoints"].append((d.get("seq"), d.get("digest"), d.get("reason")))
            elif item.topic in TOPIC_OPS:
                op = TOPIC_OPS[item.topic]
                m["ops"][op] += 1
                m["last_seq"] = d.get("seq")
                m["senders"][str(d.get("sender", ""))] += 1
                try:
                    req = wire.unpack(d["request"])
                except (McsmError, KeyError) as exc:
                    m["kinds"]["undecodable"] += 1
                    log.debug("undecodable request: %s", exc)
                    continue
                if op == "update":
                    shape = req.get("samples", {}).get("shape", [0, 7])
                    m["kinds"]["point_update" if shape[-1] == 3 else "update"] += 1
                    m["frames"].update(str(req.get(k)) for k in ("a", "b"))
                elif op == "import":
                    m["frames"].update(map(str, req.get("submap", {}).get("frames", [])))
    except (RecordingError, OSError) as exc:
        print(f"mcsm inspect: cannot read {args.file}: {exc}", file=sys.stderr)
        return 2
    size = args.file.stat().st_size
    span = (max(times) - min(times)) / 1e9 if times else 0.0
    if args.json:
        print(json.dumps({
            "file": str(args.file), "bytes": size, "complete": reader.complete,
            "tail_error": reader.tail_error, "library": reader.library, "span_s": span,
            "maps": {n: {"options": m["options"], "ops": dict(m["ops"]),
                         "frames_named": len(m["frames"]), "last_seq": m["last_seq"],
                         "checkpoints": m["checkpoints"]} for n, m in maps.items()}}))
        return 0
    print(f"file:      {args.file} ({size} bytes, written by {reader.library or '?'})")
    print(f"state:     {'complete' if reader.complete else 'TRUNCATED: ' + str(reader.tail_error)}")
    if times:
        t0 = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(min(times) / 1e9))
        print(f"time span: {span:.3f} s from {t0} UTC")
    for name, m in maps.items():
        print(f"map {name!r}: options {m['options']}")
        if m.get("restored_from"):
            print(f"  restored from {m['restored_from']}")
        ops = ", ".join(f"{k} {v}" for k, v in sorted(m["ops"].items())) or "none"
        print(f"  operations: {sum(m['ops'].values())} ({ops}); last seq {m['last_seq']}")
        if m["kinds"]:
            print("  updates:    " + ", ".join(f"{k} {v}" for k, v in sorted(m["kinds"].items())))
        print(f"  frames named in inputs: {len(m['frames'])}")
        print(f"  senders: {len(m['senders'])}")
        cps = m["checkpoints"]
        print(f"  checkpoints: {len(cps)}")
        for seq, dig, why in cps[:3] + (cps[-2:] if len(cps) > 5 else cps[3:]):
            print(f"    seq {seq:>7} {why:<8} {dig}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
