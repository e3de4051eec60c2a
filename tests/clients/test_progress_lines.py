"""``mcsm-client play``'s progress in a log or a pipe (docs/recordings.md, "Progress"): a plain
``label: done/total (rate/s)`` line at most every ``every_s`` and a last one when the run
printed any, never a carriage return; nothing when disabled."""

from __future__ import annotations

import pytest
from mcsm_client.cli_common import _Progress


def test_plain_progress_lines_in_a_log(capsys: pytest.CaptureFixture[str]) -> None:
    quiet = _Progress("play x", every_s=3600.0)  # a run shorter than the interval: silent
    for k in range(1, 11):
        quiet(k, 10)
    assert capsys.readouterr().err == ""
    p = _Progress("play x", every_s=0.0)  # (stderr is captured: not a terminal)
    for k in range(1, 4):
        p(k, 3)
    err = capsys.readouterr().err
    assert "\r" not in err
    lines = err.splitlines()
    assert [ln.split(" (")[0] for ln in lines] == ["play x: 1/3", "play x: 2/3", "play x: 3/3"]
    assert all(ln.endswith("/s)") for ln in lines)
    off = _Progress("play x", enabled=False, every_s=0.0)
    off(1, 1)
    assert capsys.readouterr().err == ""
