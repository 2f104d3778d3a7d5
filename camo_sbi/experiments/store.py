"""An atomic, resumable store for tidy experiment tables.

Each finished cell of an experiment grid is written as its own CSV file under
``<out>/cells/`` (temp file + ``os.replace``), so an interrupted run loses at most the
cell in flight, re-running skips finished cells, and the combined table can never hold
a duplicate row. `ResultStore.table` concatenates the cells in key order and
`ResultStore.write_table` materialises ``results.csv`` atomically.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from collections.abc import Iterable, Mapping
from pathlib import Path

import pandas as pd

from camo_sbi._io import atomic_write_bytes, atomic_write_text

__all__ = ["ResultStore", "atomic_write_bytes", "atomic_write_text", "cell_key"]


def cell_key(params: Mapping[str, object]) -> str:
    """A readable, filesystem-safe, order-independent key for a grid cell."""
    items = sorted((str(k), str(v)) for k, v in params.items())
    slug = "__".join(f"{k}={v}" for k, v in items)
    slug = re.sub(r"[^A-Za-z0-9=._-]+", "-", slug)
    digest = hashlib.sha1(json.dumps(items).encode()).hexdigest()[:8]
    return f"{slug[:150]}__{digest}"


class ResultStore:
    """Tidy rows grouped in cells, one atomic CSV per finished cell.

    Args:
        out: the run directory; cells live in ``out/cells``, the table in ``out/results.csv``.
    """

    def __init__(self, out: str | os.PathLike):
        self.out = Path(out)
        self.cells = self.out / "cells"
        self.cells.mkdir(parents=True, exist_ok=True)

    def _path(self, key: str) -> Path:
        return self.cells / f"{key}.csv"

    def done(self, key: str) -> bool:
        return self._path(key).exists()

    def finished_keys(self) -> set[str]:
        return {p.stem for p in self.cells.glob("*.csv")}

    def put(self, key: str, rows: Iterable[Mapping[str, object]]) -> None:
        """Write one finished cell atomically (replacing any earlier copy of the same key)."""
        df = pd.DataFrame(list(rows))
        atomic_write_text(self._path(key), df.to_csv(index=False))

    def table(self) -> pd.DataFrame:
        """All finished cells concatenated in key order (empty DataFrame if none)."""
        parts = []
        for p in sorted(self.cells.glob("*.csv")):
            try:
                df = pd.read_csv(p)
            except pd.errors.EmptyDataError:  # a cell that finished with no rows
                continue
            if len(df):
                parts.append(df)
        return pd.concat(parts, ignore_index=True) if parts else pd.DataFrame()

    def write_table(self, name: str = "results.csv") -> pd.DataFrame:
        df = self.table()
        atomic_write_text(self.out / name, df.to_csv(index=False))
        return df
