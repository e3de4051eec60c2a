"""Every ``mcsm`` / ``mcsm-client`` command line in the documentation's shell blocks parses.

README.md, CONTRIBUTING.md, ``docs/**/*.md`` and ``deploy/**/*.md``: each line of a fenced
``sh``/``bash``/``console`` block (continuations joined, split at ``&&``, ``;`` and pipes) that
runs ``mcsm`` or ``mcsm-client`` goes through the real parser, so a renamed or removed flag
fails here rather than in a user's shell. Synopses with ``[optional]`` brackets are skipped;
placeholders in capitals are plain strings to the parser; ``--ros-args`` and what follows are
ROS's, as in :func:`mcsm.cli.parser.main`.
"""

from __future__ import annotations

import contextlib
import io
import re
import shlex
from pathlib import Path

import pytest
from mcsm.cli.parser import build_parser as mcsm_parser
from mcsm_client.cli import build_parser as client_parser

ROOT = Path(__file__).resolve().parents[1]
DOCS = sorted([ROOT / "README.md", ROOT / "CONTRIBUTING.md", *ROOT.glob("docs/**/*.md"),
               *ROOT.glob("deploy/**/*.md")])
SHELL = ("", "sh", "bash", "console", "shell", "text")
COMMAND = re.compile(r"^(?:\w+=\S+\s+)*(?:\S*/)?(?:nice -n \d+ )?(mcsm|mcsm-client)\s+(.*)$")


def shell_blocks(text: str) -> list[str]:
    """The bodies of ``text``'s fenced blocks tagged as shell, or not tagged."""
    blocks: list[str] = []
    body: list[str] | None = None
    fence = ""
    for line in text.splitlines():
        stripped = line.strip()
        if fence.endswith("!"):  # inside a block of another language
            if stripped == fence[:3]:
                fence = ""
        elif body is not None:
            if stripped == fence:
                blocks.append("\n".join(body))
                body, fence = None, ""
            else:
                body.append(line)
        elif stripped.startswith(("```", "~~~")):
            fence, lang = stripped[:3], stripped[3:].strip()
            if lang in SHELL:
                body = []
            else:
                fence += "!"
    return blocks


def commands(text: str) -> list[tuple[str, list[str]]]:
    """(program, argv) of every command line in ``text``'s shell blocks."""
    out = []
    for block in shell_blocks(text):
        for line in block.replace("\\\n", " ").splitlines():
            line = line.strip().removeprefix("$ ")
            for part in re.split(r"\s*(?:&&|\|\||;|\|)\s*", line):
                m = COMMAND.match(part.strip())
                if not m or "[" in m.group(2).split("#")[0]:
                    continue
                argv = shlex.split(m.group(2), comments=True)
                cut = [i for i, a in enumerate(argv) if a in ("&", "--ros-args")
                       or a.startswith((">", "2>"))]
                argv = argv[:cut[0]] if cut else argv
                if argv and argv[-1].endswith("&"):
                    argv[-1] = argv[-1][:-1]
                out.append((m.group(1), argv))
    return out


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_documented_commands_parse(doc: Path) -> None:
    for program, argv in commands(doc.read_text()):
        parser = mcsm_parser() if program == "mcsm" else client_parser()
        err = io.StringIO()
        try:
            with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
                parser.parse_args(argv)
        except SystemExit as exc:
            assert not exc.code, f"{program} {' '.join(argv)}: {err.getvalue().strip()}"


def test_the_commands_are_found_and_a_bad_flag_fails() -> None:
    found = [c for doc in DOCS for c in commands(doc.read_text())]
    assert len(found) >= 40
    assert {p for p, _ in found} == {"mcsm", "mcsm-client"}
    text = ("```python\nmcsm = 1\n```\nmcsm prose\n"
            "```sh\nmcsm replay x.mcap --no-such-flag && mcsm-client info  # note\n```\n")
    (program, argv), (program2, argv2) = commands(text)
    assert (program, argv, program2, argv2) == ("mcsm", ["replay", "x.mcap", "--no-such-flag"],
                                                "mcsm-client", ["info"])
    with pytest.raises(SystemExit):
        with contextlib.redirect_stderr(io.StringIO()):
            mcsm_parser().parse_args(argv)
