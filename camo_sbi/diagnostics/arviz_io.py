"""ArviZ adapter: `PosteriorResult` <-> `arviz.InferenceData` (the only module importing arviz).

Why one module of ~700 lines: it is the arviz adapter (one module per third-party library):
conversion, netCDF I/O, summaries and the arviz plots all call arviz.

Layout of the InferenceData built by :func:`to_inference_data`:

* ``posterior``: variable ``limits`` with dims ``(chain, draw, joint, bound)``,
  ``joint`` = the joint names, ``bound`` = ``["lower", "upper"]``, laid out so that plain
  ``az.summary`` reads it without a warning and cannot report more effective samples than
  the result holds (every sample is in ``constant_data``): independent draws, a seeded
  subset of ``arviz_draw_count(N)`` of them in 2 chains (arviz's ESS of N independent
  draws can exceed N); weighted samples resampled
  (systematic, in a seeded random order) to ``arviz_draw_count(Kish ESS)`` draws in 2 chains,
  few enough that arviz's ESS (at most S log10 S for S draws) stays at or below the Kish
  ESS; never fewer than 8 (2 chains of 4, the fewest its diagnostics read without a
  logged warning), so below a Kish ESS of 7.2 plain arviz may report up to 8 (it counts
  a limit that is constant over the draws as one effective sample per draw); a point
  estimate (or weights that resample to one single sample) as that point twice (sd 0,
  arviz's diagnostics NaN, with arviz's logged note that they need 4 draws per chain).
* ``prior``: ``limits`` drawn from the prior (seeded), same dims (optional).
* ``observed_data``: whatever arrays the caller passes (optional), stored as given
  (no unit conversion).
* ``constant_data``: ``estimate`` (the method's point estimate), ``true_limits``
  (when known), ``prior_low`` / ``prior_high`` (a box prior's edges, when given), and for
  more than one sample ``weighted_samples`` (sample, joint, bound) with their normalised
  ``weights`` (sample): the result itself, from which anything can be recomputed (the
  toolkit's own figures and tables read them).
* ``attrs`` (on every group): method, budget, n_simulations, wall_time, compile_time, import_time, n_tasks,
  units, resampled, ``draws`` (what the draws are: "independent draws", "resampled
  from weighted samples (not MCMC)" or "point estimate"), resample_seed, weights_ess
  (the Kish effective sample size the weights imply, ``(sum w)^2 / sum w^2``; N for
  equal weights), n_samples_original, and any scalar extras of the result as
  ``extra_<key>``. The effective sample size of weighted samples is ``weights_ess``; the
  ess_bulk / ess_tail plain arviz reports on their few resampled draws cannot exceed it
  (or 8, when it is lower).

The file written by :func:`save_netcdf` loads with plain ``arviz.from_netcdf``, and plain
``arviz.summary`` prints rows like ``limits[shoulder_pan, lower]`` without a warning (a
point estimate: one logged note that its 2 draws are too few for arviz's diagnostics,
which are NaN). Limits with zero width inside a distribution (fixed joints) make arviz
divide 0 by 0 in r_hat and mcse_sd: numpy warns there, in arviz's code.
"""

from __future__ import annotations

import contextlib
import io
import logging
import numbers
import os
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path

import arviz as az
import numpy as np
import pandas as pd
import xarray as xr
from matplotlib.figure import Figure
from scipy.stats import wasserstein_distance

from camo_sbi._io import atomic_write_bytes
from camo_sbi._validation import check_positive_int, numpy_generator
from camo_sbi.diagnostics.files import ESTIMATE_DIR, POSTERIOR_DIR
from camo_sbi.diagnostics.style import (
    DOUBLE_COLUMN,
    MIN_FONT_PT,
    method_order,
    method_style,
    paper_figure,
)
from camo_sbi.inference.result import PosteriorResult

__all__ = [
    "BOUNDS",
    "DRAWS_INDEPENDENT",
    "DRAWS_POINT",
    "DRAWS_RESAMPLED",
    "draws_kind",
    "limit_draws",
    "output_dir",
    "save_in_run",
    "true_limits",
    "observed_arrays",
    "VAR_NAME",
    "arviz_draw_count",
    "to_inference_data",
    "save_netcdf",
    "load_netcdf",
    "netcdf_bytes",
    "summary",
    "truth_position",
    "posterior_width",
    "plot_posterior",
    "plot_pair",
    "plot_forest",
    "plot_corner",
    "limit_name",
    "parse_limit_names",
    "prior_box",
    "moved_from_prior",
    "compare_marginals",
]

VAR_NAME = "limits"
DRAWS_INDEPENDENT = "independent draws"
DRAWS_RESAMPLED = "resampled from weighted samples (not MCMC)"
DRAWS_POINT = "point estimate"
_REORDER_TRIES = 20
_MCMC_COLUMNS = ("mcse_mean", "mcse_sd", "ess_bulk", "ess_tail", "r_hat")
BOUNDS = ("lower", "upper")
_MIN_DRAWS = 4  # per chain: arviz's diagnostics warn below 4 draws (and below 2 chains)
_MIN_ARVIZ_DRAWS = 2 * _MIN_DRAWS  # 2 chains of 4: the fewest arviz's diagnostics accept without a log warning
_UNITS = ("rad", "deg")
_DIMS = ["joint", "bound"]


# --------------------------------------------------------------------------- helpers


def _check_joint_names(joint_names, n_joints: int) -> list[str]:
    if isinstance(joint_names, str) or not isinstance(joint_names, Sequence):
        raise TypeError(f"joint_names: expected a sequence of str, got {type(joint_names).__name__}")
    names = list(joint_names)
    if not all(isinstance(n, str) and n for n in names):
        raise TypeError("joint_names: every name must be a non-empty str")
    if len(names) != n_joints:
        raise ValueError(f"joint_names: expected {n_joints} names (one per joint), got {len(names)}")
    if len(set(names)) != len(names):
        raise ValueError(f"joint_names: names must be unique, got {names}")
    return names


def _to_numpy(x, name: str) -> np.ndarray:
    if hasattr(x, "detach"):  # torch tensor, without importing torch here
        x = x.detach().cpu().numpy()
    try:
        return np.asarray(x)
    except Exception as exc:  # pragma: no cover - exotic inputs
        raise TypeError(f"{name}: cannot convert to an array ({exc})") from exc


def _theta_vector(x, name: str, dim: int) -> np.ndarray:
    a = _to_numpy(x, name)
    if not np.issubdtype(a.dtype, np.number):
        raise TypeError(f"{name}: expected numbers, got dtype {a.dtype}")
    a = a.astype(np.float64).reshape(-1) if a.ndim == 2 and a.shape[0] == 1 else a.astype(np.float64)
    if a.shape != (dim,):
        raise ValueError(f"{name}: expected shape ({dim},) laid out [lo_1, hi_1, ...], got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: contains NaN or inf values")
    if np.any(a[0::2] > a[1::2]):
        raise ValueError(f"{name}: lower limit exceeds upper limit")
    return a


def _seed_attr(seed) -> int | str:
    numpy_generator(seed)  # validates the type
    return int(seed) if isinstance(seed, numbers.Integral) else "numpy.random.Generator"


def _attr_value(v):
    """A netCDF-safe attribute value or None (bools -> int, numpy scalars -> python)."""
    if isinstance(v, (bool, np.bool_)):
        return int(v)
    if isinstance(v, numbers.Integral):
        return int(v)
    if isinstance(v, numbers.Real):
        return float(v)
    if isinstance(v, str):
        return v
    return None


def _arviz_logger() -> logging.Logger:
    """arviz's logger: built outside logging's registry (arviz._log), so fetched from the package."""
    return getattr(az, "_log", None) or logging.getLogger("arviz")


@contextlib.contextmanager
def _quiet_arviz():
    """Silence arviz's single-chain shape warnings and constant-data KDE warnings."""
    logger = _arviz_logger()
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            warnings.simplefilter("ignore", RuntimeWarning)
            warnings.filterwarnings("ignore", message=".*alias_mapping.*")
            yield
    finally:
        logger.setLevel(level)


def _check_idata(idata, name: str = "idata") -> az.InferenceData:
    if not isinstance(idata, az.InferenceData):
        raise TypeError(f"{name}: expected an arviz.InferenceData, got {type(idata).__name__}")
    if "posterior" not in idata.groups() or VAR_NAME not in idata.posterior:
        raise ValueError(f"{name}: needs a posterior group with variable {VAR_NAME!r}")
    return idata


def _draws(idata, group: str = "posterior") -> tuple[np.ndarray, list[str]]:
    """(S, n, 2) stacked draws of ``limits`` and the joint names.

    For the posterior of weighted samples stored with their weights (``constant_data``), the
    draws are a systematic resampling of those samples, one per sample (deterministic), not
    the few draws the ``posterior`` group holds for plain arviz (`arviz_draw_count`).
    """
    da = getattr(idata, group)[VAR_NAME].transpose("chain", "draw", "joint", "bound")
    joints = [str(j) for j in da["joint"].values]
    cd = idata.constant_data if "constant_data" in idata.groups() else {}
    if group == "posterior" and "weighted_samples" in cd and "weights" in cd:
        ws = np.asarray(cd["weighted_samples"].transpose("sample", "joint", "bound").values, dtype=np.float64)
        w = np.asarray(cd["weights"].values, dtype=np.float64)
        if draws_kind(idata) == DRAWS_RESAMPLED:
            cw = np.cumsum(w)
            idx = np.searchsorted(cw, (np.arange(len(w)) + 0.5) / len(w) * cw[-1], side="right")
            return ws[np.minimum(idx, len(w) - 1)], joints
        return ws, joints
    vals = np.asarray(da.values, dtype=np.float64)
    return vals.reshape(-1, vals.shape[2], vals.shape[3]), joints


def _truth(idata) -> np.ndarray | None:
    """(n, 2) true limits or None."""
    if "constant_data" in idata.groups() and "true_limits" in idata.constant_data:
        return np.asarray(idata.constant_data["true_limits"].transpose("joint", "bound").values, dtype=np.float64)
    return None


def limit_draws(idata) -> tuple[np.ndarray, list[str]]:
    """(S, n, 2) posterior draws of the limits (units as stored) and the n joint names."""
    return _draws(_check_idata(idata))


def true_limits(idata) -> np.ndarray | None:
    """(n, 2) true limits stored with the posterior, or None."""
    return _truth(_check_idata(idata))


def prior_box(idata) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(n, 2) low and high edges of a stored box prior (units as stored), or (None, None)."""
    _check_idata(idata)
    cd = idata.constant_data if "constant_data" in idata.groups() else {}
    if "prior_low" in cd and "prior_high" in cd:
        return (np.asarray(cd["prior_low"].transpose("joint", "bound").values, dtype=np.float64),
                np.asarray(cd["prior_high"].transpose("joint", "bound").values, dtype=np.float64))
    return None, None


def moved_from_prior(idata, draws: Sequence[np.ndarray] | None = None) -> np.ndarray:
    """(2n,) how far each limit's posterior moved from the prior: the Wasserstein-1 distance
    between the posterior marginal and the prior's (its stored draws, else its box edges as a
    uniform), relative to the prior's width, averaged over ``draws`` ((S, 2n) arrays, e.g.
    several methods; default: this posterior's). NaN where the prior has no width."""
    _check_idata(idata)
    post = [np.asarray(d, dtype=np.float64) for d in draws] if draws is not None else \
        [_draws(idata)[0].reshape(-1, 2 * idata.posterior.sizes["joint"])]
    dim = post[0].shape[1]
    if "prior" in idata.groups() and VAR_NAME in idata.prior:
        prior = _draws(idata, "prior")[0].reshape(-1, dim)
    else:
        low, high = prior_box(idata)
        if low is None:
            raise ValueError("idata: no prior stored (pass prior to to_inference_data)")
        prior = np.linspace(low.reshape(-1), high.reshape(-1), 1000)
    width = np.ptp(prior, axis=0)
    out = np.full(dim, np.nan)
    for k in range(dim):
        if width[k] > 0:
            out[k] = float(np.mean([wasserstein_distance(p[:, k], prior[:, k]) for p in post])) / width[k]
    return out


def _index(joints: list[str]) -> pd.MultiIndex:
    return pd.MultiIndex.from_product([joints, list(BOUNDS)], names=["joint", "bound"])


# --------------------------------------------------------------------------- conversion


def to_inference_data(
    result: PosteriorResult,
    joint_names: Sequence[str],
    *,
    seed,
    prior=None,
    prior_draws: int = 1000,
    true_theta=None,
    observed: Mapping[str, object] | None = None,
    observed_dims: Mapping[str, Sequence[str]] | None = None,
    units: str = "rad",
    budget: int | None = None,
    n_resample: int | None = None,
    attrs: Mapping[str, object] | None = None,
) -> az.InferenceData:
    """Convert a `PosteriorResult` to an `arviz.InferenceData` over named joint limits.

    Args:
        result: the posterior; samples (N, 2n) laid out [lo_1, hi_1, ..., lo_n, hi_n] in radians.
        joint_names: n unique joint names (the ``joint`` coordinate).
        seed: int or numpy Generator, used to resample weighted samples and draw the prior.
        prior: optional prior with ``sample(n, seed) -> (n, 2n)`` (e.g. `BoxPrior`); its
            ``low`` / ``high`` edges, when present, are stored in ``constant_data``.
        prior_draws: number of prior draws for the ``prior`` group.
        true_theta: optional (2n,) true limits, stored as ``constant_data.true_limits``.
        observed: optional {name: array} (e.g. observed trajectories (n_tasks, T, n), goals
            (n_tasks, 3)), stored as-is in ``observed_data`` (never unit-converted).
        observed_dims: optional {name: dim names} for the arrays in ``observed``; a dim named
            "joint" gets the joint names as coordinates.
        units: "rad" (as is) or "deg" (limits, prior, truth and estimate converted).
        budget: simulation budget granted to the method (default: ``result.extras["budget"]``).
        n_resample: posterior draws taken from the samples (default: `arviz_draw_count` of
            their Kish ESS, N for equal weights, so that plain arviz cannot inflate it).
        attrs: extra scalar metadata (task, subject, ...) added to the attrs.

    Returns:
        InferenceData with groups posterior, constant_data and, when given, prior and
        observed_data. Weighted samples are resampled with ``seed``; ``attrs["resampled"]``
        is 1 and ``attrs["resample_seed"]`` the seed (or "numpy.random.Generator").
    """
    if not isinstance(result, PosteriorResult):
        raise TypeError(f"result: expected a PosteriorResult, got {type(result).__name__}")
    n = result.n_joints
    dim = 2 * n
    names = _check_joint_names(joint_names, n)
    if units not in _UNITS:
        raise ValueError(f"units: expected one of {_UNITS}, got {units!r}")
    seed_attr = _seed_attr(seed)
    rng = numpy_generator(seed)
    if not np.all(np.isfinite(result.samples)):
        raise ValueError("result: samples contain NaN or inf values")
    scale = float(np.degrees(1.0)) if units == "deg" else 1.0

    # posterior ----------------------------------------------------------------
    n_orig = result.samples.shape[0]
    w = result.weights
    resampled = w is not None and not np.allclose(w, 1.0 / n_orig)
    if n_resample is not None:
        n_resample = check_positive_int(n_resample, "n_resample", minimum=2)
    weights_ess = result.ess  # Kish: (sum w)^2 / sum w^2; N for equal weights
    draws_kind = DRAWS_POINT if n_orig == 1 else DRAWS_RESAMPLED if resampled else DRAWS_INDEPENDENT
    post = _posterior_draws(result, draws_kind, n_resample, rng) * scale
    post = post.reshape(post.shape[0], post.shape[1], n, 2)

    coords = {"joint": names, "bound": list(BOUNDS)}
    dims = {VAR_NAME: _DIMS, "estimate": _DIMS, "true_limits": _DIMS, "prior_low": _DIMS, "prior_high": _DIMS,
            "weighted_samples": ["sample", *_DIMS], "weights": ["sample"]}

    # prior --------------------------------------------------------------------
    prior_dict = None
    constant = {"estimate": (result.estimate * scale).reshape(n, 2)}
    if n_orig > 1:  # every sample and its weight: anything outside the toolkit can recompute from them
        constant["weighted_samples"] = (result.samples * scale).reshape(n_orig, n, 2)
        constant["weights"] = result.normalized_weights().copy()
    if prior is not None:
        if not hasattr(prior, "sample"):
            raise TypeError(f"prior: expected an object with sample(n, seed), got {type(prior).__name__}")
        prior_draws = check_positive_int(prior_draws, "prior_draws")
        pd_ = _to_numpy(prior.sample(int(prior_draws), rng), "prior").astype(np.float64)
        if pd_.shape != (prior_draws, dim):
            raise ValueError(f"prior: sample() returned shape {pd_.shape}, expected ({prior_draws}, {dim})")
        prior_dict = {VAR_NAME: (pd_ * scale).reshape(1, prior_draws, n, 2)}
        for edge in ("low", "high"):
            if hasattr(prior, edge):
                e = _to_numpy(getattr(prior, edge), f"prior.{edge}").astype(np.float64)
                if e.shape == (dim,):
                    constant[f"prior_{edge}"] = (e * scale).reshape(n, 2)
    if true_theta is not None:
        constant["true_limits"] = (_theta_vector(true_theta, "true_theta", dim) * scale).reshape(n, 2)

    # observed -----------------------------------------------------------------
    obs_dict = None
    if observed is not None:
        if not isinstance(observed, Mapping):
            raise TypeError(f"observed: expected a dict of arrays, got {type(observed).__name__}")
        obs_dict = {}
        for k, v in observed.items():
            if not isinstance(k, str) or not k:
                raise TypeError(f"observed: keys must be non-empty str, got {k!r}")
            if k in dims:
                raise ValueError(f"observed: key {k!r} clashes with a reserved variable name")
            a = _to_numpy(v, f"observed[{k!r}]")
            if not (np.issubdtype(a.dtype, np.number) or a.dtype == bool):
                raise TypeError(f"observed[{k!r}]: expected a numeric array, got dtype {a.dtype}")
            obs_dict[k] = a
        for k, d in (observed_dims or {}).items():
            if k not in obs_dict:
                raise ValueError(f"observed_dims: {k!r} is not a key of observed")
            d = list(d)
            if len(d) != obs_dict[k].ndim:
                raise ValueError(f"observed_dims: {k!r} has {obs_dict[k].ndim} dims, got names {d}")
            if "joint" in d and obs_dict[k].shape[d.index("joint")] != n:
                raise ValueError(f"observed_dims: {k!r} dim 'joint' must have length {n}")
            if "bound" in d:
                raise ValueError(f"observed_dims: {k!r} may not use the reserved dim 'bound'")
            dims[k] = d

    # attrs --------------------------------------------------------------------
    meta = {
        "method": str(result.method),
        "n_simulations": int(result.n_simulations),
        "wall_time": float(result.wall_time),
        "compile_time": float(result.compile_time),
        "import_time": float(result.import_time),
        "n_tasks": int(result.n_tasks),
        "units": units,
        "resampled": int(resampled),
        "draws": draws_kind,
        "resample_seed": seed_attr,
        "weights_ess": weights_ess,
        "n_samples_original": int(n_orig),
        "inference_library": "camo_sbi",
    }
    b = budget if budget is not None else result.extras.get("budget")
    if b is not None:
        meta["budget"] = _attr_value(b) if _attr_value(b) is not None else str(b)
    for k, v in result.extras.items():
        av = _attr_value(v)
        if av is not None and isinstance(k, str) and k != "budget":
            meta[f"extra_{k}"] = av
    for k, v in (attrs or {}).items():
        av = _attr_value(v)
        if av is None or not isinstance(k, str):
            raise TypeError(f"attrs: {k!r} must map a str to an int/float/str/bool, got {type(v).__name__}")
        meta[k] = av

    with _quiet_arviz():
        idata = az.from_dict(
            posterior={VAR_NAME: post},
            prior=prior_dict,
            observed_data=obs_dict,
            constant_data=constant,
            coords=coords,
            dims=dims,
            attrs=meta,
        )
    for g in idata.groups():  # from_dict puts attrs on posterior only in some versions
        getattr(idata, g).attrs.update(meta)
    return idata


def arviz_draw_count(kish_ess: float) -> int:
    """How many draws the ``posterior`` group holds for samples whose Kish ESS is ``kish_ess``
    (N for N equally weighted ones), so that plain arviz reports no more effective samples
    than the weights hold, wherever it can compute an ESS at all.

    arviz's ESS of S draws is S / tau with tau >= 1 / log10(S) (its own floor), so at most
    S log10(S): the largest even S >= 8 with S log10(S) <= ``kish_ess``. 8 draws (2 chains
    of 4) is the fewest arviz's diagnostics accept without logging "Shape validation
    failed"; so below a Kish ESS of 8 log10(8) = 7.22 the answer is 8, and plain arviz may
    report up to 8 effective samples for a posterior that holds fewer (its status already
    says "fallback: low effective sample size"; the file's ``weights_ess`` attribute holds
    the Kish ESS). Reporting NaN instead would need fewer than 8 draws, which arviz logs as a
    warning.
    """
    if kish_ess < _MIN_ARVIZ_DRAWS * np.log10(_MIN_ARVIZ_DRAWS):
        return _MIN_ARVIZ_DRAWS
    s = _MIN_ARVIZ_DRAWS
    while (s + 2) * np.log10(s + 2) <= kish_ess:
        s += 2
    return s


def _arviz_reads_quietly(draws: np.ndarray) -> bool:
    """True when plain ``az.summary`` reads (chains, draws, k) without a warning or a log record."""
    rec = _LogRecords()
    logger = _arviz_logger()
    logger.addHandler(rec)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            az.summary({"x": draws})
    finally:
        logger.removeHandler(rec)
    return not caught and not rec.records


class _LogRecords(logging.Handler):
    def __init__(self):
        super().__init__(level=logging.WARNING)
        self.records: list[logging.LogRecord] = []

    def emit(self, record):
        self.records.append(record)


def _posterior_draws(result: PosteriorResult, kind: str, n_resample: int | None, rng) -> np.ndarray:
    """(chains, draws, 2n) what the ``posterior`` group holds, in a shape plain ``az.summary``
    reads without a warning and whose ESS it cannot inflate beyond the weights' Kish ESS
    (or 8, the draws its diagnostics need):

    * independent draws: ``arviz_draw_count(N)`` of them (a seeded random subset), in 2 chains;
    * weighted samples: ``arviz_draw_count(Kish ESS)`` draws (or ``n_resample``) by systematic
      resampling, in a seeded random order, in 2 chains; the samples and
      weights themselves go to ``constant_data`` (``weighted_samples``, ``weights``). With
      so few draws that a random order can leave every half-chain constant (arviz then
      divides 0 by 0 in r_hat), further seeded orders are tried until arviz reads the draws
      quietly. Draws that resample to one single sample are that point twice, as below;
    * a point estimate: that point twice in one chain (mean = the estimate, sd 0; arviz's
      MCMC diagnostics need 4 draws and are NaN, which is what they are for one point).
    """
    samples = result.samples
    if kind == DRAWS_POINT:
        return _point_draws(samples[0])
    if kind == DRAWS_INDEPENDENT:  # a seeded random subset, without replacement
        m = min(n_resample or arviz_draw_count(samples.shape[0]), samples.shape[0])
        draws = samples[rng.permutation(samples.shape[0])[:m]]
        return _in_chains(draws)
    m = n_resample or arviz_draw_count(result.ess)
    resampled = result.systematic(m)
    if m >= 2 and np.all(resampled == resampled[:1]):  # one sample carries all the draws: a point
        return _point_draws(resampled[0])
    draws = _in_chains(resampled[rng.permutation(m)])
    if draws.shape[0] * draws.shape[1] <= 2 * _MIN_ARVIZ_DRAWS:
        for _ in range(_REORDER_TRIES):
            if _arviz_reads_quietly(draws):
                break
            draws = _in_chains(resampled[rng.permutation(m)])
    return draws


def _point_draws(point: np.ndarray) -> np.ndarray:
    """(1, 2, 2n): one point twice in one chain (mean = the point, sd 0)."""
    return np.broadcast_to(point, (1, 2, point.shape[0])).copy()


def _in_chains(draws: np.ndarray) -> np.ndarray:
    """(m, k) draws as (chains, m // chains, k): 2 chains of equal length (1 for a single draw)."""
    m = draws.shape[0]
    chains = 2 if m >= 2 else 1
    m -= m % chains
    return draws[:m].reshape(chains, m // chains, -1)


def observed_arrays(task) -> tuple[dict[str, np.ndarray], dict[str, list[str]]]:
    """A `Task`'s observed reaches and held-out goals as arrays for ``to_inference_data(observed=...)``.

    Returns ({name: array}, {name: dims}): ``observed_q`` (reach, step, joint) and
    ``observed_ee`` (reach, step, xyz), padded with NaN after each reach's ``observed_length``
    (a space the reach was not recorded in is all NaN); ``observed_goal`` (reach, xyz);
    ``observed_start`` (reach, joint); ``test_goal`` (test, xyz) and ``test_start``
    (test, joint) when the task has held-out goals. Radians and metres.
    """
    obs = task.observations
    if not obs:
        raise ValueError("task: has no observations")
    n, T, m = task.n_joints, max(o.length for o in obs), len(obs)
    q = np.full((m, T, n), np.nan)
    ee = np.full((m, T, 3), np.nan)
    for i, o in enumerate(obs):
        if o.q is not None:
            q[i, : o.length] = _to_numpy(o.q, "q")
        if o.ee is not None:
            ee[i, : o.length] = _to_numpy(o.ee, "ee")
    arrays = {"observed_q": q, "observed_ee": ee,
              "observed_length": np.array([o.length for o in obs], dtype=np.int64),
              "observed_goal": np.stack([_to_numpy(o.goal, "goal") for o in obs]).astype(np.float64),
              "observed_start": np.stack([_to_numpy(o.start, "start") for o in obs]).astype(np.float64)}
    dims = {"observed_q": ["reach", "step", "joint"], "observed_ee": ["reach", "step", "xyz"],
            "observed_length": ["reach"], "observed_goal": ["reach", "xyz"], "observed_start": ["reach", "joint"]}
    if task.test_goals is not None:
        arrays["test_goal"] = _to_numpy(task.test_goals, "test_goals").astype(np.float64)
        arrays["test_start"] = _to_numpy(task.test_starts, "test_starts").astype(np.float64)
        dims.update({"test_goal": ["test", "xyz"], "test_start": ["test", "joint"]})
    return arrays, dims


# --------------------------------------------------------------------------- netCDF


def netcdf_bytes(idata: az.InferenceData) -> bytes:
    """``idata`` as the bytes of the netCDF (HDF5) file arviz's ``to_netcdf`` writes: every group
    through h5netcdf into memory, zlib-compressed as arviz compresses (numbers and bytes)."""
    _check_idata(idata)
    # inside a Dask worker: no cluster lock on a buffer
    from camo_sbi.distributed import local_scheduler

    with local_scheduler():
        return _netcdf_bytes(idata)


def _netcdf_bytes(idata: az.InferenceData) -> bytes:
    buf = io.BytesIO()
    mode = "w"
    if idata.attrs:
        xr.Dataset(attrs=dict(idata.attrs)).to_netcdf(buf, mode=mode, engine="h5netcdf", group="/")
        mode = "a"
    for group in idata.groups():
        data = idata[group]
        encoding = {name: {"zlib": True} for name, v in data.variables.items() if v.dtype.kind in "biufcS"}
        data.to_netcdf(buf, mode=mode, group=group, engine="h5netcdf", encoding=encoding)
        mode = "a"
    return buf.getvalue()


def save_netcdf(idata: az.InferenceData, path) -> Path:
    """Write ``idata`` to ``path`` atomically (temp file in the same directory + os.replace).

    The HDF5 image is built in memory (`netcdf_bytes`) and written as plain bytes: a full disk
    is one OSError (ENOSPC) from the write, never an HDF5 file left half-open on disk, whose
    failing flushes at exit printed "Exception ignored" tracebacks and crashed the interpreter
    (exit 139)."""
    _check_idata(idata)
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path: expected str or PathLike, got {type(path).__name__}")
    path = Path(path)
    if not path.parent.is_dir():
        raise ValueError(f"path: directory {path.parent} does not exist")
    return atomic_write_bytes(path, netcdf_bytes(idata))


def load_netcdf(path) -> az.InferenceData:
    """Read a netCDF written by :func:`save_netcdf` (or any arviz file) fully into memory."""
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path: expected str or PathLike, got {type(path).__name__}")
    if not Path(path).is_file():
        raise ValueError(f"path: no such file {path}")
    with az.rc_context({"data.load": "eager"}):
        return az.from_netcdf(str(path), engine="h5netcdf")


# --------------------------------------------------------------------------- statistics


def _check_prob(hdi_prob) -> float:
    if isinstance(hdi_prob, bool) or not isinstance(hdi_prob, numbers.Real):
        raise TypeError(f"hdi_prob: expected a float, got {type(hdi_prob).__name__}")
    if not 0 < float(hdi_prob) < 1:
        raise ValueError(f"hdi_prob: must lie in (0, 1), got {hdi_prob}")
    return float(hdi_prob)


def output_dir(idata: az.InferenceData) -> str:
    """The run-directory folder of ``idata``'s file: ``estimates`` for a point estimate, else
    ``posteriors`` (`camo_sbi.diagnostics.files`)."""
    return ESTIMATE_DIR if draws_kind(idata) == DRAWS_POINT else POSTERIOR_DIR


def save_in_run(idata: az.InferenceData, run_dir, name: str) -> Path:
    """`save_netcdf` of ``idata`` as ``run_dir/<output_dir(idata)>/<name>.nc`` (folder created)."""
    d = Path(run_dir) / output_dir(idata)
    d.mkdir(parents=True, exist_ok=True)
    return save_netcdf(idata, d / f"{name}.nc")


def draws_kind(idata: az.InferenceData) -> str:
    """What the posterior draws are (`DRAWS_INDEPENDENT`, `DRAWS_RESAMPLED`, `DRAWS_POINT`).

    Read from ``attrs["draws"]``; files written before that attribute existed are judged by
    ``attrs["resampled"]`` and the number of draws.
    """
    _check_idata(idata)
    a = idata.posterior.attrs
    if "draws" in a:
        return str(a["draws"])
    if int(a.get("n_samples_original", 2)) == 1:
        return DRAWS_POINT
    return DRAWS_RESAMPLED if int(a.get("resampled", 0)) else DRAWS_INDEPENDENT


def summary(idata: az.InferenceData, hdi_prob: float = 0.94) -> pd.DataFrame:
    """Per joint limit: mean, sd, hdi (arviz.summary), and the MCMC columns where they mean something.

    mcse / ess_bulk / ess_tail are kept for independent draws only: draws resampled from
    weighted samples repeat a few samples, so those columns would report the number of
    draws, not the effective sample size (``attrs["weights_ess"]``, Kish, is that); mean,
    sd and HDI come from every stored sample (weighted ones resampled, `limit_draws`), not
    from the few draws of the ``posterior`` group. r_hat is dropped:
    the stored chains are halves of one sample, not MCMC chains. Rows are named like ``limits[shoulder, lower]``; a ``truth``
    column is added when the true limits are stored. Fixed (zero-variance) limits show sd 0.
    """
    _check_idata(idata)
    hdi_prob = _check_prob(hdi_prob)
    source = idata
    if "constant_data" in idata.groups() and "weights" in idata.constant_data:  # from every sample
        draws, joints = _draws(idata)
        source = _limits_idata(draws, joints)
    with _quiet_arviz():
        df = az.summary(source, var_names=[VAR_NAME], hdi_prob=hdi_prob, kind="all")
    drop = [c for c in _MCMC_COLUMNS if c in df and draws_kind(idata) != DRAWS_INDEPENDENT]
    if "r_hat" in df:  # the 2 chains are halves of independent or resampled draws, not MCMC chains
        drop.append("r_hat")
    df = df.drop(columns=sorted(set(drop)))
    truth = _truth(idata)
    if truth is not None:
        _, joints = _draws(idata)
        t = pd.Series(truth.reshape(-1), index=_index(joints))
        df["truth"] = [t[(str(j), str(b))] for j, b in _row_coords(idata, df.index)]
    return df


def _row_coords(idata, index) -> list[tuple[str, str]]:
    """(joint, bound) for each row label produced by az.summary (same order as stacking)."""
    da = idata.posterior[VAR_NAME]
    pairs = [(str(j), str(b)) for j in da["joint"].values for b in da["bound"].values]
    if len(pairs) != len(index):  # pragma: no cover - defensive
        raise ValueError("idata: unexpected summary layout")
    return pairs


def truth_position(idata: az.InferenceData) -> pd.DataFrame:
    """The truth's quantile in each posterior marginal (mid-rank: ties count half).

    Returns a DataFrame indexed by (joint, bound) with columns ``truth``, ``quantile``
    (0 = below every draw, 1 = above every draw, ~U(0,1) over calibrated replications)
    and ``zero_width`` (all draws equal: a fixed limit or a point estimate).
    """
    _check_idata(idata)
    truth = _truth(idata)
    if truth is None:
        raise ValueError("idata: no true limits stored (pass true_theta to to_inference_data)")
    draws, joints = _draws(idata)
    below = (draws < truth).mean(axis=0)
    ties = (draws == truth).mean(axis=0)
    fixed = np.ptp(draws, axis=0) == 0
    return pd.DataFrame(
        {"truth": truth.reshape(-1), "quantile": (below + 0.5 * ties).reshape(-1), "zero_width": fixed.reshape(-1)},
        index=_index(joints),
    )


def _az_hdi(draws: np.ndarray, prob: float) -> tuple[np.ndarray, np.ndarray]:
    """``az.hdi`` of (S, k) draws, per column, as (lower (k,), upper (k,)): the draws go in as one
    chain (arviz's shortest interval holding ``prob`` of the sorted draws)."""
    h = np.asarray(az.hdi(np.asarray(draws, dtype=np.float64)[None], hdi_prob=prob))
    return h[:, 0], h[:, 1]


def posterior_width(idata: az.InferenceData, hdi_prob: float = 0.94) -> pd.DataFrame:
    """Posterior HDI width relative to the prior's width at the same probability.

    ``relative_width`` near 1: the observations say nothing about that limit; near 0:
    the limit is pinned down. Prior width is ``hdi_prob * (high - low)`` for a stored
    box prior (exact for uniforms), else the HDI width of the prior draws. Fixed
    coordinates (prior width 0) get NaN.

    Returns a DataFrame indexed by (joint, bound) with columns hdi_lower, hdi_upper,
    posterior_width, prior_width, relative_width.
    """
    _check_idata(idata)
    hdi_prob = _check_prob(hdi_prob)
    draws, joints = _draws(idata)
    lo, hi = _az_hdi(draws.reshape(draws.shape[0], -1), hdi_prob)
    post_w = hi - lo
    cd = idata.constant_data if "constant_data" in idata.groups() else {}
    if "prior_low" in cd and "prior_high" in cd:
        pw = hdi_prob * (
            cd["prior_high"].transpose("joint", "bound").values - cd["prior_low"].transpose("joint", "bound").values
        ).reshape(-1)
    elif "prior" in idata.groups() and VAR_NAME in idata.prior:
        pdraws, _ = _draws(idata, "prior")
        plo, phi = _az_hdi(pdraws.reshape(pdraws.shape[0], -1), hdi_prob)
        pw = phi - plo
    else:
        raise ValueError("idata: no prior stored (pass prior to to_inference_data)")
    pw = np.asarray(pw, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(pw > 0, post_w / np.where(pw > 0, pw, 1.0), np.nan)
    return pd.DataFrame(
        {"hdi_lower": lo, "hdi_upper": hi, "posterior_width": post_w, "prior_width": pw, "relative_width": rel},
        index=_index(joints),
    )


# --------------------------------------------------------------------------- plots


def _select_joints(idata, joints) -> list[str]:
    _, all_joints = _draws(idata)
    if joints is None:
        return all_joints
    if isinstance(joints, str) or not isinstance(joints, Sequence):
        raise TypeError(f"joints: expected a sequence of joint names, got {type(joints).__name__}")
    unknown = [j for j in joints if j not in all_joints]
    if unknown:
        raise ValueError(f"joints: unknown joint names {unknown}; known: {all_joints}")
    if not joints:
        raise ValueError("joints: empty selection")
    return list(joints)


def _scale(idata, degrees: bool) -> tuple[float, str]:
    """(factor, unit) that turn the stored limits into what a figure shows: degrees when
    ``degrees`` and the file holds radians (a person reads angles in degrees)."""
    units = str(idata.posterior.attrs.get("units", "rad"))
    if degrees and units == "rad":
        return float(np.degrees(1.0)), "deg"
    return 1.0, units


def _limits_idata(draws: np.ndarray, joints: Sequence[str], attrs=None) -> az.InferenceData:
    """A posterior-only InferenceData of (S, n, 2) limit draws (one chain); a single draw
    (a point estimate) is repeated 4 times, so arviz draws it as a zero-width interval."""
    d = np.asarray(draws, dtype=np.float64)
    if d.shape[0] < 2:
        d = np.broadcast_to(d[:1], (4,) + d.shape[1:])
    with _quiet_arviz():
        return az.from_dict(posterior={VAR_NAME: np.array(d)[None]},
                            coords={"joint": list(joints), "bound": list(BOUNDS)}, dims={VAR_NAME: _DIMS},
                            attrs=dict(attrs or {}))


def _display_idata(idata, degrees: bool):
    """(posterior-only idata in display units, (n, 2) truth or None, unit)."""
    f, unit = _scale(idata, degrees)
    draws, joints = _draws(idata)
    truth = _truth(idata)
    attrs = {**idata.posterior.attrs, "units": unit}
    return _limits_idata(draws * f, joints, attrs), (None if truth is None else truth * f), unit


def limit_name(joint: str, bound: int | str) -> str:
    """``("panda_joint4", "lower")`` -> ``"panda_joint4_lo"``: a limit's name in flags and tables."""
    b = BOUNDS.index(bound) if isinstance(bound, str) else int(bound)
    return f"{joint}_{('lo', 'hi')[b]}"


def parse_limit_names(names: Sequence[str], joints: Sequence[str]) -> list[tuple[int, int]]:
    """``["panda_joint4_lo", ...]`` -> [(joint index, bound index)], checked against ``joints``."""
    known = {limit_name(j, b): (i, b) for i, j in enumerate(joints) for b in range(2)}
    bad = [n for n in names if n not in known]
    if bad:
        raise ValueError(f"--corner-limits: unknown limits {bad}; known: {', '.join(known)}")
    return [known[n] for n in names]


@paper_figure
def plot_posterior(idata: az.InferenceData, *, joints: Sequence[str] | None = None,
                   hdi_prob: float = 0.94, figsize=None, degrees: bool = True) -> Figure:
    """One panel per (joint, bound): the density of the draws, their mean and ``hdi_prob`` HDI,
    the truth a dashed black line (what ``arviz.plot_posterior`` shows, drawn with matplotlib).

    The density is arviz's KDE (`az.kde`, as ``arviz.plot_posterior`` draws it) in the
    method's colour (`camo_sbi.diagnostics.style`); the mean is written above it
    (``mean=...``) and the HDI (arviz's, as in `posterior_width`) is the thick black bar at
    the bottom with its end values. In degrees when the file holds radians
    (``degrees=False``: as stored). The truth is named once in the figure legend. Fixed
    (zero-variance) limits are drawn as a single vertical line with a note. Fixed margins
    (no layout engine: the panels are a grid of known size). Returns a matplotlib Figure
    (not attached to pyplot).
    """
    _check_idata(idata)
    hdi_prob = _check_prob(hdi_prob)
    sel = _select_joints(idata, joints)
    f, units = _scale(idata, degrees)
    draws, all_joints = _draws(idata)
    draws = draws * f
    truth = _truth(idata)
    truth = None if truth is None else truth * f
    method = str(idata.posterior.attrs.get("method", "posterior"))
    color = method_style(method).color
    w, h = figsize or (DOUBLE_COLUMN, 1.5 * len(sel) + 0.5)
    # margins in inches: the suptitle and legend on top, tick labels and the x label below each row
    fig = Figure(figsize=(w, h))
    axes = np.atleast_2d(fig.subplots(len(sel), 2, squeeze=False, gridspec_kw=dict(
        left=0.2 / w, right=1 - 0.2 / w, top=1 - 0.55 / h, bottom=0.45 / h,
        hspace=0.65 / max(0.3, (h - 1.0) / len(sel) - 0.65), wspace=0.12)))
    cols = [(all_joints.index(j), c) for j in sel for c in range(2)]
    lo_hdi, hi_hdi = _az_hdi(np.stack([draws[:, ji, c] for ji, c in cols], axis=1), hdi_prob)
    for k, (ji, c) in enumerate(cols):
        ax = axes[k // 2, k % 2]
        j, b = all_joints[ji], BOUNDS[c]
        x = draws[:, ji, c]
        tv = None if truth is None else float(truth[ji, c])
        ax.set_yticks([])
        for side in ("left", "right", "top"):
            ax.spines[side].set_visible(False)
        if np.ptp(x) == 0:
            ax.axvline(x[0], color=color, lw=2)
            ax.set_title(f"{j}, {b} (fixed = {x[0]:.3g})")
            pad = max(0.1, 0.05 * abs(float(x[0])))
            ax.set_xlim(float(x[0]) - pad, float(x[0]) + pad)
        else:
            with _quiet_arviz():
                grid, pdf = az.kde(x)
            ax.plot(grid, pdf, color=color, lw=1.2)
            ax.set_ylim(-0.12 * pdf.max(), 1.25 * pdf.max())
            mean = float(np.mean(x))
            ax.text(mean, 1.02 * pdf.max(), f"mean={mean:.3g}", ha="center", va="bottom", gid="point-estimate")
            lo, hi = float(lo_hdi[k]), float(hi_hdi[k])
            ax.plot([lo, hi], [-0.06 * pdf.max()] * 2, color="k", lw=3, solid_capstyle="butt", gid="hdi")
            ax.text(lo, 0.0, f"{lo:.3g}", ha="right", va="bottom")
            ax.text(hi, 0.0, f"{hi:.3g}", ha="left", va="bottom")
            ax.text((lo + hi) / 2, 0.0, f"{hdi_prob:.0%} HDI", ha="center", va="bottom")
            ax.set_title(f"{j}, {b}")
        if tv is not None:
            ax.axvline(tv, color="k", ls="--", lw=1.2, label="truth")
            lo_x, hi_x = ax.get_xlim()
            ax.set_xlim(min(lo_x, tv - 0.02 * (hi_x - lo_x)), max(hi_x, tv + 0.02 * (hi_x - lo_x)))
        ax.locator_params(axis="x", nbins=6)
        ax.set_xlabel(f"limit [{units}]")
    fig.suptitle(f"{method}: joint limits, {hdi_prob:.0%} HDI", y=1 - 0.08 / h, va="top")
    if truth is not None:
        fig.legend(handles=[axes[0, 0].lines[-1]], labels=["truth"], loc="upper right",
                   bbox_to_anchor=(1 - 0.1 / w, 1 - 0.05 / h), frameon=False)
    return fig


@paper_figure
def plot_pair(idata: az.InferenceData, *, joints: Sequence[str] | None = None, max_joints: int = 3,
              kind: str = "scatter", figsize=None, degrees: bool = True) -> Figure:
    """Pairwise scatter/kde of the free limits of a few joints, truth marked as crosses
    (arviz.plot_pair; degrees when the file holds radians).

    Args:
        joints: joints to show (default: the first ``max_joints`` with a non-fixed limit).
        kind: "scatter", "kde" or "hexbin" (arviz.plot_pair).
    """
    _check_idata(idata)
    shown, truth, units = _display_idata(idata, degrees)
    draws, all_joints = _draws(shown)
    if joints is None:
        free = [j for i, j in enumerate(all_joints) if np.ptp(draws[:, i, :], axis=0).max() > 0]
        sel = free[:max_joints]
    else:
        sel = _select_joints(idata, joints)
    cols = [(all_joints.index(j), c) for j in sel for c in range(2) if np.ptp(draws[:, all_joints.index(j), c]) > 0]
    if len(cols) < 2:
        raise ValueError("joints: need at least two non-fixed limits to draw a pair plot")
    if kind not in ("scatter", "kde", "hexbin"):
        raise ValueError(f"kind: expected 'scatter', 'kde' or 'hexbin', got {kind!r}")
    labels = [f"{all_joints[i]}, {BOUNDS[c]} [{units}]" for i, c in cols]
    flat = {lab: draws[:, i, c][None, :] for lab, (i, c) in zip(labels, cols, strict=True)}
    sub = az.from_dict(posterior=flat)
    k = len(cols)
    side = min(DOUBLE_COLUMN, 2.0 * (k - 1) + 0.8)
    fig = Figure(figsize=figsize or (side, side), layout="constrained")
    axes = np.asarray(fig.subplots(k - 1, k - 1, squeeze=False))
    ref = None if truth is None else {lab: float(truth[i, c]) for lab, (i, c) in zip(labels, cols, strict=True)}
    with _quiet_arviz():
        az.plot_pair(sub, var_names=labels, kind=kind, ax=axes if k > 2 else axes[0, 0],
                     reference_values=ref, textsize=MIN_FONT_PT, show=False,
                     scatter_kwargs={"alpha": 0.4, "s": 4} if kind == "scatter" else None)
    fig.suptitle(f"{idata.posterior.attrs.get('method', 'posterior')}: pairwise limits")
    return fig


@paper_figure
def plot_forest(idatas: Sequence[az.InferenceData], model_names: Sequence[str], *,
                joints: Sequence[str] | None = None, hdi_prob: float = 0.94,
                truth: bool = True, figsize=None, degrees: bool = True, title: str | None = None) -> Figure:
    """Forest plot of the limits across methods (arviz.plot_forest: one row per model per
    limit; median, quartiles and the ``hdi_prob`` HDI), in degrees when the files hold radians.

    A model with a single draw (a baseline's point estimate) is a zero-width interval: a
    dot. With ``truth=True`` and true limits stored in the first InferenceData, the truth
    is added as an extra model named "truth" (black). Each model in its method's colour
    (`camo_sbi.diagnostics.style`); the legend sits outside, to the right.
    """
    if isinstance(idatas, az.InferenceData) or not isinstance(idatas, Sequence) or not idatas:
        raise TypeError("idatas: expected a non-empty list of arviz.InferenceData")
    for i, d in enumerate(idatas):
        _check_idata(d, f"idatas[{i}]")
    if isinstance(model_names, str) or not isinstance(model_names, Sequence):
        raise TypeError(f"model_names: expected a list of str, got {type(model_names).__name__}")
    names = [str(m) for m in model_names]
    if len(names) != len(idatas):
        raise ValueError(f"model_names: expected {len(idatas)} names, got {len(names)}")
    hdi_prob = _check_prob(hdi_prob)
    sel = _select_joints(idatas[0], joints)
    shown = [_display_idata(d, degrees) for d in idatas]
    units = shown[0][2]
    data, labels = [s[0] for s in shown], list(names)
    t = shown[0][1]
    if truth and t is not None:
        _, all_joints = _draws(idatas[0])
        data.append(_limits_idata(t[None], all_joints))
        labels.append("truth")
    order = [labels.index(m) for m in method_order(labels[:len(names)])] + list(range(len(names), len(labels)))
    data, labels = [data[i] for i in order], [labels[i] for i in order]
    rows = len(sel) * 2 * len(data)
    fig = Figure(figsize=figsize or (DOUBLE_COLUMN, 0.8 + 0.085 * rows + 0.12 * len(sel) * 2), layout="constrained")
    ax = fig.subplots()
    with _quiet_arviz():
        az.plot_forest(data, model_names=labels, var_names=[VAR_NAME], coords={"joint": sel},
                       combined=True, hdi_prob=hdi_prob, ax=ax, textsize=MIN_FONT_PT, show=False,
                       markersize=3, linewidth=1.0,
                       labeller=az.labels.mix_labellers((az.labels.NoModelLabeller, az.labels.NoVarLabeller))(),
                       colors=[method_style(m).color for m in labels])
    ax.set_title(title or f"joint limits per method: median, quartiles, {hdi_prob:.0%} HDI (a dot alone: "
                          "a point estimate)")
    ax.set_xlabel(f"limit [{units}]")
    for lab in ax.get_yticklabels():
        lab.set_fontsize(MIN_FONT_PT)
    legend = ax.get_legend()
    if legend is not None:  # arviz puts it over the first rows: move it outside, to the right
        handles, texts = legend.legend_handles, [t.get_text() for t in legend.get_texts()]
        legend.remove()
        ax.legend(handles, texts, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    return fig


@paper_figure
def plot_corner(idatas: Sequence[az.InferenceData], model_names: Sequence[str], limits: Sequence[tuple[int, int]],
                *, points: Mapping[str, az.InferenceData] | None = None, truth: bool = True,
                degrees: bool = True, max_scatter: int = 400, title: str | None = None) -> Figure:
    """Corner plot of k chosen limits (``limits``: (joint index, bound index)), several
    methods overlaid: arviz.plot_pair once per method on the same axes (scatter below the
    diagonal, marginal densities on it), the truth as black lines and crosses, and the
    baselines' point estimates (``points``: {name: InferenceData}) as their markers.
    Degrees when the files hold radians."""
    k = len(limits)
    if k < 2:
        raise ValueError("limits: a corner plot needs at least two limits")
    names = [str(m) for m in model_names]
    if len(names) != len(idatas) or not names:
        raise ValueError(f"model_names: expected {len(idatas)} names, got {len(names)}")
    shown = {m: _display_idata(_check_idata(d), degrees) for m, d in zip(names, idatas, strict=True)}
    units = next(iter(shown.values()))[2]
    _, joints = _draws(idatas[0])
    labels = [f"{joints[j]} {BOUNDS[b]} [{units}]" for j, b in limits]
    side = min(DOUBLE_COLUMN, 1.55 * k + 0.9)
    fig = Figure(figsize=(side, side + 0.5), layout="constrained")
    axes = np.asarray(fig.subplots(k, k, squeeze=False))
    t = next(iter(shown.values()))[1]
    tv = None if (t is None or not truth) else np.array([t[j, b] for j, b in limits])
    for m in method_order(names):
        draws, _ = _draws(shown[m][0])
        cols = np.stack([draws[:, j, b] for j, b in limits], axis=1)
        step = max(1, cols.shape[0] // max_scatter)
        sub = az.from_dict(posterior={lab: cols[::step, i][None] for i, lab in enumerate(labels)})
        st = method_style(m)
        with _quiet_arviz():
            az.plot_pair(sub, var_names=labels, kind="scatter", marginals=True, ax=axes, show=False,
                         textsize=MIN_FONT_PT, scatter_kwargs={"color": st.color, "alpha": 0.4, "s": 6},
                         marginal_kwargs={"color": st.color, "plot_kwargs": {"linewidth": 1.2}})
        axes[0, 0].plot([], [], color=st.color, lw=1.5, label=m)
    for m, d in method_order_items(points or {}):
        f, _ = _scale(d, degrees)
        est, _ = _draws(d)
        p = np.array([est[0, j, b] * f for j, b in limits])
        st = method_style(m)
        for r in range(k):
            for c in range(r + 1):
                if r == c:
                    axes[r, c].axvline(p[c], color=st.color, ls=st.linestyle, lw=1.0)
                else:
                    axes[r, c].plot(p[c], p[r], marker=st.marker, color=st.color, ms=5, ls="none", mec="white")
        axes[0, 0].plot([], [], color=st.color, ls=st.linestyle, marker=st.marker, label=f"{m} (point)")
    if tv is not None:
        for r in range(k):
            for c in range(r + 1):
                axes[r, c].axvline(tv[c], color="k", lw=0.9)
                if r != c:
                    axes[r, c].axhline(tv[r], color="k", lw=0.9)
                    axes[r, c].plot(tv[c], tv[r], marker="+", color="k", ms=8, mew=1.3)
        axes[0, 0].plot([], [], color="k", lw=0.9, label="truth")
    for ax in axes.reshape(-1):
        ax.tick_params(labelsize=MIN_FONT_PT)
        ax.xaxis.label.set_fontsize(MIN_FONT_PT)
        ax.yaxis.label.set_fontsize(MIN_FONT_PT)
    handles, texts = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, texts, loc="outside lower center", ncols=min(4, len(texts)), frameon=False,
               title=title or "diagonal: density of the draws; below: draws; black: truth")
    return fig


def method_order_items(d: Mapping[str, object]) -> list[tuple[str, object]]:
    """``d``'s items in legend order (`camo_sbi.diagnostics.style.method_order`)."""
    return [(k, d[k]) for k in method_order(list(d))]


# --------------------------------------------------------------------------- comparison


def _marginal_inputs(x, name: str) -> tuple[np.ndarray, np.ndarray | None]:
    if isinstance(x, PosteriorResult):
        return x.samples, x.weights
    if isinstance(x, az.InferenceData):
        _check_idata(x, name)
        d, _ = _draws(x)
        return d.reshape(d.shape[0], -1), None
    raise TypeError(f"{name}: expected a PosteriorResult or arviz.InferenceData, got {type(x).__name__}")


def compare_marginals(result_a, result_b, *, joint_names: Sequence[str] | None = None) -> pd.DataFrame:
    """Wasserstein-1 distance between the marginals of two posteriors, per (joint, bound).

    Accepts `PosteriorResult` (weights honoured) or InferenceData from `to_inference_data`
    (units as stored). Returns a DataFrame indexed by (joint, bound) with column
    ``wasserstein``; a 0 means identical marginals.
    """
    a, wa = _marginal_inputs(result_a, "result_a")
    b, wb = _marginal_inputs(result_b, "result_b")
    if a.shape[1] != b.shape[1]:
        raise ValueError(f"result_b: dimension {b.shape[1]} differs from result_a's {a.shape[1]}")
    n = a.shape[1] // 2
    if joint_names is None:
        joint_names = (_draws(result_a)[1] if isinstance(result_a, az.InferenceData)
                       else [f"joint_{i}" for i in range(n)])
    names = _check_joint_names(joint_names, n)
    dist = [wasserstein_distance(a[:, k], b[:, k], wa, wb) for k in range(2 * n)]
    return pd.DataFrame({"wasserstein": dist}, index=_index(names))
