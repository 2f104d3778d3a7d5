"""An infer report (issue 34, item 7) read in headless Chromium: no two titles, captions or table
headers overlap on the page, the wide limits table marks a method that fell back with a dagger,
and the page does not scroll sideways. The panel titles inside each figure are checked by
tests/test_limits_reading.py (their rendered extents, in the default tier).

    apt-get install -y chromium
    .venv/bin/python -m pytest -m browser tests/test_infer_report_browser.py -s
"""

from __future__ import annotations

import json

import pandas as pd
import pytest

from tests._chromium import Chromium, find_chromium
from tests.test_infer_cli import ABC_TINY, MODEL, NOISE

BOXES = """
(() => {
  const out = [];
  for (const el of document.querySelectorAll('h1, h2, h3, figcaption, caption, th, .meta')) {
    const r = el.getBoundingClientRect();
    if (r.width > 0 && r.height > 0)
      out.push({tag: el.tagName, text: el.textContent.trim().slice(0, 60), x0: r.left, y0: r.top + window.scrollY,
                x1: r.right, y1: r.bottom + window.scrollY, parent: el.parentElement === null ? '' : el.parentElement.tagName});
  }
  return JSON.stringify(out);
})()
"""


@pytest.fixture(scope="module")
def infer_report(tmp_path_factory):
    if find_chromium() is None:
        pytest.skip("chromium not installed (apt-get install -y chromium)")
    from camo_sbi.experiments.cli import main

    base = tmp_path_factory.mktemp("infer_browser")
    rec = base / "reaches.csv"
    assert main(["simulate-observations", *MODEL, "--limits", "tests/data/arm7_limits.json", "--reaches", "3",
                 "--seed", "2", *NOISE, "--out", str(rec)]) == 0
    out = base / "out"
    assert main(["infer", "--observations", str(rec), *MODEL, "--methods", "naive,nominal,camo,abc-smc",
                 "--budget", "40", "--seed", "0", *NOISE, "--config", f"abc-smc={json.dumps(ABC_TINY)}",
                 "--out", str(out)]) == 0
    return out


def _overlap(a, b) -> bool:
    return a["x0"] < b["x1"] - 0.5 and b["x0"] < a["x1"] - 0.5 and a["y0"] < b["y1"] - 0.5 and b["y0"] < a["y1"] - 0.5


@pytest.mark.browser
@pytest.mark.parametrize("width", (1280, 800))
def test_infer_report_titles_do_not_overlap(infer_report, width):
    html = infer_report / "report.html"
    with Chromium() as browser:
        browser.open(html.resolve().as_uri(), width=width)
        boxes = json.loads(browser.evaluate(BOXES))
        page = browser.measure()
        shot = browser.screenshot(infer_report / f"report_{width}px.png")
    print(f"\nscreenshot: {shot}")
    assert len(boxes) > 10
    clashes = [(a["text"], b["text"]) for i, a in enumerate(boxes) for b in boxes[i + 1:] if _overlap(a, b)]
    assert not clashes, clashes[:5]
    assert page["scrollWidth"] <= page["innerWidth"], f"horizontal scroll; too wide: {page['wide']}"
    limits = pd.read_csv(infer_report / "limits.csv")
    fell_back = sorted(set(limits.loc[limits.status != "ok", "method"]))
    assert fell_back, "abc-smc at this tiny budget was expected to fall back (the dagger is what is checked)"
    headers = [b["text"] for b in boxes if b["tag"] == "TH"]
    for m in fell_back:
        assert f"{m} \u2020" in headers, (m, headers)
    for m in set(limits.method) - set(fell_back):
        assert m in headers and f"{m} \u2020" not in headers
