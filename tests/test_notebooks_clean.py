"""Static checks of notebooks/*.ipynb (executing them is nbmake's job: ``pytest --nbmake``).

Each notebook is committed clean (no outputs, no execution counts, so nothing stale can
disagree with the code), starts with a parameters cell reading
``CAMO_SBI_SCALE`` (the tests run the "small" settings), runs on the stock ``python3``
kernel, and uses only camo_sbi's public API: no ``_``-prefixed module or name is
imported, and no ``_``-prefixed attribute is touched.
"""

from __future__ import annotations

import ast
import json
import re
from pathlib import Path

import pytest

NOTEBOOKS_DIR = Path(__file__).resolve().parents[1] / "notebooks"
NOTEBOOKS = sorted(NOTEBOOKS_DIR.glob("*.ipynb"))
SCALE_VAR = "CAMO_SBI_SCALE"
# IPython-only lines: magics (%, %%), shell escapes (!), help (obj? / ?obj)
_IPYTHON_LINE = re.compile(r"^\s*(%|!|\?)|^\s*[\w.]+\?{1,2}\s*$")


def _load(path: Path) -> dict:
    return json.loads(path.read_text(encoding="utf-8"))


def _source(cell: dict) -> str:
    src = cell.get("source", "")
    return "".join(src) if isinstance(src, list) else src


def _code_cells(nb: dict) -> list[tuple[int, str]]:
    return [(i, _source(c)) for i, c in enumerate(nb["cells"]) if c.get("cell_type") == "code"]


def _parse(src: str, where: str) -> ast.Module:
    """Parse a code cell, with IPython-only lines blanked (line numbers kept)."""
    lines = ["" if _IPYTHON_LINE.search(line) else line for line in src.splitlines()]
    try:
        return ast.parse("\n".join(lines))
    except SyntaxError as exc:  # pragma: no cover - reported as a failure
        pytest.fail(f"{where}: not valid Python: {exc}")


def _reads_scale(tree: ast.Module) -> bool:
    """``SCALE = os.environ.get("CAMO_SBI_SCALE", ...)`` or ``os.getenv("CAMO_SBI_SCALE", ...)``."""
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Assign) and isinstance(node.value, ast.Call)):
            continue
        if not any(isinstance(t, ast.Name) and t.id == "SCALE" for t in node.targets):
            continue
        call = node.value
        name = ast.unparse(call.func)
        if name in ("os.environ.get", "os.getenv", "environ.get", "getenv") and call.args:
            first = call.args[0]
            if isinstance(first, ast.Constant) and first.value == SCALE_VAR:
                return True
    return False


def _private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def test_notebooks_exist():
    assert NOTEBOOKS, f"no notebooks found under {NOTEBOOKS_DIR}"


@pytest.fixture(params=NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def notebook(request) -> tuple[str, dict]:
    return request.param.name, _load(request.param)


def test_committed_without_outputs(notebook):
    name, nb = notebook
    dirty = []
    for i, cell in enumerate(nb["cells"]):
        if cell.get("cell_type") != "code":
            if cell.get("outputs") or cell.get("execution_count") is not None:
                dirty.append(f"cell {i}: a {cell.get('cell_type')} cell with outputs")
            continue
        if cell.get("outputs"):
            dirty.append(f"cell {i}: {len(cell['outputs'])} output(s)")
        if cell.get("execution_count") is not None:
            dirty.append(f"cell {i}: execution_count = {cell['execution_count']}")
    assert not dirty, (f"{name} is committed with outputs; clear them (Jupyter: Edit > Clear Outputs "
                       f"of All Cells, then save):\n  " + "\n  ".join(dirty))


def test_runs_on_the_stock_kernel(notebook):
    name, nb = notebook
    kernel = nb.get("metadata", {}).get("kernelspec", {}).get("name")
    assert kernel == "python3", f"{name}: kernelspec {kernel!r}; nbmake needs the stock 'python3' kernel"


def test_first_code_cell_reads_the_scale(notebook):
    name, nb = notebook
    cells = _code_cells(nb)
    assert cells, f"{name}: no code cell"
    i, src = cells[0]
    assert _reads_scale(_parse(src, f"{name} cell {i}")), (
        f"{name}: the first code cell (cell {i}) must be the parameters cell and read "
        f'SCALE = os.environ.get("{SCALE_VAR}", "full") (tests run it with "small")')


def test_uses_only_the_public_api(notebook):
    name, nb = notebook
    problems = []
    imports_camo_sbi = False
    for i, src in _code_cells(nb):
        for node in ast.walk(_parse(src, f"{name} cell {i}")):
            if isinstance(node, ast.Import):
                modules = [(a.name, None) for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    problems.append(f"cell {i}: relative import")
                    continue
                modules = [(node.module or "", a.name) for a in node.names]
            else:
                if isinstance(node, ast.Attribute) and _private(node.attr):
                    problems.append(f"cell {i}: private attribute .{node.attr}")
                continue
            for module, imported in modules:
                if module.split(".")[0] != "camo_sbi":
                    continue
                imports_camo_sbi = True
                parts = module.split(".") + ([imported] if imported else [])
                bad = [p for p in parts if _private(p) or p == "*"]
                if bad:
                    problems.append(f"cell {i}: imports {'.'.join(parts)} ({', '.join(bad)} is not public)")
    assert imports_camo_sbi, f"{name}: does not import camo_sbi at all"
    assert not problems, f"{name} reaches past the public API:\n  " + "\n  ".join(problems)
