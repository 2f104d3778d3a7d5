"""Render the HTML report in headless Chromium and check the screenshot is not blank.

Run on purpose: ``pytest -m browser tests/test_report_browser.py`` (needs
``apt-get install chromium``; skipped otherwise). Chromium runs with networking
disabled features and a throw-away profile, loading the file:// URL offline.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from camo_sbi.diagnostics import arviz_io, calibration, report
from camo_sbi.inference.result import PosteriorResult
from camo_sbi.priors import BoxPrior

CHROMIUM_CANDIDATES = ("/usr/bin/chromium", "chromium", "chromium-browser", "google-chrome")


def _chromium() -> str | None:
    for c in CHROMIUM_CANDIDATES:
        p = shutil.which(c) or (c if Path(c).is_file() else None)
        if p:
            return p
    return None


def _run_dir(root: Path) -> Path:
    root.mkdir()
    (root / "config.json").write_text(json.dumps({"scenario": "reaching", "seeds": [0, 1]}))
    rng = np.random.default_rng(0)
    rows = [("reach", "s0", m, b, seed, k, "limit_rmse", 0.3 / np.sqrt(k) * 2000 / (b + 1000) + 0.01 * rng.random())
            for m in ("camo", "npe") for b in (1000, 4000) for k in (1, 3, 5) for seed in (0, 1)]
    pd.DataFrame(rows, columns=list(report.RESULTS_COLUMNS)).to_csv(root / "results.csv", index=False)
    prior = BoxPrior(np.array([[-2.0, 2.0], [-1.0, 1.5]]), np.array([0.1, 0.2]))
    truth = prior.sample(1, 1).numpy()[0]
    (root / "posteriors").mkdir()
    for i, m in enumerate(("camo", "npe")):
        s = truth + 0.1 * np.random.default_rng(i).standard_normal((1000, 4))
        r = PosteriorResult(m, s, None, truth, 4000, 1.0, 5)
        idata = arviz_io.to_inference_data(r, ["shoulder", "elbow"], seed=0, prior=prior, true_theta=truth)
        arviz_io.save_netcdf(idata, root / "posteriors" / f"{m}.nc")
    theta = rng.standard_normal((60, 2))
    post = theta[:, None, :] * 0.8 + 0.6 * rng.standard_normal((60, 300, 2))
    calibration.central_interval_coverage(post, theta).assign(method="npe").to_csv(root / "coverage.csv", index=False)
    return root


@pytest.mark.browser
def test_report_renders_in_headless_chromium(tmp_path):
    chromium = _chromium()
    if chromium is None:
        pytest.skip("chromium not installed (apt-get install -y chromium)")
    html = report.write_report(_run_dir(tmp_path / "run"), tmp_path / "report.html", title="browser check")
    png = tmp_path / "shot.png"
    cmd = [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
           "--disable-background-networking", "--disable-component-update", "--disable-sync",
           "--hide-scrollbars", f"--user-data-dir={tmp_path / 'profile'}", f"--screenshot={png}",
           "--window-size=1280,4000", html.resolve().as_uri()]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=180, check=False)
    assert png.is_file(), f"no screenshot (rc={proc.returncode}): {proc.stderr[-2000:]}"
    from matplotlib.image import imread

    img = imread(str(png))  # (H, W, 3|4) floats in [0, 1]
    assert img.shape[0] >= 1000 and img.shape[1] >= 1000
    gray = img[..., :3].mean(axis=2)
    assert gray.var() > 1e-3, "screenshot is blank (no pixel variance)"
    # not merely text on white: the embedded figures put many non-white pixels on the page
    assert (gray < 0.9).mean() > 0.01
