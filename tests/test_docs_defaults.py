"""A default the docs state is the code's: every "`--flag` (VALUE)" and
"`--flag`, default VALUE" in README.md, docs/ and deploy/ is checked against the parsers of
both commands (a changed default left in the prose fails here), and the ROS node's parameter
defaults docs/ros2.md states against its parameter table."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from mcsm.cli.parser import build_parser as mcsm_parser
from mcsm_client.cli import build_parser as client_parser

ROOT = Path(__file__).resolve().parents[1]
STATED = re.compile(r"`(--[a-z0-9-]+)`(?: \(|, default )([0-9][0-9,.]*)(?:\s+([KMG])iB)?")
UNITS = {None: 1, "K": 2**10, "M": 2**20, "G": 2**30}


def _defaults() -> dict[str, set[float]]:
    """Every long option of both commands (all subcommands) and its numeric defaults."""
    out: dict[str, set[float]] = {}

    def walk(p: argparse.ArgumentParser) -> None:
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                for sub in a.choices.values():
                    walk(sub)
            elif isinstance(a.default, int | float) and not isinstance(a.default, bool):
                for o in a.option_strings:
                    out.setdefault(o, set()).add(float(a.default))

    walk(mcsm_parser())
    walk(client_parser())
    return out


def test_defaults_stated_in_the_docs_are_the_parsers() -> None:
    defaults = _defaults()
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")),
             *sorted((ROOT / "deploy").glob("*.md"))]
    checked, wrong = [], []
    for page in pages:
        text = page.read_text()
        for m in STATED.finditer(text):
            flag, number, unit = m.groups()
            if flag not in defaults:
                continue  # a flag without a numeric default (or of another tool)
            value = float(number.replace(",", "")) * UNITS[unit]
            where = f"{page.name}:{text.count(chr(10), 0, m.start()) + 1} {flag}"
            checked.append(where)
            if value not in defaults[flag]:
                wrong.append(f"{where}: docs say {m.group(0)!r}, the parser {defaults[flag]}")
    assert not wrong, "\n".join(wrong)
    assert len(checked) >= 8, checked  # the pattern still finds the stated defaults


def test_ros_parameter_defaults_in_docs_are_the_nodes() -> None:
    """docs/ros2.md's table of input topics and its "`name` (VALUE)" mentions state the
    node's parameter defaults (``mcsm ros2 --help`` prints them from the same table)."""
    from mcsm_client.ros2.params import PARAMETERS

    text = (ROOT / "docs" / "ros2.md").read_text()
    checked = []
    for m in re.finditer(r"^\| `([a-z_]+)` \| `([^`]*)` \|", text, re.M):
        name, value = m.groups()
        if name in PARAMETERS:
            checked.append(name)
            assert PARAMETERS[name][0] == [value], (name, value)
    for m in re.finditer(r"`([a-z_]+)` \((`[^`]*`|[0-9.]+)(?: s)?\)", text):
        name, value = m.groups()
        if name in PARAMETERS:
            checked.append(name)
            default = PARAMETERS[name][0]
            if value.startswith("`"):
                assert default == value.strip("`"), (name, value)
            else:
                assert float(default) == float(value), (name, value)
    assert {"odometry_topics", "constraint_topics", "landmark_topics", "keyframe_distance_m",
            "keyframe_angle_rad", "reorder_window_s", "publish_period_s",
            "map_frame"} <= set(checked)


def test_core_api_listing_states_the_constructors_and_policies_defaults() -> None:
    """docs/core-api.md's listing: the first choice of every ``StochasticMap`` keyword is its
    default, and the Policy values it spells out are the shipped ones."""
    import inspect

    from mcsm import StochasticMap
    from mcsm.core import relinearize
    from mcsm.core.relinearize import Policy
    from mcsm.core.smap import DEFAULT_POLICY

    text = (ROOT / "docs" / "core-api.md").read_text()
    block = text[text.index("m = StochasticMap(n_samples,"):]
    block = block[:block.index("\n#")]  # the call, up to the comments under it
    names = {"DEFAULT_POLICY": DEFAULT_POLICY}
    stated = {}
    for m in re.finditer(r"(\w+)=((?:\{[^}]*\}|[^|,)\n])+)", block):
        name, first = m.groups()
        stated[name] = eval(first.strip(), {}, names)  # noqa: S307 - the docs' literal
    params = inspect.signature(StochasticMap).parameters
    assert set(stated) == set(params) - {"n_samples"}
    for name, value in stated.items():
        assert params[name].default == value, (name, value, params[name].default)
    # the policies, from the comments (their "# " taken off, lines joined)
    prose = " ".join(line.lstrip("# ") for line in text.splitlines() if line.startswith("#"))
    calls = {m.group(1): m.group(2) for m in re.finditer(
        r"(DEFAULT_POLICY|REPAIR_ONLY|RECOMMENDED|relinearize\.Policy)\s*=?\s*(Policy\([^)]*\)"
        r"|\([^)]*\))", prose)}
    want = {"DEFAULT_POLICY": DEFAULT_POLICY, "REPAIR_ONLY": relinearize.REPAIR_ONLY,
            "RECOMMENDED": relinearize.RECOMMENDED, "relinearize.Policy": Policy()}
    assert set(calls) == set(want), calls
    for name, call in calls.items():
        got = eval(call if call.startswith("Policy") else f"Policy{call}",  # noqa: S307
                   {"Policy": Policy, "None": None, "True": True, "False": False})
        assert got == want[name], (name, call)


def test_deploy_md_states_the_timeout_and_id_memory_defaults() -> None:
    """docs/deploy.md: every call's deadline defaults to 10 s (library and CLI); request ids
    are remembered for 10 minutes, at most 100 000 per map (the server's flags too)."""
    import inspect

    from mcsm.map.state import DEFAULT_ID_TTL_S, DEFAULT_LRU
    from mcsm_client.client import DEFAULT_TIMEOUT_S, MapClient

    text = (ROOT / "docs" / "deploy.md").read_text()
    assert "(`timeout_s`, default 10 s)" in text
    assert "remembered for 10 minutes (`--id-ttl-s`, at most 100 000 ids per map" in text
    assert inspect.signature(MapClient).parameters["timeout_s"].default == 10.0
    assert DEFAULT_TIMEOUT_S == 10.0  # the CLI's --timeout-s default, and its help's
    assert (DEFAULT_ID_TTL_S, DEFAULT_LRU) == (600.0, 100_000)
    served = mcsm_parser().parse_args(["serve"])
    assert (served.id_ttl_s, served.id_memory) == (600.0, 100_000)
