"""Execute notebooks/*.ipynb and write them, with their outputs, as Markdown under docs/notebooks/.

    .venv/bin/pip install -e ".[docs]"
    .venv/bin/python docs/render_notebooks.py            # all four, small scale (~2-4 min on 2 cores)
    .venv/bin/python docs/render_notebooks.py 01_quickstart --scale full

The notebooks themselves stay committed without outputs (tests/test_notebooks_clean.py), so
nothing stale in them can disagree with the code; these renderings are what a reader browsing
the repository sees: ``docs/notebooks/<name>.md`` (the code, its printed output, tables
and figures) with the figures as PNG files in ``docs/notebooks/<name>_files/``. Each
rendering starts with a header naming the scale it ran at; tests/test_notebooks_clean.py
checks that its code cells are the notebook's current sources (re-render after editing a
notebook). Uses nbconvert (the ``docs`` extra) and the stock ``python3`` kernel.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = ROOT / "notebooks"
OUT = ROOT / "docs" / "notebooks"
HEADER = ("<!-- rendered by docs/render_notebooks.py from notebooks/{name}.ipynb "
          "(CAMO_SBI_SCALE={scale}); edit the notebook, not this file -->\n\n")


def render(path: Path, out_dir: Path, scale: str, timeout: int = 600) -> Path:
    """Execute one notebook (working directory notebooks/) and write its Markdown rendering."""
    import nbformat
    from nbconvert import MarkdownExporter
    from nbconvert.preprocessors import ExecutePreprocessor

    nb = nbformat.read(path, as_version=4)
    os.environ["CAMO_SBI_SCALE"] = scale  # the kernel inherits it; the parameters cell reads it
    # the inline backend: pyplot figures become PNG outputs (the test-suite's Agg shows none)
    os.environ["MPLBACKEND"] = "module://matplotlib_inline.backend_inline"
    ExecutePreprocessor(timeout=timeout, kernel_name="python3").preprocess(nb, {"metadata": {"path": str(path.parent)}})
    files = f"{path.stem}_files"
    body, resources = MarkdownExporter().from_notebook_node(
        nb, resources={"output_files_dir": files, "unique_key": path.stem})
    out_dir.mkdir(parents=True, exist_ok=True)
    shutil.rmtree(out_dir / files, ignore_errors=True)
    for name, data in resources.get("outputs", {}).items():
        target = out_dir / name
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(data)
    md = out_dir / f"{path.stem}.md"
    md.write_text(HEADER.format(name=path.stem, scale=scale) + body, encoding="utf-8")
    return md


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("names", nargs="*", help="notebook names (default: all in notebooks/)")
    p.add_argument("--scale", choices=("small", "full"), default="small")
    p.add_argument("--out", type=Path, default=OUT)
    args = p.parse_args(argv)
    paths = sorted(NOTEBOOKS.glob("*.ipynb"))
    if args.names:
        known = {q.stem: q for q in paths}
        unknown = [n for n in args.names if n.removesuffix(".ipynb") not in known]
        if unknown:
            p.error(f"names: unknown notebooks {unknown}; known: {sorted(known)}")
        paths = [known[n.removesuffix(".ipynb")] for n in args.names]
    for path in paths:
        t0 = time.perf_counter()
        md = render(path, args.out, args.scale)
        print(f"{md.relative_to(ROOT) if md.is_relative_to(ROOT) else md}  ({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
