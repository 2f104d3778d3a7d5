"""What the report's own figures hold (issue 38: drawn cheaply, the same content).

The posterior-predictive figure draws each method's paths as one collection per panel (every
draw's path, projected on the panel's view); an embedded figure is emptied once saved.
"""

from __future__ import annotations

import numpy as np
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure

from camo_sbi.diagnostics import report
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
