"""Render a real run's HTML report in headless Chromium at 1280-1600 px, as a reader would.

Run on purpose (the default test command excludes the ``browser`` marker)::

    apt-get install -y chromium
    .venv/bin/python -m pytest -m browser tests/test_report_browser.py -s

Chromium is driven over its DevTools protocol on a pipe (tests/_chromium.py: standard
library only, offline, a throw-away profile). The test runs a small real ``camo-sbi
compare`` (CAMO, naive, ABC-SMC; two budgets, two seeds), writes its report, and checks
that the page has no horizontal scroll at 1400 px, that every image decodes, and that the
console logged no error. It writes ``report_1400px.png`` (the whole page) beside the
report and prints where: look at it. The same checks run at 1280 and 1600 px. ``CAMO_SBI_REPORT_RUN=DIR`` checks the report of an
existing run directory instead (rewritten from DIR's files, screenshot into DIR).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from camo_sbi.diagnostics import report
from tests._chromium import Chromium, find_chromium

WIDTHS = (1280, 1400, 1600)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    given = os.environ.get("CAMO_SBI_REPORT_RUN")
    if given:
        return Path(given)
    from camo_sbi.experiments.cli import main

    out = tmp_path_factory.mktemp("browser") / "run"
    argv = ["compare", "--methods", "camo,naive,abc-smc", "--budgets", "100,200", "--seeds", "2", "--tasks", "2",
            "--test-goals", "2", "--no-report", "--out", str(out)]
    assert main(argv) == 0
    return out


@pytest.fixture(scope="module")
def html(run_dir) -> Path:
    if find_chromium() is None:
        pytest.skip("chromium not installed (apt-get install -y chromium)")
    return report.write_report(run_dir, run_dir / "report.html", title="browser check")


@pytest.mark.browser
@pytest.mark.parametrize("width", WIDTHS)
def test_report_reads_in_headless_chromium(html, width):
    t0 = time.perf_counter()
    with Chromium() as browser:
        browser.open(html.resolve().as_uri(), width=width)
        page = browser.measure()
        shot = browser.screenshot(html.parent / f"report_{width}px.png")
    print(f"\nscreenshot: {shot} ({time.perf_counter() - t0:.1f} s in Chromium)")
    assert page["innerWidth"] == width
    assert page["scrollWidth"] <= page["innerWidth"], f"horizontal scroll; too wide: {page['wide']}"
    assert len(page["images"]) >= 5  # figures of every section that has data
    broken = [src for src, complete, width in page["images"] if not (complete and width > 0)]
    assert not broken, f"{len(broken)} images did not load: {broken}"
    assert page["console_errors"] == []
    from matplotlib.image import imread

    img = imread(str(shot))  # (H, W, 3|4) floats in [0, 1]
    assert img.shape[1] == width and img.shape[0] >= min(page["scrollHeight"], 16000) - 1
    gray = img[..., :3].mean(axis=2)
    assert (gray < 0.9).mean() > 0.01  # figures and tables, not an empty page
