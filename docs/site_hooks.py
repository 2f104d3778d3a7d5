"""MkDocs hooks of the documentation site (`mkdocs.yml`: ``hooks: [docs/site_hooks.py]``).

A page holds a directive, an HTML comment on a line of its own, where a part of it is generated
at build time, so that the page cannot drift from the code or the data:

    <!-- cli-help: compare -->                 the command's `--help` text (argparse, 100 columns)
    <!-- cli-help: reproduce panda -->
    <!-- table: calibrate calibration/panda --> a table printed by docs/readme_tables.py from a run
                                               directory (its path relative to docs/)
    <!-- include: calibration/panda/summary.txt -->   a text file of docs/, verbatim
    <!-- csv: studies/active_design_s0.csv -->    a CSV file of docs/ as a table, its cells as written
    <!-- calibration-verdicts -->              the verdict per model and method
                                               (camo_sbi.diagnostics.calibration.calibration_verdicts)

An unknown directive, a command without a parser or a missing file fails the build.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import sys
from pathlib import Path

DOCS = Path(__file__).resolve().parent
ROOT = DOCS.parent
DIRECTIVE = re.compile(r"^<!-- (cli-help|table|include|csv|calibration-verdicts)(?::\s*(.*?))?\s*-->$", re.M)
ANY_DIRECTIVE = re.compile(r"^<!-- ([a-z-]+)(:[^>]*)? -->$", re.M)
KNOWN = {"cli-help", "table", "include", "csv", "calibration-verdicts"}
HELP_COLUMNS = "100"


def cli_help(command: str) -> str:
    """`camo-sbi COMMAND --help` as argparse prints it at a fixed width."""
    from camo_sbi.experiments.cli import build_parser

    old = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = HELP_COLUMNS
    try:
        parser = build_parser()
        for word in command.split():
            sub = next((a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction"), None)
            if sub is None or word not in sub.choices:
                raise ValueError(f"cli-help: no command {command!r} in camo-sbi's parser")
            parser = sub.choices[word]
        return parser.format_help()
    finally:
        if old is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = old


def table(args: str) -> str:
    """A table of docs/readme_tables.py (``KIND DIR [DIR2]``, directories relative to docs/)."""
    sys.path.insert(0, str(DOCS))
    try:
        import readme_tables
    finally:
        sys.path.remove(str(DOCS))
    kind, *dirs = args.split()
    paths = [DOCS / d for d in dirs]
    missing = [str(p) for p in paths if not p.is_dir()]
    if missing:
        raise ValueError(f"table: no run directory {missing[0]}")
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        readme_tables.main([kind, *map(str, paths)])
    return out.getvalue().rstrip()


def include(path: str) -> str:
    p = DOCS / path
    if not p.is_file():
        raise ValueError(f"include: no file docs/{path}")
    return "```text\n" + p.read_text().rstrip() + "\n```"


def csv_table(path: str) -> str:
    import csv

    p = DOCS / path
    if not p.is_file():
        raise ValueError(f"csv: no file docs/{path}")
    with open(p, newline="") as f:
        rows = list(csv.reader(f))
    out = ["| " + " | ".join(rows[0]) + " |", "|" + "---|" * len(rows[0])]
    return "\n".join(out + ["| " + " | ".join(r) + " |" for r in rows[1:]])


def verdicts() -> str:
    from camo_sbi.diagnostics.verdicts import calibration_verdicts

    rows = calibration_verdicts()
    out = ["| model | method | mean \\|coverage − α\\| | mean coverage − α | coverage at α = 0.5 / 0.9 | verdict |",
           "|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['model']} | {r['method']} | {r['mean_abs_dev']:.3f} | {r['mean_dev']:+.3f} | "
                   f"{r['cov@0.5']:.2f} / {r['cov@0.9']:.2f} | {r['verdict']} |")
    return "\n".join(out)


def render(markdown: str) -> str:
    """The page with every directive replaced (a comment that looks like a directive but is
    none of the known ones is an error: a typo would otherwise vanish from the page)."""
    for m in ANY_DIRECTIVE.finditer(markdown):
        if m.group(1) not in KNOWN:
            raise ValueError(f"unknown directive {m.group(0)!r}")

    def one(m: re.Match) -> str:
        kind, arg = m.group(1), (m.group(2) or "").strip()
        if kind == "cli-help":
            return "```text\n" + cli_help(arg).rstrip() + "\n```"
        if kind == "table":
            return table(arg)
        if kind == "include":
            return include(arg)
        if kind == "csv":
            return csv_table(arg)
        return verdicts()

    return DIRECTIVE.sub(one, markdown)


def on_page_markdown(markdown, page, config, files):  # noqa: ARG001 - MkDocs' hook signature
    try:
        return render(markdown)
    except ValueError as exc:
        from mkdocs.exceptions import PluginError

        raise PluginError(f"{page.file.src_uri}: {exc}") from exc
