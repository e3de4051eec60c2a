"""The exit codes every ``mcsm`` subcommand shares and the helpers for input and output files
(one recording or a split set), progress and the state line of a read."""


from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import Any

from mcsm import wire

log = logging.getLogger("mcsm")



# exit codes of every subcommand (documented in docs/recordings.md; keep them stable)
EXIT_OK = 0
EXIT_DIVERGED = 1  # replay: a checkpoint, a sequence number or an input does not match
EXIT_USAGE = 2  # bad arguments, missing or unreadable file, not a recording, unwritable output
EXIT_RECORDING_FAILED = 3  # serve: the recording could not be written; serving stopped
EXIT_CUT = 4  # the file ends before its clean close (SIGKILL, full disk): the prefix was used
EXIT_DAMAGED = 5  # a CRC does not match or a record does not decode: read up to the damage
EXIT_OTHER_ARITHMETIC = 6  # replay: recorded by another arithmetic version; not compared

EXIT_CODES_HELP = """exit codes:
  0  success (replay: every checkpoint matches and the file is complete)
  1  replay diverged (a digest, a sequence number or an input does not match)
  2  usage error: bad arguments, missing or unreadable file, not an mcsm recording,
     output path exists or is not writable, a split recording with a gap or mixed files
  3  serve: the recording could not be written (serving stopped)
  4  the recording is cut (no clean close): inspect/replay used every complete record
  5  the recording is damaged (CRC mismatch or undecodable record): read up to the damage
  6  replay: recorded by another arithmetic version of the core; digests not comparable
130  interrupted (Ctrl-C); serve stops cleanly on SIGINT and exits 0
(replay reports the first that applies in the order 1, 5, 4, 6)"""




# ------------------------------------------------------------------------------------ common
def _version_text() -> str:
    from mcsm import __version__
    from mcsm.core import ARITHMETIC_VERSION

    return (f"mcsm {__version__} (core arithmetic version {ARITHMETIC_VERSION}, wire protocol "
            f"v{wire.VERSION}, recording format v2)")


def _input_files(cmd: str, args: list[Path]) -> tuple[list[Path], str | None]:
    """The files ``args`` name (one recording, or a split recording's files in set order,
    :mod:`mcsm.log.recset`) and why they cannot be read (None if they can)."""
    from mcsm.log.recset import expand, order
    from mcsm.log.topics import RecordingError

    try:
        files = expand(args)
    except RecordingError as exc:
        return [], f"mcsm {cmd}: {exc}"
    for f in files:
        why = _input_file(cmd, f)
        if why:
            return files, why
    try:
        return order(files), None
    except (RecordingError, OSError) as exc:
        return files, f"mcsm {cmd}: {exc}"


def _label(files: list[Path]) -> str:
    return str(files[0]) if len(files) == 1 else f"{files[0]} .. {files[-1].name}"


def _input_file(cmd: str, path: Path) -> str | None:
    """Why ``path`` cannot be read as an input file (None if it can)."""
    if not path.exists():
        return f"mcsm {cmd}: {path}: no such file"
    if path.is_dir():
        return f"mcsm {cmd}: {path}: is a directory, not a recording"
    try:
        with open(path, "rb"):
            pass
    except OSError as exc:
        return f"mcsm {cmd}: {path}: cannot open: {exc.strerror or exc}"
    from mcsm.log.filetype import not_a_recording

    why = not_a_recording(path)  # e.g. a Foxglove scene: not damaged, not ours
    return f"mcsm {cmd}: {path}: {why}" if why else None


def _output_file(cmd: str, path: Path) -> str | None:
    """Why ``path`` cannot be written as a new output file (None if it can); checked before
    any long work starts."""
    import os

    if path.exists():
        return f"mcsm {cmd}: {path}: exists; refusing to overwrite"
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        return f"mcsm {cmd}: {path}: directory {parent} does not exist"
    if not os.access(parent, os.W_OK | os.X_OK):
        return f"mcsm {cmd}: {path}: directory {parent} is not writable"
    return None


def _progress(args: argparse.Namespace, label: str) -> Any:
    from mcsm.log.progress import progress_bar

    return None if getattr(args, "no_progress", False) else progress_bar(label=label)


def _state_line(complete: bool, cut: bool, damage: str | None, tail: str | None) -> str:
    if complete:
        return "complete"
    if damage is not None:
        return f"DAMAGED: {damage}"
    if cut:
        return f"CUT (no clean close): {tail}"
    return "not read to the end"
