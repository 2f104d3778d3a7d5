"""The import layers of camo_sbi, as sbi's import-graph test guards its own.

Every import statement in the package counts: module level, inside functions (the
registry's lazy loaders) and under ``if TYPE_CHECKING:``. Layers, bottom to top:

    0  _validation, _io, _files, _memory, _plugins  (argument checks, atomic writes, user files,
                                         work bounds, entry points)
    0.5 _threads, _compiling             (the shared thread runner of the numba kernels; the
                                         one-line notice when they compile)
    1  simulators                        (the batched simulators)
    2  priors, budget                    (the box prior, the simulation counter)
    3  task, distributed                 (the run contract's input; where work runs)
    4  inference                         (methods, the registry, distances, KDE)
    5  scenarios, evaluation, io         (goal design and scenes; metrics and claims; recordings)
    5.5 design                           (active design: the next reach, from posterior draws)
    6  diagnostics                       (arviz, calibration, reports)
    7  experiments                       (the CLI and the studies)
    8  __main__                          (``python -m camo_sbi``: the CLI's entry point)

A module may import its own layer's package or any lower layer, never a higher one, and
never a sibling package of its own layer; the package root (``camo_sbi.__version__``) imports
nothing and lies below them all; the module graph has no cycle.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "camo_sbi"

LAYERS = {
    "_validation": 0, "_io": 0, "_files": 0, "_memory": 0, "_plugins": 0, "_threads": 0.5, "_compiling": 0.5,
    "simulators": 1,
    "priors": 2, "budget": 2,
    "task": 3, "distributed": 3,
    "inference": 4,
    "scenarios": 5, "evaluation": 5, "io": 5,
    "design": 5.5,
    "diagnostics": 6,
    "experiments": 7,
    "__main__": 8,
}


def _module_name(path: Path) -> str:
    rel = path.relative_to(PKG.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


MODULES = {_module_name(p): p for p in PKG.rglob("*.py")}


def _resolve(target: str) -> str | None:
    """The camo_sbi module an import names (a package's ``__init__`` when it is not a module)."""
    if not target.startswith("camo_sbi"):
        return None
    while target and target not in MODULES:
        target = target.rpartition(".")[0]
    return target or None


def _imports(name: str) -> set[str]:
    path = MODULES[name]
    tree = ast.parse(path.read_text(), filename=str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = set()
    for node in ast.walk(tree):  # every import, wherever it stands
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1] + [base]).rstrip(".")
            targets = [f"{base}.{a.name}" for a in node.names] + [base]
        else:
            continue
        for t in targets:
            r = _resolve(t)
            if r is not None and r != name:
                out.add(r)
    return out


GRAPH = {name: _imports(name) for name in MODULES}


def _top(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else None


def test_every_package_module_has_a_layer():
    unknown = sorted({_top(m) for m in MODULES} - set(LAYERS) - {None})
    assert not unknown, f"add these to LAYERS: {unknown}"


@pytest.mark.parametrize("name", sorted(MODULES))
def test_imports_respect_the_layers(name):
    top = _top(name)
    if top is None:  # camo_sbi/__init__.py
        assert not GRAPH[name], "the package root imports nothing"
        return
    bad = []
    for target in sorted(GRAPH[name]):
        other = _top(target)
        if other is None:
            continue  # the package root (its __version__) imports nothing: below every layer
        if LAYERS[other] > LAYERS[top] or (LAYERS[other] == LAYERS[top] and other != top):
            bad.append(f"{target} (layer {LAYERS[other]} '{other}' above or beside layer {LAYERS[top]} '{top}')")
    assert not bad, f"{name} imports {bad}"


def test_the_rules_of_the_issue_in_words():
    for name, targets in GRAPH.items():
        tops = {_top(t) for t in targets}
        if _top(name) == "simulators":
            assert not tops & {"inference", "experiments"}, name
        if _top(name) == "inference":
            assert not tops & {"experiments", "diagnostics"}, name


def test_no_import_cycles():
    """Tarjan's strongly connected components over the module graph: all of size one."""
    index, low, stack, on, sccs = {}, {}, [], set(), []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in GRAPH[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            sccs.append(comp)

    for v in sorted(GRAPH):
        if v not in index:
            visit(v)
    cycles = [sorted(c) for c in sccs if len(c) > 1]
    assert not cycles, f"import cycles: {cycles}"


def test_the_graph_is_not_vacuous():
    assert len(MODULES) > 30
    assert "camo_sbi.task" in GRAPH["camo_sbi.inference.camo"]
    assert "camo_sbi.inference.camo" in GRAPH["camo_sbi.inference.registry"]  # a lazy loader counts
    assert "camo_sbi.simulators.controller" in GRAPH["camo_sbi.simulators.simulator"]


#: third-party libraries reached through one adapter module each (README, Architecture)
ADAPTERS = {
    "arviz": {"camo_sbi.diagnostics.arviz_io"},
    "xarray": {"camo_sbi.diagnostics.arviz_io"},  # arviz's data model, used only to write netCDF in memory
    "pyabc": {"camo_sbi.inference.abc_smc"},
    "sbi": {"camo_sbi.inference.sbi_adapter"},
    "ezc3d": {"camo_sbi.io.c3d"},
    "bvhio": set(),  # camo_sbi/io/bvh.py parses BVH itself (bvhio looped forever on cut-off files)
    "pytorch_kinematics": {"camo_sbi.simulators.chain"},
    "pybullet": {"camo_sbi.scenarios.block_stacking"},
    "jinja2": {"camo_sbi.diagnostics.pages"},
    "markupsafe": {"camo_sbi.diagnostics.pages"},
}


def _third_party(name: str) -> set[str]:
    """The top-level names of the absolute imports outside camo_sbi in module ``name``."""
    out = set()
    for node in ast.walk(ast.parse(MODULES[name].read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            out.add(node.module.split(".")[0])
    return out - {"camo_sbi"}


@pytest.mark.parametrize("library", sorted(ADAPTERS))
def test_each_adapted_library_is_imported_by_its_adapter_only(library):
    importers = {name for name in MODULES if library in _third_party(name)}
    assert importers == ADAPTERS[library], f"{library} is imported by {sorted(importers)}"
