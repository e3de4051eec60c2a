"""Recording sets: the files of one split recording, named on a command line.

``mcsm serve --split-size B`` / ``--split-duration S`` (like rosbag2's ``--max-bag-size`` and
``--max-bag-duration``) writes ``run_0000.mcap``, ``run_0001.mcap``, ... for ``--record
run.mcap``: each file starts with every map's config and a snapshot (with the remembered
request ids and the retract window), so each replays on its own; together they replay as one
recording. Each file's ``mcsm`` metadata record names its set (a random id) and its index in
the set.

The commands that read recordings (``replay``, ``inspect``, ``recover``, ``cat``, ``plot``,
``serve --restore``) take one or more arguments, each a file, a directory (its ``*.mcap``
files) or a glob pattern (``'run_*.mcap'``, quoted or expanded by the shell).
:func:`resolve` turns them into the files in set order and refuses, with a message naming the
files:

* a **mixed set**: files of different sets, or a file that belongs to no set together with
  other files;
* a **gap**: a missing index between two given files (a set may start after index 0: every
  file replays on its own, so a set's later files are a valid recording);
* the same file (or the same index) twice.
"""

from __future__ import annotations

import glob
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from mcap.records import Metadata

from mcsm.recording import RecordingError, RecordingReader


@dataclass(frozen=True)
class SetFile:
    """One file and its place in a set (``set_id`` is "" for a file of no set)."""

    path: Path
    set_id: str
    index: int


def expand(args: Sequence[str | os.PathLike[str]]) -> list[Path]:
    """The files named by ``args``: a directory gives its ``*.mcap`` files, a pattern with
    ``*``, ``?`` or ``[`` that is not itself a file gives its matches, anything else itself.

    Raises
    ------
    RecordingError
        If a directory or a pattern names no recording, or nothing was given.
    """
    out: list[Path] = []
    for a in args:
        p = Path(a)
        if p.is_dir():
            found = sorted(q for q in p.glob("*.mcap") if q.is_file())
            if not found:
                raise RecordingError(str(p), "a directory without *.mcap files")
            out.extend(found)
        elif not p.exists() and any(c in str(a) for c in "*?["):
            found = sorted(Path(m) for m in glob.glob(str(a)) if Path(m).is_file())
            if not found:
                raise RecordingError(str(a), "no file matches this pattern")
            out.extend(found)
        else:
            out.append(p)
    if not out:
        raise RecordingError("", "no recording given")
    return out


def set_file(path: Path) -> SetFile:
    """``path``'s set id and index, read from its ``mcsm`` metadata record (near the start).

    Raises
    ------
    RecordingError
        If it is not an MCAP file.
    OSError
        If it cannot be read.
    """
    for rec in RecordingReader(path).raw():
        if isinstance(rec, Metadata) and rec.name == "mcsm":
            set_id = str(rec.metadata.get("set", ""))
            try:
                index = int(rec.metadata.get("set_index", "0"))
            except ValueError:
                index = 0
            return SetFile(path, set_id, index if set_id else 0)
    return SetFile(path, "", 0)


def order(files: Sequence[Path]) -> list[Path]:
    """``files`` in set order, checked (see the module's docstring).

    Raises
    ------
    RecordingError
        A mixed set, a gap, or a file given twice.
    OSError
        If a file cannot be read.
    """
    paths = list(files)
    seen: dict[Path, Path] = {}
    for p in paths:
        r = p.resolve()
        if r in seen:
            raise RecordingError(str(p), "given twice")
        seen[r] = p
    if len(paths) == 1:
        return paths
    info = [set_file(p) for p in paths]
    lone = [f for f in info if not f.set_id]
    if lone:
        raise RecordingError(str(lone[0].path), "mixed set: this file is not part of a split "
                             "recording, so it cannot be read together with other files")
    ids = sorted({f.set_id for f in info})
    if len(ids) > 1:
        a = next(f for f in info if f.set_id == ids[0])
        b = next(f for f in info if f.set_id == ids[1])
        raise RecordingError(str(b.path), f"mixed set: it belongs to split recording "
                             f"{b.set_id[:8]}, but {a.path.name} to {a.set_id[:8]}")
    info.sort(key=lambda f: f.index)
    for prev, nxt in zip(info, info[1:], strict=False):
        if nxt.index == prev.index:
            raise RecordingError(str(nxt.path), f"the same file of the set as {prev.path.name} "
                                 f"(index {prev.index})")
        if nxt.index != prev.index + 1:
            missing = ", ".join(str(k) for k in range(prev.index + 1, nxt.index))
            raise RecordingError(str(nxt.path), f"gap in the split recording: file(s) {missing} "
                                 f"of the set are missing between {prev.path.name} (index "
                                 f"{prev.index}) and {nxt.path.name} (index {nxt.index})")
    return [f.path for f in info]


def resolve(args: Sequence[str | os.PathLike[str]]) -> list[Path]:
    """:func:`expand` then :func:`order`: the recording named by ``args``, in set order."""
    return order(expand(args))


__all__ = ["SetFile", "expand", "set_file", "order", "resolve"]
