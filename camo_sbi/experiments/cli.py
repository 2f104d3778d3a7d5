"""The `camo-sbi` command line."""

from __future__ import annotations

import argparse
import os
import sys

__all__ = ["main"]


def _demo(args) -> int:
    from camo_sbi.experiments.demo import main as demo_main

    return demo_main(args)


def build_parser() -> argparse.ArgumentParser:
    from camo_sbi.experiments import amortize, calibrate, compare, hrc, manipulator

    parser = argparse.ArgumentParser(prog="camo-sbi", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    rep = sub.add_parser("reproduce", help="reproduce the paper's experiments")
    rsub = rep.add_subparsers(dest="experiment", required=True)
    p = rsub.add_parser("panda", help="manipulator experiment (paper Fig. 2-3); --model human also works")
    manipulator.add_arguments(p)
    p.set_defaults(func=manipulator.main)
    p = rsub.add_parser("hrc", help="human-robot block stacking (paper Fig. 5)")
    hrc.add_arguments(p)
    p.set_defaults(func=hrc.main)

    commands = (
        ("render-scene", "render the block-stacking scene to a PNG", hrc.add_render_arguments, hrc.render_main),
        ("compare", "compare inference methods on a grid (resumable)", compare.add_arguments, compare.main),
        ("calibrate", "coverage and SBC of each method over synthetic subjects", calibrate.add_arguments,
         calibrate.main),
        ("amortize", "train an amortized estimator (npe-amortized) once per body model", amortize.add_arguments,
         amortize.main),
        ("report", "write a self-contained HTML report of a run directory", _report_arguments, _report),
        ("demo", "simulate a batch of reaches and plot them", _demo_arguments, _demo),
    )
    for name, help_text, add_arguments, func in commands:
        p = sub.add_parser(name, help=help_text)
        add_arguments(p)
        p.set_defaults(func=func)
    return parser


def _report_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_dir")
    p.add_argument("-o", "--output", default=None, help="HTML path (default: RUN_DIR/report.html)")


def _demo_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", choices=("panda", "human"), default="panda")
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="runs/demo")


def _report(args) -> int:
    from pathlib import Path

    from camo_sbi.diagnostics.report import write_report

    out = Path(args.output) if args.output else Path(args.run_dir) / "report.html"
    path = write_report(args.run_dir, out)
    print(f"report: {path}")
    return 0


def main(argv: list[str] | None = None) -> int:
    import matplotlib

    if "MPLBACKEND" not in os.environ:
        matplotlib.use("Agg")  # figures go to files; a library import never switches backends
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except ValueError as exc:
        parser.exit(2, f"camo-sbi: error: {exc}\n")
    except KeyboardInterrupt:
        print("interrupted: finished cells are saved; re-run the same command to resume", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
