"""`camo-sbi report`: a self-contained HTML report of a run directory (compare, reproduce,
calibrate, robustness, infer), written by `camo_sbi.diagnostics.report.write_report`; left as it
is when the report on disk was built from the same inputs (``--force`` rebuilds it).

Only light modules at import time: the report's modules (matplotlib, arviz) are imported by `main`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from camo_sbi.experiments.figure_options import (
    add_corner_argument,
    add_figure_format_argument,
    corner_limits,
    figure_formats,
)

__all__ = ["add_arguments", "main"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_dir", help="a run directory (compare, reproduce, calibrate, robustness, infer)")
    p.add_argument("-o", "--output", default=None, help="HTML path (default: RUN_DIR/report.html)")
    p.add_argument("--force", action="store_true",
                   help="rebuild even if the report on disk was built from the same inputs")
    add_figure_format_argument(p)
    add_corner_argument(p)


def main(args) -> int:
    from camo_sbi.diagnostics.report import report_is_current, write_report

    out = Path(args.output) if args.output else Path(args.run_dir) / "report.html"
    formats = figure_formats(args)  # png alone: the figures live in the page only
    options = {"corner_limits": corner_limits(args), "figure_formats": None if formats == ("png",) else formats}
    current = not args.force and Path(args.run_dir).is_dir() and report_is_current(args.run_dir, out, **options)
    path = write_report(args.run_dir, out, force=args.force, progress=True, **options)
    print(f"report: {path}" + (" (unchanged: built from the same inputs; --force rebuilds it)" if current else ""))
    return 0
