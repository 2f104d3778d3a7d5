"""Module docstrings say what the code does and why, never what it measured (issue 26): numbers
measured on a machine go stale, so they live in docs/studies/*.md with their commands."""

from __future__ import annotations

import ast
import re
from pathlib import Path

PACKAGE = Path(__file__).parents[1] / "camo_sbi"

# a measurement: a time, a speed-up, a measured rate or score; not a definition or a constant
MEASURED = re.compile(
    r"\b\d+(\.\d+)?\s?(ms|s|min|minutes|seconds|hours)\b(?! ?=)"  # a duration ("~2 s", "14.7 min")
    r"|\b\d+(\.\d+)?\s?(x|×)\s+(faster|slower)"  # a speed-up
    r"|\b(faster|slower) than\b.*\d"  # a comparison with a number
    r"|\b[Mm]easured\b[^.]*\d"  # "Measured: 0.047 ..."
    r"|\btook\b[^.]*\d"  # "took 14.7 min"
    r"|~\s?\d+(\.\d+)?(-\d+(\.\d+)?)?\s?%"  # an approximate share ("~1-2 % of the draws")
)


def _docstrings():
    """(where, docstring) of every module and of every config class (whose field docs used to
    repeat measurements)."""
    for path in sorted(PACKAGE.rglob("*.py")):
        tree = ast.parse(path.read_text())
        where = path.relative_to(PACKAGE.parent)
        yield where, ast.get_docstring(tree, clean=False) or ""
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef) and node.name.endswith("Config"):
                yield f"{where}:{node.name}", ast.get_docstring(node, clean=False) or ""


def test_no_module_or_config_docstring_holds_a_measured_number():
    found = [f"{where}: {line.strip()}" for where, doc in _docstrings() for line in doc.splitlines()
             if MEASURED.search(line)]
    assert found == [], "\n".join(found)


def test_the_pattern_catches_the_measurements_that_used_to_be_there():
    for line in ("importing sbi costs ~2 s per process", "this is 1.8x faster than the earlier one",
                 "Measured (same setting): 2 moves 0.285", "200 000 Panda simulations took 14.7 min",
                 "whose compilation alone took ~20 s here", "ESS is ~1-2 % of the draws"):
        assert MEASURED.search(line), line
    for line in ("dt = 0.02, P = 5", "0.162 H male, 0.159 H female", "the 90% interval", "for α = 0.05, 0.10"):
        assert not MEASURED.search(line), line
