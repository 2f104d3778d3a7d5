"""Derived files of a run (figures) rebuilt only when their inputs change.

    digest = outputs.digest_files([out / "results.csv"], extra=("compare figures", 1))
    paths = outputs.cached(out, "figures", digest)       # None: rebuild
    if paths is None:
        paths = make_figures(df, out)
        outputs.record(out, "figures", digest, paths)

``OUT/outputs.json`` records, per name, the sha256 of the inputs and of every file written. An
output is current only if its inputs digest matches AND every recorded file is still there with
the recorded content, so a deleted or edited figure is rebuilt. The HTML report keeps its own
digest inside the page (`camo_sbi.diagnostics.report`).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable
from pathlib import Path

from camo_sbi._files import read_json
from camo_sbi._io import atomic_write_text

__all__ = ["RECORD", "cached", "digest_files", "record"]

RECORD = "outputs.json"


def _sha(path: Path) -> str | None:
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError:
        return None


def digest_files(paths: Iterable[Path], *, extra=()) -> str:
    """sha256 over the names and contents of ``paths`` (a missing file counts as missing) and ``extra``."""
    from camo_sbi import __version__

    h = hashlib.sha256(json.dumps([__version__, *map(str, extra)]).encode())
    for p in paths:
        p = Path(p)
        h.update(f"{p.name}\0{_sha(p)}\0".encode())
    return h.hexdigest()


def _load(out: Path) -> dict:
    try:
        data = read_json(Path(out) / RECORD)
    except ValueError:
        return {}
    return data if isinstance(data, dict) else {}


def cached(out, name: str, digest: str) -> list[Path] | None:
    """The files of output ``name`` if they were built from ``digest`` and are intact, else None."""
    entry = _load(out).get(name)
    if not isinstance(entry, dict) or entry.get("inputs") != digest or not isinstance(entry.get("files"), dict):
        return None
    files = {Path(out) / rel: sha for rel, sha in entry["files"].items()}
    if not files or any(_sha(p) != sha for p, sha in files.items()):
        return None
    return list(files)


def record(out, name: str, digest: str, paths: Iterable[Path]) -> None:
    """Record that output ``name`` (``paths``, inside ``out``) was built from ``digest``."""
    out = Path(out)
    data = _load(out)
    data[name] = {"inputs": digest,
                  "files": {str(Path(p).relative_to(out)): _sha(Path(p)) for p in paths}}
    atomic_write_text(out / RECORD, json.dumps(data, indent=2, sort_keys=True) + "\n")
