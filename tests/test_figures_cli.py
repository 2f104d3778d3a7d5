"""The figure flags from the command line: --figure-format and --corner-limits, as a new user runs them."""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET

import pytest
from pypdf import PdfReader

from camo_sbi.experiments.cli import main

TINY = ["compare", "--model", "panda", "--methods", "camo,naive", "--budgets", "60", "--seeds", "2",
        "--tasks", "2", "--test-goals", "2"]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("figs") / "run"
    assert main([*TINY, "--figure-format", "pdf,svg", "--corner-limits",
                 "panda_joint1_lo,panda_joint1_hi,panda_joint2_hi", "--out", str(out)]) == 0
    return out


def test_compare_writes_pdf_and_svg_figures(run):
    for name in ("error_vs_tasks", "wall_time"):
        assert PdfReader(run / f"{name}.pdf").pages, name
        assert ET.parse(run / f"{name}.svg").getroot().tag.endswith("svg")
    assert not list(run.glob("*.png"))  # only the formats asked for
    report_figs = sorted(p.suffix for p in (run / "report_figures").iterdir())
    assert ".pdf" in report_figs and ".svg" in report_figs and ".png" not in report_figs


def test_a_two_seed_report_has_no_interval_and_degrees(run):
    text = (run / "report.html").read_text(encoding="utf-8")
    tables = text.split('<section id="comparison-table">', 1)[1].split("</section>", 1)[0]
    assert "±" not in tables and "mean (min–max) over 2 seeds" in tables
    assert re.search(r"<td>[-\d.,]+ \([-\d.,]+(–| to )[-\d.,]+\)</td>", tables)  # a range built from the 2 seeds
    posteriors = text.split('<section id="posteriors">', 1)[1].split("</section>", 1)[0]
    assert "in degrees (arviz forest plot)" in posteriors
    assert "panda_joint1_lo, panda_joint1_hi, panda_joint2_hi" in posteriors  # --corner-limits honoured
    assert "the limits asked for (--corner-limits)" in posteriors


def test_the_format_is_not_a_setting_and_a_bad_one_exits_2(run, capsys):
    # another format into the same directory: no refusal, no cell recomputed
    cells = {p: p.stat().st_mtime_ns for p in (run / "cells").rglob("*") if p.is_file()}
    assert main([*TINY, "--figure-format", "png", "--no-report", "--out", str(run)]) == 0
    assert (run / "error_vs_tasks.png").read_bytes()[:4] == b"\x89PNG"
    assert cells and {p: p.stat().st_mtime_ns for p in (run / "cells").rglob("*") if p.is_file()} == cells
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        main([*TINY, "--figure-format", "png,eps", "--out", str(run)])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--figure-format" in err[0] and "eps" in err[0]
    with pytest.raises(SystemExit) as exc:
        main([*TINY, "--corner-limits", "panda_joint1", "--out", str(run)])
    assert exc.value.code == 2 and "--corner-limits" in capsys.readouterr().err
