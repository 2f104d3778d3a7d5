"""The documentation site and the one-page README (issue 37).

The site builds in MkDocs' strict mode (a broken link, a missing page, a docstring griffe cannot
parse or an unknown directive of docs/site_hooks.py fails); every command has its page, whose
options are generated from the parser; the README stays one page whose links resolve and whose
test command is .ci/run's; the calibration verdicts are read from the measured coverage files.
"""

from __future__ import annotations

import csv
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
sys.path.insert(0, str(DOCS))
import site_hooks  # noqa: E402 - docs/site_hooks.py, the site's build hooks

sys.path.remove(str(DOCS))


def test_the_site_builds_in_strict_mode(tmp_path):
    """`mkdocs build --strict` (what a reader gets with `mkdocs serve`): every page, the API
    reference from the docstrings, the generated command options and tables; no warning."""
    out = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-q", "-d", str(tmp_path / "site")],
                         cwd=ROOT, capture_output=True, text=True, timeout=600,
                         env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    assert out.returncode == 0, out.stderr[-3000:]
    site = tmp_path / "site"
    infer = (site / "commands" / "infer" / "index.html").read_text()
    assert "usage: camo-sbi infer" in infer and "--observations" in infer  # generated from the parser
    assert "camo_sbi.inference.registry.run_method" in (site / "api" / "inference" / "index.html").read_text()
    calib = (site / "results" / "calibration" / "index.html").read_text()
    assert "mildly over-confident" in calib and "&lt;!-- " not in calib and "<!-- calibration" not in calib
    for page in ("guide", "notebooks/01_quickstart", "studies/grid_identity", "adding-a-method"):
        assert (site / page / "index.html").is_file(), page


def _commands():
    from camo_sbi.experiments.cli import COMMANDS, REPRODUCE

    return [(c.name, c.name) for c in COMMANDS] + [(f"reproduce-{c.name}", f"reproduce {c.name}") for c in REPRODUCE]


def test_every_command_has_a_page_with_its_generated_options():
    pages = {p.stem for p in (DOCS / "commands").glob("*.md")} - {"index"}
    assert pages == {page for page, _ in _commands()}
    for page, command in _commands():
        text = (DOCS / "commands" / f"{page}.md").read_text()
        assert f"<!-- cli-help: {command} -->" in text, page
        assert site_hooks.render(f"<!-- cli-help: {command} -->").startswith(f"```text\nusage: camo-sbi {command}")


def test_an_unknown_directive_or_command_fails_the_build():
    with pytest.raises(ValueError, match="unknown directive"):
        site_hooks.render("<!-- cli-hepl: compare -->")
    with pytest.raises(ValueError, match="no command 'comapre'"):
        site_hooks.render("<!-- cli-help: comapre -->")
    with pytest.raises(ValueError, match="no file docs/nothing.txt"):
        site_hooks.render("<!-- include: nothing.txt -->")
    assert site_hooks.render("<!-- not a directive: x -->\ntext") == "<!-- not a directive: x -->\ntext"


def test_the_readme_is_one_page_whose_links_resolve():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 300
    targets = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
    assert targets, "the README links to the documentation"
    missing = [t for t in targets if not t.startswith("http") and not (ROOT / t).exists()]
    assert missing == []
    # the README's test command is the one .ci/run runs (the shared hook greps for it)
    assert "\n.venv/bin/python -m pytest -q\n" in text
    assert "\n.venv/bin/python -m pytest -q\n" in (ROOT / ".ci" / "run").read_text()
    assert "mkdocs serve" in text and "mkdocs build --strict" in text


def test_the_readme_numbers_link_to_their_pages():
    """Each bullet of the README's findings names its command and links to its results page."""
    text = (ROOT / "README.md").read_text()
    found = text.split("## What we found", 1)[1].split("\n## ", 1)[0]
    bullets = [b for b in found.split("\n- ")[1:]]
    assert len(bullets) >= 4
    for b in bullets:
        if re.search(r"\d", b):
            assert "](docs/" in b and "`camo-sbi " in b, b


# ------------------------------------------------------------------ results read from data


def test_the_measured_calibration_file_is_what_the_docs_runs_measured():
    """camo_sbi/diagnostics/calibration_measured.csv equals what docs/calibration/measured.py
    derives from the coverage.csv files of the measured runs (so neither drifts)."""
    sys.path.insert(0, str(DOCS / "calibration"))
    try:
        import measured
    finally:
        sys.path.remove(str(DOCS / "calibration"))
    assert measured.TARGET.read_text() == measured.measured_text()


def test_the_untouched_coverage_file_is_what_the_binding_bound_rows_measured():
    """camo_sbi/diagnostics/untouched_measured.csv equals what docs/studies/exact_binding/measured.py
    derives from the study's rows, and one of its numbers recounted here by hand."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("eb_measured", DOCS / "studies" / "exact_binding" / "measured.py")
    measured = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(measured)
    assert measured.TARGET.read_text() == measured.measured_text()
    from camo_sbi.diagnostics.verdicts import untouched_verdict, untouched_verdicts

    rows = []
    for f in sorted((DOCS / "studies" / "exact_binding").glob("panda_s*.csv")):
        with open(f, newline="") as fh:
            rows += [r for r in csv.DictReader(fh) if r["method"] == "camo-seq" and r["touched"] == "False"]
    camo = next(r for r in untouched_verdicts() if r["model"] == "panda" and r["method"] == "camo-seq")
    assert camo["bounds"] == len(rows) > 0 and camo["covered"] == sum(r["covered90"] == "True" for r in rows)
    cov, text = untouched_verdict("camo-seq", "panda")
    assert cov == camo["coverage90"] and f"covered {camo['covered']} of {len(rows)}" in text
    assert untouched_verdict("naive", "panda")[1] == "a point estimate (no interval)"


def test_the_two_seed_verdicts_are_what_the_seed_files_say_and_the_readme_counts_them():
    """docs/studies/two_seeds.csv equals what two_seeds.py combines from the committed per-seed
    files; the README's counts (40 informative verdicts agree; 16 of 18 active-vs-random tests
    hold under both) are recounted from it, and one verdict by hand from the seed files."""
    import importlib.util

    import pandas as pd

    spec = importlib.util.spec_from_file_location("two_seeds", DOCS / "studies" / "two_seeds.py")
    two = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(two)
    combined = two.combine([0, 1])
    committed = pd.read_csv(DOCS / "studies" / "two_seeds.csv")
    assert list(committed.columns) == list(combined.columns) and len(committed) == len(combined)
    for col in ("holds_s0", "holds_s1", "holds_both", "agree"):
        assert committed[col].tolist() == combined[col].astype(bool).tolist(), col
    inf = combined[combined.study == "informative"]
    design = combined[combined.study == "active vs random"]
    assert len(inf) == 40 and inf.agree.all()
    assert len(design) == 18 and int(design.holds_both.sum()) == 16
    readme = (ROOT / "README.md").read_text()
    assert "All 40 verdicts of its claims table are the same under a second seed" in readme
    assert "16 of 18\n  paired tests hold under both seeds 0 and 1" in readme
    s1 = pd.read_csv(DOCS / "studies" / "active_design_s1.csv")  # by hand: camo-hull, Panda, binding error
    row = s1[(s1.model == "panda") & (s1.method == "camo-hull") & (s1.metric == "limit_error_binding_deg")].iloc[0]
    got = design[(design.model == "panda") & (design.method == "camo-hull")
                 & (design.metric == "limit_error_binding_deg")].iloc[0]
    assert bool(got.holds_s1) == (row.p_holm < 0.05 and row.active_minus_random < 0)


def test_the_untouched_rule_on_hand_made_counts():
    from camo_sbi.diagnostics.verdicts import binomial_below, untouched_verdict, untouched_word

    assert abs(binomial_below(5, 10) - 0.001634937) < 1e-8  # scipy.stats.binom.cdf(5, 10, 0.9)
    assert untouched_word(9, 10) == "calibrated on untouched bounds"
    assert untouched_word(17, 20) == "calibrated on untouched bounds"  # 0.85: at the tolerance's edge
    assert untouched_word(1, 6) == "over-confident on untouched bounds"
    assert untouched_word(8, 10) == "coverage below 0.90 on untouched bounds, too few to tell (binomial p=0.26)"
    assert untouched_word(2, 2).startswith("coverage above 0.90 on untouched bounds, too few to tell")
    assert untouched_verdict("nominal", "panda")[1] == "a point (no posterior)"
    cov, text = untouched_verdict("no-such-method", "panda")
    assert cov != cov and text == "not measured on untouched bounds"


def test_verdicts_are_a_rule_on_the_measured_numbers():
    from camo_sbi.diagnostics.verdicts import calibration_verdict, calibration_verdicts, verdict

    # the rule on hand-made numbers
    assert verdict(-0.01, 0.02, False) == "calibrated"
    assert verdict(-0.05, 0.05, False) == "mildly over-confident"
    assert verdict(-0.1, 0.1, False) == "over-confident"
    assert verdict(0.25, 0.25, False) == "strongly under-confident"
    assert verdict(0.0, 0.4, True) == "a point estimate, not a posterior"
    # the measured file: the Panda's CAMO pooled deviation, recomputed here from coverage.csv
    with open(DOCS / "calibration" / "panda" / "coverage.csv", newline="") as f:
        rows = [r for r in csv.DictReader(f) if r["method"] == "camo" and r["coordinate"] == "overall"]
    dev = sum(float(r["coverage"]) - float(r["alpha"]) for r in rows) / len(rows)
    camo = next(r for r in calibration_verdicts() if r["model"] == "panda" and r["method"] == "camo")
    assert abs(camo["mean_dev"] - dev) < 1e-5 and camo["verdict"] == "over-confident"
    assert calibration_verdict("camo", "human") == "mildly over-confident"
    assert calibration_verdict("nominal", "panda") == "a point (no posterior)"
    assert calibration_verdict("npe", "arm7") == "not calibrated on this model (panda: calibrated; human: calibrated)"
    assert calibration_verdicts("model,method\n") == []


def test_no_measured_speed_up_in_the_help():
    """Help text quotes no measurement (a speed-up, a time): those live in the documentation."""
    from camo_sbi.experiments.cli import build_parser

    texts = [site_hooks.cli_help(command) for _, command in _commands()] + [build_parser().format_help()]
    for text in texts:
        assert not re.search(r"\d(\.\d+)?x (faster|less|more)|\d(\.\d+)? ?× ", text), text[:200]
