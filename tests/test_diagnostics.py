"""Diagnostics: arviz conversion + netCDF, calibration (coverage / SBC / C2ST), HTML report.

Everything is built from fakes here (PosteriorResult, BoxPrior, results.csv), so these
tests do not depend on the simulators or inference methods. Runs in well under 60 s.
"""

from __future__ import annotations

import base64
import dataclasses
import json
import re
import warnings

import arviz as az
import numpy as np
import pandas as pd
import pytest
from matplotlib.figure import Figure

from camo_sbi.diagnostics import arviz_io, calibration, report
from camo_sbi.inference.result import PosteriorResult
from camo_sbi.priors import BoxPrior

JOINTS = ["shoulder", "elbow", "wrist"]


# --------------------------------------------------------------------------- fixtures


@pytest.fixture
def prior() -> BoxPrior:
    bounds = np.array([[-2.0, 2.0], [-1.0, 1.5], [-3.0, 0.5]])
    start = np.array([0.1, 0.2, -1.0])
    return BoxPrior(bounds, start, fixed={2: (-2.0, 0.0)})  # wrist known: zero-width coordinates


def _informative_result(prior: BoxPrior, truth: np.ndarray, *, method="camo", n=2000, seed=0,
                        weighted=False, width=0.05) -> PosteriorResult:
    """Samples concentrated around ``truth`` (fixed coordinates exact)."""
    rng = np.random.default_rng(seed)
    s = truth + width * rng.standard_normal((n, truth.size))
    s[:, ~prior.free_mask.numpy()] = truth[~prior.free_mask.numpy()]
    w = rng.random(n) if weighted else None
    return PosteriorResult(method, s, w, truth.copy(), n_simulations=5000, wall_time=1.5, n_tasks=4,
                           extras={"budget": 5000, "epsilon": 0.2})


@pytest.fixture
def truth(prior) -> np.ndarray:
    return prior.sample(1, 123).numpy()[0]


# --------------------------------------------------------------------------- conversion


def test_to_inference_data_keeps_values_names_and_metadata(prior, truth):
    r = _informative_result(prior, truth)
    obs = {"trajectories": np.zeros((4, 20, 3)), "goals": np.ones((4, 3))}
    idata = arviz_io.to_inference_data(
        r, JOINTS, seed=0, prior=prior, prior_draws=300, true_theta=truth, observed=obs,
        observed_dims={"trajectories": ["task", "time", "joint"]}, attrs={"task": "reach", "subject": "s0"})
    assert set(idata.groups()) == {"posterior", "prior", "observed_data", "constant_data"}
    lim = idata.posterior["limits"]
    assert lim.dims == ("chain", "draw", "joint", "bound")
    # independent draws: a subset of arviz_draw_count(N) distinct samples in 2 chains (plain
    # az.summary wants 2 for r_hat; at most S log10 S effective draws <= N)
    m = arviz_io.arviz_draw_count(len(r.samples))
    assert lim.sizes["chain"] == 2 and lim.sizes["draw"] == m // 2 and 500 < m * np.log10(m) <= len(r.samples)
    assert list(lim["joint"].values) == JOINTS and list(lim["bound"].values) == ["lower", "upper"]
    # exact values, layout [lo_1, hi_1, ...] -> (joint, bound)
    rows = lim.values.reshape(m, -1)
    pos = [int(np.flatnonzero((r.samples == row).all(axis=1))[0]) for row in rows]
    assert len(set(pos)) == m
    np.testing.assert_array_equal(lim.sel(joint="elbow", bound="upper").values.reshape(-1), r.samples[pos, 3])
    np.testing.assert_array_equal(idata.constant_data["weighted_samples"].values.reshape(len(r.samples), -1),
                                  r.samples)
    np.testing.assert_array_equal(idata.constant_data["weights"].values, np.full(len(r.samples), 1 / len(r.samples)))
    np.testing.assert_array_equal(idata.constant_data["true_limits"].values.reshape(-1), truth)
    np.testing.assert_array_equal(idata.constant_data["estimate"].values.reshape(-1), r.estimate)
    assert idata.prior["limits"].sizes["draw"] == 300
    assert bool(prior.contains(idata.prior["limits"].values[0].reshape(300, -1)).all())
    assert list(idata.observed_data["trajectories"]["joint"].values) == JOINTS
    a = idata.posterior.attrs
    assert (a["method"], a["n_simulations"], a["n_tasks"], a["budget"], a["units"]) == ("camo", 5000, 4, 5000, "rad")
    assert a["wall_time"] == 1.5 and a["resampled"] == 0 and a["extra_epsilon"] == 0.2
    assert (a["task"], a["subject"]) == ("reach", "s0")


def test_degrees_convert_limits_truth_and_prior(prior, truth):
    r = _informative_result(prior, truth)
    rad = arviz_io.to_inference_data(r, JOINTS, seed=1, prior=prior, true_theta=truth)
    deg = arviz_io.to_inference_data(r, JOINTS, seed=1, prior=prior, true_theta=truth, units="deg")
    np.testing.assert_allclose(deg.posterior["limits"].values, np.degrees(rad.posterior["limits"].values))
    np.testing.assert_allclose(deg.prior["limits"].values, np.degrees(rad.prior["limits"].values))
    np.testing.assert_allclose(deg.constant_data["true_limits"].values, np.degrees(truth.reshape(3, 2)))
    assert deg.posterior.attrs["units"] == "deg"


def test_weighted_samples_resampled_reproducibly(prior, truth):
    r = _informative_result(prior, truth, weighted=True, n=4000, width=0.3)
    a = arviz_io.to_inference_data(r, JOINTS, seed=7)
    b = arviz_io.to_inference_data(r, JOINTS, seed=7)
    c = arviz_io.to_inference_data(r, JOINTS, seed=8)
    np.testing.assert_array_equal(a.posterior["limits"].values, b.posterior["limits"].values)
    assert not np.array_equal(a.posterior["limits"].values, c.posterior["limits"].values)
    assert a.posterior.attrs["resampled"] == 1 and a.posterior.attrs["resample_seed"] == 7
    assert a.posterior.attrs["weights_ess"] == pytest.approx(1 / np.sum(r.weights**2))
    # the posterior group: arviz_draw_count(Kish ESS) draws in 2 chains, each one of the samples
    m = arviz_io.arviz_draw_count(r.ess)
    assert a.posterior["limits"].shape[:2] == (2, m // 2) and m * np.log10(m) <= r.ess
    assert np.isin(a.posterior["limits"].values.reshape(m, -1)[:, 0], r.samples[:, 0]).all()
    # the samples and weights themselves are stored; the toolkit's draws resample them
    np.testing.assert_allclose(a.constant_data["weights"].values, r.weights)
    draws = arviz_io.limit_draws(a)[0].reshape(4000, -1)
    assert np.isin(draws[:, 0], r.samples[:, 0]).all()
    # tolerance: weighted mean preserved within 0.1 posterior sd (resampling SE ~ sd/sqrt(4000) = 0.016 sd)
    sd = r.samples.std(axis=0)
    free = sd > 0
    assert np.all(np.abs(draws.mean(axis=0) - r.mean())[free] < 0.1 * sd[free])
    np.testing.assert_allclose(draws.mean(axis=0)[~free], r.mean()[~free], atol=1e-12)


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # plain az.summary on zero-variance (fixed) limits
def test_netcdf_roundtrip_loads_with_plain_arviz(tmp_path, prior, truth):
    r = _informative_result(prior, truth, weighted=True)
    idata = arviz_io.to_inference_data(r, JOINTS, seed=3, prior=prior, prior_draws=200, true_theta=truth,
                                       observed={"goals": np.ones((4, 3))})
    path = tmp_path / "camo.nc"
    assert arviz_io.save_netcdf(idata, path) == path
    assert [p.name for p in tmp_path.iterdir()] == ["camo.nc"]  # no temp file left behind
    plain = az.from_netcdf(str(path))
    np.testing.assert_array_equal(plain.posterior["limits"].values, idata.posterior["limits"].values)
    np.testing.assert_array_equal(plain.constant_data["true_limits"].values, truth.reshape(3, 2))
    assert plain.posterior.attrs["method"] == "camo" and plain.posterior.attrs["resample_seed"] == 3
    s = az.summary(plain)
    for j in JOINTS:
        for b in ("lower", "upper"):
            assert f"limits[{j}, {b}]" in s.index
    loaded = arviz_io.load_netcdf(path)
    np.testing.assert_array_equal(loaded.prior["limits"].values, idata.prior["limits"].values)
    arviz_io.save_netcdf(loaded, path)  # overwrite an existing file (atomically replaced)
    assert az.from_netcdf(str(path)).posterior.sizes["draw"] == idata.posterior.sizes["draw"]


def test_summary_truth_position_and_width(prior, truth):
    r = _informative_result(prior, truth, width=0.02)
    idata = arviz_io.to_inference_data(r, JOINTS, seed=0, prior=prior, true_theta=truth)
    s = arviz_io.summary(idata)
    assert "r_hat" not in s.columns and {"mean", "sd", "hdi_3%", "hdi_97%", "ess_bulk", "truth"} <= set(s.columns)
    assert s.loc["limits[wrist, lower]", "sd"] == 0  # fixed coordinate: zero variance is fine
    tp = arviz_io.truth_position(idata)
    assert tp.loc[("wrist", "lower"), "zero_width"] and tp.loc[("wrist", "lower"), "quantile"] == 0.5
    assert tp["quantile"].between(0.02, 0.98).all()  # truth at the centre of these fake posteriors
    w = arviz_io.posterior_width(idata)
    # informative posterior: 94% HDI ~ 2*1.88*0.02 = 0.075 rad, far below the prior width
    assert (w.loc[["shoulder", "elbow"], "relative_width"] < 0.2).all()
    assert w.loc["wrist", "relative_width"].isna().all()
    # a posterior equal to the prior is uninformed: relative width ~ 1 (tolerance 0.1)
    flat = PosteriorResult("prior", prior.sample(4000, 5).numpy(), None, truth, 0, 0.0, 0)
    wf = arviz_io.posterior_width(arviz_io.to_inference_data(flat, JOINTS, seed=0, prior=prior))
    np.testing.assert_allclose(wf.loc[["shoulder", "elbow"], "relative_width"], 1.0, atol=0.1)


def test_plots_return_figures(prior, truth):
    a = arviz_io.to_inference_data(_informative_result(prior, truth), JOINTS, seed=0, true_theta=truth)
    b = arviz_io.to_inference_data(_informative_result(prior, truth, method="npe", seed=1, weighted=True),
                                   JOINTS, seed=0, true_theta=truth)
    for fig in (arviz_io.plot_posterior(a), arviz_io.plot_pair(a, joints=["shoulder", "elbow"]),
                arviz_io.plot_forest([a, b], ["camo", "npe"]), arviz_io.plot_posterior(a, joints=["wrist"])):
        assert isinstance(fig, Figure) and fig.axes
        fig.clear()


def test_plot_posterior_shows_mean_hdi_and_truth(prior, truth):
    """Each free limit's panel carries the mean of the draws (text), the 94% HDI of
    `posterior_width` (the thick bar, same numbers) and the truth; in degrees."""
    for weighted in (False, True):
        idata = arviz_io.to_inference_data(_informative_result(prior, truth, weighted=weighted), JOINTS,
                                           seed=0, true_theta=truth, prior=prior)
        draws = np.degrees(arviz_io.limit_draws(idata)[0])
        width = arviz_io.posterior_width(idata)
        fig = arviz_io.plot_posterior(idata)
        axes = np.asarray(fig.axes).reshape(len(JOINTS), 2)
        for ji, joint in enumerate(JOINTS):
            for c, bound in enumerate(arviz_io.BOUNDS):
                ax, x = axes[ji, c], draws[:, ji, c]
                dashed = [ln for ln in ax.lines if ln.get_linestyle() == "--"]
                assert len(dashed) == 1 and np.isclose(dashed[0].get_xdata()[0], np.degrees(truth[2 * ji + c]))
                if np.ptp(x) == 0:  # the fixed wrist: one line at its value, named in the title
                    assert "fixed" in ax.get_title()
                    continue
                est = [t for t in ax.texts if t.get_gid() == "point-estimate"]
                assert len(est) == 1 and est[0].get_text() == f"mean={x.mean():.3g}"
                bar = [ln for ln in ax.lines if ln.get_gid() == "hdi"]
                assert len(bar) == 1
                np.testing.assert_allclose(bar[0].get_xdata(),
                                           np.degrees(width.loc[(joint, bound), ["hdi_lower", "hdi_upper"]]
                                                      .to_numpy(dtype=float)))
                assert any(t.get_text() == "94% HDI" for t in ax.texts)
                assert ax.get_xlabel() == "limit [deg]"
        assert fig.get_suptitle() == "camo: joint limits, 94% HDI"
        fig.clear()


def test_compare_marginals_wasserstein(prior, truth):
    a = _informative_result(prior, truth, n=3000, seed=0)
    shifted = PosteriorResult("shift", a.samples + 0.1, None, a.estimate + 0.1, 0, 0.0, 4)
    d = arviz_io.compare_marginals(a, shifted, joint_names=JOINTS)
    np.testing.assert_allclose(d["wasserstein"], 0.1, atol=1e-9)
    same = arviz_io.compare_marginals(a, a)
    assert (same["wasserstein"] == 0).all() and list(same.index.get_level_values(0)[::2]) == [
        "joint_0", "joint_1", "joint_2"]
    # weights are honoured: weight only samples below the truth -> shifted lower
    w = (a.samples[:, 0] < truth[0]).astype(float)
    lowered = PosteriorResult("w", a.samples, w, a.estimate, 0, 0.0, 4)
    assert arviz_io.compare_marginals(a, lowered).iloc[0, 0] > 0.02


def test_arviz_io_bad_inputs(prior, truth, tmp_path):
    r = _informative_result(prior, truth)
    with pytest.raises(ValueError, match="^joint_names"):
        arviz_io.to_inference_data(r, ["a", "b"], seed=0)
    with pytest.raises(ValueError, match="^joint_names"):
        arviz_io.to_inference_data(r, ["a", "a", "b"], seed=0)
    with pytest.raises(TypeError, match="^joint_names"):
        arviz_io.to_inference_data(r, "abc", seed=0)
    with pytest.raises(TypeError, match="^result"):
        arviz_io.to_inference_data(r.samples, JOINTS, seed=0)
    with pytest.raises(ValueError, match="^units"):
        arviz_io.to_inference_data(r, JOINTS, seed=0, units="grad")
    with pytest.raises(TypeError, match="^seed"):
        arviz_io.to_inference_data(r, JOINTS, seed=1.5)
    with pytest.raises(ValueError, match="^true_theta"):
        arviz_io.to_inference_data(r, JOINTS, seed=0, true_theta=truth[:4])
    with pytest.raises(ValueError, match="^true_theta"):
        arviz_io.to_inference_data(r, JOINTS, seed=0, true_theta=truth[::-1])  # lo > hi
    with pytest.raises(ValueError, match="^prior_draws"):
        arviz_io.to_inference_data(r, JOINTS, seed=0, prior=prior, prior_draws=0)
    with pytest.raises(TypeError, match="^observed"):
        arviz_io.to_inference_data(r, JOINTS, seed=0, observed=[1, 2])
    with pytest.raises(TypeError, match="^idata"):
        arviz_io.save_netcdf({"not": "idata"}, tmp_path / "x.nc")
    idata = arviz_io.to_inference_data(r, JOINTS, seed=0)
    with pytest.raises(ValueError, match="^path"):
        arviz_io.save_netcdf(idata, tmp_path / "missing_dir" / "x.nc")
    with pytest.raises(ValueError, match="^path"):
        arviz_io.load_netcdf(tmp_path / "nope.nc")
    with pytest.raises(ValueError, match="^idata"):
        arviz_io.truth_position(idata)  # no truth stored
    with pytest.raises(ValueError, match="^idata"):
        arviz_io.posterior_width(idata)  # no prior stored
    with pytest.raises(ValueError, match="^hdi_prob"):
        arviz_io.summary(idata, hdi_prob=1.5)
    with pytest.raises(ValueError, match="^joints"):
        arviz_io.plot_posterior(idata, joints=["knee"])
    with pytest.raises(ValueError, match="^model_names"):
        arviz_io.plot_forest([idata, idata], ["one"])
    with pytest.raises(ValueError, match="^result_b"):
        arviz_io.compare_marginals(r, PosteriorResult("x", np.zeros((5, 2)), None, np.zeros(2), 0, 0.0, 1))


# --------------------------------------------------------------------------- calibration


def _gaussian_toy(S=200, N=500, D=4, shrink=1.0, seed=0):
    """Conjugate Gaussian: theta ~ N(0, 1), x ~ N(theta, 0.5^2); posterior exact, sd optionally shrunk.

    A fifth coordinate is fixed (0.3 in both posterior and truth) and must be ignored.
    """
    rng = np.random.default_rng(seed)
    sig = 0.5
    theta = rng.standard_normal((S, D))
    x = theta + sig * rng.standard_normal((S, D))
    pm, ps = x / (1 + sig**2), np.sqrt(sig**2 / (1 + sig**2)) / shrink
    post = pm[:, None, :] + ps * rng.standard_normal((S, N, D))
    post = np.concatenate([post, np.full((S, N, 1), 0.3)], axis=2)
    theta = np.concatenate([theta, np.full((S, 1), 0.3)], axis=1)
    return post, theta, pm, ps


def test_coverage_calibrated_on_diagonal_overconfident_below():
    post, theta, _, _ = _gaussian_toy()
    cov = calibration.central_interval_coverage(post, theta)
    assert set(cov["coordinate"]) == {"theta_0", "theta_1", "theta_2", "theta_3", "overall"}  # fixed one ignored
    overall = cov[cov["coordinate"] == "overall"]
    assert (overall["n"] == 200 * 4).all()
    # tolerances: per coordinate (200 subjects, SE <= 0.035) |coverage - alpha| < 0.1;
    # pooled over 4 coordinates (800, SE <= 0.018) < 0.06
    assert (cov["coverage"] - cov["alpha"]).abs().max() < 0.1
    assert (overall["coverage"] - overall["alpha"]).abs().max() < 0.06
    post3, theta3, _, _ = _gaussian_toy(shrink=3.0)
    over = calibration.central_interval_coverage(post3, theta3)
    o = over[over["coordinate"] == "overall"].set_index("alpha")["coverage"]
    # sd shrunk 3x: expected coverage 2*Phi(z_a/3)-1, e.g. 0.43 at alpha=0.9 -> far below the diagonal
    assert (o.index - o.values)[o.index >= 0.5].min() > 0.2
    assert (o.values < o.index).all()


def test_coverage_weighted_importance_samples():
    """Samples from a 2x wider proposal, importance-weighted to the exact posterior, stay calibrated."""
    rng = np.random.default_rng(1)
    _, theta, pm, ps = _gaussian_toy(S=200, N=10)
    theta = theta[:, :4]
    prop = pm[:, None, :] + 2 * ps * rng.standard_normal((200, 2000, 4))
    z = (prop - pm[:, None, :]) / ps
    logw = -0.5 * z**2 + 0.5 * (z / 2) ** 2  # target / proposal, per coordinate (independent)
    # one weight vector per subject must serve all coordinates: weight by the product
    w = np.exp(logw.sum(axis=2) - logw.sum(axis=2).max(axis=1, keepdims=True))
    cov = calibration.central_interval_coverage(list(prop), theta, weights=list(w))
    overall = cov[cov["coordinate"] == "overall"]
    # tolerance 0.08 (the weighted ESS is ~ 1/5 of 2000 draws, plus subject noise)
    assert (overall["coverage"] - overall["alpha"]).abs().max() < 0.08
    # same result when the weights come from PosteriorResult objects
    results = [PosteriorResult("is", prop[s], w[s], pm[s], 0, 0.0, 1) for s in range(200)]
    cov2 = calibration.central_interval_coverage(results, theta)
    np.testing.assert_allclose(cov2["coverage"], cov["coverage"])


def test_weighted_quantile_matches_numpy_hazen():
    x = np.random.default_rng(0).standard_normal((101, 3))
    q = np.array([0.05, 0.5, 0.95])
    np.testing.assert_allclose(calibration.weighted_quantile(x, np.ones(101), q),
                               np.quantile(x, q, axis=0, method="hazen"), atol=1e-12)
    # integer weights behave like repeated samples (up to interpolation at the ends)
    xs = np.array([0.0, 1.0, 2.0])
    med = calibration.weighted_quantile(xs, np.array([1.0, 1.0, 4.0]), np.array([0.5]))
    assert med[0, 0] > 1.0


def test_one_weighted_quantile_for_estimates_limits_and_calibration():
    """The calibration's quantile is the inference layer's (one definition), and a scalar level gives (D,)."""
    from camo_sbi.inference import result

    assert calibration.weighted_quantile is result.weighted_quantile
    rng = np.random.default_rng(1)
    x, w = rng.standard_normal((50, 4)), rng.random(50)
    both = result.weighted_quantile(x, w, [0.05, 0.95])
    np.testing.assert_array_equal(result.weighted_quantile(x, w, 0.05), both[0])
    np.testing.assert_array_equal(result.weighted_median(x, w), result.weighted_quantile(x, w, 0.5))
    # Hazen by hand for three weighted samples: midpoint CDF 0.1, 0.35, 0.75 at values 0, 1, 2
    one = result.weighted_quantile(np.array([2.0, 0.0, 1.0]), np.array([0.5, 0.2, 0.3]), 0.55)
    np.testing.assert_allclose(one, [1.5])
    for bad, name in (((x, w, 1.5), "q:"), ((x, -w, 0.5), "w:"), ((x[:0], None, 0.5), "x:")):
        with pytest.raises(ValueError, match=name):
            result.weighted_quantile(*bad)


def test_sbc_ranks_uniform_when_calibrated():
    post, theta, _, _ = _gaussian_toy()
    ranks = calibration.sbc_ranks(post, theta, n_draws=100, seed=0)
    assert ranks.shape == (200, 5) and np.isnan(ranks[:, 4]).all()  # fixed coordinate ignored
    assert np.nanmin(ranks) >= 0 and np.nanmax(ranks) <= 100
    np.testing.assert_array_equal(ranks, calibration.sbc_ranks(post, theta, n_draws=100, seed=0))
    u = calibration.sbc_uniformity(ranks, 100).set_index("coordinate")
    assert "theta_4" not in u.index
    assert u.loc["overall", "chi2_pvalue"] > 0.01 and u.loc["overall", "ks_pvalue"] > 0.01
    assert u["chi2_pvalue"].min() > 0.001  # 5 tests: Bonferroni-style threshold
    post3, theta3, _, _ = _gaussian_toy(shrink=3.0)
    u3 = calibration.sbc_uniformity(calibration.sbc_ranks(post3, theta3, 100, seed=0), 100).set_index("coordinate")
    assert u3.loc["overall", "chi2_pvalue"] < 1e-6 and u3.loc["overall", "ks_pvalue"] < 1e-6


def test_c2st_same_vs_different():
    rng = np.random.default_rng(0)
    a, b = rng.standard_normal((300, 2)), rng.standard_normal((400, 2))  # b subsampled to 300
    same = calibration.c2st(a, b, seed=0)
    assert abs(same - 0.5) < 0.1  # chance level; SE of a 600-point CV accuracy ~ 0.02
    far = calibration.c2st(a, b + 3.0, seed=0)
    assert far > 0.9
    assert calibration.c2st(a, b, seed=0) == same  # seeded


def test_plot_coverage_and_calibration_bad_inputs():
    post, theta, _, _ = _gaussian_toy(S=30, N=100)
    cov = calibration.central_interval_coverage(post, theta)
    fig = calibration.plot_coverage({"exact": cov, "copy": cov})
    assert isinstance(fig, Figure) and len(fig.axes[0].lines) == 3  # diagonal + 2 methods
    fig = calibration.plot_coverage(cov.assign(method="exact"))
    assert isinstance(fig, Figure)
    with pytest.raises(ValueError, match="^true_thetas"):
        calibration.central_interval_coverage(post, theta[:10])
    with pytest.raises(ValueError, match="^alphas"):
        calibration.central_interval_coverage(post, theta, alphas=[0.5, 1.2])
    with pytest.raises(ValueError, match="^samples_per_subject"):
        calibration.central_interval_coverage(np.full((3, 10, 2), 1.0), np.ones((3, 2)))  # all fixed
    with pytest.raises(TypeError, match="^samples_per_subject"):
        calibration.central_interval_coverage("samples", theta)
    with pytest.raises(ValueError, match="^weights"):
        calibration.central_interval_coverage(post, theta, weights=[np.ones(100)] * 29)
    with pytest.raises(ValueError, match="^n_draws"):
        calibration.sbc_ranks(post, theta, n_draws=0, seed=0)
    with pytest.raises(TypeError, match="^seed"):
        calibration.sbc_ranks(post, theta, n_draws=10, seed="zero")
    with pytest.raises(ValueError, match="^ranks"):
        calibration.sbc_uniformity(np.array([[3.0], [50.0]]), n_draws=10)
    with pytest.raises(ValueError, match="^samples_b"):
        calibration.c2st(np.zeros((50, 2)), np.zeros((50, 3)), seed=0)
    with pytest.raises(ValueError, match="^df_by_method"):
        calibration.plot_coverage(cov)  # no method column


# --------------------------------------------------------------------------- report


def make_run_dir(root, prior: BoxPrior, truth: np.ndarray, seeds: int = 3):
    """A fake run directory with config.json, results.csv, posteriors/*.nc and coverage.csv."""
    root.mkdir(parents=True, exist_ok=True)
    (root / "config.json").write_text(json.dumps({"scenario": "reaching", "robot": "panda",
                                                  "camo": {"n_samples": 1000, "kde_bw": 0.1}, "seeds": [0, 1, 2]}))
    rng = np.random.default_rng(0)
    rows = []
    for method, budgets in (("camo", [1000, 5000]), ("abc-smc", [1000, 5000]), ("naive", [np.nan])):
        for budget in budgets:
            for n_tasks in (1, 3, 5):
                for seed in range(seeds):
                    for subject in ("s0", "s1"):
                        err = 0.3 / np.sqrt(n_tasks) * (1 if np.isnan(budget) else 2000 / (budget + 1000))
                        rows.append(("reach", subject, method, budget, seed, n_tasks, "limit_rmse",
                                     err * (1 + 0.1 * rng.standard_normal())))
                        rows.append(("reach", subject, method, budget, seed, n_tasks, "wall_time",
                                     abs(rng.normal(5.0, 1.0))))
    table = pd.DataFrame(rows, columns=list(report.RESULTS_COLUMNS))
    table["status"] = "ok"
    table.loc[(table.method == "abc-smc") & (table.seed == 1), "status"] = "fallback: stopped at the prior population"
    table.to_csv(root / "results.csv", index=False)
    (root / "posteriors").mkdir()
    for i, method in enumerate(("camo", "npe", "naive")):
        r = _informative_result(prior, truth, method=method, seed=i, weighted=method == "camo", width=0.1)
        if method == "naive":  # a baseline: one point, no posterior
            r = dataclasses.replace(r, samples=truth[None, :] + 0.05, weights=None, estimate=truth + 0.05)
        idata = arviz_io.to_inference_data(r, JOINTS, seed=0, prior=prior, prior_draws=200, true_theta=truth,
                                           attrs={"task": "reach", "subject": "s0", "seed": 0})
        arviz_io.save_netcdf(idata, root / "posteriors" / f"base_seed=0__budget=5000__method={method}__1a2b.nc")
    post, theta, _, _ = _gaussian_toy(S=50, N=200)
    post3, _, _, _ = _gaussian_toy(S=50, N=200, shrink=3.0)
    cov = pd.concat([calibration.central_interval_coverage(post, theta).assign(method="npe"),
                     calibration.central_interval_coverage(post3, theta).assign(method="camo")])
    cov.to_csv(root / "coverage.csv", index=False)
    return root


def _check_self_contained(text: str) -> list[str]:
    srcs = re.findall(r"""\bsrc\s*=\s*["']?([^"'\s>]*)""", text, flags=re.I)
    assert all(s.startswith("data:image/png;base64,") for s in srcs), [s[:40] for s in srcs]
    assert not re.search(r"<link\b|<script\b|url\(|@import|href=\"http", text, flags=re.I)
    for s in srcs:
        assert base64.b64decode(s.split(",", 1)[1])[:8] == b"\x89PNG\r\n\x1a\n"
    return srcs


def test_report_has_every_section_and_embeds_every_image(tmp_path, prior, truth):
    run = make_run_dir(tmp_path / "run", prior, truth)
    out = report.write_report(run, tmp_path / "out" / "report.html", title="Toy <run>")
    assert out.is_file() and [p.name for p in out.parent.iterdir()] == ["report.html"]
    text = out.read_text(encoding="utf-8")
    for sid, name in report.SECTIONS:
        assert f'<section id="{sid}"><h2>{name}</h2>' in text
    sections = {sid: text.split(f'<section id="{sid}">', 1)[1].split("</section>", 1)[0] for sid, _ in report.SECTIONS}
    assert "Toy &lt;run&gt;" in text  # escaped title
    # every input was present (the toy posteriors hold no observed reaches to replay)
    assert [sid for sid, body in sections.items() if "not available" in body] == ["posterior-predictive"]
    assert "camo.n_samples" in text and "reaching" in text  # settings flattened
    # comparison: one table per metric, methods as rows, budgets as columns; 3 seeds: mean (min–max)
    tables = re.findall(r"<table.*?</table>", sections["comparison-table"], flags=re.S)
    assert len(tables) == 2 * 2  # (limit_rmse, wall_time) x (subject s0, s1)
    assert all(len(re.findall(r"<th[ >]", t)) <= 4 for t in tables)  # method, 1000, 5000, "any budget"
    lim = next(t for t in tables if "<caption>limit rmse</caption>" in t)
    assert "mean (min–max) over 3 seeds" in text and "±" not in sections["comparison-table"]
    assert re.search(r"<td>[\d.]+ \([\d.]+–[\d.]+\)</td>", lim)
    assert "band = 95% confidence interval" in sections["error-vs-tasks"]  # 3 seeds x 2 subjects per point
    assert "in degrees" in sections["posteriors"]  # the forest and corner plots
    assert "abc-smc †" in lim and "camo †" not in lim
    assert "fallback: stopped at the prior population" in sections["comparison-table"]
    # headings in words, never the cell's file name
    heads = re.findall(r"<(?:h3|summary)>(.*?)</(?:h3|summary)>", text)
    assert heads and not any(".nc" in h or "__" in h for h in heads)
    assert "budget 5000 simulations per observed task, seed 0" in sections["posteriors"]
    # the baseline is a point on the limits plot, never its own marginal panels
    assert "Marginal posteriors: camo" in text and "Marginal posteriors: naive" not in text
    # diagnostics: the weighted posterior shows its Kish ESS and no MCMC columns
    diag = sections["diagnostics"]
    camo_ess = 1 / np.sum(_informative_result(prior, truth, seed=0, weighted=True).weights ** 2)
    assert f"{camo_ess:.1f} of 2000" in diag and "resampled from weighted samples" in diag
    camo_details = diag.split("<summary>camo", 1)[1].split("</details>", 1)[0]
    npe_details = diag.split("<summary>npe", 1)[1].split("</details>", 1)[0]
    assert "<th>ess_bulk</th>" not in camo_details and "<th>r_hat</th>" not in camo_details
    assert "<th>ess_bulk</th>" in npe_details
    assert "limits[shoulder, lower]" in text  # diagnostics: arviz summary by name
    srcs = _check_self_contained(text)
    # error vs tasks, error vs budget, limits, corner, 2 marginal plots, 1 coverage plot
    assert len(srcs) == 7


@pytest.mark.parametrize("seeds", [2, 5])
def test_a_report_of_few_seeds_has_no_interval_built_from_them(tmp_path, prior, truth, seeds):
    """Before: 2 seeds gave cells like '218 ± 1,269' (Student t with 1 degree of freedom)."""
    run = make_run_dir(tmp_path / "run", prior, truth, seeds=seeds)
    (run / "posteriors").rename(tmp_path / "no_posteriors")  # the tables and figures only
    text = report.write_report(run, tmp_path / "r.html").read_text(encoding="utf-8")
    body = text.split('<section id="comparison-table">', 1)[1].split('<section id="posteriors">', 1)[0]
    if seeds < 5:
        assert "±" not in body and "Student t" not in body
        assert f"mean (min–max) over {seeds} seeds" in body and "dots = each seed" in body
    else:  # five seeds: the interval, as before
        assert "±" in body and "95% confidence interval of the mean" in body


def test_forest_plot_is_arviz_in_degrees(prior, truth):
    from matplotlib.collections import LineCollection

    r = _informative_result(prior, truth)
    a = arviz_io.to_inference_data(r, JOINTS, seed=0, true_theta=truth)
    point = dataclasses.replace(r, samples=truth[None, :] + 0.05, weights=None, estimate=truth + 0.05)
    p = arviz_io.to_inference_data(point, JOINTS, seed=0)
    fig = arviz_io.plot_forest([a, p], ["camo", "naive"])
    ax = fig.axes[0]
    assert ax.get_xlabel() == "limit [deg]"
    xs = np.concatenate([np.asarray(ln.get_xdata(), float) for ln in ax.get_lines()]
                        + [seg[:, 0] for c in ax.collections if isinstance(c, LineCollection) for seg in c.get_segments()])
    xs = xs[np.isfinite(xs)]
    lo, hi = np.degrees(prior.low.numpy()).min(), np.degrees(prior.high.numpy()).max()
    assert xs.size and lo - 1 <= xs.min() and xs.max() <= hi + 1 and np.ptp(xs) > 5  # degrees, not radians
    assert {t.get_text() for t in ax.get_legend().get_texts()} == {"camo", "naive", "truth"}
    rad = arviz_io.plot_forest([a], ["camo"], degrees=False)
    assert rad.axes[0].get_xlabel() == "limit [rad]"


@pytest.mark.slow  # in the slow tier for the default tier's 4-minute budget (issue 28)
def test_corner_plot_shows_the_restricted_limits_or_the_ones_asked_for(tmp_path, prior, truth):
    run = make_run_dir(tmp_path / "run", prior, truth)
    posts, _ = report._load_posteriors(run, 24)
    members = [(str(d.posterior.attrs["method"]), d, p) for p, d, _ in posts if not report._is_point(d)]
    sel, joints, why = report._corner_selection(members)
    restricted = {k for k in range(2 * len(JOINTS)) if prior.free_mask.numpy()[k]
                  and (truth[k] > prior.low.numpy()[k] if k % 2 == 0 else truth[k] < prior.high.numpy()[k])}
    assert {2 * j + b for j, b in sel} <= restricted and len(sel) >= 2 and "restricted" in why
    chosen = [f"{JOINTS[0]}_hi", f"{JOINTS[1]}_lo"]
    sel, _, why = report._corner_selection(members, chosen)
    assert sel == [(0, 1), (1, 0)] and "--corner-limits" in why
    with pytest.raises(ValueError, match="^--corner-limits: unknown"):
        report._corner_selection(members, ["knee_lo", "knee_hi"])
    text = report.write_report(run, tmp_path / "r.html", corner_limits=chosen,
                               figure_formats=["svg"]).read_text(encoding="utf-8")
    assert f"{JOINTS[0]}_hi, {JOINTS[1]}_lo" in text
    svgs = sorted((tmp_path / "report_figures").glob("*.svg"))
    assert any("corner" in p.name for p in svgs) and any("limits_per_method" in p.name for p in svgs)
    # without a truth: the limits whose posterior moved most from the prior come first
    draws = prior.sample(2000, 3).numpy()
    free = np.flatnonzero(prior.free_mask.numpy())
    k = int(free[-1])
    lo, hi = prior.low.numpy()[k], prior.high.numpy()[k]
    draws[:, k] = lo + 0.05 * (hi - lo) * np.random.default_rng(0).random(2000)  # pinned near one edge
    flat = PosteriorResult("camo", draws, None, draws.mean(axis=0), 0, 0.0, 1)
    idata = arviz_io.to_inference_data(flat, JOINTS, seed=0, prior=prior, prior_draws=2000)
    moved = arviz_io.moved_from_prior(idata)
    assert int(np.nanargmax(moved)) == k and moved[k] > 0.3 and np.nanmax(np.delete(moved, k)) < 0.1
    sel, _, why = report._corner_selection([("camo", idata, None)])
    assert sel[0] == (k // 2, k % 2) and "moved most from the prior" in why


def test_report_with_missing_inputs_says_not_available(tmp_path):
    run = tmp_path / "empty"
    run.mkdir()
    out = report.write_report(run, tmp_path / "r.html")
    text = out.read_text(encoding="utf-8")
    for sid, name in report.SECTIONS:
        section = text.split(f'<section id="{sid}">', 1)[1].split("</section>", 1)[0]
        assert f"<h2>{name}</h2>" in section and "not available" in section, sid
    assert "calibration was not computed" in text
    _check_self_contained(text)
    # partial inputs: a results.csv with a single n_tasks and a broken posterior file
    pd.DataFrame([("reach", "s0", "camo", 1000, 0, 3, "limit_rmse", 0.1)],
                 columns=list(report.RESULTS_COLUMNS)).to_csv(run / "results.csv", index=False)
    (run / "posteriors").mkdir()
    (run / "posteriors" / "broken.nc").write_bytes(b"not a netcdf file")
    text = report.write_report(run, tmp_path / "r.html").read_text(encoding="utf-8")
    assert "fewer than two distinct n_tasks values" in text and "broken.nc could not be read" in text


def test_report_bad_inputs(tmp_path):
    with pytest.raises(ValueError, match="^run_dir"):
        report.write_report(tmp_path / "missing", tmp_path / "r.html")
    with pytest.raises(TypeError, match="^run_dir"):
        report.write_report(3, tmp_path / "r.html")
    with pytest.raises(ValueError, match="^out_path"):
        report.write_report(tmp_path, tmp_path)
    with pytest.raises(TypeError, match="^title"):
        report.write_report(tmp_path, tmp_path / "r.html", title=5)


@pytest.mark.slow  # statistical (C2ST random forests, ~12 s)
def test_posterior_comparison_identical_vs_shifted(prior, truth):
    """Same draws: W1 = 0 and C2ST at chance; shifted by 5 sd: large W1 and C2ST near 1."""
    base = _informative_result(prior, truth, method="camo", seed=1)
    same = dataclasses.replace(base, method="abc-smc")
    shifted_s = base.samples.copy()
    shifted_s[:, prior.free_mask.numpy()] += 0.25
    shifted = dataclasses.replace(base, method="npe", samples=shifted_s)
    posts = []
    for r in (base, same, shifted):
        idata = arviz_io.to_inference_data(r, JOINTS, seed=0, attrs={"subject": "s0"})
        posts.append((None, idata, ""))
    table = report._posterior_comparison_table(posts)
    assert len(table) == 3 and "<table" in report._posterior_comparison(posts, "")
    row = table[(table["method A"] == "abc-smc") & (table["method B"] == "camo")].iloc[0]
    assert row["mean W1 over free marginals [deg]"] == pytest.approx(0.0, abs=1e-12)
    assert 0.35 < row["C2ST accuracy"] < 0.65
    row = table[(table["method A"] == "camo") & (table["method B"] == "npe")].iloc[0]
    assert row["mean W1 over free marginals [deg]"] == pytest.approx(np.degrees(0.25), rel=0.05)
    assert row["C2ST accuracy"] > 0.95


def test_weighted_draws_are_marked_resampled_and_lose_the_mcmc_columns(prior, truth):
    """arviz's ess_bulk counts resampled draws (~N); the weights' Kish ESS is what they are worth."""
    r = _informative_result(prior, truth, weighted=True)
    r = dataclasses.replace(r, weights=np.r_[np.full(5, 1.0), np.full(r.samples.shape[0] - 5, 1e-4)])
    idata = arviz_io.to_inference_data(r, JOINTS, seed=0, true_theta=truth)
    a = idata.posterior.attrs
    assert a["draws"] == arviz_io.DRAWS_RESAMPLED == arviz_io.draws_kind(idata)
    assert a["weights_ess"] == pytest.approx(r.ess) and r.ess < 10
    s = arviz_io.summary(idata)
    assert not {"ess_bulk", "ess_tail", "mcse_mean", "mcse_sd", "r_hat"} & set(s.columns)
    assert {"mean", "sd", "hdi_3%", "hdi_97%", "truth"} <= set(s.columns)
    plain = arviz_io.to_inference_data(dataclasses.replace(r, weights=None), JOINTS, seed=0)
    assert arviz_io.draws_kind(plain) == arviz_io.DRAWS_INDEPENDENT and "ess_bulk" in arviz_io.summary(plain)
    point = dataclasses.replace(r, samples=truth[None, :], weights=None, estimate=truth)
    assert arviz_io.draws_kind(arviz_io.to_inference_data(point, JOINTS, seed=0)) == arviz_io.DRAWS_POINT


@pytest.mark.parametrize("log_sd", [1.0, 2.2, 3.0, 5.0])
def test_plain_arviz_cannot_inflate_the_ess_of_weighted_samples(tmp_path, prior, truth, log_sd):
    """Issue 25's case: 500 weighted draws whose Kish ESS is ~15 were read by plain az.summary as
    ess_bulk 395-491. Saved now, plain arviz reports at most the Kish ESS (or, below 8, at most the
    8 draws its diagnostics need), without a warning."""
    rng = np.random.default_rng(int(log_sd * 10))
    r = _informative_result(prior, truth, weighted=True, n=500, width=0.3)
    lw = log_sd * rng.standard_normal(500)
    r = dataclasses.replace(r, weights=np.exp(lw - lw.max()))
    path = arviz_io.save_netcdf(arviz_io.to_inference_data(r, JOINTS, seed=0, true_theta=truth), tmp_path / "w.nc")
    free = [f"limits[{j}, {b}]" for j in ("shoulder", "elbow") for b in ("lower", "upper")]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        # the free joints (arviz divides 0 by 0 on the fixed wrist's zero-width limits)
        s = az.summary(az.from_netcdf(str(path)), coords={"joint": ["shoulder", "elbow"]}).loc[free]
    ess = s[["ess_bulk", "ess_tail"]].to_numpy()
    assert not (ess > max(r.ess, 8)).any(), (r.ess, ess)
    # the old layout (every sample resampled, one chain) for contrast: arviz counted the draws
    old = az.from_dict(posterior={"x": r.resample(500, np.random.default_rng(0))[None, :, :4]})
    with arviz_io._quiet_arviz():
        inflated = az.ess(old)["x"].values.max()
    assert inflated > (3 * r.ess if r.ess < 50 else r.ess)
    # and the toolkit's own summary still reads every weighted sample (mean within 0.05 sd of the weighted mean)
    t = arviz_io.summary(arviz_io.load_netcdf(path)).loc[free]
    sd = r.samples.std(axis=0)[:4]
    assert np.all(np.abs(t["mean"].to_numpy() - r.mean()[:4]) < 0.05 * sd)


def test_arviz_draw_count_bounds_arviz_s_ess():
    for kish in np.r_[1.0, np.linspace(1.1, 50, 200), 395.0, 3411.8]:
        m = arviz_io.arviz_draw_count(kish)
        assert m % 2 == 0 and m >= 8  # two equal chains of at least 4: what arviz's diagnostics need
        if kish >= 7.23:  # arviz's ESS of m draws is at most m log10 m
            assert m * np.log10(m) <= kish + 1e-12 < (m + 2) * np.log10(m + 2)
        else:  # 8 draws, the fewest arviz's diagnostics read without a logged warning
            assert m == 8
    assert arviz_io.arviz_draw_count(15.4) == 12 and arviz_io.arviz_draw_count(7.3) == 8
    assert arviz_io.arviz_draw_count(2.3) == 8


@pytest.mark.parametrize("kish_target", [1.3, 2.3, 4.0, 6.5])
def test_few_effective_samples_read_quietly_by_plain_arviz_within_its_floor(kish_target):
    """Below a Kish ESS of 7.2, 8 resampled draws: plain az.summary warns about nothing and
    reports at most 8 effective samples (the draws it reads), whatever the seed."""
    rng = np.random.default_rng(11)
    n = 100
    a = rng.gamma(0.05, size=n)
    for p in np.linspace(0.05, 30, 600):  # sharpen the weights until their Kish ESS reaches the target
        w = a**p / np.sum(a**p)
        if 1.0 / np.sum(w**2) <= kish_target:
            break
    th = np.sort(rng.normal(size=(n, 3, 2)), axis=-1).reshape(n, 6)
    r = PosteriorResult(samples=th, weights=w, estimate=th[0], method="x", n_simulations=0, wall_time=0.0, n_tasks=1)
    assert 1.0 <= r.ess <= kish_target
    for seed in range(5):
        idata = arviz_io.to_inference_data(r, ["a", "b", "c"], seed=seed)
        d = idata.posterior["limits"].values
        if np.all(d == d[0, 0]):  # one sample carries every resampled draw: stored as a point
            assert d.shape[:2] == (1, 2)
            continue
        assert d.shape[:2] == (2, 4)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            s = az.summary(idata)
        assert (s[["ess_bulk", "ess_tail"]].to_numpy() <= 8).all()


def test_report_replays_the_observed_reaches_against_posterior_draws(tmp_path):
    """compare saves the observed reaches beside the posterior; the report simulates 50 draws."""
    import torch

    from camo_sbi.scenarios.reaching import make_reaching_task
    from camo_sbi.simulators import panda

    sim = panda()
    theta = torch.stack([sim.bounds[:, 0] * 0.6 + 0.4 * sim.start, sim.bounds[:, 1] * 0.6 + 0.4 * sim.start],
                        dim=1).reshape(-1).to(torch.float64)
    task = make_reaching_task(sim, theta, n_train=2, n_test=1, seed=0, name="panda", subject="toy")
    rng = np.random.default_rng(0)
    samples = np.clip(theta.numpy() + 0.05 * rng.standard_normal((300, theta.numel())), None, None)
    samples[:, 0::2] = np.minimum(samples[:, 0::2], samples[:, 1::2])
    r = PosteriorResult("camo", samples, rng.random(300), theta.numpy(), 600, 0.1, 2)
    observed, dims = arviz_io.observed_arrays(task)
    idata = arviz_io.to_inference_data(r, sim.joint_names, seed=0, prior=task.prior, true_theta=theta,
                                       observed=observed, observed_dims=dims,
                                       attrs={"task": "panda", "subject": "toy", "seed": 0, "budget": 300,
                                              "model_spec": '{"kind": "panda"}'})  # what compare stores
    run = tmp_path / "run"
    (run / "posteriors").mkdir(parents=True)
    arviz_io.save_netcdf(idata, run / "posteriors" / "cell.nc")
    loaded = arviz_io.load_netcdf(run / "posteriors" / "cell.nc")
    L = task.observations[1].length
    np.testing.assert_allclose(loaded.observed_data["observed_ee"].values[1, :L], task.observations[1].ee.numpy())
    assert np.isnan(loaded.observed_data["observed_ee"].values[1, L:]).all()
    ppc = report._predictive([(run / "posteriors" / "cell.nc", loaded, "")], "")  # the report's section
    assert "not available" not in ppc and ppc.count("<img") == 1
    assert "<h3>camo, budget 300, seed 0, 2 tasks</h3>" in ppc and "50 posterior draws" in ppc
    # the whole report in a fresh process: the helper process simulates the draws, so the report's
    # own process never imports torch, and the figure is the one drawn in this process
    import re
    import subprocess
    import sys

    code = ("import sys; from camo_sbi.diagnostics import report; "
            f"report.write_report({str(run)!r}, {str(tmp_path / 'r.html')!r}); print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split()[-1] == "False"
    png = re.compile(r'src="(data:image/png;base64,[^"]+)"[^>]*alt="posterior-predictive reaches of camo"')
    assert png.findall((tmp_path / "r.html").read_text()) == png.findall(str(ppc)) != []


def test_hdi_is_arviz_s_and_the_shortest_interval():
    """posterior_width's HDI comes from az.hdi (no hand-written HDI in the package); checked against
    the shortest interval holding floor(prob * S) + 1 sorted draws, computed here by brute force."""
    rng = np.random.default_rng(3)
    draws = rng.gamma(2.0, 1.0, size=(301, 4))
    lo, hi = arviz_io._az_hdi(draws, 0.9)
    s = np.sort(draws, axis=0)
    k = int(np.floor(0.9 * len(s)))
    for j in range(draws.shape[1]):
        i = min(range(len(s) - k), key=lambda i: s[i + k, j] - s[i, j])  # first shortest
        assert (lo[j], hi[j]) == (s[i, j], s[i + k, j])
