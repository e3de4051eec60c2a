"""The commands that read recordings: ``mcsm replay`` (bit-identical check), ``inspect``,
``recover`` and ``cat`` (one file or a split set)."""


from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

from mcsm import wire
from mcsm.cli.common import (
    EXIT_CUT,
    EXIT_DAMAGED,
    EXIT_DIVERGED,
    EXIT_OK,
    EXIT_OTHER_ARITHMETIC,
    EXIT_USAGE,
    _input_files,
    _label,
    _output_file,
    _progress,
    _state_line,
)
from mcsm.errors import McsmError
from mcsm.map import ops

log = logging.getLogger("mcsm")



# ------------------------------------------------------------------------------------ replay
MACHINE_BOUND = ("method=paper in the quaternion space runs on numpy/BLAS: it replays "
                 "bit-identically only on the machine family that recorded it")


def replay_cmd(args: argparse.Namespace) -> int:
    from mcsm.core import ARITHMETIC_VERSION
    from mcsm.log.replay import replay
    from mcsm.log.topics import RecordingError

    files, why = _input_files("replay", args.file)
    if why:
        print(why, file=sys.stderr)
        return EXIT_USAGE
    label = _label(files)
    bar = _progress(args, f"replay {files[0].name}" + (f" (+{len(files) - 1} files)"
                                                       if len(files) > 1 else ""))
    try:
        rep = replay(files, progress=bar)
    except (RecordingError, OSError) as exc:
        print(f"mcsm replay: cannot read {label}: {exc}", file=sys.stderr)
        return EXIT_USAGE
    finally:
        if bar is not None:
            bar.close()
    digests = rep.final_digests()
    speed = rep.n_inputs / rep.elapsed_s if rep.elapsed_s > 0 else float("inf")
    other = rep.other_arithmetic
    n_cp = len(rep.checkpoints)
    if rep.divergence is not None:
        code, status = EXIT_DIVERGED, "diverged"
        verdict = f"DIVERGED: {rep.divergence}"
    elif rep.damage is not None:
        code, status = EXIT_DAMAGED, "damaged"
        verdict = (f"DAMAGED: {rep.damage}; replayed {rep.n_inputs} inputs and verified "
                   f"{rep.checkpoints_ok} checkpoints before the damage (`mcsm recover` saves "
                   "the intact records)")
    elif rep.cut:
        code, status = EXIT_CUT, "cut"
        verdict = (f"CUT: the file ends without a clean close ({rep.tail_error}); replayed "
                   f"{rep.n_inputs} inputs and verified {rep.checkpoints_ok} checkpoints "
                   "before the cut; anything after it is not in the file")
    elif other:
        code, status = EXIT_OTHER_ARITHMETIC, "other_arithmetic"
        versions = ", ".join(f"map {n!r} version {v}" for n, v in other.items())
        verdict = (f"OTHER ARITHMETIC: recorded by arithmetic version(s) {versions}; this mcsm "
                   f"computes with version {ARITHMETIC_VERSION}, so its digests cannot be "
                   f"reproduced here (not a divergence): {rep.checkpoints_other_arithmetic} "
                   "checkpoints not compared")
    else:
        code, status = EXIT_OK, "identical"
        verdict = "identical"
    if args.json:
        print(json.dumps({"file": label, "files": [str(f) for f in files],
                          "status": status, "exit_code": code,
                          "identical": code == EXIT_OK, "divergence": rep.divergence,
                          "inputs": rep.n_inputs, "checkpoints": n_cp,
                          "checkpoints_ok": rep.checkpoints_ok,
                          "checkpoints_other_arithmetic": rep.checkpoints_other_arithmetic,
                          "complete": rep.complete, "cut": rep.cut, "damage": rep.damage,
                          "tail_error": rep.tail_error,
                          "arithmetic_versions": rep.arithmetic_versions,
                          "arithmetic_version_here": ARITHMETIC_VERSION, "digests": digests,
                          "seq": {n: s.seq for n, s in rep.states.items()},
                          "elapsed_s": rep.elapsed_s, "ops_per_s": speed}))
        return code
    not_compared = (f", {rep.checkpoints_other_arithmetic} not comparable (other arithmetic)"
                    if rep.checkpoints_other_arithmetic else "")
    print(f"{label}: {rep.n_inputs} inputs replayed in {rep.elapsed_s:.3f} s "
          f"({speed:.0f} ops/s); {rep.checkpoints_ok}/{n_cp} checkpoints match{not_compared}")
    for name, d in digests.items():
        print(f"map {name}: seq {rep.states[name].seq}, digest {d}")
        if not rep.states[name].map.portable:
            print(f"map {name}: {MACHINE_BOUND}")
    print(verdict)
    return code


# ------------------------------------------------------------------------------------ inspect
def inspect_cmd(args: argparse.Namespace) -> int:
    """Inspect each file (of a split recording: in set order); the exit code is the worst:
    5 (damaged) over 4 (cut) over 0."""
    from mcsm.log.recset import set_file

    files, why = _input_files("inspect", args.file)
    if why:
        print(why, file=sys.stderr)
        return EXIT_USAGE
    codes = []
    for k, f in enumerate(files):
        code = _inspect_one(f, args.json)
        if code == EXIT_USAGE:
            return code
        codes.append(code)
        if len(files) > 1 and not args.json:
            sf = set_file(f)
            print(f"  split recording {sf.set_id[:8]}: file {k + 1} of {len(files)} given "
                  f"(index {sf.index} of the set)")
    return max(codes, key=lambda c: {EXIT_DAMAGED: 2, EXIT_CUT: 1}.get(c, 0))


def _inspect_one(path: Path, as_json: bool) -> int:
    from mcsm.core import ARITHMETIC_VERSION
    from mcsm.log.reader import RecordingReader
    from mcsm.log.topics import (
        TOPIC_CHECKPOINT,
        TOPIC_CONFIG,
        TOPIC_OPS,
        TOPIC_SNAPSHOT,
        RecordingError,
    )

    reader = RecordingReader(path, edges=False)  # snapshots checked, not kept
    maps: dict[str, dict[str, Any]] = {}
    times: list[int] = []
    try:
        for item in reader:
            d = item.data
            name = str(d.get("map"))
            m = maps.setdefault(name, {"options": None, "ops": Counter(), "kinds": Counter(),
                                       "frames": set(), "checkpoints": [], "last_seq": 0,
                                       "senders": Counter(), "arithmetic_version": None})
            times.append(item.log_time_ns)
            if item.topic == TOPIC_CONFIG:
                m["options"] = d.get("options")
                m["gate_defer"] = d.get("gate_defer")
                m["restored_from"] = d.get("restored_from")
                m["arithmetic_version"] = d.get("arithmetic_version",
                                                reader.arithmetic_version)
            elif item.topic == TOPIC_CHECKPOINT:
                m["checkpoints"].append((d.get("seq"), d.get("digest"), d.get("reason")))
            elif item.topic == TOPIC_SNAPSHOT:
                m.setdefault("snapshots", []).append(d.get("seq"))
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
        print(f"mcsm inspect: cannot read {path}: {exc}", file=sys.stderr)
        return EXIT_USAGE
    size = path.stat().st_size
    span = (max(times) - min(times)) / 1e9 if times else 0.0
    code = EXIT_OK if reader.complete else EXIT_DAMAGED if reader.damage else EXIT_CUT
    if reader.layout == "indexed":
        crcs = (f"{reader.n_chunks_crc}/{reader.n_chunks} chunk CRCs"
                f"{', data section CRC' if reader.data_crc else ''}"
                f"{', summary CRC' if reader.summary_crc else ''} verified"
                f"{'' if reader.complete else ' before it stopped'}")
    elif reader.layout == "flat":
        crcs = "flat layout without CRCs (format 1): integrity not verifiable"
    else:
        crcs = "no records"
    n_in = sum(sum(m["ops"].values()) for m in maps.values())
    per_op = size / n_in if n_in else 0.0
    meta = reader.metadata.get("mcsm", {})
    if as_json:
        print(json.dumps({
            "file": str(path), "bytes": size, "bytes_per_input": per_op,
            "set": meta.get("set"), "set_index": meta.get("set_index"),
            "complete": reader.complete, "cut": reader.cut, "damage": reader.damage,
            "tail_error": reader.tail_error, "exit_code": code, "library": reader.library,
            "layout": reader.layout, "chunks": reader.n_chunks,
            "chunk_crcs": reader.n_chunks_crc, "data_crc": reader.data_crc,
            "summary_crc": reader.summary_crc, "arithmetic_version": reader.arithmetic_version,
            "arithmetic_version_here": ARITHMETIC_VERSION, "span_s": span,
            "maps": {n: {"options": m["options"], "gate_defer": m.get("gate_defer"),
                         "ops": dict(m["ops"]),
                         "arithmetic_version": m["arithmetic_version"],
                         "frames_named": len(m["frames"]), "last_seq": m["last_seq"],
                         "snapshots": m.get("snapshots", []),
                         "checkpoints": m["checkpoints"]} for n, m in maps.items()}}))
        return code
    print(f"file:      {path} ({size} bytes, {per_op / 1e3:.1f} kB per input, written by "
          f"{reader.library or '?'})")
    state = _state_line(reader.complete, reader.cut, reader.damage, reader.tail_error)
    print(f"state:     {state}")
    print(f"integrity: {crcs}")
    print(f"arithmetic version {reader.arithmetic_version} (this mcsm: {ARITHMETIC_VERSION})")
    if times:
        t0 = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(min(times) / 1e9))
        print(f"time span: {span:.3f} s from {t0} UTC")
    for name, m in maps.items():
        print(f"map {name!r}: options {m['options']}")
        opts = m["options"] if isinstance(m["options"], dict) else {}
        if opts.get("method") == "paper" and opts.get("space") == "quaternion":
            print(f"  {MACHINE_BOUND}")
        if m["arithmetic_version"] not in (None, reader.arithmetic_version):
            print(f"  arithmetic version {m['arithmetic_version']}")
        if m.get("restored_from"):
            print(f"  restored from {m['restored_from']}")
        if m.get("gate_defer"):
            print(f"  --gate-defer {m['gate_defer']}")
        ops = ", ".join(f"{k} {v}" for k, v in sorted(m["ops"].items())) or "none"
        print(f"  operations: {sum(m['ops'].values())} ({ops}); last seq {m['last_seq']}")
        if m["kinds"]:
            print("  updates:    " + ", ".join(f"{k} {v}" for k, v in sorted(m["kinds"].items())))
        print(f"  frames named in inputs: {len(m['frames'])}")
        print(f"  senders: {len(m['senders'])}")
        snaps = m.get("snapshots", [])
        if snaps:
            print(f"  snapshots: {len(snaps)} (seq {snaps[0]} .. {snaps[-1]})")
        cps = m["checkpoints"]
        shown = (f" (the first 3 and the last 2 of {len(cps)} listed; --json lists all)"
                 if len(cps) > 5 else "")
        print(f"  checkpoints: {len(cps)}{shown}")
        for seq, dig, why_cp in cps[:3] + (cps[-2:] if len(cps) > 5 else cps[3:]):
            print(f"    seq {seq:>7} {why_cp:<8} {dig}")
    return code


# ------------------------------------------------------------------------------------ recover
def recover_cmd(args: argparse.Namespace) -> int:
    """Recover one file into ``-o FILE``, or each file of a split recording into the new
    directory ``-o DIR`` (same names)."""
    why = _output_file("recover", args.output)  # before anything is read
    if why:
        print(why, file=sys.stderr)
        return EXIT_USAGE
    files, why = _input_files("recover", args.file)
    if why:
        print(why, file=sys.stderr)
        return EXIT_USAGE
    if len(files) == 1:
        return _recover_one(args, files[0], args.output)
    args.output.mkdir()
    for f in files:
        code = _recover_one(args, f, args.output / f.name)
        if code != EXIT_OK:
            return code
    return EXIT_OK


def _recover_one(args: argparse.Namespace, src: Path, dst: Path) -> int:
    from mcsm.log.recover import recover
    from mcsm.log.topics import TOPIC_CHECKPOINT, TOPIC_CONFIG, RecordingError

    bar = _progress(args, f"recover {src.name}")
    try:
        rep = recover(src, dst, progress=bar)
    except (RecordingError, OSError) as exc:  # (recover removes a copy it started)
        print(f"mcsm recover: {exc}", file=sys.stderr)
        return EXIT_USAGE
    finally:
        if bar is not None:
            bar.close()
    state = _state_line(rep.source_complete, rep.source_cut, rep.damage, rep.tail_error)
    print(f"{src}: {state}")
    if rep.chunks_after_damage:
        print(f"  {rep.chunks_after_damage} intact chunks after the damage were copied too; the "
              "records lost in the damaged part leave a gap, where a replay of the copy stops")
    print(f"{dst}: {rep.n_inputs} inputs, {rep.messages[TOPIC_CHECKPOINT]} checkpoints, "
          f"{rep.messages[TOPIC_CONFIG]} map configs ({rep.bytes_written} bytes, indexed)")
    return EXIT_OK


# ------------------------------------------------------------------------------------ cat
def _summarise(obj: Any, with_samples: bool) -> Any:
    """An AT as its mean and covariance (or every sample), points as mean and covariance."""
    import numpy as np

    from mcsm.core import mean_and_cov

    x = np.asarray(obj, dtype=np.float64)
    out: dict[str, Any] = {"n": int(x.shape[0])}
    if with_samples:
        out["samples"] = x.tolist()
        return out
    if x.shape[-1] == 7:
        mean, cov = mean_and_cov(x)
    else:
        mean, cov = x.mean(axis=0), np.cov(x, rowvar=False)
    out["mean"] = [float(v) for v in mean]
    out["cov"] = np.asarray(cov).tolist()
    return out


def _input_json(op: str, req: Any, with_samples: bool) -> dict[str, Any]:
    out = ops.get(op).describe(req)
    if isinstance(req, wire.UpdateRequest):
        out["samples"] = _summarise(req.samples, with_samples)
    elif isinstance(req, wire.SubmapImportRequest):
        out["edges"] = [_summarise(e, with_samples) for e in req.submap.edges[1:]]
    return out


def cat_cmd(args: argparse.Namespace) -> int:
    from mcsm.log.reader import RecordingReader

    files, why = _input_files("cat", args.file)
    if why:
        print(why, file=sys.stderr)
        return EXIT_USAGE
    n_samples: dict[str, int] = {}
    for f in files:
        reader = RecordingReader(f, edges=False)
        code = _cat_file(args, f, reader, n_samples)
        if code != EXIT_OK:
            return code
    return EXIT_OK


def _cat_file(args: argparse.Namespace, path: Path, reader: Any,
              n_samples: dict[str, int]) -> int:
    from mcsm.log.topics import TOPIC_CONFIG, TOPIC_OPS, RecordingError
    from mcsm.log.topics import decode_input as decode

    try:
        for item in reader:
            d = item.data
            name = str(d.get("map"))
            if item.topic == TOPIC_CONFIG:
                n_samples.setdefault(name, int(d.get("options", {}).get("n_samples", 0)))
                continue
            op = TOPIC_OPS.get(item.topic)
            if op is None:
                continue
            line: dict[str, Any] = {"map": name, "seq": d.get("seq"), "op": op,
                                    "recv_ns": d.get("recv_ns"), "sender": d.get("sender"),
                                    "id": d.get("id")}
            try:
                req = decode(op, bytes(d["request"]), n_samples.get(name, 0))
                line.update(_input_json(op, req, args.samples))
            except (McsmError, KeyError, TypeError, ValueError) as exc:
                line["error"] = f"{type(exc).__name__}: {exc}"
            if args.json:
                print(json.dumps(line))
            else:
                print(_cat_text(line))
    except BrokenPipeError:
        raise
    except (RecordingError, OSError) as exc:
        print(f"mcsm cat: cannot read {path}: {exc}", file=sys.stderr)
        return EXIT_USAGE
    if not reader.complete:
        print(f"mcsm cat: {path}: "
              f"{_state_line(False, reader.cut, reader.damage, reader.tail_error)}",
              file=sys.stderr)
        return EXIT_DAMAGED if reader.damage else EXIT_CUT
    return EXIT_OK


def _cat_text(line: dict[str, Any]) -> str:
    """An input's line; an AT's covariance (or with --samples its samples) on indented lines."""
    head = f"{line['map']} seq {line['seq']} {line['op']}"
    if "error" in line:
        return f"{head} undecodable: {line['error']}"
    rows: list[str] = []
    if "samples" in line:
        s = line["samples"]
        mean = " ".join(f"{v:.6g}" for v in s.get("mean", []))
        body = f"{line['a']} -> {line['b']} N={s['n']}" + (f" mean [{mean}]" if mean else "")
        labels = "tx ty tz rx ry rz" if len(s.get("mean", [])) == 7 else "x y z"
        rows = [f"  {'cov (' + labels + ')' if i == 0 else '':<24}"
                + " ".join(f"{v:11.4g}" for v in r) for i, r in enumerate(s.get("cov", []))]
        rows += ["  " + " ".join(f"{v:.17g}" for v in r) for r in s.get("samples", [])]
    elif "frame" in line:
        body = line["frame"]
    elif "target" in line:
        body = f"of {line['target']}"
    else:
        body = f"{len(line.get('frames', []))} frames"
    return "\n".join([f"{head} {body} (sender {line['sender']}, id {line['id']})", *rows])
