"""Execute notebooks/*.ipynb and write them, with their outputs, as Markdown under docs/notebooks/.

    .venv/bin/pip install -e ".[docs]"
    .venv/bin/python docs/render_notebooks.py --scale full          # all four at the notebooks' full settings
    .venv/bin/python docs/render_notebooks.py 04_method_comparison   # small scale (quick settings)

The notebooks themselves stay committed without outputs (tests/test_notebooks_clean.py), so
nothing stale in them can disagree with the code; these renderings are what a reader browsing
the repository sees: ``docs/notebooks/<name>.md`` (the code, its printed output, tables
and figures) with the figures as PNG files in ``docs/notebooks/<name>_files/``. Each
rendering starts with a VISIBLE note naming the scale it ran at and how long it took; a
small-scale rendering also gives the measured time of the notebook's full run (recorded in
``docs/notebooks/timings.json`` by the last full rendering; an entry
``unfinished_after_seconds`` records a full run stopped unfinished, as observed), so a
reader knows its curves carry small-sample artefacts and what the full run costs.
tests/test_notebooks_clean.py
checks that its code cells are the notebook's current sources (re-render after editing a
notebook). Uses nbconvert (the ``docs`` extra) and the stock ``python3`` kernel.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = ROOT / "notebooks"
OUT = ROOT / "docs" / "notebooks"
TIMINGS = OUT / "timings.json"
HEADER = ("<!-- rendered by docs/render_notebooks.py from notebooks/{name}.ipynb "
          "(CAMO_SBI_SCALE={scale}); edit the notebook, not this file -->\n\n{note}\n\n")


def _minutes(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.1f} min"


def scale_note(name: str, scale: str, seconds: float, timings: dict) -> str:
    """The visible first lines of a rendering: the scale, its time, and for a small-scale
    rendering the full run's measured time (or that it was not measured)."""
    if scale == "full":
        return (f"> **Rendered at full scale** (`CAMO_SBI_SCALE=full`, the settings in the first code cell) "
                f"in {_minutes(seconds)} on this project's 2-core machine (shared with other jobs: a timing under load).")
    full = timings.get(name) or {}
    if "seconds" in full:
        cost = (f"The full run (`CAMO_SBI_SCALE=full`) took {_minutes(full['seconds'])} (2 cores, under load) "
                f"when last rendered ({full['date']}); too slow to render here.")
    elif "unfinished_after_seconds" in full:
        cost = (f"The full run (`CAMO_SBI_SCALE=full`) had not finished after "
                f"{_minutes(full['unfinished_after_seconds'])} ({full['date']}, {full.get('conditions', 'under load')}) "
                "and was stopped: its full time is unmeasured, longer than that.")
    else:
        cost = "The full run (`CAMO_SBI_SCALE=full`) has not been timed."
    return (f"> **Rendered at small scale** (`CAMO_SBI_SCALE=small`, the quick settings the tests use) in "
            f"{_minutes(seconds)}: few runs, small budgets, so the curves and tables below carry "
            f"small-sample artefacts; read them as a demonstration, not as results. {cost} "
            f"Full scale: `python docs/render_notebooks.py {name} --scale full`.")


def render(path: Path, out_dir: Path, scale: str, timeout: int = 3600) -> Path:
    """Execute one notebook (working directory notebooks/) and write its Markdown rendering,
    headed by `scale_note`; a full rendering records its time in timings.json."""
    t0 = time.perf_counter()
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
    seconds = time.perf_counter() - t0
    timings_path = out_dir / TIMINGS.name
    timings = json.loads(timings_path.read_text()) if timings_path.is_file() else {}
    if scale == "full":
        timings[path.stem] = {"seconds": round(seconds, 1), "date": time.strftime("%Y-%m-%d")}
        timings_path.write_text(json.dumps(timings, indent=1, sort_keys=True) + "\n")
    md = out_dir / f"{path.stem}.md"
    note = scale_note(path.stem, scale, seconds, timings)
    md.write_text(HEADER.format(name=path.stem, scale=scale, note=note) + body, encoding="utf-8")
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
