"""`camo-sbi run study.toml`: a whole comparison (models, subjects, methods, budgets, seeds,
settings) described in one TOML file, run as one `compare` grid per body model
(`EXAMPLE` below, also ``docs/study_example.toml``)

Every key is a `compare` option spelled without its dashes (``test-goals`` or ``test_goals``);
a list is joined with commas, ``true`` gives a flag (``no-report = true``), ``config`` is a table
of method tables (given to every entry that runs the method). So a study accepts exactly what ``compare`` accepts, checked by compare's own
parser before anything runs: an unknown key or a bad value exits 2 naming the file, the entry and
the key. ``urdf``, ``limits`` and ``amortized`` paths are relative to the study file.

Recorded: ``OUT/study.toml`` (the file as run) and ``OUT/study.json`` (its sha256 and, per entry,
the equivalent ``camo-sbi compare`` command line); each entry's compare manifest records
``study`` (the file and the entry's name) next to its settings. Re-running the same study skips
every finished cell (each grid resumes like ``compare``); a study whose settings changed is
refused per entry, like a re-run of ``compare`` with other settings. ``OUT/results.csv`` is the
concatenation of the entries' tables, each row led by an ``entry`` column (the entry's name, unique
in the file, also ignoring case; the ``task`` column names the model, which two entries may share).
``--dry-run`` prints the compare command lines and runs nothing.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shlex
from pathlib import Path

from camo_sbi._files import parse_toml, read_text

__all__ = ["add_arguments", "compare_argvs", "load_study", "main"]

EXAMPLE = """\
name = "panda and a small human"         # optional title
out = "runs/study"                        # default: runs/<file stem>; paths are relative to the file
methods = ["camo", "camo-hull", "abc-smc", "npe"]
budgets = [500, 2000]
seeds = 3
tasks = 5

[config]                                  # per-method overrides, as --config METHOD=JSON
abc-smc = { population_size = 100 }

[[model]]                                 # one compare grid per entry, in OUT/<name>/
model = "panda"
subjects = ["elbow_restricted", "wrist_restricted"]

[[model]]
name = "human-1.6"
model = "human"
height = 1.6
methods = ["camo", "camo-hull", "abc-smc"]  # an entry may override any top-level key
"""
"""A study file: every key but name, out, config and [[model]] is a compare option."""
_STUDY_KEYS = ("name", "out", "model", "config")
_PATH_KEYS = ("urdf", "limits", "amortized")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("study", type=Path, help="the study file (TOML; see the format below)")
    p.add_argument("--out", type=Path, default=None, help="output directory (default: the file's out, else "
                                                          "runs/<file stem>)")
    p.add_argument("--workers", type=int, default=None, help="parallel worker processes per grid (overrides "
                                                             "the file's)")
    p.add_argument("--dry-run", action="store_true", help="print each entry's compare command and run nothing")
    p.epilog = (p.epilog or "") + "\n\nstudy file format:\n" + "\n".join(f"  {line}" for line in EXAMPLE.splitlines())


class _Refusal(argparse.ArgumentParser):
    """compare's parser, raising ValueError instead of printing usage and exiting."""

    def error(self, message):
        raise ValueError(message)


def _compare_parser() -> argparse.ArgumentParser:
    from camo_sbi.experiments import compare

    p = _Refusal(prog="compare", add_help=False)
    compare.add_arguments(p)
    return p


def load_study(path: Path) -> tuple[dict, str]:
    """The parsed study and its text (ValueError naming the file otherwise)."""
    path = Path(path)
    text = read_text(path, str(path))
    study = parse_toml(text, str(path))
    models = study.get("model")
    if not isinstance(models, list) or not models or not all(isinstance(m, dict) for m in models):
        raise ValueError(f"{path}: needs at least one [[model]] table")
    return study, text


def _flag_value(key: str, value, where: str, options: dict) -> list[str]:
    flag = "--" + key.replace("_", "-")
    if flag not in options:
        known = ", ".join(sorted(o[2:] for o in options if o not in ("--out", "--config")))
        raise ValueError(f"{where}: unknown key {key!r} (a study takes compare's options: {known})")
    action = options[flag]
    if action.nargs == 0:  # a flag
        if not isinstance(value, bool):
            raise ValueError(f"{where}: {key} = {value!r}: expected true or false")
        return [flag] if value else []
    if isinstance(value, list):
        value = ",".join(str(v) for v in value)
    elif isinstance(value, bool) or isinstance(value, dict):
        raise ValueError(f"{where}: {key} = {value!r}: expected a number, a string or a list")
    return [flag, str(value)]


def compare_argvs(study: dict, path: Path, out: Path) -> list[tuple[str, list[str]]]:
    """(entry name, compare argv) per [[model]] entry, checked by compare's parser (ValueError
    naming the file, the entry and the key on an unknown key or a bad value)."""
    from camo_sbi.experiments import compare

    parser = _compare_parser()
    options = {o: a for a in parser._actions for o in a.option_strings}
    base = {k: v for k, v in study.items() if k not in _STUDY_KEYS}
    configs = study.get("config", {})
    if not isinstance(configs, dict) or not all(isinstance(c, dict) for c in configs.values()):
        raise ValueError(f"{path}: [config]: expected a table of method tables, e.g. npe = {{ max_epochs = 50 }}")
    entries, seen, used = [], set(), set()
    for i, entry in enumerate(study["model"], 1):
        merged = {**base, **{k: v for k, v in entry.items() if k != "name"}}
        name = str(entry.get("name") or merged.get("model") or Path(str(merged.get("urdf", f"model{i}"))).stem)
        where = f"{path}: [[model]] {i} ({name})"
        if name.casefold() in seen or not name or "/" in name or "\\" in name or name.startswith("."):
            raise ValueError(f"{where}: name {name!r} must be unique (also ignoring case) and a plain "
                             f"directory name")
        seen.add(name.casefold())
        if "config" in entry or "out" in entry:
            raise ValueError(f"{where}: 'config' and 'out' belong to the study, not to an entry")
        argv = []
        for key, value in merged.items():
            if key.replace("_", "-") in _PATH_KEYS and isinstance(value, str):
                value = str((path.parent / value).resolve())
            argv += _flag_value(key, value, where, options)
        argv += ["--out", str(out / name)]
        try:
            methods = compare.grid_methods(parser.parse_args(argv).methods)
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from exc
        for method, cfg in configs.items():  # [config] applies to the entries that run the method
            if method in methods:
                used.add(method)
                argv += ["--config", f"{method}={json.dumps(cfg, sort_keys=True)}"]
        entries.append((name, argv))
    unused = sorted(set(configs) - used)
    if unused:
        raise ValueError(f"{path}: [config]: {unused[0]!r} is not a method of any [[model]] entry")
    return entries


def _check_sizes(entries: list[tuple[str, list[str]]], path: Path) -> None:
    """Every entry's counts (seeds, tasks, test-goals, workers) against this machine's memory,
    before the first entry runs (`compare.check_grid_size`; its own check follows per entry with
    the model's real size): ValueError naming the file, the entry and the key."""
    from camo_sbi.experiments import compare

    parser = _compare_parser()
    names = {"seeds": "seeds", "tasks": "tasks", "test_goals": "test-goals", "workers": "workers"}
    for i, (name, argv) in enumerate(entries, 1):
        args = parser.parse_args(argv)
        if min(args.seeds, args.tasks, args.test_goals, args.workers) < 1:
            continue  # compare refuses these itself, naming the flag
        subjects = len([s for s in str(args.subjects or "x").split(",") if s.strip()]) or 1
        try:
            compare.check_grid_size(args, subjects=subjects, names=names)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{path}: [[model]] {i} ({name}): {exc}") from exc


def main(args) -> int:
    from camo_sbi._io import atomic_write_text
    from camo_sbi.experiments import compare

    path = Path(args.study)
    study, text = load_study(path)
    out = args.out or (path.parent / study["out"] if "out" in study else Path("runs") / path.stem)
    entries = compare_argvs(study, path, out)
    if args.workers is not None:
        entries = [(n, [*argv, "--workers", str(args.workers)]) for n, argv in entries]
    _check_sizes(entries, path)
    commands = {n: "camo-sbi compare " + shlex.join(argv) for n, argv in entries}
    if args.dry_run:
        print("\n".join(commands.values()))
        return 0
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "study.toml", text)
    atomic_write_text(out / "study.json", json.dumps(
        {"file": str(path), "sha256": hashlib.sha256(text.encode()).hexdigest(), "name": study.get("name"),
         "entries": commands}, indent=2) + "\n")
    parser = _compare_parser()
    for i, (name, argv) in enumerate(entries, 1):
        print(f"== study entry {i}/{len(entries)} ({name}): {commands[name]}", flush=True)
        entry_args = parser.parse_args(argv)
        entry_args.study = {"file": str(path), "entry": name}  # recorded in the entry's manifest
        try:
            compare.main(entry_args)
        except ValueError as exc:
            raise ValueError(f"{path}: [[model]] {i} ({name}): {exc}") from exc
    import pandas as pd

    # the entry's name first in every row: two entries on one model (other seed, other height)
    # share every other column, and only the entry tells their rows apart
    table = pd.concat([pd.read_csv(out / name / "results.csv").assign(entry=name) for name, _ in entries],
                      ignore_index=True)
    table = table[["entry", *(c for c in table.columns if c != "entry")]]
    atomic_write_text(out / "results.csv", table.to_csv(index=False))
    print(f"study: {out / 'results.csv'} ({len(table)} rows from {len(entries)} grids); "
          f"reports: {', '.join(str(out / n / 'report.html') for n, _ in entries)}")
    return 0
