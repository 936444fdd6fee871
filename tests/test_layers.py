"""The package layers hold: no package imports one above it, no module takes part in an import
circle (inside a package or across packages), and every package has its place in the order.

Every ``import``/``from ... import`` in every module of ``adnmesh/`` counts, including those
inside functions. The layers, bottom up (docs/architecture.md):

foundation (``config``, ``errors``, ``names``, ``files``) → the loop numerics and the physical
models (``loopmodel``, ``grid``, ``dermodels``) → ``tuning`` and ``analysis`` → ``wire`` (the
protocol table) → ``control`` (the agents' state machines) → ``sim`` (bus-free runtime) →
``recording`` (the file format) → ``results`` (what a run means) → ``runtime`` (the only Zenoh
users) → the command line and the agent programs (``cli``, ``commands``, ``agents``).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "adnmesh"

LAYERS = (
    ("__init__", "config", "errors", "names", "files", "reactive"),
    ("loopmodel", "grid", "dermodels"),
    ("tuning", "analysis", "adn", "identify", "cascade"),
    ("wire",),
    ("control",),
    ("sim",),
    ("recording",),
    ("results", "study"),
    ("devices",),
    ("runtime",),
    ("cli", "__main__", "commands", "agents"),
)
"""Top-level modules and packages of adnmesh by layer, bottom up; a package or module not named
here fails :func:`test_every_package_has_a_layer`."""

LAYER_OF = {unit: level for level, units in enumerate(LAYERS) for unit in units}


def unit_of(module: str) -> str:
    """``adnmesh.wire.keys`` -> ``wire``; ``adnmesh.config`` -> ``config``."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def modules() -> dict[str, Path]:
    """Module name -> its file, for every module of the package."""
    found = {}
    for path in PACKAGE.rglob("*.py"):
        relative = path.relative_to(PACKAGE.parent).with_suffix("")
        found[".".join(relative.parts).removesuffix(".__init__")] = path
    return found


def imports() -> dict[str, set[str]]:
    """Module name -> the adnmesh modules it imports (a name imported from a package that is
    a module of it counts as that module; otherwise the package itself)."""
    known = modules()
    graph: dict[str, set[str]] = {}
    for module, path in known.items():
        package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
        targets: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:     # relative: resolve against the package
                    base = ".".join([*package[:len(package) - node.level + 1],
                                     *([node.module] if node.module else [])])
                targets |= {base} | {f"{base}.{a.name}" for a in node.names}
        resolved = set()
        for target in targets:
            while target and target not in known:
                target = target.rpartition(".")[0]
            if target and target != module and not module.startswith(target + "."):
                resolved.add(target)
        graph[module] = resolved
    return graph


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_every_package_has_a_layer() -> None:
    units = {unit_of(m) for m in modules()}
    unknown = sorted(units - set(LAYER_OF))
    assert not unknown, f"packages or modules of adnmesh without a layer in LAYERS: {unknown}"


def test_no_package_imports_one_above_it() -> None:
    wrong = []
    for module, targets in imports().items():
        layer = LAYER_OF.get(unit_of(module))      # None: test_every_package_has_a_layer
        for target in targets:
            above = LAYER_OF.get(unit_of(target), -1)
            if layer is not None and target != "adnmesh" and above > layer:
                wrong.append(f"{module} imports {target}")
    assert not wrong, "\n".join(sorted(wrong))


def test_no_module_is_in_an_import_circle() -> None:
    found = circles(imports())
    assert not found, "import circles: " + "; ".join(" <-> ".join(c) for c in found)


def test_the_checks_see_a_circle_an_upward_import_and_an_unknown_package(
        tmp_path: Path, monkeypatch) -> None:
    """The checks above can fail: a fake package whose control imports the runtime, whose
    wire has a circle inside (a lazy import counts), and which has a package of no layer."""
    fake = tmp_path / "adnmesh"
    for package in ("control", "runtime", "wire", "gadgets"):
        (fake / package).mkdir(parents=True)
        (fake / package / "__init__.py").write_text("")
    (fake / "__init__.py").write_text("")
    (fake / "control" / "a.py").write_text("from adnmesh.runtime.b import x\n")
    (fake / "runtime" / "b.py").write_text("x = 1\n")
    (fake / "wire" / "c.py").write_text("from adnmesh.wire import d\n")
    (fake / "wire" / "d.py").write_text("def f():\n    from adnmesh.wire.c import y\n")
    monkeypatch.setattr(__import__(__name__), "PACKAGE", fake)
    with pytest.raises(AssertionError, match="control.a imports adnmesh.runtime.b"):
        test_no_package_imports_one_above_it()
    with pytest.raises(AssertionError, match="adnmesh.wire.c <-> adnmesh.wire.d"):
        test_no_module_is_in_an_import_circle()
    with pytest.raises(AssertionError, match="gadgets"):
        test_every_package_has_a_layer()


def test_no_function_in_the_runtime_is_longer_than_60_lines() -> None:
    long = []
    for path in (PACKAGE / "runtime").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                length = node.end_lineno - node.lineno + 1
                if length > 60:
                    long.append(f"{path.name}:{node.lineno} {node.name}: {length} lines")
    assert not long, "\n".join(long)
