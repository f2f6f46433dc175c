"""The import graph, read from the source: layers only point down, no cycle, no private name crosses a file.

Layers, lowest first (a module may import from its own layer or any lower one):
shared checks, the compilation cache, Ctrl-C → parameters, Brownian driver (and the weak scheme's increments it draws) →
system → noise, mechanics, bodies (specs) → scenes → ensemble, options, solvers → simulate →
statistics, analysis, work precision, sweeps, plots → fit → runs (and the CLI) → the package's top level.
"""

import ast
import pathlib

SRC = pathlib.Path(__file__).resolve().parents[1] / "src" / "nhsde"

LAYERS = [
    {"_misc", "_compilation_cache", "_interrupt"},
    {"_params", "_brownian", "_weak"},
    {"_system"},
    {"noise", "mechanics", "bodies"},
    {"scenes"},
    {"_ensemble", "_options", "_solvers"},
    {"_simulate"},
    {"statistics", "analysis", "_work_precision", "_sweep", "plot"},
    {"fit"},
    {"runs"},
    {"__init__"},
]
RANK = {unit: rank for rank, units in enumerate(LAYERS) for unit in units}


def _unit(module: str) -> str:
    """``nhsde.scenes._ball`` → ``scenes``; ``nhsde._simulate`` → ``_simulate``; ``nhsde`` → ``__init__``."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def _module_name(path: pathlib.Path) -> str:
    rel = path.relative_to(SRC.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: pathlib.Path):
    """``(imported module, imported names)`` for every import in the file, function-local ones included."""
    module = _module_name(path)
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != "nhsde":
                continue
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                if (SRC.parent / sub.replace(".", "/")).is_dir() or (
                    SRC.parent / f"{sub.replace('.', '/')}.py"
                ).exists():
                    yield sub, ()
                else:
                    yield target, (alias.name,)
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == "nhsde":
                    yield alias.name, ()


FILES = sorted(SRC.rglob("*.py"))


def test_every_module_belongs_to_a_layer():
    units = {_unit(_module_name(f)) for f in FILES}
    assert units <= set(RANK), f"modules outside the layer map: {sorted(units - set(RANK))}"


def test_imports_only_point_down():
    upward = []
    for f in FILES:
        src_unit = _unit(_module_name(f))
        for target, _ in _imports(f):
            dst_unit = _unit(target)
            if dst_unit != src_unit and RANK[dst_unit] > RANK[src_unit]:
                upward.append(f"{f.relative_to(SRC)} imports {target} ({src_unit} → {dst_unit})")
    assert not upward, "\n".join(upward)


def test_no_private_name_crosses_a_file_boundary():
    crossing = []
    for f in FILES:
        for target, names in _imports(f):
            for name in names:
                if name.startswith("_"):
                    crossing.append(f"{f.relative_to(SRC)}: from {target} import {name}")
    assert not crossing, "\n".join(crossing)


def test_the_subpackage_graph_has_no_cycle():
    edges: dict[str, set[str]] = {}
    for f in FILES:
        src_unit = _unit(_module_name(f))
        for target, _ in _imports(f):
            if _unit(target) != src_unit:
                edges.setdefault(src_unit, set()).add(_unit(target))
    state: dict[str, int] = {}

    def visit(node, trail):
        if state.get(node) == 1:
            raise AssertionError("import cycle: " + " → ".join(trail + [node]))
        if state.get(node) == 2:
            return
        state[node] = 1
        for nxt in sorted(edges.get(node, ())):
            visit(nxt, trail + [node])
        state[node] = 2

    for node in sorted(edges):
        visit(node, [])


def test_tests_import_only_public_names():
    """Tests use the public API; the few that test an internal say so in their name (``test_internal_*.py``)."""
    private = []
    for f in sorted(pathlib.Path(__file__).parent.glob("test_*.py")):
        if f.name.startswith("test_internal_") or f.name == pathlib.Path(__file__).name:
            continue
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("nhsde"):
                parts = node.module.split(".") + [a.name for a in node.names]
                if any(p.startswith("_") for p in parts):
                    private.append(f"{f.name}: from {node.module} import {', '.join(a.name for a in node.names)}")
            elif isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
                if isinstance(node.value, ast.Name) and node.value.id in ("nhsde",):
                    private.append(f"{f.name}: nhsde.{node.attr}")
    assert not private, "\n".join(private)
