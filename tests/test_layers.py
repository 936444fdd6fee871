"""The package layers of DESIGN.md hold: no package imports one above it, and no two packages
import each other (directly or around a longer cycle).

Every ``import``/``from ... import`` in every module of ``adnmesh/`` counts, including those
inside functions. Layers, bottom up: the foundation (``errors``, ``config``) → the numerics
(pure: plant, frequency and step response, margins, tuning, analyses, the grid and DER models,
the table) → ``wire`` → ``control`` → ``sim`` → ``recording`` → ``runtime`` → the commands.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "adnmesh"

LAYERS = {
    "foundation": 0, "numerics": 1, "wire": 2, "control": 3, "sim": 4, "recording": 5,
    "runtime": 6, "commands": 7,
}
GROUP = {
    "errors": "foundation", "config": "foundation", "wire": "wire", "control": "control",
    "sim": "sim", "recording": "recording", "runtime": "runtime", "commands": "commands",
    "cli": "commands", "__main__": "commands", "__init__": "foundation",
}
"""Top-level module or package -> its layer group; anything else is numerics."""


def unit_of(module: str) -> str:
    """``adnmesh.wire.keys`` -> ``wire``; ``adnmesh.loopmodel.evaluation`` -> ``loop``."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def imports() -> dict[str, set[str]]:
    """Module name -> the adnmesh modules it imports."""
    found: dict[str, set[str]] = {}
    for path in PACKAGE.rglob("*.py"):
        relative = path.relative_to(PACKAGE.parent).with_suffix("")
        module = ".".join(relative.parts).removesuffix(".__init__")
        package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
        targets = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                targets.add(node.module)
            elif isinstance(node, ast.ImportFrom):   # relative: resolve against the package
                base = package[:len(package) - node.level + 1]
                names = [node.module] if node.module else [a.name for a in node.names]
                targets |= {".".join([*base, name]) for name in names}
        found[module] = {t for t in targets if t == "adnmesh" or t.startswith("adnmesh.")}
    return found


def unit_graph() -> dict[str, set[str]]:
    graph: dict[str, set[str]] = {}
    for module, targets in imports().items():
        source = unit_of(module)
        graph.setdefault(source, set())
        graph[source] |= {unit_of(t) for t in targets if unit_of(t) != source}
    return graph


def test_no_package_imports_one_above_it() -> None:
    wrong = []
    for module, targets in imports().items():
        layer = LAYERS[GROUP.get(unit_of(module), "numerics")]
        for target in targets:
            if target == "adnmesh":
                continue
            target_layer = LAYERS[GROUP.get(unit_of(target), "numerics")]
            if target_layer > layer:
                wrong.append(f"{module} imports {target}")
    assert not wrong, "\n".join(sorted(wrong))


def test_no_cycle_between_packages() -> None:
    graph = unit_graph()
    state: dict[str, int] = {}

    def visit(unit: str, path: list[str]) -> None:
        state[unit] = 1
        for nxt in sorted(graph.get(unit, ())):
            if state.get(nxt) == 1:
                cycle = path[path.index(nxt):] + [nxt] if nxt in path else [unit, nxt]
                pytest.fail("import cycle between packages: " + " -> ".join(cycle))
            if nxt not in state:
                visit(nxt, [*path, nxt])
        state[unit] = 2

    for unit in sorted(graph):
        if unit not in state:
            visit(unit, [unit])


def test_the_check_sees_a_cycle_and_an_upward_import(tmp_path: Path, monkeypatch) -> None:
    """The checks above can fail: a fake package whose control imports the runtime."""
    fake = tmp_path / "adnmesh"
    (fake / "control").mkdir(parents=True)
    (fake / "runtime").mkdir()
    (fake / "control" / "a.py").write_text("from adnmesh.runtime.b import x\n")
    (fake / "runtime" / "b.py").write_text("def f():\n    from adnmesh.control.a import y\n")
    monkeypatch.setattr(__import__(__name__), "PACKAGE", fake)
    with pytest.raises(AssertionError, match="control.a imports adnmesh.runtime.b"):
        test_no_package_imports_one_above_it()
    with pytest.raises(pytest.fail.Exception, match="control -> runtime -> control"):
        test_no_cycle_between_packages()


def test_no_function_in_the_runtime_is_longer_than_60_lines() -> None:
    long = []
    for path in (PACKAGE / "runtime").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                length = node.end_lineno - node.lineno + 1
                if length > 60:
                    long.append(f"{path.name}:{node.lineno} {node.name}: {length} lines")
    assert not long, "\n".join(long)
