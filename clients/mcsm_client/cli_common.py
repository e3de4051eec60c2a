"""What every ``mcsm-client`` command shares: exit codes, :class:`UsageError`, the
connection and in-process flags, the client and in-process map a command talks to, noise
covariances from ``--sigma``/``--cov``, output (``--json`` or text, acks, counts), output-file
checks and the progress line. The commands are in :mod:`mcsm_client.cli_map` and
:mod:`mcsm_client.cli_run`; the parser and ``main`` in :mod:`mcsm_client.cli`.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from mcsm.serve.connect import add_connection_args, client_kwargs

from mcsm_client.client import DEFAULT_TIMEOUT_S

EXIT_OK, EXIT_REFUSED, EXIT_USAGE, EXIT_TIMEOUT, EXIT_INTERRUPTED = 0, 1, 2, 3, 130
EXIT_GATE_REJECTED = 4  # update: recorded and acknowledged, but the gate refused it


class UsageError(Exception):
    """A command-line value that argparse alone cannot check."""


def _add_common(p: argparse.ArgumentParser) -> None:
    add_connection_args(p, suppress=True)
    p.add_argument("--timeout-s", type=float, default=argparse.SUPPRESS,
                   help="how long one request waits for the server, seconds (default "
                        f"{DEFAULT_TIMEOUT_S:g})")


def _add_in_process(p: argparse.ArgumentParser) -> None:
    p.add_argument("--in-process", type=int, default=None, metavar="N",
                   help="no server: use an in-process map with N samples per AT")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")


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
    if ack.kind == "rejected":  # recorded and acknowledged, but the map is unchanged
        head = "pending" if v is not None and v.status == "pending" else "rejected"
        return f"{head} seq={ack.seq} id={ack.request_id}{comp}{extra}"
    return f"ok seq={ack.seq} id={ack.request_id} {ack.kind}{comp}{extra}"


def _count(n: int, noun: str) -> str:
    """``1 frame``, ``2 frames``."""
    return f"{n} {noun}{'' if n == 1 else 's'}"


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

