"""Metrics as data (issue 26): the catalog's list drives the scorer, every table and every figure.

A toy metric added to `camo_sbi.evaluation.catalog.METRICS` (with its score function, nothing
else) must reach compare's results.csv, its printed summary, its figures and its report, and
robustness's rows, table and figure, without any other edit.
"""

from __future__ import annotations

import pandas as pd
import pytest

from camo_sbi.diagnostics import report, style
from camo_sbi.evaluation import catalog
from camo_sbi.evaluation.catalog import Metric
from camo_sbi.experiments.cli import main

TOY = Metric("toy_score", "toy score of the estimate", "mm", "value", headline=True, group="toy",
             score=lambda s: 1.0 + float(abs(s.result.estimate).sum()))


@pytest.fixture
def toy(monkeypatch):
    """The catalog with the toy metric appended, and every figure's axis texts as they are saved."""
    monkeypatch.setattr(catalog, "METRICS", [*catalog.METRICS, TOY])
    drawn: list[str] = []
    save = style.save_figures

    def spy(fig, path, formats=("png",), **kw):
        drawn.extend(t for ax in fig.axes for t in (ax.get_title(), ax.get_ylabel()))
        return save(fig, path, formats, **kw)

    monkeypatch.setattr(style, "save_figures", spy)
    shown: list[list[str]] = []
    panels = report._xy_panels

    def report_spy(sub, metrics, *a, **kw):
        shown.append(list(metrics))
        return panels(sub, metrics, *a, **kw)

    monkeypatch.setattr(report, "_xy_panels", report_spy)
    return drawn, shown


def test_catalog_rejects_bad_metrics():
    with pytest.raises(ValueError, match="aggregate"):
        Metric("x", "x", "", "median")
    with pytest.raises(ValueError, match="name"):
        Metric("x", "x", "", "mean", per_joint=True)
    with pytest.raises(TypeError, match="score"):
        Metric("x", "x", "", "value", score=3)
    with pytest.raises(ValueError, match="name: unknown metric"):
        catalog.get("no_such_metric")
    family = catalog.get("limit_error_deg_panda_joint3")
    assert family.per_joint and family.row("panda_joint3") == "limit_error_deg_panda_joint3"
    assert catalog.find("limit_error_deg").name == "limit_error_deg"  # the mean, not the family
    assert style.metric_label("eq2_joint").endswith("[deg]")  # stored in radians, shown in degrees


def test_names_are_unique_and_headline_order_is_the_list_order():
    names = [m.name for m in catalog.METRICS]
    assert len(names) == len(set(names))
    assert catalog.headline() == [m.name for m in catalog.METRICS if m.headline and not m.per_joint]
    assert catalog.tagged("primary") == ["cartesian_error_mm"]


def test_a_metric_added_to_the_list_reaches_every_table_and_figure(toy, tmp_path, capsys):
    drawn, shown = toy
    out = tmp_path / "compare"
    assert main(["compare", "--model", "panda", "--methods", "naive", "--budgets", "20", "--seeds", "1",
                 "--tasks", "2", "--test-goals", "2", "--out", str(out)]) == 0
    df = pd.read_csv(out / "results.csv")
    toy_rows = df[df.metric == "toy_score"]
    assert set(toy_rows.method) == {"naive", "nominal", "oracle"} and set(toy_rows.n_tasks) == {1, 2}
    assert (toy_rows.value >= 1.0).all()
    assert "toy score" in capsys.readouterr().out  # the printed summary table (metrics in words)
    assert any("toy score of the estimate [mm]" in t for t in drawn)  # compare's figures
    assert shown and all("toy_score" in s for s in shown)  # the report's figure panels
    html = (out / "report.html").read_text()
    assert "toy score of the estimate [mm]" in html  # the report's table caption

    drawn.clear()
    rob = tmp_path / "robustness"
    assert main(["robustness", "--model", "panda", "--methods", "naive,oracle", "--seeds", "1", "--tasks", "2",
                 "--test-goals", "2", "--budget", "20", "--conditions", "clean", "--out", str(rob)]) == 0
    rdf = pd.read_csv(rob / "results.csv")
    assert set(rdf[rdf.metric == "toy_score"].method) == {"naive", "oracle"}
    # the one scorer there too: per-joint limit errors and the interval coverage
    assert {"limit_error_deg_panda_joint1", "coverage90", "cartesian_error_mm"} <= set(rdf.metric)
    assert "toy_score" in pd.read_csv(rob / "robustness.csv").columns
    assert any("toy score" in t for t in drawn)  # the robustness figure
