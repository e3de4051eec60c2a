"""Commands other packages add to ``mcsm`` (entry-point group ``mcsm.commands``), and the rule
that lets the client package add ``mcsm view``: no ``mcsm`` module imports ``mcsm_client``."""

from __future__ import annotations

import ast
from pathlib import Path
from typing import Any

import pytest
from mcsm import cli

SERVICE = Path(__file__).resolve().parents[2] / "service" / "mcsm"


def test_no_mcsm_module_imports_the_client_package() -> None:
    """Read every import of ``service/mcsm`` (also those inside functions)."""
    offenders = []
    for path in SERVICE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            offenders += [f"{path.relative_to(SERVICE)}: {n}" for n in names
                          if n == "mcsm_client" or n.startswith("mcsm_client.")]
    assert offenders == []


def test_view_comes_from_the_entry_point_group() -> None:
    plugins = cli.plugin_commands()
    assert plugins["view"].__name__ == "mcsm_client.view_command"
    args = cli.build_parser().parse_args(["view", "--foxglove-port", "0"])
    assert args.command == "view" and args.foxglove_port == 0


class _EP:
    def __init__(self, name: str, value: str, load: Any) -> None:
        self.name, self.value, self.load = name, value, load


def test_a_broken_plugin_is_named_and_left_out(monkeypatch: pytest.MonkeyPatch,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    import importlib.metadata

    def broken() -> Any:
        raise ImportError("no module named 'rclpy'")

    good = cli.plugin_commands()["view"]
    monkeypatch.setattr(cli, "_plugins", None)
    monkeypatch.setattr(importlib.metadata, "entry_points", lambda group: [
        _EP("ros2", "somepkg.ros2_command", broken), _EP("view", good.__name__, lambda: good)])
    found = cli.plugin_commands()
    assert set(found) == {"view"}
    err = capsys.readouterr().err
    assert err.strip() == ("mcsm: command 'ros2' (somepkg.ros2_command) could not be loaded: "
                           "ImportError: no module named 'rclpy'")
    monkeypatch.setattr(cli, "_plugins", None)  # the next caller reads the real group again
