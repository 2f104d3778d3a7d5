"""How the limits read (issue 34, items 5-7): "exercised" compares the recorded extreme with the
estimate itself; every estimate sits beside the joint's observed range; a fallback carries a
dagger; the report's titles do not overlap and its bars are not clipped; a BVH channel out of
the model's range names the channel, the frame and the map entry and never suggests --degrees."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from camo_sbi.experiments.infer_limits import (
    EXERCISED_MARGIN_DEG,
    FALLBACK_MARK,
    OVERCONFIDENT_MARK,
    limits_table,
    wide_limits,
)
from camo_sbi.experiments.infer_report import reach_figure
from camo_sbi.inference.result import PosteriorResult
from camo_sbi.io.recordings import load_recording
from camo_sbi.io.schema import K_SIGMA
from camo_sbi.priors import BoxPrior
from camo_sbi.task import NoiseModel, Observation
from tests.test_infer_cli import DATA, JOINTS
from tests.test_infer_cli import sim as sim  # noqa: PLC0414 (the arm7 model fixture)

FORE = JOINTS.index("fore_roll")


def _task(sim, upper_deg: float, noise_deg: float = 0.0):
    """Two reaches; fore_roll's recorded extreme upward is ``upper_deg`` (the other joints hold)."""
    s = sim.start.double()
    obs = []
    for top in (upper_deg - 5.0, upper_deg):
        q = s.repeat(6, 1)
        q[:, FORE] = torch.linspace(0.0, math.radians(top), 6, dtype=torch.float64)
        obs.append(Observation(q[0].clone(), sim.forward_kinematics(q[-1]).double(), q, None))
    return SimpleNamespace(observations=tuple(obs), noise=NoiseModel(joint_deg=noise_deg), name="arm7",
                           prior=BoxPrior(sim.bounds, s))


def _posterior(sim, name: str, upper_deg: float, interval_from_deg: float, status: str = "ok"):
    """Draws whose fore_roll upper bound spans [interval_from_deg, upper_deg + 10], estimate upper_deg."""
    b = sim.bounds.double().numpy()
    est = b.reshape(-1).copy()
    k = 2 * FORE + 1
    est[k] = math.radians(upper_deg)
    samples = np.repeat(est[None], 200, axis=0)
    samples[:, k] = np.radians(np.linspace(interval_from_deg, upper_deg + 10.0, 200))
    return PosteriorResult(name, samples, None, est, 100, 0.1, 2, status=status)


def _row(table, method, bound="upper"):
    t = table[(table.method == method) & (table.joint == "fore_roll") & (table.bound == bound)]
    return t.iloc[0]


def test_a_wide_interval_from_the_observed_extreme_is_not_exercised(sim):
    """The issue's case: forearm upper estimated at 50.2 deg, the recorded angle never passed
    14.0 deg, the 90% interval begins at the observed extreme: NOT exercised (the old rule,
    "a reach within 4 sigma of the interval", passed it)."""
    task = _task(sim, 14.0)
    table = limits_table({"camo": _posterior(sim, "camo", 50.2, 11.5)}, sim, task)
    r = _row(table, "camo")
    assert r.lower_90_deg <= 14.0 <= r.upper_90_deg and r.estimate_deg == pytest.approx(50.2)
    assert r.exercised is not None and not r.exercised and r.reaches_at_bound == 0
    assert r.observed_max_deg == pytest.approx(14.0) and r.margin_deg == pytest.approx(EXERCISED_MARGIN_DEG, abs=1e-3)


@pytest.mark.parametrize("estimate, expected", [(15.9, True), (12.1, True), (16.3, False), (11.7, False)])
def test_exercised_means_within_the_margin_of_the_estimate(sim, estimate, expected):
    """Margin 2 deg (no noise): 14.0 recorded, an estimate 1.9 deg off is exercised, 2.3 deg off
    is not, on either side (an estimate short of the recorded extreme was passed by the data)."""
    table = limits_table({"camo": _posterior(sim, "camo", estimate, estimate - 1.0)}, sim, _task(sim, 14.0))
    assert bool(_row(table, "camo").exercised) is expected


def test_margin_adds_the_noise_allowance(sim):
    table = limits_table({"camo": _posterior(sim, "camo", 17.0, 16.0)}, sim, _task(sim, 14.0, noise_deg=0.5))
    r = _row(table, "camo")
    assert r.margin_deg == pytest.approx(EXERCISED_MARGIN_DEG + K_SIGMA * 0.5, abs=1e-4)
    assert bool(r.exercised) is True  # 3.0 deg off, within 2 + 4 x 0.5


def test_naive_is_the_observed_range_and_not_called_exercised(sim):
    """naive's bound is the recorded extreme itself: exercised by construction, which says
    nothing about a limit; its exercised is left empty and it is never starred."""
    from camo_sbi.inference.baselines import point_result

    task = _task(sim, 14.0)
    est = sim.bounds.double().numpy().reshape(-1).copy()
    est[2 * FORE + 1] = math.radians(14.0)
    table = limits_table({"naive": point_result("naive", est, 2, 0.0)}, sim, task)
    assert _row(table, "naive").exercised is None
    wide = wide_limits(table)
    assert "*" not in wide.loc["fore_roll", "naive"]
    assert wide.loc["fore_roll", "observed"] == "0.0 .. 14.0"


def test_wide_table_marks_a_fallback_with_a_dagger(sim):
    task = _task(sim, 14.0)
    res = {"camo": _posterior(sim, "camo", 15.0, 14.0),
           "abc-smc": _posterior(sim, "abc-smc", 50.2, 14.0, status="fallback: low effective sample size (ESS 5.1)")}
    wide = wide_limits(limits_table(res, sim, task))
    assert list(wide.columns) == ["observed", "camo", f"abc-smc {FALLBACK_MARK}"]
    assert wide.loc["fore_roll", "camo"].endswith("15.0")  # exercised: no star
    assert wide.loc["fore_roll", f"abc-smc {FALLBACK_MARK}"].endswith("50.2*")


def test_a_method_measured_over_confident_on_untouched_bounds_is_marked(sim):
    """limits.csv carries each method's measured coverage on untouched binding bounds and its
    verdict; the wide table marks the methods measured over-confident there, by the model's name."""
    from camo_sbi.diagnostics.verdicts import untouched_verdicts

    measured = {(r["model"], r["method"]): r for r in untouched_verdicts()}
    over = next(m for (model, m), r in measured.items() if model == "panda" and r["verdict"].startswith("over-"))
    task = _task(sim, 14.0)
    res = {"camo-js": _posterior(sim, "camo-js", 15.0, 14.0), over: _posterior(sim, over, 15.0, 14.0)}
    table = limits_table(res, sim, SimpleNamespace(**{**vars(task), "name": "panda"}))
    row = _row(table, over)
    assert row.untouched_calibration == measured[("panda", over)]["verdict"]
    assert row.untouched_coverage_90 == measured[("panda", over)]["coverage90"] < 0.85
    assert _row(table, "camo-js").untouched_calibration == "not measured on untouched bounds"
    assert list(wide_limits(table).columns) == ["observed", "camo-js", f"{over} {OVERCONFIDENT_MARK}"]
    # on a model not measured nothing is marked, and the measured models are named
    other = limits_table(res, sim, task)
    assert _row(other, over).untouched_calibration.startswith("not measured on this model (panda: over-confident")
    assert list(wide_limits(other).columns) == ["observed", "camo-js", over]


def _overlaps(boxes) -> list:
    return [(i, k) for i in range(len(boxes)) for k in range(i + 1, len(boxes)) if boxes[i].overlaps(boxes[k])]


def test_reach_figure_titles_do_not_overlap(sim):
    """Four methods, one with the issue's long fallback status: the panel titles (measured as
    rendered, in pixels) do not overlap, and the status is not in any title."""
    task = _task(sim, 14.0)
    long = "fallback: low effective sample size (ESS 5.1 of 100 particles, below 0.1 N); kept the prior's best"
    res = {m: _posterior(sim, m, 15.0, 14.0, status=long if m == "abc-smc" else "ok")
           for m in ("naive", "camo-seq", "abc-smc", "npe")}
    draws = {m: torch.as_tensor(r.samples[:3]) for m, r in res.items()}
    fig = reach_figure(sim, task.observations[1], res, draws)
    renderer = fig.canvas.get_renderer() if hasattr(fig.canvas, "get_renderer") else None
    if renderer is None:
        from matplotlib.backends.backend_agg import FigureCanvasAgg

        renderer = FigureCanvasAgg(fig).get_renderer()
    fig.draw_without_rendering()
    titles = [ax.title for ax in fig.axes if ax.get_title()]
    assert [t.get_text() for t in titles] == ["naive", "camo-seq", f"abc-smc {FALLBACK_MARK}", "npe"]
    boxes = [t.get_window_extent(renderer) for t in titles]
    assert not _overlaps(boxes)
    width = fig.bbox.width
    assert all(0 <= b.x0 and b.x1 <= width for b in boxes)  # inside the figure


def test_limits_figure_shows_every_range_unclipped(sim):
    """Each grey bar (the model's range), the recorded range and every estimate lie inside the x axis;
    no floating "not exercised" annotation (the legend says it)."""
    from camo_sbi.diagnostics.figures import plot_limits

    task = _task(sim, 14.0)
    table = limits_table({"camo": _posterior(sim, "camo", 50.2, 14.0)}, sim, task)
    b = np.degrees(sim.bounds.double().numpy())
    ranges = {j: (float(b[i, 0]), float(b[i, 1])) for i, j in enumerate(JOINTS)}
    fig = plot_limits(table, ranges)
    ax = fig.axes[0]
    lo, hi = ax.get_xlim()
    assert lo < b[:, 0].min() and hi > b[:, 1].max()
    assert not [t for t in ax.texts if "not exercised" in t.get_text()]
    labels = [t.get_text() for t in fig.legends[0].get_texts()] if fig.legends else \
        [t.get_text() for t in ax.get_legend().get_texts()]
    assert "not exercised (hollow)" in labels and "recorded range (functional)" in labels


def test_limits_figure_legend_fits_the_figure(sim):
    """Seven legend entries (four methods, model range, recorded range, not exercised): the
    legend, as rendered, lies inside the figure (it was once cut on both sides)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from camo_sbi.diagnostics.figures import plot_limits

    task = _task(sim, 14.0)
    res = {m: _posterior(sim, m, 15.0, 14.0) for m in ("camo", "naive", "nominal", "abc-smc")}
    b = np.degrees(sim.bounds.double().numpy())
    fig = plot_limits(limits_table(res, sim, task), {j: (float(b[i, 0]), float(b[i, 1])) for i, j in enumerate(JOINTS)})
    renderer = FigureCanvasAgg(fig).get_renderer()
    fig.draw_without_rendering()
    box = fig.legends[0].get_window_extent(renderer)
    assert len(fig.legends[0].get_texts()) == 7
    assert box.x0 >= 0 and box.x1 <= fig.bbox.width and box.y0 >= 0


# ----------------------------------------------------------------------------- BVH out of range


def test_bvh_channel_out_of_range_names_channel_frame_and_entry(sim, tmp_path):
    from camo_sbi.experiments.models import load_limits
    from camo_sbi.experiments.simulate import simulate_recordings
    from tests.test_mocap import write_bvh

    theta = load_limits(DATA / "arm7_limits.json", sim).reshape(-1)
    obs = tuple(Observation(o.start, sim.forward_kinematics(o.q[-1]).double(), o.q, None)
                for o in simulate_recordings(sim, theta, 2, seed=6))
    bvh, mapping = write_bvh(tmp_path / "arm.bvh", obs, list(sim.joint_names), signs=[1] * 7, offsets=[0.0] * 7)
    mapping["joints"]["elbow"]["offset_deg"] = 200.0  # a wrong entry: every elbow angle 200 deg off
    bad = tmp_path / "map.json"
    bad.write_text(json.dumps(mapping))
    with pytest.raises(ValueError) as err:
        load_recording(bvh, sim, goal="final", bvh_map=bad, resample=None)
    msg = str(err.value)
    assert msg.startswith(f"{bvh}: frame 0: BVH channel B3.Yrotation = ")
    assert f"--bvh-map {bad} entry 'elbow' (sign 1, offset_deg 200: its channel" in msg
    assert "degrees" not in msg.replace(" deg", "") and "--degrees" not in msg
    with pytest.raises(ValueError, match=r"^--degrees: a BVH file's channels are in degrees"):
        load_recording(bvh, sim, goal="final", bvh_map=bvh.with_suffix(".json"), resample=None, degrees=True)
