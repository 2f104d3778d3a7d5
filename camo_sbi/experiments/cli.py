"""The `camo-sbi` command line."""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import warnings

__all__ = ["Terminated", "main"]

_RESUME = "finished cells are saved; re-run the same command to resume"


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill``, ``timeout``, SLURM), raised in the main thread and handled like Ctrl-C."""


@contextlib.contextmanager
def _sigterm_as_exception():
    """SIGTERM raises `Terminated` once (later ones are ignored while cleaning up); yields the state."""
    state = {"terminated": False}

    def handler(signum, frame):
        if not state["terminated"]:
            state["terminated"] = True
            raise Terminated()

    try:
        previous = signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread: leave SIGTERM alone
        yield state
        return
    try:
        yield state
    finally:
        signal.signal(signal.SIGTERM, previous)


@contextlib.contextmanager
def _one_line_warnings():
    """camo_sbi's own warnings (a damaged cell, an unusable kernel cache) as ``camo-sbi: warning: ...``."""
    original = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        if category.__module__.startswith("camo_sbi"):
            print(f"camo-sbi: warning: {message}", file=sys.stderr if file is None else file, flush=True)
        else:
            original(message, category, filename, lineno, file, line)

    warnings.showwarning = show
    try:
        yield
    finally:
        warnings.showwarning = original


def _demo(args) -> int:
    from camo_sbi.experiments.demo import main as demo_main

    return demo_main(args)


def build_parser() -> argparse.ArgumentParser:
    from camo_sbi.experiments import (
        amortize,
        calibrate,
        compare,
        hrc,
        manipulator,
        recorded,
        robustness,
    )

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
        ("simulate-observations", "write synthetic recorded reaches of a subject (recording format)",
         recorded.add_simulate_arguments, recorded.simulate_main),
        ("infer", "infer joint limits from recorded reaches", recorded.add_infer_arguments, recorded.infer_main),
        ("robustness", "every method under observation noise, a faster recorder and a mis-sized model",
         robustness.add_arguments, robustness.main),
    )
    for name, help_text, add_arguments, func in commands:
        p = sub.add_parser(name, help=help_text)
        add_arguments(p)
        p.set_defaults(func=func)
    return parser


def _report_arguments(p: argparse.ArgumentParser) -> None:
    from camo_sbi.experiments.figure_options import add_corner_argument, add_figure_format_argument

    p.add_argument("run_dir")
    p.add_argument("-o", "--output", default=None, help="HTML path (default: RUN_DIR/report.html)")
    add_figure_format_argument(p)
    add_corner_argument(p)


def _demo_arguments(p: argparse.ArgumentParser) -> None:
    from camo_sbi.experiments.figure_options import add_figure_format_argument
    from camo_sbi.experiments.models import add_model_arguments

    add_model_arguments(p, limits=False)
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="runs/demo")
    add_figure_format_argument(p)


def _report(args) -> int:
    from pathlib import Path

    from camo_sbi.diagnostics.report import write_report
    from camo_sbi.experiments.figure_options import corner_limits, figure_formats

    out = Path(args.output) if args.output else Path(args.run_dir) / "report.html"
    formats = figure_formats(args)  # png alone: the figures live in the page only
    path = write_report(args.run_dir, out, corner_limits=corner_limits(args),
                        figure_formats=None if formats == ("png",) else formats)
    print(f"report: {path}")
    return 0


def main(argv: list[str] | None = None) -> int:
    import matplotlib

    if "MPLBACKEND" not in os.environ:
        matplotlib.use("Agg")  # figures go to files; a library import never switches backends
    parser = build_parser()
    args = parser.parse_args(argv)
    with _sigterm_as_exception() as state:
        try:
            with _one_line_warnings():
                return int(args.func(args) or 0)
        except ValueError as exc:
            parser.exit(2, f"camo-sbi: error: {exc}\n")
        except KeyboardInterrupt as exc:
            terminated = isinstance(exc, Terminated) or state["terminated"]
            print(f"{'terminated' if terminated else 'interrupted'}: {_RESUME}", file=sys.stderr)
            return 143 if terminated else 130
        except Exception:
            if not state["terminated"]:
                raise
            # SIGTERM sent to the whole process group (timeout, SLURM) can break the worker pool
            # before the parent's own handler runs: still a termination, not a crash
            print(f"terminated: {_RESUME}", file=sys.stderr)
            return 143


if __name__ == "__main__":
    sys.exit(main())
