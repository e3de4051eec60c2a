"""The house rules of CONTRIBUTING.md ("Layers"), read from the code itself: every import
(lazy and type-checking-only imports included) of every ``mcsm`` package points down its
layers, every ``mcsm`` module belongs to a layer, no ``mcsm`` module imports ``mcsm_client``,
the import graph of ``mcsm`` and ``mcsm_client`` has no cycle, and no module in ``service/``
or ``clients/`` is over 600 lines or lacks a docstring saying what it holds."""

from __future__ import annotations

import ast
from functools import cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"mcsm": ROOT / "service" / "mcsm", "mcsm_client": ROOT / "clients" / "mcsm_client"}
# what each layer may import (besides itself); mcsm.errors is the shared bottom; "mcsm" is the
# top package alone (its __init__: __version__ and the core's names), not its subpackages
ALLOWED = {"mcsm.core": ("mcsm.errors",),
           "mcsm.wire": ("mcsm.errors", "mcsm.core"),
           "mcsm.map": ("mcsm.errors", "mcsm.core", "mcsm.wire"),
           "mcsm.log": ("mcsm.errors", "mcsm.core", "mcsm", "mcsm.wire", "mcsm.map"),
           "mcsm.viz": ("mcsm.errors", "mcsm.core", "mcsm", "mcsm.wire", "mcsm.map", "mcsm.log"),
           "mcsm.serve": ("mcsm.errors", "mcsm.core", "mcsm", "mcsm.wire", "mcsm.map",
                          "mcsm.log"),
           "mcsm.cli": ("mcsm.errors", "mcsm.core", "mcsm", "mcsm.wire", "mcsm.map", "mcsm.log",
                        "mcsm.viz", "mcsm.serve"),
           "mcsm.errors": ()}
TOP = ("mcsm.errors", "mcsm.core")  # what the top package ``mcsm`` itself may import
MAX_LINES = 600


def _modules() -> dict[str, Path]:
    mods = {}
    for root in PACKAGES.values():
        for f in root.rglob("*.py"):
            name = ".".join(f.relative_to(root.parent).with_suffix("").parts)
            mods[name.removesuffix(".__init__")] = f
    return mods


@cache
def _graph() -> dict[str, set[str]]:
    """Each module's imports of ``mcsm``/``mcsm_client`` modules (read once per session)."""
    mods = _modules()

    def resolve(name: str) -> str:
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name

    edges: dict[str, set[str]] = {}
    for m, f in mods.items():
        out = set()
        base = m.split(".") if f.name == "__init__.py" else m.split(".")[:-1]
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.Import):
                out |= {resolve(a.name) for a in node.names if a.name.split(".")[0] in PACKAGES}
            elif isinstance(node, ast.ImportFrom):
                mod = node.module or ""
                if node.level:
                    mod = ".".join(base[: len(base) - node.level + 1] + ([mod] if mod else []))
                if mod.split(".")[0] in PACKAGES:
                    out |= {resolve(f"{mod}.{a.name}") if f"{mod}.{a.name}" in mods
                            else resolve(mod) for a in node.names}
        edges[m] = out - {m, ""}
    return edges


def _cycles(edges: dict[str, set[str]]) -> list[set[str]]:
    """Strongly connected components of more than one module (iterative Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[set[str]] = []
    for start in sorted(edges):
        if start in index:
            continue
        work = [(start, iter(sorted(edges[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on.add(start)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(edges.get(w, ())))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = set()
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.add(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(comp)
    return out


def _allows(allowed: str, dep: str) -> bool:
    """``dep`` is the module ``allowed`` or inside it (the top package ``mcsm`` only itself)."""
    return dep == allowed or (allowed != "mcsm" and dep.startswith(allowed + "."))


def _layer(m: str) -> str | None:
    return next((lay for lay in ALLOWED if m == lay or m.startswith(lay + ".")), None)


def test_the_lower_layers_import_only_downwards() -> None:
    edges = _graph()
    assert {"mcsm.core.smap", "mcsm.wire.codec", "mcsm.map.ops", "mcsm.log.replay",
            "mcsm.viz.scene"} <= set(edges)  # it reads them
    bad = []
    for m, deps in sorted(edges.items()):
        lay = _layer(m)
        if lay is None:
            continue
        ok = (lay, *ALLOWED[lay])
        bad += [(m, d) for d in sorted(deps) if not any(_allows(a, d) for a in ok)]
    assert bad == []


def test_no_mcsm_module_imports_the_client_package() -> None:
    edges = _graph()
    assert [(m, d) for m, deps in edges.items() if m.split(".")[0] == "mcsm"
            for d in deps if d.split(".")[0] == "mcsm_client"] == []


def test_no_import_cycle() -> None:
    assert _cycles(_graph()) == []


def test_every_mcsm_module_has_a_layer() -> None:
    edges = _graph()
    assert [m for m in sorted(edges) if m.split(".")[0] == "mcsm" and m != "mcsm"
            and _layer(m) is None] == []
    assert all(any(_allows(a, d) for a in TOP) for d in edges["mcsm"]), edges["mcsm"]


def test_rooms_are_small_and_say_what_they_hold() -> None:
    """No module over 600 lines (the C kernel is not Python and not counted); every module's
    first lines are a docstring."""
    too_big, silent = [], []
    for root in PACKAGES.values():
        for f in sorted(root.rglob("*.py")):
            text = f.read_text()
            if len(text.splitlines()) > MAX_LINES:
                too_big.append(f"{f.relative_to(ROOT)}: {len(text.splitlines())} lines")
            if not ast.get_docstring(ast.parse(text)):
                silent.append(str(f.relative_to(ROOT)))
    assert too_big == [] and silent == [], (too_big, silent)


def test_the_layer_rule_refuses_an_upward_import() -> None:
    """The rule above would fail on the imports it forbids: the recording importing the server
    or the viz, the viz importing the server or the CLI, a layer reaching into ``mcsm.*`` through
    the top package's name."""
    assert _allows("mcsm", "mcsm") and not _allows("mcsm", "mcsm.serve.server")
    for lay, dep in [("mcsm.log", "mcsm.serve.server"), ("mcsm.log", "mcsm.viz.scene"),
                     ("mcsm.log", "mcsm.serve.replication"), ("mcsm.viz", "mcsm.serve.server"),
                     ("mcsm.viz", "mcsm.cli"), ("mcsm.map", "mcsm.log.writer"),
                     ("mcsm.serve", "mcsm.viz.scene"), ("mcsm.serve", "mcsm.cli.parser"),
                     ("mcsm.cli", "mcsm_client.client"), ("mcsm.core", "mcsm.wire.codec")]:
        assert not any(_allows(a, dep) for a in (lay, *ALLOWED[lay])), (lay, dep)
    assert any(_allows(a, "mcsm.log.reader") for a in ALLOWED["mcsm.viz"])


def test_the_cycle_finder_finds_a_cycle() -> None:
    """The check above would fail on a cycle (a graph with one, and one without)."""
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [{"a", "b", "c"}]
    assert _cycles({"a": {"b"}, "b": set()}) == []
