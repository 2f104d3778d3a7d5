"""Where a run directory keeps its netCDF files (stdlib only: the report's cache check reads it
without importing arviz or torch).

``posteriors/`` holds sampled posteriors; ``estimates/`` holds point estimates (naive,
nominal, oracle, ...). A point is not a posterior: arviz's summary of one warns (its
diagnostics need 2 chains of 4 draws, and a constant chain divides by zero), so plain
``az.summary`` reads every file in ``posteriors/`` without a warning. The files share one
format (`camo_sbi.diagnostics.arviz_io`); ``arviz_io.output_dir`` says which folder a file
belongs in.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["ESTIMATE_DIR", "POSTERIOR_DIR", "saved_files"]

POSTERIOR_DIR = "posteriors"
ESTIMATE_DIR = "estimates"


def saved_files(run_dir: str | os.PathLike) -> list[Path]:
    """A run directory's netCDF files: its posteriors, then its point estimates, each sorted."""
    run_dir = Path(run_dir)
    return [p for d in (POSTERIOR_DIR, ESTIMATE_DIR) if (run_dir / d).is_dir()
            for p in sorted((run_dir / d).glob("*.nc"))]
