"""An atomic, resumable, self-checking store for tidy experiment tables.

Each finished cell of an experiment grid is written as its own CSV file under
``<out>/cells/`` (temp file + ``os.replace``), so an interrupted run loses at most the
cell in flight, re-running skips finished cells, and the combined table can never hold
a duplicate row. `ResultStore.table` concatenates the current grid's cells in key order
(cells of other settings in the same directory are counted, never read) and
`ResultStore.write_table` materialises ``results.csv`` atomically.

Every cell has an integrity record ``<out>/integrity/<key>.json`` (its byte count,
sha256, row count, column names and dtypes), written atomically *after* the CSV, by the
process that wrote the cell (so parallel workers never share a file). A cell counts as
finished only when its bytes match the record: a truncated, emptied, overwritten or
garbage cell, or one without a record (a crash between the two writes, an older
camo_sbi), is reported by name (`CorruptCellWarning`), never read, and recomputed by
the command that finds it. Cells are read with the recorded dtypes, so integer columns
stay integers.
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import os
import re
import warnings
from collections.abc import Iterable, Mapping
from pathlib import Path

import pandas as pd

from camo_sbi._files import read_json
from camo_sbi._io import atomic_write_bytes, atomic_write_text

__all__ = ["CorruptCellWarning", "ResultStore", "atomic_write_bytes", "atomic_write_text", "cell_key"]

_RECORD_FORMAT = 1
log = logging.getLogger(__name__)


class CorruptCellWarning(RuntimeWarning):
    """A cell file that does not match its integrity record: it is ignored and recomputed."""


def cell_key(params: Mapping[str, object]) -> str:
    """A readable, filesystem-safe, order-independent key for a grid cell."""
    items = sorted((str(k), str(v)) for k, v in params.items())
    slug = "__".join(f"{k}={v}" for k, v in items)
    slug = re.sub(r"[^A-Za-z0-9=._-]+", "-", slug)
    digest = hashlib.sha1(json.dumps(items).encode()).hexdigest()[:8]
    return f"{slug[:150]}__{digest}"


class ResultStore:
    """Tidy rows grouped in cells, one atomic, checksummed CSV per finished cell.

    Args:
        out: the run directory; cells live in ``out/cells``, their integrity records in
            ``out/integrity``, the table in ``out/results.csv``.
    """

    def __init__(self, out: str | os.PathLike):
        self.out = Path(out)
        self.cells = self.out / "cells"
        self.records = self.out / "integrity"
        self.cells.mkdir(parents=True, exist_ok=True)
        self._reported: set[str] = set()
        self.ignored = 0  # cells the last `table` call left out (not among its keys)

    def _path(self, key: str) -> Path:
        return self.cells / f"{key}.csv"

    def _record_path(self, key: str) -> Path:
        return self.records / f"{key}.json"

    # ------------------------------------------------------------------ integrity

    def problem(self, key: str) -> str | None:
        """Why cell ``key`` cannot be used ("missing" if it was never written), or None if intact."""
        return self._check(key)[0]

    def _check(self, key: str) -> tuple[str | None, bytes | None, dict | None]:
        try:
            data = self._path(key).read_bytes()
        except FileNotFoundError:
            return "missing", None, None
        except OSError as exc:
            return f"unreadable ({exc.strerror or exc})", None, None
        try:
            if not self._record_path(key).exists():
                raise FileNotFoundError(self._record_path(key))
            record = read_json(self._record_path(key), "record")
            size, digest = int(record["bytes"]), str(record["sha256"])
            if not isinstance(record["columns"], list) or not isinstance(record["dtypes"], dict):
                raise ValueError("bad columns/dtypes")
            int(record["rows"])
        except FileNotFoundError:
            return ("no integrity record (written by an older camo_sbi, or the run stopped between "
                    "the cell and its record)"), None, None
        except (OSError, ValueError, KeyError, TypeError) as exc:
            return f"unreadable integrity record ({type(exc).__name__}: {exc})", None, None
        if not data and size:
            return f"empty (expected {size} bytes)", None, None
        if len(data) != size:
            return f"{len(data)} bytes, expected {size} (truncated or modified)", None, None
        if hashlib.sha256(data).hexdigest() != digest:
            return "checksum mismatch (modified or garbage bytes)", None, None
        return None, data, record

    def _report(self, key: str, reason: str, action: str) -> None:
        if key not in self._reported:
            self._reported.add(key)
            warnings.warn(f"cell {self._path(key)}: {reason}; {action}", CorruptCellWarning, stacklevel=3)

    def done(self, key: str) -> bool:
        """Is cell ``key`` finished and intact? A damaged cell is reported (`CorruptCellWarning`)."""
        reason = self.problem(key)
        if reason is not None and reason != "missing":
            self._report(key, reason, "not used, it will be recomputed")
        return reason is None

    def finished_keys(self) -> set[str]:
        """Keys of the intact cells (damaged ones are reported and left out)."""
        return {p.stem for p in self.cells.glob("*.csv") if self.done(p.stem)}

    # ------------------------------------------------------------------ write / read

    def put(self, key: str, rows: Iterable[Mapping[str, object]]) -> None:
        """Write one finished cell atomically (replacing any earlier copy of the same key), then its record."""
        df = pd.DataFrame(list(rows))
        data = df.to_csv(index=False).encode("utf-8")
        record = {"format": _RECORD_FORMAT, "file": self._path(key).name, "rows": len(df), "bytes": len(data),
                  "sha256": hashlib.sha256(data).hexdigest(), "columns": [str(c) for c in df.columns],
                  "dtypes": {str(c): str(t) for c, t in df.dtypes.items()}}
        atomic_write_bytes(self._path(key), data)
        atomic_write_text(self._record_path(key), json.dumps(record, indent=1))

    def read(self, key: str) -> pd.DataFrame | None:
        """Cell ``key`` as written (recorded dtypes), or None if it is missing or damaged (reported)."""
        reason, data, record = self._check(key)
        if reason is None:
            try:
                df = _parse(data, record)
            except (ValueError, TypeError) as exc:  # matches its checksum but not its columns: a bug
                reason = f"does not parse as recorded ({type(exc).__name__}: {exc})"
            else:
                return df
        if reason != "missing":
            self._report(key, reason, "left out of the table")
        return None

    def table(self, keys: Iterable[str] | None = None) -> pd.DataFrame:
        """The intact cells ``keys`` (the current grid's) concatenated in key order; damaged ones are reported.

        Cells under ``cells/`` that are not among ``keys`` (left by a run of other settings, e.g.
        after someone edited manifest.json) are never read: `ignored` counts them and a log
        line says how many. ``keys=None``: every cell in the directory (for inspection only).
        """
        present = {p.stem for p in self.cells.glob("*.csv")}
        wanted = present if keys is None else set(keys)
        self.ignored = len(present - wanted)
        if self.ignored:
            log.warning("%d cell(s) in %s are not part of this grid (other settings): left out of the table",
                        self.ignored, self.cells)
        parts = []
        for key in sorted(wanted):
            df = self.read(key)
            if df is not None and len(df):
                parts.append(df)
        return pd.concat(parts, ignore_index=True) if parts else pd.DataFrame()

    def write_table(self, name: str = "results.csv", *, keys: Iterable[str] | None = None) -> pd.DataFrame:
        """`table` (of ``keys``) written atomically to ``out/name``."""
        df = self.table(keys)
        atomic_write_text(self.out / name, df.to_csv(index=False))
        return df


def _parse(data: bytes, record: dict) -> pd.DataFrame:
    columns, dtypes, rows = record["columns"], record["dtypes"], int(record["rows"])
    if not columns:
        df = pd.DataFrame()
    else:
        known = {c: t for c, t in dtypes.items() if _is_plain_dtype(t)}
        df = pd.read_csv(io.BytesIO(data), dtype=known)
    if [str(c) for c in df.columns] != columns or len(df) != rows:
        raise ValueError(f"{len(df)} rows and columns {list(df.columns)}, recorded {rows} and {columns}")
    return df


def _is_plain_dtype(name: str) -> bool:
    """dtypes read_csv is told to use (numbers, bools, strings); others (object, ...) are inferred as before."""
    return name in ("str", "bool") or re.fullmatch(r"u?int(8|16|32|64)|float(16|32|64)", name) is not None
