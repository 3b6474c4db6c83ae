"""The import rules of docs/architecture.md, checked on every import statement of the package
(module level and function local): no upward or sideways arrow between layers, no circle between modules."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "dtoc"

#: layer of each top-level part of the package and the layers it may import (docs/architecture.md)
ALLOWED: dict[str, set[str]] = {
    "base": {"base"},  # dtoc.constants, dtoc.errors, dtoc.util
    "seq": {"base", "seq"},
    "hardware": {"base", "seq", "hardware"},
    "sim": {"base", "seq", "hardware", "sim"},
    "identify": {"base", "seq", "hardware", "sim", "identify"},
    "optimize": {"base", "seq", "hardware", "sim", "optimize"},
    "batch": {"base", "seq", "hardware", "optimize", "batch"},
    "api": {"base", "seq", "hardware", "sim", "identify", "optimize", "batch", "api"},
    "cli": {"base", "seq", "hardware", "sim", "identify", "optimize", "batch", "api", "cli"},
}


def _layer(module: str) -> str:
    parts = module.split(".")
    if module == "dtoc":
        return "api"
    if parts[1] == "__main__":
        return "cli"
    if parts[1] in ("constants", "errors", "util", "version"):
        return "base"
    return parts[1]


def _module_name(path: Path) -> str:
    rel = path.relative_to(PKG.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: Path) -> list[tuple[str, int]]:
    """(imported dtoc module, line) of every import statement in the file, wherever it stands."""
    tree = ast.parse(path.read_text(), filename=str(path))
    me = _module_name(path)
    pkg = me if path.name == "__init__.py" else me.rsplit(".", 1)[0]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names if a.name.split(".")[0] == "dtoc"]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if mod.split(".")[0] != "dtoc":
                continue
            for a in node.names:  # `from dtoc.sim import metrics` imports the module dtoc.sim.metrics
                sub = f"{mod}.{a.name}"
                out.append((sub if _is_module(sub) else mod, node.lineno))
    return out


def _is_module(name: str) -> bool:
    p = PKG.parent.joinpath(*name.split("."))
    return p.with_suffix(".py").is_file() or (p / "__init__.py").is_file()


def _graph() -> dict[str, list[tuple[str, int]]]:
    return {_module_name(p): _imports(p) for p in sorted(PKG.rglob("*.py"))}


def test_the_walker_sees_function_local_imports(tmp_path):
    """The checker itself: an import inside a function body counts."""
    imports = [m for m, _ in _imports(PKG / "sim" / "comparison.py")]
    assert "dtoc.sim.pdg" in imports  # imported inside compare_ideal_realized
    assert "dtoc.sim.metrics" in imports  # `from dtoc.sim import metrics`


def test_no_upward_or_sideways_import_between_layers():
    bad = []
    for mod, imps in _graph().items():
        for target, line in imps:
            if _layer(target) not in ALLOWED[_layer(mod)]:
                bad.append(f"{mod}:{line} imports {target} ({_layer(mod)} -> {_layer(target)})")
    assert not bad, "\n".join(bad)


def test_package_inits_and_seq_stay_light():
    """`seq` imports nothing above it; the sub-package __init__ files import nothing heavy."""
    for mod, imps in _graph().items():
        if mod.startswith("dtoc.seq"):
            assert all(_layer(t) in ("base", "seq") for t, _ in imps), mod


def test_no_import_circle_between_modules():
    graph = {m: {t for t, _ in imps if t != m} for m, imps in _graph().items()}
    # a package's __init__ re-exporting its modules is not a circle through the modules
    for m in graph:
        graph[m] = {t for t in graph[m] if not (t in graph and m.startswith(t + "."))}
    state: dict[str, int] = {}
    cycles: list[list[str]] = []

    def visit(node: str, stack: list[str]) -> None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if nxt not in graph:
                continue
            if state.get(nxt) == 1:
                cycles.append(stack[stack.index(nxt) :] + [nxt])
            elif state.get(nxt) is None:
                visit(nxt, stack)
        stack.pop()
        state[node] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [])
    assert not cycles, "\n".join(" -> ".join(c) for c in cycles)


@pytest.mark.parametrize("layer", sorted(ALLOWED))
def test_every_layer_has_modules(layer):
    assert any(_layer(m) == layer for m in _graph()), layer


def test_tests_import_no_private_names():
    """Tests use the modules' public names only (a private name is free to change)."""
    bad = []
    for f in sorted(PKG.parent.joinpath("tests").glob("*.py")):
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("dtoc"):
                bad += [
                    f"{f.name}:{node.lineno} {a.name}"
                    for a in node.names
                    if a.name.startswith("_") and not a.name.startswith("__")
                ]
    assert not bad, bad
