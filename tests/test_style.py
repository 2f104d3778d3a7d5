"""The shared figure style: colours per method, integer task ticks, log axes, CI captions, robust scale."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from matplotlib.colors import to_hex

from camo_sbi.diagnostics import calibration, plot_primitives, style
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
    a = plot_primitives.plot_lines(_tidy(["camo", "naive", "abc-smc"], [1, 2, 3]))
    b = plot_primitives.plot_lines(_tidy(["camo-js", "camo-cs", "camo-hull", "naive", "oracle"], [1, 2, 3]))
    bars = plot_primitives.plot_bars(_tidy(["naive", "npe"], [1]))
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
        ax = plot_primitives.plot_lines(_tidy(["camo", "naive"], xs, seeds=2))
        ticks = [t for t in ax.get_xticks() if ax.get_xlim()[0] <= t <= ax.get_xlim()[1]]
        assert ticks and all(float(t).is_integer() for t in ticks), ticks


def test_log_axis_only_with_two_budgets(tmp_path):
    one = _tidy(["camo", "naive"], [500], x="budget")
    assert plot_primitives.plot_lines(one, x="budget", logx=True).get_xscale() == "linear"
    two = _tidy(["camo", "naive"], [100, 1000], x="budget")
    ax = plot_primitives.plot_lines(two, x="budget", logx=True)
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
    ax = plot_primitives.plot_lines(_tidy(["camo", "naive"], [1, 2], seeds=6))
    title = ax.get_legend().get_title().get_text()
    assert "95% CI of the mean" in title and "over 6 runs" in title and "Student t" in title
    assert style.band_label([5, 7]).endswith("over 5–7 runs (Student t)")
    assert "no interval" in style.band_label(1)
    bars = plot_primitives.plot_bars(_tidy(["camo", "naive"], [1], seeds=5))
    assert "95% CI of the mean over 5 runs" in bars.get_xlabel()
    few = plot_primitives.plot_lines(_tidy(["camo", "naive"], [1, 2], seeds=2)).get_legend().get_title().get_text()
    assert "each of 2 runs" in few and "no CI band" in few and "Student" not in few
    assert "each of 3–4 runs" in style.band_label([3, 4])


def _bands(ax) -> int:
    from matplotlib.collections import PolyCollection

    return sum(isinstance(c, PolyCollection) for c in ax.collections)


def _dots(ax) -> np.ndarray:
    from matplotlib.collections import PathCollection

    return np.concatenate([c.get_offsets() for c in ax.collections if isinstance(c, PathCollection)]
                          or [np.empty((0, 2))])


@pytest.mark.parametrize("seeds", [2, 4])
def test_a_figure_of_few_seeds_draws_its_points_not_bands(seeds):
    """Before: 2 seeds drew a Student-t band (t with 1 dof: 12.7 sd wide, below 0 for errors)."""
    df = _tidy(["camo", "npe", "naive"], [1, 2, 3], seeds=seeds)
    ax = plot_primitives.plot_lines(df)
    assert _bands(ax) == 0  # no fill_between
    dots = _dots(ax)
    assert len(dots) == len(df)  # every run is drawn
    np.testing.assert_allclose(np.sort(dots[:, 1]), np.sort(df["value"].to_numpy()))
    # jittered: no two dots of one method at one x share an x position
    assert len(np.unique(np.round(dots[:, 0], 9))) == len(dots)
    assert np.all(np.abs(dots[:, 0] - np.round(dots[:, 0])) < 0.5)  # still next to their x
    camo = next(ln for ln in ax.get_lines() if ln.get_label() == "camo")  # the line is the mean
    np.testing.assert_allclose(camo.get_ydata(), df[df.method == "camo"].groupby("n_tasks")["value"].mean())
    bars = plot_primitives.plot_bars(df[df.n_tasks == 3])
    assert all(c.errorbar is None for c in bars.containers if hasattr(c, "errorbar"))
    assert not [ln for ln in bars.get_lines() if ln.get_label().startswith("_") and len(ln.get_xdata()) == 2
                and ln.get_xdata()[0] == ln.get_xdata()[1]]  # no error-bar segments
    assert len(_dots(bars)) == 3 * seeds
    many = plot_primitives.plot_lines(_tidy(["camo", "npe"], [1, 2, 3], seeds=5))
    assert _bands(many) == 2 and len(_dots(many)) == 0  # 5 seeds: bands, as before


def test_cells_of_few_values_show_a_range_not_an_interval():
    """Before: '218 ± 1,269' from 2 seeds; now the mean and the range."""
    assert style.cell_text([10.0, 426.0]) == "218 (10–426)"
    assert "±" not in style.cell_text([1.0, 2.0, 3.0, 4.0])
    assert style.cell_text([-3.0, 5.0]) == "1 (-3 to 5)"
    assert style.cell_text([2.5]) == "2.5" and style.cell_text([7.0, 7.0]) == "7" and style.cell_text([]) == "–"
    five = [1.0, 2.0, 3.0, 4.0, 5.0]
    m, half = style.mean_ci(five)
    assert style.cell_text(five) == f"3 ± {style.number(half, 2)}"
    assert "no confidence interval" in style.cell_rule(2, "seeds") and "min–max" in style.cell_rule(2)
    assert "Student t" in style.cell_rule(5) and "±" in style.cell_rule([5, 6])
    assert style.few_runs([2, 8]) and not style.few_runs([5, 8]) and not style.few_runs(5)


def test_radian_metrics_are_shown_in_degrees():
    df = pd.DataFrame({"metric": ["reference_joint", "cartesian_error_mm"], "value": [np.pi, 3.0]})
    shown = style.display_metric(df)
    np.testing.assert_allclose(shown["value"], [180.0, 3.0])
    assert df["value"].iloc[0] == np.pi  # the input (the file's radians) is untouched
    assert style.metric_label("reference_joint").endswith("[deg]")
    assert style.metric_label("eq2_joint").endswith("[deg]")
    from camo_sbi.evaluation import catalog

    assert not any(style.metric_label(m.row("j1")).endswith("[rad]") for m in catalog.METRICS)
    assert style.metric_label("limit_error_deg_panda_joint2") == "|limit error| of panda_joint2 [deg]"


def _texts_pt(fig) -> list[float]:
    return [t.get_fontsize() for t in fig.findobj(lambda a: hasattr(a, "get_fontsize") and hasattr(a, "get_text"))
            if t.get_text().strip() and t.get_visible()]


def test_svg_and_pdf_are_written_and_parse(tmp_path):
    import xml.etree.ElementTree as ET

    from pypdf import PdfReader

    df = pd.DataFrame([{"method": m, "budget": 500, "seed": s, "n_tasks": k, "metric": metric, "value": 1.0 + s + k}
                       for m in ("camo", "naive") for s in range(2) for k in (1, 2)
                       for metric in ("cartesian_error_mm", "limit_error_deg", "wall_time")])
    paths = compare.make_figures(df, tmp_path, formats=("pdf", "svg"))
    assert sorted(p.name for p in paths) == ["error_vs_tasks.pdf", "error_vs_tasks.svg", "wall_time.pdf",
                                             "wall_time.svg"]
    assert not list(tmp_path.glob("*.png"))
    svg = ET.parse(tmp_path / "error_vs_tasks.svg").getroot()
    assert svg.tag.endswith("svg")
    width_in = float(svg.get("width").removesuffix("pt")) / 72
    assert width_in == pytest.approx(style.DOUBLE_COLUMN)  # the paper's double-column width
    texts = [t for t in svg.iter() if t.tag.endswith("text")]  # svg.fonttype none: text stays text
    assert any("observed tasks" in "".join(t.itertext()) for t in texts)
    sizes = [float(m) for t in texts for m in __import__("re").findall(r"font-size:\s*([\d.]+)px|font:\s*([\d.]+)px",
                                                                        t.get("style", ""))[0] if m]
    assert sizes and min(sizes) >= style.MIN_FONT_PT  # px = pt at svg's 72 dpi
    reader = PdfReader(tmp_path / "wall_time.pdf")
    box = reader.pages[0].mediabox
    assert float(box.width) / 72 == pytest.approx(style.SINGLE_COLUMN)
    assert "Wall time" in reader.pages[0].extract_text()
    with pytest.raises(ValueError, match="^--figure-format:"):
        style.parse_figure_formats("png,eps")
    assert style.parse_figure_formats("PNG, pdf,png") == ("png", "pdf")


@pytest.mark.parametrize("maker", ["compare", "manipulator", "coverage"])
def test_paper_figures_have_no_text_below_8_pt(maker, tmp_path):
    from camo_sbi.experiments import reproduce_panda

    seen = []
    orig = style.save_figures

    def spy(fig, path, formats=("png",), dpi=style.PNG_DPI):
        seen.append((fig.get_figwidth(), _texts_pt(fig)))
        return orig(fig, path, formats, dpi)

    rows = [{"method": m, "run": s, "budget": 500, "seed": s, "n_tasks": k, "metric": metric,
             "value": 1.0 + s + k} for m in ("camo", "naive", "nominal") for s in range(3) for k in (1, 2)
            for metric in ("cartesian_error_mm", "limit_error_deg", "wall_time", "reference_cartesian",
                           "joint_error_deg", "reference_joint", "limit_error_binding_deg")]
    import unittest.mock as mock

    with mock.patch.object(style, "save_figures", spy):
        if maker == "compare":
            compare.make_figures(pd.DataFrame(rows), tmp_path)
        elif maker == "manipulator":
            reproduce_panda.make_figures(pd.DataFrame(rows), tmp_path)
        else:
            cov = pd.DataFrame({"method": ["camo"] * 2, "alpha": [0.1, 0.9], "coverage": [0.1, 0.8]})
            fig = calibration.plot_coverage(cov)
            seen.append((fig.get_figwidth(), _texts_pt(fig)))
    assert seen
    for width, sizes in seen:
        assert width in (style.SINGLE_COLUMN, style.DOUBLE_COLUMN)
        assert sizes and min(sizes) >= style.MIN_FONT_PT


def test_robust_scale_clips_a_dwarfing_baseline():
    df = _tidy(["camo", "abc-smc", "naive"], [1, 2, 3], seeds=2, scale={"camo": 100, "abc-smc": 150,
                                                                        "naive": 250_000})
    ax = plot_primitives.plot_lines(df)
    methods_top = df[df.method != "naive"]["value"].max()
    assert ax.get_ylim()[1] < 3 * methods_top  # the methods fill the axis
    texts = " ".join(t.get_text() for t in ax.texts)
    assert "naive off scale" in texts
    assert "camo" not in texts
    raw = plot_primitives.plot_lines(df, robust=False)
    assert raw.get_ylim()[1] > 200_000  # without it the baseline flattens every method
    # no clipping when nothing dwarfs
    calm = plot_primitives.plot_lines(_tidy(["camo", "naive"], [1, 2], scale={"naive": 200}))
    assert not calm.texts
    bars = plot_primitives.plot_bars(df[df.n_tasks == 3])
    assert bars.get_ylim()[1] < 3 * methods_top and any("off scale" in t.get_text() for t in bars.texts)
    with pytest.raises(ValueError, match="^factor:"):
        plot_primitives.robust_ylim(ax, {}, factor=1)


def test_demo_out_path_is_a_file_or_a_directory(tmp_path):
    assert demo.figure_path(tmp_path / "demo.png") == tmp_path / "demo.png"
    assert demo.figure_path(tmp_path / "figs") == tmp_path / "figs" / "demo.png"
    with pytest.raises(ValueError, match="^--out:"):
        demo.figure_path(tmp_path / "demo.pdf")  # the format is --figure-format's
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
    assert demo.main(argparse.Namespace(model="panda", batch=8, seed=0, out=str(out), figure_format="png,svg")) == 0
    assert out.is_file() and out.read_bytes()[:4] == b"\x89PNG"
    assert out.with_suffix(".svg").read_text().lstrip().startswith("<?xml")
    ax3d = next(a for a in drawn[0].axes if a.name == "3d")
    assert (ax3d.get_xlabel(), ax3d.get_ylabel(), ax3d.get_zlabel()) == ("x [m]", "y [m]", "z [m]")
    colors = {to_hex(ln.get_color()) for ln in ax3d.get_lines()}
    assert colors <= {to_hex(demo.REACHED_COLOR), to_hex(demo.NOT_REACHED_COLOR), "#000000"}
