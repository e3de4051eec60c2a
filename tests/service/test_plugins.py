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
    from mcsm_client import view_command

    args = cli.build_parser().parse_args(["view", "--foxglove-port", "0"])
    assert args.command == "view" and args.foxglove_port == 0
    assert args.plugin_run is view_command.run


class _EP:
    def __init__(self, name: str, value: str, load: Any) -> None:
        self.name, self.value, self.load = name, value, load


def test_a_broken_plugin_is_named_and_left_out(monkeypatch: pytest.MonkeyPatch,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    import importlib.metadata

    from mcsm_client import view_command

    def broken() -> Any:
        raise ImportError("no module named 'rclpy'")

    monkeypatch.setattr(importlib.metadata, "entry_points", lambda group: [
        _EP("ros2", "somepkg.ros2_command:add_parser", broken),
        _EP("view", "mcsm_client.view_command:add_parser", lambda: view_command.add_parser)])
    parser = cli.build_parser()
    err = capsys.readouterr().err
    assert err.strip() == ("mcsm: warning: subcommand 'ros2' (somepkg.ros2_command:add_parser) "
                           "not loaded: ImportError: no module named 'rclpy'")
    assert parser.parse_args(["view"]).plugin_run is view_command.run  # the others still load
    with pytest.raises(SystemExit):
        parser.parse_args(["ros2"])
