"""Figure helpers for experiment tables, kept under their old import path.

The figures' style lives in `camo_sbi.diagnostics.style` and its plot primitives in
`camo_sbi.diagnostics.plot_primitives` (both also used by the HTML report); this module
re-exports the ones experiments and notebooks import from here.
"""

from __future__ import annotations

from camo_sbi.diagnostics.plot_primitives import plot_bars, plot_lines
from camo_sbi.diagnostics.style import mean_ci, new_figure, save_figure, save_figures

__all__ = ["mean_ci", "new_figure", "plot_bars", "plot_lines", "save_figure", "save_figures"]
