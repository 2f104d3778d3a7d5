"""The figure flags of the commands: ``--figure-format`` (every command that makes figures)
and ``--corner-limits`` (every command that writes a report).

Light on purpose (no matplotlib import), since every command's parser is built at start-up;
the formats themselves and their check live in `camo_sbi.diagnostics.style`.
"""

from __future__ import annotations

import argparse

__all__ = ["add_corner_argument", "add_figure_format_argument", "corner_limits", "figure_formats"]


def add_figure_format_argument(p: argparse.ArgumentParser) -> None:
    """``--figure-format png,pdf,svg``: the formats every figure of the command is written in."""
    p.add_argument("--figure-format", default="png", metavar="FORMATS",
                   help="comma-separated figure formats, any of png,pdf,svg (default: png); figures are "
                        "drawn at paper widths (3.5 in single, 7 in double column) with fonts >= 8 pt")


def figure_formats(args) -> tuple[str, ...]:
    """The checked ``--figure-format`` of ``args`` (png for a namespace without the flag);
    a bad value is a ValueError naming the flag."""
    text = getattr(args, "figure_format", None) or "png"
    if text == "png":  # the default: checking it needs no matplotlib (a re-run of a finished grid imports none)
        return ("png",)
    from camo_sbi.diagnostics.style import parse_figure_formats

    return parse_figure_formats(text)


def add_corner_argument(p: argparse.ArgumentParser) -> None:
    """``--corner-limits a,b,c``: the limits the report's corner plot shows."""
    p.add_argument("--corner-limits", default=None, metavar="LIMITS",
                   help="comma-separated limits for the report's corner plot, each JOINT_lo or JOINT_hi "
                        "(e.g. panda_joint4_lo,panda_joint4_hi); default: the restricted limits when the "
                        "truth is known, else those that moved most from the prior")


def corner_limits(args) -> list[str] | None:
    """``--corner-limits`` as a list of names (None: the report chooses); names are checked
    against the posteriors' joints when the report is drawn."""
    text = getattr(args, "corner_limits", None)
    if text is None:
        return None
    names = [t.strip() for t in str(text).split(",") if t.strip()]
    bad = [n for n in names if not (n.endswith("_lo") or n.endswith("_hi"))]
    if bad or len(names) < 2:
        raise ValueError(f"--corner-limits: expected at least two comma-separated names JOINT_lo / JOINT_hi, "
                         f"got {text!r}")
    return list(dict.fromkeys(names))
