"""The README stays true: its Python example runs as written against a real server, it states
the gate's default and every exit code (its command lines parse: tests/test_docs_commands.py)."""

from __future__ import annotations

import re
import signal
import subprocess
import sys
from pathlib import Path

from tests.service.daemon_util import start_daemon

README = Path(__file__).resolve().parents[1] / "README.md"
DEFAULT_ENDPOINT = "tcp/127.0.0.1:7457"


def test_readme_python_example_runs(tmp_path: Path) -> None:
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
    assert blocks, "the README has no Python example"
    code = blocks[0]
    assert DEFAULT_ENDPOINT in code  # the example talks to a default server...
    d = start_daemon(tmp_path, "--samples", "1000")
    try:  # ...here one on a free port
        code = code.replace(DEFAULT_ENDPOINT, d.endpoint)
        code += ("\nassert samples.shape == (1000, 7) and cov.shape == (6, 6)\n"
                 "assert ack.seq == 1 and ack.kind == 'new_component'\n")
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                           timeout=120, cwd=tmp_path)
        assert r.returncode == 0, r.stderr
    finally:
        assert d.stop(signal.SIGINT) == 0, d.log_text()


def test_readme_states_the_gate_default() -> None:
    """The README says what the gate's default is, and it is the default of the core, of
    ``mcsm serve`` and of a server's new maps."""
    from mcsm import StochasticMap
    from mcsm.cli import build_parser
    from mcsm.core.smap import DEFAULT_GATE
    from mcsm.serve.server import ServerOptions, new_map

    text = " ".join(README.read_text().split())
    m = re.search(r"Loop closures are gated at ([0-9.]+) by default", text)
    assert m is not None, "the README does not state the gate's default"
    assert float(m.group(1)) == DEFAULT_GATE
    assert "--gate none" in text
    assert StochasticMap(10).gate == DEFAULT_GATE
    assert build_parser().parse_args(["serve"]).gate == DEFAULT_GATE
    assert build_parser().parse_args(["serve", "--gate", "none"]).gate is None
    assert new_map(ServerOptions().map_options).gate == DEFAULT_GATE


def test_readme_lists_every_exit_code() -> None:
    """Each exit code of ``mcsm`` and ``mcsm-client`` is in the README's lists (0-6: a
    replicated map's deposed primary follows the log instead of exiting 7)."""
    from mcsm import cli
    from mcsm_client import cli as client_cli

    text = " ".join(README.read_text().split())
    ours = text.split("Exit codes of `mcsm`:")[1].split("Of `mcsm-client`:")[0]
    theirs = text.split("Of `mcsm-client`:")[1].split(". ")[0:8]
    codes = {v for k, v in vars(cli).items() if k.startswith("EXIT_") and isinstance(v, int)}
    assert codes == set(range(7))
    for code in sorted(codes):
        assert re.search(rf"(^|[ ,]){code} ", ours), f"mcsm exit code {code} missing"
    client = {v for k, v in vars(client_cli).items()
              if k.startswith("EXIT_") and isinstance(v, int)}
    assert client == {0, 1, 2, 3, 4, 130}
    for code in sorted(client):
        assert re.search(rf"(^|[ ,]){code} ", " ".join(theirs)), f"client code {code} missing"


def test_first_make_shows_progress_while_the_venv_is_built(tmp_path: Path) -> None:
    """The recipe that builds ``.venv`` says what it does before each long step (it was silent
    for about 53 s); ``make -n`` prints the recipe without running it."""
    root = README.parent
    r = subprocess.run(["make", "-n", "-B", "-C", str(root), ".venv/.installed-stamp"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    out = r.stdout
    steps = ["setting up .venv", "[1/4] creating .venv", "[2/4] upgrading pip",
             "[3/4] installing mcsm", "[4/4] building tf2_msgs", ".venv is ready"]
    where = [out.find(s) for s in steps]
    assert all(w >= 0 for w in where) and where == sorted(where), out
    assert out.find("[3/4]") < out.find("pip install --progress-bar off -e") < \
        out.find("[4/4]")
    assert "--quiet -e" not in out  # pip's own lines (Collecting ...) are shown
