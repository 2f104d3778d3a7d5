"""The run directory (``--out``) of an experiment command: one lock, one manifest, one store.

``with RunDirectory(out, "compare", settings, wait=args.wait) as run:`` (``run.store`` is the
`ResultStore`)

* takes an exclusive lock on ``out/run.lock`` (``fcntl.flock``, held until the block ends and
  released by the kernel if the process dies). A second run on the same directory stops with
  ``--out DIR: another camo-sbi run holds it (pid N); ...`` or, with ``wait=True``, waits;
* on the first run writes ``out/manifest.json``: the experiment, the package version and the
  resolved settings that determine results (`run_settings` leaves out the runtime options
  `RUNTIME_OPTIONS`: --out, --workers, --scheduler, --no-report, --wait, --figure-format,
  --corner-limits), plus ``config.json``
  (the same settings, read by `camo_sbi.diagnostics.report`);
* removes the ``.NAME.XXXX.tmp`` files of atomic writes a killed run left (`remove_stale_tmp`);
* on later runs compares: other settings, another experiment or another camo_sbi version stop
  the command with one line naming the flags that differ, e.g.
  ``--out runs/x: holds a run with other settings: --tasks 3 (here 2), --seed 0 (here 1); use a new --out``,
  so rows of two configurations never mix in one table.

Every refusal is a ValueError whose message starts with ``--out`` (the CLI exits 2).
"""

from __future__ import annotations

import json
import logging
import os
import re
import sys
import time
from collections.abc import Mapping
from pathlib import Path

from camo_sbi._files import parse_json
from camo_sbi._io import atomic_write_text
from camo_sbi.experiments.store import ResultStore

try:
    import fcntl
except ImportError:  # not POSIX: no locking
    fcntl = None

__all__ = ["MANIFEST", "RUNTIME_OPTIONS", "RunDirectory", "refuse_links", "remove_stale_tmp", "run_settings"]

log = logging.getLogger(__name__)

MANIFEST = "manifest.json"
LOCK = "run.lock"
CONFIG = "config.json"
_FORMAT = 1
RUNTIME_OPTIONS = frozenset({"out", "workers", "scheduler", "no_report", "wait", "func", "command", "experiment",
                             "figure_format", "corner_limits", "force"})
"""argparse destinations that never change a result (and the CLI's own bookkeeping)."""
# files an experiment leaves in its directory: present without a manifest = an older run
_RESULT_FILES = ("results.csv", "coverage.csv", "limits.csv")


def run_settings(args, *, ignore=(), **resolved) -> dict:
    """The settings in ``args`` (a Namespace or mapping) that determine results, JSON-ready.

    Every option except `RUNTIME_OPTIONS` and ``ignore``; ``resolved`` values (parsed lists,
    defaults filled in) replace or add entries, so equivalent spellings compare equal.
    """
    items = dict(args) if isinstance(args, Mapping) else dict(vars(args))
    out = {k: v for k, v in items.items() if k not in RUNTIME_OPTIONS and k not in set(ignore)}
    out.update(resolved)
    return json.loads(json.dumps(out, default=str))


def _package_version() -> str:
    import camo_sbi

    return str(getattr(camo_sbi, "__version__", "unknown"))


def _show(v) -> str:
    if v is _MISSING:
        return "unset"
    if isinstance(v, bool):
        return "on" if v else "off"
    if v is None:
        return "none"
    if isinstance(v, list):
        return ",".join(_show(x) for x in v)
    if isinstance(v, dict):
        return json.dumps(v, sort_keys=True, separators=(",", ":"))
    return str(v)


_MISSING = object()


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


class RunDirectory:
    """``--out`` of one experiment command: lock + manifest + `ResultStore`. Use as a context manager.

    Args:
        out: the directory (created if missing).
        experiment: the command's name, e.g. "compare", "reproduce panda".
        settings: the resolved settings that determine results (see `run_settings`).
        wait: block until another run holding the directory finishes instead of refusing.

    Attributes (after entering): ``store`` (`ResultStore`), ``manifest`` (dict), ``created``
    (True if this run wrote the manifest), ``path``.
    """

    def __init__(self, out: str | os.PathLike, experiment: str, settings: Mapping, *, wait: bool = False,
                 force: bool = False, with_store: bool = True):
        self.force = bool(force)
        self.with_store = bool(with_store)
        self.replaced: list[str] = []  # with force: the differences of the run this one replaces
        self.path = Path(out)
        self.experiment = str(experiment)
        self.settings = json.loads(json.dumps(dict(settings), default=str))
        self.wait = bool(wait)
        self.version = _package_version()
        self.store: ResultStore | None = None
        self.manifest: dict | None = None
        self.created = False
        self.removed_tmp = 0
        self._fd: int | None = None

    # ------------------------------------------------------------------ context manager

    def __enter__(self) -> RunDirectory:
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def open(self) -> RunDirectory:
        if self.path.exists() and not self.path.is_dir():
            raise ValueError(f"--out {self.path}: exists and is not a directory")
        self.path.mkdir(parents=True, exist_ok=True)
        refuse_links(self.path)  # before the lock file is opened: nothing here may point elsewhere
        self._acquire()
        try:
            self._check_manifest()
            self.removed_tmp = remove_stale_tmp(self.path)
            if self.with_store:
                self.store = ResultStore(self.path)
        except BaseException:
            self.close()
            raise
        return self

    def close(self) -> None:
        fd, self._fd = self._fd, None
        if fd is None:
            return
        try:
            os.ftruncate(fd, 0)
            if fcntl is not None:
                fcntl.flock(fd, fcntl.LOCK_UN)
        finally:
            os.close(fd)

    # ------------------------------------------------------------------ lock

    def _acquire(self) -> None:
        fd = os.open(self.path / LOCK, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC | getattr(os, "O_NOFOLLOW", 0), 0o644)
        try:
            if fcntl is not None:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:
                    holder = _holder(fd)
                    if not self.wait:
                        raise ValueError(f"--out {self.path}: another camo-sbi run holds it (pid {holder}); "
                                         "wait for it or pass --wait") from None
                    print(f"--out {self.path}: waiting for the camo-sbi run holding it (pid {holder})",
                          file=sys.stderr, flush=True)
                    t0 = time.monotonic()
                    fcntl.flock(fd, fcntl.LOCK_EX)  # interruptible: Ctrl-C / SIGTERM end the wait
                    print(f"--out {self.path}: acquired after {time.monotonic() - t0:.1f} s", file=sys.stderr,
                          flush=True)
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        except BaseException:
            os.close(fd)
            raise
        self._fd = fd

    # ------------------------------------------------------------------ manifest

    def _check_manifest(self) -> None:
        path = self.path / MANIFEST
        try:
            text = path.read_bytes()
        except FileNotFoundError:
            self._create_manifest()
            return
        try:
            old = parse_json(text.decode("utf-8"), MANIFEST)  # a binary file: UnicodeDecodeError, a ValueError
            if not isinstance(old, dict) or not isinstance(old.get("settings"), dict):
                raise ValueError("not a manifest object")
        except ValueError as exc:
            raise ValueError(f"--out {self.path}: its {MANIFEST} is unreadable ({exc}); use a new --out") from None
        if old.get("experiment") != self.experiment:
            raise ValueError(f"--out {self.path}: holds a '{old.get('experiment')}' run, not '{self.experiment}'; "
                             "use a new --out")
        diffs = self.differences(old)
        if diffs and self.force:  # the caller removes the old run's outputs (see `replaced`)
            log.warning("--out %s: replacing a run with other settings: %s", self.path, ", ".join(diffs))
            self.replaced = diffs
            path.unlink()
            self._create_manifest(check_leftovers=False)
            return
        if diffs:
            raise ValueError(f"--out {self.path}: holds a run with other settings: {', '.join(diffs)}; "
                             f"use a new --out{' or --force' if self.experiment == 'infer' else ''}")
        self.manifest = old
        self._write_config()

    def differences(self, manifest: Mapping) -> list[str]:
        """``"--flag old (here new)"`` for every setting (and the version) where ``manifest`` differs."""
        old = manifest.get("settings", {})
        diffs = []
        for name in [*old, *(k for k in self.settings if k not in old)]:
            a, b = old.get(name, _MISSING), self.settings.get(name, _MISSING)
            if a != b:
                diffs.append(f"{_flag(name)} {_show(a)} (here {_show(b)})")
        if manifest.get("camo_sbi_version") != self.version:
            diffs.append(f"camo_sbi {manifest.get('camo_sbi_version')} (here {self.version})")
        return diffs

    def _create_manifest(self, *, check_leftovers: bool = True) -> None:
        leftovers = [p.name for p in (self.path / n for n in _RESULT_FILES) if p.exists()]
        cells = self.path / "cells"
        if cells.is_dir() and any(cells.glob("*.csv")):
            leftovers.append("cells/")
        if leftovers and self.force:
            log.warning("--out %s: replacing results without a run manifest (%s)", self.path, ", ".join(leftovers))
            self.replaced = [f"results without a manifest ({', '.join(leftovers)})"]
        elif leftovers and check_leftovers:
            raise ValueError(f"--out {self.path}: holds results ({', '.join(leftovers)}) without a run manifest "
                             "(an older camo-sbi?); use a new --out")
        self.manifest = {"format": _FORMAT, "experiment": self.experiment, "camo_sbi_version": self.version,
                         "settings": self.settings,
                         "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "created_by_pid": os.getpid()}
        atomic_write_text(self.path / MANIFEST, json.dumps(self.manifest, indent=2) + "\n")
        self.created = True
        self._write_config()

    def _write_config(self) -> None:
        """``config.json`` for the report: the experiment, the version and the settings (identical on resume)."""
        config = {"experiment": self.experiment, "camo_sbi_version": self.version, **self.settings}
        text = json.dumps(config, indent=2)
        p = self.path / CONFIG
        if not (p.is_file() and p.read_text() == text):
            atomic_write_text(p, text)


def refuse_links(out: Path) -> None:
    """ValueError naming the first symbolic link under the run folder ``out`` (``out`` itself may
    be one: the user chose it). A planted ``OUT/cells`` or ``OUT/posteriors`` link would make
    the run write its files wherever it points, outside --out; a run folder holds its own files
    only, so a link in it is refused, not followed."""
    for root, dirs, files in os.walk(out):  # never descends through a link (followlinks=False)
        for name in sorted(dirs + files):
            p = Path(root) / name
            if p.is_symlink():
                raise ValueError(f"--out {out}: {p} is a symbolic link (to {os.readlink(p)!r}); a run folder "
                                 f"holds its own files only: remove the link or use a new --out")


def remove_stale_tmp(out: Path) -> int:
    """Delete the temporary files of interrupted atomic writes (``.NAME.XXXX.tmp``, left by a kill -9)
    anywhere under ``out``; call it holding the lock, when no other run can be writing there.
    Returns how many were removed (a log line says so)."""
    n = 0
    for p in out.rglob(".*.tmp"):
        if _TMP.fullmatch(p.name) and p.is_file() and not p.is_symlink():
            try:
                p.unlink()
                n += 1
            except FileNotFoundError:
                pass
    if n:
        log.info("removed %d stale temporary file(s) of an interrupted run under %s", n, out)
    return n


_TMP = re.compile(r"\..+\.[A-Za-z0-9_]{6,}\.tmp")


def _holder(fd: int) -> str:
    try:
        text = os.pread(fd, 64, 0).decode("ascii", "replace").strip()
    except OSError:
        text = ""
    return text if text.isdigit() else "unknown"
