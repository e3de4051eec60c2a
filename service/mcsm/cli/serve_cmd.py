"""``mcsm serve``, ``mcsm router``: the option parsers of the server's flags (sizes, gate,
gate scale, history, relinearisation policy, deferral, inflation), the server's run loop and
its exit codes, and the NATS options of a replicated server."""


from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

from mcsm import wire
from mcsm.cli.common import (
    EXIT_OK,
    EXIT_RECORDING_FAILED,
    EXIT_USAGE,
)
from mcsm.core.relinearize import Policy
from mcsm.core.smap import DEFAULT_POLICY
from mcsm.errors import McsmError
from mcsm.log.writer import new_recording_problem
from mcsm.map.deferral import DeferOptions

log = logging.getLogger("mcsm")



# ------------------------------------------------------------------------------------ serve
def _bytes(text: str) -> int:
    """A byte count: digits with an optional K, M or G suffix (KiB, MiB, GiB)."""
    t = text.strip().upper().removesuffix("B").removesuffix("I")
    scale = {"K": 1 << 10, "M": 1 << 20, "G": 1 << 30}.get(t[-1:], 1)
    try:
        n = int(float(t[:-1] if scale > 1 else t) * scale)
    except ValueError:
        n = -1
    if n < 0:
        raise argparse.ArgumentTypeError(f"expected a byte count such as 1048576 or 512M, "
                                         f"got {text!r}")
    return n


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


def _spread(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        v = 0.0
    if not 1.0 <= v <= 2.0:
        raise argparse.ArgumentTypeError(f"expected a number in [1, 2], got {text!r}")
    return v


def _gate_scale(text: str) -> dict[str, Any] | None:
    if text == "none":
        return None
    parts = text.split(":")
    try:
        d: dict[str, Any] = {"window": int(parts[0]), "open": float(parts[1]),
                             "max": float(parts[2])}
    except (ValueError, IndexError):
        d = {"window": 0, "open": 0.0, "max": 0.0}
    if len(parts) != 3 or not (1 <= d["window"] <= 999 and d["open"] >= 1.0
                               and d["max"] >= 1.0):
        raise argparse.ArgumentTypeError(f"expected W:T:S (W in [1, 999], T, S >= 1) or "
                                         f"'none', got {text!r}")
    return d


def _history(text: str) -> int | None:
    if text == "none":
        return None
    try:
        n = int(text)
    except ValueError:
        n = 0
    if not 2**16 <= n <= 2**40:
        raise argparse.ArgumentTypeError(f"expected a byte count in [65536, 2**40] or 'none', "
                                         f"got {text!r}")
    return n


def _every(text: str) -> int | None:
    return None if text == "none" else _defer(text)


def _policy(args: argparse.Namespace) -> dict[str, Any] | None:
    """The relinearisation policy of the serve flags (None: none, not even a spread for
    requested relinearisations)."""
    pol = DEFAULT_POLICY or Policy()
    triggers = (args.relinearize_nis, args.relinearize_every, args.relinearize_regate)
    recentre = pol.recentre if args.relinearize_recentre is None else args.relinearize_recentre
    if args.history is None:
        if triggers in ((pol.nis, pol.every, pol.regate), (None, None, None)) \
                and not args.relinearize_recentre \
                and args.relinearize_readmit in (pol.readmit, None) \
                and args.relinearize_calibrate in (None, 0):
            return None  # --history none turns the default policy off
        raise McsmError("--relinearize-* needs a history (not --history none)")
    if triggers == (None, None, None) and args.relinearize_spread == 1.0 and not recentre:
        return None  # (readmit acts only through regate or recentre)
    calibrate = args.relinearize_calibrate or None  # 0: none
    if args.relinearize_calibrate is None and args.relinearize_readmit is not None:
        calibrate = pol.calibrate  # the default, where it applies (it needs readmit)
    return {"nis": args.relinearize_nis, "every": args.relinearize_every,
            "regate": args.relinearize_regate, "gap": args.relinearize_gap,
            "spread": args.relinearize_spread, "recentre": recentre,
            "readmit": args.relinearize_readmit, "calibrate": calibrate}


def _defer(text: str) -> int:
    try:
        k = int(text)
    except ValueError:
        k = 0
    if k < 1:
        raise argparse.ArgumentTypeError(f"expected a number of updates >= 1, got {text!r}")
    return k


def _inflation(text: str) -> float | str:
    if text == "adaptive":
        return text
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a number in [1, 2) or 'adaptive', got {text!r}") from None


def router_cmd(args: argparse.Namespace) -> int:
    """``mcsm router``: a Zenoh router (no map of its own) until SIGINT or SIGTERM."""
    import zenoh

    from mcsm.serve.connect import router_config, zenoh_error_text

    logging.basicConfig(level=getattr(logging, str(args.log_level).upper(), logging.INFO),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
                        stream=sys.stderr)
    try:
        conf = router_config(args.listen, args.zenoh_config)
        session = zenoh.open(conf)
    except (McsmError, zenoh.ZError, OSError) as exc:
        print(f"mcsm router: {zenoh_error_text(exc)}", file=sys.stderr)
        return 2
    stop = threading.Event()
    old = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT,
                                                                       signal.SIGTERM)}
    print(f"routing on {args.listen} (zid {session.zid()})", flush=True)
    try:
        while not stop.wait(0.5):
            pass
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)
        session.close()
    return 0


def serve(args: argparse.Namespace) -> int:
    import zenoh

    from mcsm.log.progress import progress_bar
    from mcsm.serve.connect import (
        listen_endpoints,
        security_warning,
        server_config,
        zenoh_error_text,
    )
    from mcsm.serve.server import Server, ServerOptions

    logging.basicConfig(level=getattr(logging, str(args.log_level).upper(), logging.INFO),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
                        stream=sys.stderr)
    record = args.record
    if record is not None and (why := new_recording_problem(Path(record))):
        more = f", or go on from it with --restore {record} --record NEW.mcap"
        print(f"mcsm serve: --record {record}: {why}{more if Path(record).exists() else ''}",
              file=sys.stderr)
        return EXIT_USAGE
    if record is None:
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        record = Path("recordings") / f"run-{stamp}.mcap"
        k = 1
        while record.exists() and k < 1000:
            record = Path("recordings") / f"run-{stamp}-{k}.mcap"
            k += 1
    restore: list[Path] | None = None
    if args.restore:
        from mcsm.log.recset import resolve

        try:
            restore = resolve(args.restore)
        except (McsmError, OSError) as exc:
            print(f"mcsm serve: --restore: {exc}", file=sys.stderr)
            return EXIT_USAGE
    # restoring without --map serves the recording's maps (or "default" if it has none)
    standby_of = list(dict.fromkeys(args.standby_of or []))
    maps = args.map or ([] if args.restore or standby_of else [wire.DEFAULT_MAP])
    try:
        policy = _policy(args)
    except McsmError as exc:
        print(f"mcsm serve: {exc}", file=sys.stderr)
        return 2
    opts = ServerOptions(
        maps=list(dict.fromkeys(maps)), prefix=args.prefix,
        map_options={"n_samples": args.samples, "method": args.method, "space": args.space,
                     "analysis": args.analysis, "shrink": args.shrink,
                     "inflation": args.inflation, "gain": args.gain, "gate": args.gate,
                     "gate_scale": args.gate_scale, "history": args.history,
                     "relinearize": policy},
        record=record, restore=restore, checkpoint_every=max(1, args.checkpoint_every),
        queue_size=args.queue_size, queue_bytes=max(1, args.queue_bytes),
        retract_window_bytes=args.retract_window_bytes, split_bytes=args.split_size,
        split_s=max(0.0, args.split_duration), fsync=args.fsync, lru_size=max(1, args.id_memory),
        id_ttl_s=max(0.0, args.id_ttl_s), snapshot_every=max(1, args.snapshot_every),
        snapshots_kept=max(1, args.snapshots_kept),
        disk_snapshot_every=max(0, args.disk_snapshot_every), standby_of=standby_of,
        device=args.device,
        gate_defer=None if args.gate_defer is None else DeferOptions(expiry=args.gate_defer))
    try:
        opts.nats = _nats_options(args)
        for name in [*opts.maps, *opts.standby_of]:
            wire.map_keys(name, opts.prefix)
        if opts.device != "cpu":  # one clear line now, not a traceback at the first map
            from mcsm.core.device import backend_for
            backend_for(opts.device)
        conf = server_config(args.listen, args.zenoh_config, connect=args.connect)
    except (McsmError, zenoh.ZError, OSError) as exc:
        print(f"mcsm serve: {zenoh_error_text(exc)}", file=sys.stderr)
        return 2
    warning = security_warning(conf)
    if warning is not None:
        log.warning("%s", warning)
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as exc:
        print(f"mcsm serve: cannot open the Zenoh session: {zenoh_error_text(exc)}",
              file=sys.stderr)
        return 2
    stop = threading.Event()

    def on_signal(signum: int, _frame: Any) -> None:
        log.info("signal %d: shutting down", signum)
        stop.set()

    old_handlers = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    server = Server(session, opts, progress=progress_bar() if args.restore else None)
    code = EXIT_OK
    try:
        try:
            server.start()
        except (McsmError, OSError) as exc:  # (after --restore's progress line: a new line)
            print(f"{chr(10) if args.restore else ''}mcsm serve: {exc}", file=sys.stderr)
            code = EXIT_RECORDING_FAILED if _no_space(exc) else EXIT_USAGE
            return code
        if args.restore:
            sys.stderr.write("\n")
        log.info("recording to %s", opts.record)
        via = f" (joined {' '.join(args.connect)})" if args.connect else ""
        print(f"listening on {' '.join(listen_endpoints(conf)) or '-'}{via}", flush=True)
        while not stop.wait(0.5):
            if server.failed.is_set():
                log.critical("stopping after a recording failure")
                code = EXIT_RECORDING_FAILED
                break
    finally:
        server.close()
        session.close()
        for sig, handler in old_handlers.items():
            signal.signal(sig, handler)
    if server.failed.is_set():  # also when closing the file hit the full disk
        print(f"mcsm serve: stopped: the recording {server.recording_path} could not be "
              "written (see the log); it holds every acknowledged input", file=sys.stderr)
        return EXIT_RECORDING_FAILED
    return code


def _no_space(exc: BaseException) -> bool:
    """An error of writing the recording itself (full disk, quota, file size limit, I/O)."""
    import errno

    return isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG,
                                                      errno.EIO)


def _nats_options(args: argparse.Namespace) -> Any:
    """``--nats``, ``--nats-auth``, ... as :class:`mcsm.serve.replication.NatsOptions` (None
    without ``--nats``: then nothing of NATS is imported).

    Raises
    ------
    McsmError
        A replication flag without ``--nats``, or unreadable credentials.
    """
    urls = [u.strip() for a in (args.nats or []) for u in a.split(",") if u.strip()]
    if not urls:
        if args.nats_auth is not None:
            raise McsmError("--nats-auth needs --nats URL")
        return None
    from mcsm.serve.replication import NatsOptions

    o = NatsOptions(urls=urls, replicas=max(1, args.replicas),
                    lease_ttl_s=max(0.2, args.lease_ttl),
                    max_bytes=max(0, args.log_max_bytes), max_age_s=max(0.0, args.log_max_age))
    if args.nats_auth is not None:
        a = NatsOptions.load_auth(args.nats_auth)
        o.user, o.password = a.get("user"), a.get("password")
        o.tls_ca, o.tls_cert, o.tls_key = a.get("tls_ca"), a.get("tls_cert"), a.get("tls_key")
    if o.max_age_s and o.max_age_s < args.id_ttl_s:
        raise McsmError(f"--log-max-age {o.max_age_s:g} is below --id-ttl-s {args.id_ttl_s:g}: "
                        "the log's de-duplication window must fit in it")
    return o
