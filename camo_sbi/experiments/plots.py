"""Figure helpers for experiment tables, kept under their old import path.

The figures' style and primitives live in `camo_sbi.diagnostics.style` (also used by the
HTML report); this module re-exports the ones experiments and notebooks import from here.
"""

from __future__ import annotations

from camo_sbi.diagnostics.style import (
    mean_ci,
    new_figure,
    plot_bars,
    plot_lines,
    save_figure,
    save_figures,
)

__all__ = ["mean_ci", "new_figure", "plot_bars", "plot_lines", "save_figure", "save_figures"]
