"""What the report's own figures hold (issue 38: drawn cheaply, the same content).

The posterior-predictive figure draws each method's paths as one collection per panel (every
draw's path, projected on the panel's view); an embedded figure is emptied once saved. The
helper process (`camo_sbi.diagnostics.report_helper`) gives the same C2ST numbers as the
report's own process, and a failed or missing job is redone there.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure

from camo_sbi.diagnostics import report, report_helper
from camo_sbi.diagnostics.figures import plot_predictive


def _paths(rng, n, length=12):
    return [np.cumsum(rng.normal(size=(length + k, 3)), axis=0) for k in range(n)]


def test_predictive_panels_hold_every_draw_of_every_method():
    rng = np.random.default_rng(0)
    observed = _paths(rng, 2)
    predicted = {"camo": [_paths(rng, 5), _paths(rng, 5)], "npe": [_paths(rng, 3), _paths(rng, 3)]}
    goals = rng.normal(size=(2, 3))
    fig = plot_predictive(observed, predicted, goals=goals, title="t")
    axes = np.asarray(fig.axes[:4]).reshape(2, 2)  # rows: top view (x-y), side view (x-z)
    for r, (a, b) in enumerate(((0, 1), (0, 2))):
        for i in range(2):
            ax = axes[r, i]
            by_method = {c.get_gid(): c for c in ax.collections if isinstance(c, LineCollection)}
            assert set(by_method) == {"draws:camo", "draws:npe"}
            for meth, paths in predicted.items():
                segs = by_method[f"draws:{meth}"].get_segments()
                assert len(segs) == len(paths[i])
                for seg, p in zip(segs, paths[i], strict=True):
                    np.testing.assert_allclose(seg, p[:, [a, b]])
            # the panel's limits contain every draw (the collection counts for autoscaling)
            pts = np.concatenate([p[:, [a, b]] for meth in predicted for p in predicted[meth][i]])
            x0, x1 = ax.get_xlim()
            y0, y1 = ax.get_ylim()
            assert x0 <= pts[:, 0].min() and pts[:, 0].max() <= x1
            assert y0 <= pts[:, 1].min() and pts[:, 1].max() <= y1
    fig.clear()


def test_an_embedded_figure_is_emptied():
    fig = Figure()
    axes = fig.subplots(2, 2)
    for ax in axes.flat:
        ax.plot([0, 1], [1, 0])
    fig.suptitle("x")
    out = report.figure_html(fig, "caption", alt="alt")
    assert "data:image/png;base64," in str(out)
    assert not fig.axes and not fig.texts and fig.get_suptitle() == ""


# --------------------------------------------------------------------------- the helper process


def _posts(tmp_path):
    """Three sampled posteriors of one cell (as `report._load_posteriors` returns them)."""
    from camo_sbi.diagnostics import arviz_io
    from camo_sbi.inference.result import PosteriorResult

    rng = np.random.default_rng(3)
    truth = np.array([-1.0, 1.0, -0.5, 0.7])
    posts = []
    for k, method in enumerate(("camo", "npe", "abc-smc")):
        s = truth + (0.05 + 0.02 * k) * rng.standard_normal((300 + 100 * k, 4))
        r = PosteriorResult(method, s, None, truth.copy(), n_simulations=100, wall_time=1.0, n_tasks=2,
                            extras={"budget": 100, "seed": 0})
        idata = arviz_io.to_inference_data(r, ["a", "b"], seed=0, true_theta=truth)
        path = arviz_io.save_netcdf(idata, tmp_path / f"{method}.nc")
        posts.append((path, arviz_io.load_netcdf(path), ""))
    return posts


def test_the_comparison_table_is_the_same_with_the_helper_process(tmp_path):
    posts = _posts(tmp_path)
    alone = report._posterior_comparison_table(posts)
    with report_helper.Helper() as helper:
        pre = report._prefetch(posts, helper)
        assert pre is not None and all(j is not None for j in pre.comparison[2])  # the C2ST went to the helper
        token = report._PREFETCH.set(pre)
        try:
            helped = report._posterior_comparison_table(posts)
        finally:
            report._PREFETCH.reset(token)
    assert len(alone) == 3 and alone["C2ST accuracy"].notna().all()
    pd.testing.assert_frame_equal(alone, helped)


def test_a_failed_or_missing_helper_job_is_none():
    with report_helper.Helper() as helper:
        bad = helper.submit("c2st", np.zeros((3, 2)), np.zeros((3, 2)), 0, 500)  # too few draws: raises there
        good = helper.submit("c2st", *np.random.default_rng(0).normal(size=(2, 40, 2)), 0, 500)
        assert helper.submit("os.system", "true") is None  # only the report's jobs
        assert helper.result(bad) is None
        assert 0.0 <= helper.result(good) <= 1.0
        assert helper.result(None) is None
    off = report_helper.Helper(enabled=False)
    assert off.submit("c2st", np.zeros((40, 2)), np.zeros((40, 2)), 0, 500) is None


def test_a_helper_that_died_gives_none(tmp_path):
    helper = report_helper.Helper()
    job = helper.submit("c2st", *np.random.default_rng(0).normal(size=(2, 40, 2)), 0, 500)
    helper._proc.kill()
    assert helper.result(job) is None
    helper.close()


def test_the_helper_does_not_run_the_callers_script(tmp_path):
    """A script without a ``__main__`` guard that builds a report runs once (no spawn re-import)."""
    import subprocess
    import sys

    marker = tmp_path / "ran.txt"
    script = tmp_path / "unguarded.py"
    script.write_text(
        "from camo_sbi.diagnostics import report_helper\n"
        f"open({str(marker)!r}, 'a').write('x')\n"
        "with report_helper.Helper() as h:\n"
        "    j = h.submit('c2st', [[0.0, 1.0]] * 20, [[1.0, 0.0]] * 20, 0, 500)\n"
        "    print(h.result(j))\n")
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert marker.read_text() == "x" and float(out.stdout) >= 0.5
