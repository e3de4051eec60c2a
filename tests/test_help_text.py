"""Every ``--help`` the two commands print is text for a user: a description at the top, no
reStructuredText left over from a docstring (the top-level description once was a docstring's
first line, cut mid-sentence, with its markup)."""

from __future__ import annotations

import argparse
import re

import pytest
from mcsm.cli.parser import build_parser as mcsm_parser
from mcsm_client.cli import build_parser as client_parser

MARKUP = re.compile(r"``|:(?:func|mod|class|data|meth|attr):`")


def _parsers(parser: argparse.ArgumentParser,
             name: str) -> list[tuple[str, argparse.ArgumentParser]]:
    """``parser`` and every subcommand's parser under it, with their command lines."""
    out = [(name, parser)]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub, subparser in action.choices.items():
                out += _parsers(subparser, f"{name} {sub}")
    return out


def _helps(parser: argparse.ArgumentParser, name: str) -> list[tuple[str, str]]:
    """(name, help text) of ``parser`` and every subcommand under it."""
    return [(cmd, p.format_help()) for cmd, p in _parsers(parser, name)]


@pytest.mark.parametrize("make, name", [(mcsm_parser, "mcsm"), (client_parser, "mcsm-client")])
def test_every_help_is_plain_text_with_a_description(make, name) -> None:  # type: ignore[no-untyped-def]
    helps = _helps(make(), name)
    assert len(helps) > 10  # the subcommands were found
    for cmd, text in helps:
        assert not MARKUP.search(text), f"{cmd} --help shows markup: {MARKUP.search(text)}"
    top = helps[0][1].split("\n\n")
    description = next(part for part in top[1:] if part.strip())
    assert description.rstrip().endswith("."), f"{name}'s description is cut: {description!r}"


@pytest.mark.parametrize("make, name", [(mcsm_parser, "mcsm"), (client_parser, "mcsm-client")])
def test_every_option_says_what_it_does(make, name) -> None:  # type: ignore[no-untyped-def]
    """An option listed without a word of help (``sim --landmarks`` once) leaves the user to
    guess; a suppressed one is not listed and needs none."""
    bare = [f"{cmd} {action.option_strings[0]}" for cmd, p in _parsers(make(), name)
            for action in p._actions
            if action.option_strings and action.help is None
            and not isinstance(action, argparse._HelpAction | argparse._VersionAction)]
    assert not bare, f"options without help: {bare}"
