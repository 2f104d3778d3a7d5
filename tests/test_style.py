"""The shared figure style: colours per method, integer task ticks, log axes, CI captions, robust scale."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from matplotlib.colors import to_hex

from camo_sbi.diagnostics import calibration, style
from camo_sbi.experiments import compare, demo


def _tidy(methods, xs, x="n_tasks", seeds=3, scale=None, seed=0):
    rng = np.random.default_rng(seed)
    scale = scale or {}
    rows = [{"method": m, x: v, "seed": s, "value": scale.get(m, 100.0) / v * (1 + 0.1 * rng.standard_normal())}
            for m in methods for v in xs for s in range(seeds)]
    return pd.DataFrame(rows)


def _line_colors(ax) -> dict[str, str]:
    return {ln.get_label(): to_hex(ln.get_color()) for ln in ax.get_lines() if not ln.get_label().startswith("_")}


def test_a_method_has_the_same_colour_in_every_figure():
    """Before: colours were the position in each figure's legend, so naive changed colour."""
    a = style.plot_lines(_tidy(["camo", "naive", "abc-smc"], [1, 2, 3]))
    b = style.plot_lines(_tidy(["camo-js", "camo-cs", "camo-hull", "naive", "oracle"], [1, 2, 3]))
    bars = style.plot_bars(_tidy(["naive", "npe"], [1]))
    cov = pd.DataFrame({"method": ["naive (point estimate)", "naive (point estimate)", "camo", "camo"],
                        "alpha": [0.1, 0.9, 0.1, 0.9], "coverage": [0.1, 0.1, 0.1, 0.8]})
    cov_ax = calibration.plot_coverage(cov).axes[0]
    naive = to_hex(style.method_style("naive").color)
    assert _line_colors(a)["naive"] == _line_colors(b)["naive"] == naive
    assert _line_colors(cov_ax)["naive (point estimate)"] == naive
    bar = next(c for c in bars.containers if c.get_label() == "naive").patches[0]
    assert to_hex(bar.get_facecolor()) == naive
    assert _line_colors(a)["camo"] == _line_colors(cov_ax)["camo"] != naive
    methods = _line_colors(b)
    assert len(set(methods.values())) == len(methods)  # five methods, five colours


def test_baselines_are_grey_and_unknown_names_deterministic():
    for name in ("naive", "nominal", "oracle", "majority"):
        st = style.method_style(name)
        r, g, b = (int(to_hex(st.color)[i:i + 2], 16) for i in (1, 3, 5))
        assert st.baseline and r == g == b, name  # grey or black
    markers = {style.method_style(n).marker for n in ("naive", "nominal", "oracle", "majority")}
    assert len(markers) == 4
    assert style.method_style("my-new-method") == style.method_style("my-new-method")
    assert not style.method_style("my-new-method").baseline
    assert style.method_order(["naive", "npe", "oracle", "camo"]) == ["camo", "npe", "naive", "oracle"]
    with pytest.raises(TypeError, match="^name:"):
        style.method_style(3)


def test_task_axes_have_integer_ticks_only():
    for xs in ([1, 2, 3], list(range(1, 26))):
        ax = style.plot_lines(_tidy(["camo", "naive"], xs, seeds=2))
        ticks = [t for t in ax.get_xticks() if ax.get_xlim()[0] <= t <= ax.get_xlim()[1]]
        assert ticks and all(float(t).is_integer() for t in ticks), ticks


def test_log_axis_only_with_two_budgets(tmp_path):
    one = _tidy(["camo", "naive"], [500], x="budget")
    assert style.plot_lines(one, x="budget", logx=True).get_xscale() == "linear"
    two = _tidy(["camo", "naive"], [100, 1000], x="budget")
    ax = style.plot_lines(two, x="budget", logx=True)
    assert ax.get_xscale() == "log" and sorted(ax.get_xticks()) == [100, 1000]
    # compare's figures: one budget -> no error-vs-budget figure, wall time as bars
    rows = [{"method": m, "budget": 500, "seed": s, "n_tasks": k, "metric": metric, "value": 1.0 + s + k}
            for m in ("camo", "naive") for s in range(2) for k in (1, 2)
            for metric in ("cartesian_error_mm", "limit_error_deg", "wall_time")]
    paths = compare.make_figures(pd.DataFrame(rows), tmp_path)
    assert sorted(p.name for p in paths) == ["error_vs_tasks.png", "wall_time.png"]
    assert not (tmp_path / "error_vs_budget.png").exists()
    more = pd.DataFrame(rows + [{**r, "budget": 2000} for r in rows])
    assert "error_vs_budget.png" in {p.name for p in compare.make_figures(more, tmp_path / "two")}


def test_legend_title_names_the_interval():
    ax = style.plot_lines(_tidy(["camo", "naive"], [1, 2], seeds=2))
    title = ax.get_legend().get_title().get_text()
    assert "95% CI of the mean" in title and "over 2 runs" in title and "Student t" in title
    assert style.band_label([3, 5]).endswith("over 3–5 runs (Student t)")
    assert "no interval" in style.band_label(1)
    bars = style.plot_bars(_tidy(["camo", "naive"], [1], seeds=4))
    assert "95% CI of the mean over 4 runs" in bars.get_xlabel()


def test_robust_scale_clips_a_dwarfing_baseline():
    df = _tidy(["camo", "abc-smc", "naive"], [1, 2, 3], seeds=2, scale={"camo": 100, "abc-smc": 150,
                                                                        "naive": 250_000})
    ax = style.plot_lines(df)
    methods_top = df[df.method != "naive"]["value"].max()
    assert ax.get_ylim()[1] < 3 * methods_top  # the methods fill the axis
    texts = " ".join(t.get_text() for t in ax.texts)
    assert "naive off scale" in texts
    assert "camo" not in texts
    raw = style.plot_lines(df, robust=False)
    assert raw.get_ylim()[1] > 200_000  # without it the baseline flattens every method
    # no clipping when nothing dwarfs
    calm = style.plot_lines(_tidy(["camo", "naive"], [1, 2], scale={"naive": 200}))
    assert not calm.texts
    bars = style.plot_bars(df[df.n_tasks == 3])
    assert bars.get_ylim()[1] < 3 * methods_top and any("off scale" in t.get_text() for t in bars.texts)
    with pytest.raises(ValueError, match="^factor:"):
        style.robust_ylim(ax, {}, factor=1)


def test_demo_out_path_is_a_file_or_a_directory(tmp_path):
    assert demo.figure_path(tmp_path / "demo.png") == tmp_path / "demo.png"
    assert demo.figure_path(tmp_path / "figs") == tmp_path / "figs" / "demo.png"
    with pytest.raises(ValueError, match="^--out:"):
        demo.figure_path(tmp_path / "demo.pdf")
    assert len({demo.REACHED_COLOR, demo.NOT_REACHED_COLOR, demo.LIMIT_COLOR}) == 3


def test_save_figure_writes_a_png_atomically(tmp_path):
    fig, axes = style.new_figure(1, 2)
    axes[0, 0].plot([0, 1])
    path = style.save_figure(fig, tmp_path / "sub" / "f.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [p.name for p in path.parent.iterdir()] == ["f.png"]


def test_demo_writes_the_file_it_is_given_with_labelled_axes(tmp_path, monkeypatch):
    import argparse

    drawn = []
    make = demo.make_figure
    monkeypatch.setattr(demo, "make_figure", lambda *a: drawn.append(make(*a)) or drawn[-1])
    out = tmp_path / "figs" / "demo.png"
    assert demo.main(argparse.Namespace(model="panda", batch=8, seed=0, out=str(out))) == 0
    assert out.is_file() and out.read_bytes()[:4] == b"\x89PNG"
    ax3d = next(a for a in drawn[0].axes if a.name == "3d")
    assert (ax3d.get_xlabel(), ax3d.get_ylabel(), ax3d.get_zlabel()) == ("x [m]", "y [m]", "z [m]")
    colors = {to_hex(ln.get_color()) for ln in ax3d.get_lines()}
    assert colors <= {to_hex(demo.REACHED_COLOR), to_hex(demo.NOT_REACHED_COLOR), "#000000"}
