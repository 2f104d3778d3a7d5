"""Calibration checks over many simulated subjects: coverage, SBC ranks, C2ST; distances to a reference.

Each check takes, for S subjects with known true limits, posterior samples
``samples_per_subject`` — a (S, N, D) array, a list of S arrays (N_s, D), or a list
of `PosteriorResult` (their weights are used) — and ``true_thetas`` (S, D).
Coordinates whose posterior has zero width in a subject (fixed / known limits of a
strong prior) are ignored for that subject.

No arviz here; :func:`c2st` uses sbi's through the project's one sbi module,
``camo_sbi/inference/sbi_adapter.py``.
"""

from __future__ import annotations

import numbers
from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd
from matplotlib.figure import Figure
from scipy import stats

from camo_sbi._validation import check_positive_int, numpy_generator
from camo_sbi.diagnostics.style import (
    MIN_FONT_PT,
    SINGLE_COLUMN,
    method_order,
    method_style,
    paper_figure,
)
from camo_sbi.inference import sbi_adapter
from camo_sbi.inference.result import (  # the one definition (re-exported)
    PosteriorResult,
    weighted_quantile,
)

__all__ = [
    "DEFAULT_ALPHAS",
    "weighted_quantile",
    "central_interval_coverage",
    "sbc_ranks",
    "sbc_uniformity",
    "c2st",
    "distinct_draws",
    "mmd",
    "reference_distances",
    "plot_coverage",
]

DEFAULT_ALPHAS = np.linspace(0.05, 0.95, 19)


# --------------------------------------------------------------------------- inputs


def _array(x, name: str, ndim: int) -> np.ndarray:
    if hasattr(x, "detach"):  # torch tensor
        x = x.detach().cpu().numpy()
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"{name}: cannot convert to a float array ({exc})") from exc
    if a.ndim != ndim:
        raise ValueError(f"{name}: expected {ndim} dimensions, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: contains NaN or inf values")
    return a


def _subjects(samples_per_subject, true_thetas, weights):
    """-> list of (x (N_s, D), w (N_s,) normalised or None), truths (S, D)."""
    if isinstance(samples_per_subject, (str, bytes)) or not (
        isinstance(samples_per_subject, (Sequence, np.ndarray)) or hasattr(samples_per_subject, "detach")
    ):
        raise TypeError(
            "samples_per_subject: expected a (S, N, D) array or a list of (N_s, D) arrays / PosteriorResult, "
            f"got {type(samples_per_subject).__name__}"
        )
    if len(samples_per_subject) == 0:
        raise ValueError("samples_per_subject: no subjects given")
    truths = _array(true_thetas, "true_thetas", 2)
    S, D = truths.shape
    if len(samples_per_subject) != S:
        raise ValueError(f"true_thetas: {S} rows but {len(samples_per_subject)} subjects of samples")
    if weights is not None and len(weights) != S:
        raise ValueError(f"weights: expected one weight vector per subject ({S}), got {len(weights)}")
    out = []
    for s in range(S):
        item = samples_per_subject[s]
        w = None
        if isinstance(item, PosteriorResult):
            x, w = item.samples, item.weights
        else:
            x = _array(item, f"samples_per_subject[{s}]", 2)
        if x.shape[1] != D or x.shape[0] < 1:
            raise ValueError(f"samples_per_subject[{s}]: expected shape (N, {D}), got {x.shape}")
        if weights is not None and weights[s] is not None:
            w = _array(weights[s], f"weights[{s}]", 1)
            if w.shape != (x.shape[0],):
                raise ValueError(f"weights[{s}]: expected shape ({x.shape[0]},), got {w.shape}")
            if np.any(w < 0) or w.sum() <= 0:
                raise ValueError(f"weights[{s}]: must be non-negative and not all zero")
        if w is not None:
            w = w / w.sum()
        out.append((x, w))
    return out, truths


def _names(names, D: int) -> list[str]:
    if names is None:
        return [f"theta_{i}" for i in range(D)]
    names = [str(n) for n in names]
    if len(names) != D:
        raise ValueError(f"names: expected {D} names, got {len(names)}")
    return names


def _alphas(alphas) -> np.ndarray:
    a = _array(np.atleast_1d(alphas) if not hasattr(alphas, "detach") else alphas, "alphas", 1)
    if a.size == 0 or np.any((a <= 0) | (a >= 1)):
        raise ValueError("alphas: every level must lie strictly between 0 and 1")
    return a


# --------------------------------------------------------------------------- coverage


def central_interval_coverage(samples_per_subject, true_thetas, alphas=DEFAULT_ALPHAS,
                              weights=None, *, names: Sequence[str] | None = None) -> pd.DataFrame:
    """Fraction of true coordinates inside the central α-interval of their posterior marginal.

    The central α-interval is [q_(1-α)/2, q_(1+α)/2] of the (weighted) marginal. A calibrated
    posterior gives coverage ≈ α at every α; an over-confident one falls below the diagonal.

    Args:
        samples_per_subject: (S, N, D) array, list of (N_s, D) arrays, or list of PosteriorResult.
        true_thetas: (S, D) the true parameters.
        alphas: credibility levels in (0, 1).
        weights: optional list of (N_s,) weights per subject (overrides PosteriorResult weights).
        names: optional D coordinate names (default ``theta_0``...).

    Returns:
        Tidy DataFrame with columns ``alpha``, ``coordinate`` (a name or "overall"),
        ``coverage`` and ``n`` (subjects counted). Zero-width marginals (fixed coordinates)
        are not counted; a coordinate fixed in every subject gets no rows.
    """
    subj, truths = _subjects(samples_per_subject, true_thetas, weights)
    a = _alphas(alphas)
    D = truths.shape[1]
    labels = _names(names, D)
    q = np.concatenate([(1 - a) / 2, (1 + a) / 2])
    inside = np.zeros((len(subj), a.size, D), dtype=bool)
    valid = np.zeros((len(subj), D), dtype=bool)
    for s, (x, w) in enumerate(subj):
        qs = weighted_quantile(x, w, q)
        lo, hi = qs[: a.size], qs[a.size:]
        inside[s] = (lo <= truths[s]) & (truths[s] <= hi)
        valid[s] = np.ptp(x, axis=0) > 0
    rows = []
    for d in range(D):
        n = int(valid[:, d].sum())
        if n == 0:
            continue
        cov = inside[valid[:, d], :, d].mean(axis=0)
        rows += [{"alpha": float(al), "coordinate": labels[d], "coverage": float(c), "n": n}
                 for al, c in zip(a, cov, strict=True)]
    n_all = int(valid.sum())
    if n_all == 0:
        raise ValueError("samples_per_subject: every marginal has zero width; nothing to calibrate")
    cov_all = (inside & valid[:, None, :]).sum(axis=(0, 2)) / n_all
    rows += [{"alpha": float(al), "coordinate": "overall", "coverage": float(c), "n": n_all}
             for al, c in zip(a, cov_all, strict=True)]
    return pd.DataFrame(rows, columns=["alpha", "coordinate", "coverage", "n"])


# --------------------------------------------------------------------------- SBC


def sbc_ranks(samples_per_subject, true_thetas, n_draws: int, seed, weights=None) -> np.ndarray:
    """Rank of each true coordinate among ``n_draws`` posterior draws (simulation-based calibration).

    For each subject, L = ``n_draws`` draws are taken from its posterior (without replacement
    when unweighted and N >= L, otherwise multinomial by weight); the rank is the number of
    draws below the truth, ties broken uniformly at random. For a calibrated posterior (truth
    drawn from the prior) ranks are uniform on {0, ..., L}.

    Returns:
        (S, D) float array of ranks in [0, L]; NaN where the subject's marginal has zero width.
    """
    subj, truths = _subjects(samples_per_subject, true_thetas, weights)
    L = check_positive_int(n_draws, "n_draws")
    rng = numpy_generator(seed)
    ranks = np.full(truths.shape, np.nan)
    for s, (x, w) in enumerate(subj):
        N = x.shape[0]
        if w is None:
            idx = rng.choice(N, size=L, replace=N < L)
        else:
            idx = rng.choice(N, size=L, replace=True, p=w)
        d = x[idx]
        below = (d < truths[s]).sum(axis=0)
        ties = (d == truths[s]).sum(axis=0)
        r = below + rng.integers(0, ties + 1)
        ok = np.ptp(x, axis=0) > 0
        ranks[s, ok] = r[ok]
    return ranks


def sbc_uniformity(ranks, n_draws: int, *, n_bins: int | None = None,
                   names: Sequence[str] | None = None) -> pd.DataFrame:
    """Chi-square and KS tests of uniformity of SBC ranks, per coordinate and pooled.

    Args:
        ranks: (S, D) from :func:`sbc_ranks` (NaN entries ignored).
        n_draws: the L used for the ranks (ranks lie in {0, ..., L}).
        n_bins: chi-square bins over the L+1 rank values (default: about S/5, 2..20, so
            expected counts stay >= 5); expected counts account for unequal bin sizes.

    Returns:
        DataFrame with columns coordinate, n, chi2, dof, chi2_pvalue, ks_pvalue (KS on the
        rank midpoints (r + 0.5) / (L + 1) against U(0, 1); slightly conservative for small L).
        The "overall" row pools all coordinates (not independent: a rough summary).
    """
    L = check_positive_int(n_draws, "n_draws")
    r = np.asarray(ranks, dtype=np.float64)
    if r.ndim != 2:
        raise ValueError(f"ranks: expected shape (S, D), got {r.shape}")
    finite = r[np.isfinite(r)]
    if finite.size and (finite.min() < 0 or finite.max() > L):
        raise ValueError(f"ranks: values must lie in [0, {L}] (is n_draws right?)")
    labels = _names(names, r.shape[1])

    def test(v: np.ndarray, label: str) -> dict:
        v = v[np.isfinite(v)].astype(int)
        n = v.size
        B = n_bins if n_bins is not None else int(np.clip(n // 5, 2, 20))
        B = check_positive_int(B, "n_bins", minimum=2)
        B = min(B, L + 1)
        bin_of = np.arange(L + 1) * B // (L + 1)
        p = np.bincount(bin_of, minlength=B) / (L + 1)
        obs = np.bincount(bin_of[v], minlength=B)
        exp = n * p
        chi2 = float(((obs - exp) ** 2 / exp).sum())
        ks = stats.kstest((v + 0.5) / (L + 1), "uniform").pvalue if n else np.nan
        return {"coordinate": label, "n": n, "chi2": chi2, "dof": B - 1,
                "chi2_pvalue": float(stats.chi2.sf(chi2, B - 1)), "ks_pvalue": float(ks)}

    rows = [test(r[:, d], labels[d]) for d in range(r.shape[1]) if np.isfinite(r[:, d]).any()]
    if not rows:
        raise ValueError("ranks: every entry is NaN (all coordinates fixed)")
    rows.append(test(r.reshape(-1), "overall"))
    return pd.DataFrame(rows)


# --------------------------------------------------------------------------- C2ST


def c2st(samples_a, samples_b, seed, *, n_folds: int = 5, classifier: str = "rf",
         max_samples: int | None = None) -> float:
    """Classifier two-sample test accuracy between two sample sets (0.5: indistinguishable, 1: disjoint).

    Uses ``sbi.utils.metrics.c2st`` through `camo_sbi.inference.sbi_adapter` (sbi 0.27: random
    forest, z-scored by ``samples_a``'s statistics, ``n_folds`` cross-validation).
    The larger set is subsampled (seeded) to the size of the smaller so 0.5 is the chance level.

    Args:
        samples_a: (N_a, D) equally weighted samples (resample first if weighted).
        samples_b: (N_b, D), the same.
        seed: int or numpy Generator (subsampling and the classifier's seed).
        classifier: "rf" or "mlp".
        max_samples: optional cap on samples per set.
    """
    a = _array(samples_a, "samples_a", 2)
    b = _array(samples_b, "samples_b", 2)
    if a.shape[1] != b.shape[1]:
        raise ValueError(f"samples_b: dimension {b.shape[1]} differs from samples_a's {a.shape[1]}")
    if classifier not in ("rf", "mlp"):
        raise ValueError(f"classifier: expected 'rf' or 'mlp', got {classifier!r}")
    n_folds = check_positive_int(n_folds, "n_folds", minimum=2)
    rng = numpy_generator(seed)
    m = min(a.shape[0], b.shape[0])
    if max_samples is not None:
        m = min(m, check_positive_int(max_samples, "max_samples"))
    if m < 2 * n_folds:
        raise ValueError(f"samples_a: need at least {2 * n_folds} samples per set for {n_folds}-fold CV, got {m}")
    a = a[rng.choice(a.shape[0], m, replace=False)] if a.shape[0] > m else a
    b = b[rng.choice(b.shape[0], m, replace=False)] if b.shape[0] > m else b
    int_seed = int(seed) if isinstance(seed, numbers.Integral) else int(rng.integers(2**31 - 1))
    return sbi_adapter.c2st(a, b, seed=int_seed, n_folds=n_folds, classifier=classifier)


def distinct_draws(samples, weights, n: int, seed) -> np.ndarray:
    """(m, D) draws of a weighted sample without repeating a sample, m = min(n, samples with weight > 0).

    A classifier two-sample test sees a sample drawn twice in both its training and test folds
    and recognises it, so resampling WITH replacement inflates C2ST (docs/guide/reference_posteriors.md
    shows by how much for SMC particles against a grid posterior). Drawn
    without replacement with probabilities proportional to ``weights`` (None: equal): exact
    for equal weights, an approximation otherwise that is close while m is well below the
    weights' effective sample size (the ESS is reported next to every C2ST row).
    """
    x = _array(samples, "samples", 2)
    n = check_positive_int(n, "n")
    rng = numpy_generator(seed)
    w = np.full(x.shape[0], 1.0 / x.shape[0]) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (x.shape[0],) or not np.all(np.isfinite(w)) or np.any(w < 0) or not w.sum() > 0:
        raise ValueError(f"weights: expected {x.shape[0]} finite non-negative weights with a positive sum")
    m = min(n, int(np.count_nonzero(w)))
    return x[rng.choice(x.shape[0], m, replace=False, p=w / w.sum())]


def mmd(samples_a, samples_b, seed, *, max_samples: int | None = 2000) -> float:
    """Unbiased squared MMD between two sample sets (sbi's, Gaussian kernel, median heuristic), on
    coordinates z-scored by ``samples_a``'s statistics (as sbi's C2ST does) so every limit
    counts alike; each set subsampled (seeded) to at most ``max_samples`` rows (the cost is
    quadratic)."""
    a = _array(samples_a, "samples_a", 2)
    b = _array(samples_b, "samples_b", 2)
    if a.shape[1] != b.shape[1]:
        raise ValueError(f"samples_b: dimension {b.shape[1]} differs from samples_a's {a.shape[1]}")
    rng = numpy_generator(seed)
    if max_samples is not None:
        m = check_positive_int(max_samples, "max_samples", minimum=2)
        a = a[rng.choice(a.shape[0], m, replace=False)] if a.shape[0] > m else a
        b = b[rng.choice(b.shape[0], m, replace=False)] if b.shape[0] > m else b
    mean, std = a.mean(0), a.std(0)
    std = np.where(std > 0, std, 1.0)
    import torch

    return sbi_adapter.mmd(torch.from_numpy((a - mean) / std), torch.from_numpy((b - mean) / std))


def reference_distances(result: PosteriorResult, reference, seed, *, n: int = 2000) -> dict:
    """C2ST and MMD of ``result``'s posterior against ``reference`` draws (N, D), sbibm-style.

    Both sets are `distinct_draws` (at most ``n``; the reference's are equally weighted), on
    the coordinates that vary in the reference (known limits of a strong prior are constant
    and carry nothing). Returns ``{"c2st", "mmd", "distinct_draws", "posterior"}``: a result
    that is a point estimate (one sample: naive, nominal, oracle) or has fewer than 10
    distinct draws is not a posterior: NaN distances and ``posterior`` False, never a number
    made up for it.
    """
    if not isinstance(result, PosteriorResult):
        raise TypeError(f"result: expected a PosteriorResult, got {type(result).__name__}")
    ref = _array(reference, "reference", 2)
    if ref.shape[1] != result.samples.shape[1]:
        raise ValueError(f"reference: dimension {ref.shape[1]} differs from the result's {result.samples.shape[1]}")
    rng = numpy_generator(seed)
    draws = distinct_draws(result.samples, result.weights, n, rng)
    distinct = int(np.unique(draws, axis=0).shape[0])
    if result.samples.shape[0] == 1 or distinct < 10:
        return {"c2st": float("nan"), "mmd": float("nan"), "distinct_draws": distinct, "posterior": False}
    ref = distinct_draws(ref, None, n, rng)
    vary = ref.std(0) > 0
    return {"c2st": c2st(ref[:, vary], draws[:, vary], rng), "mmd": mmd(ref[:, vary], draws[:, vary], rng),
            "distinct_draws": distinct, "posterior": True}


# --------------------------------------------------------------------------- plot


@paper_figure
def plot_coverage(df_by_method, *, coordinate: str = "overall", title: str | None = None,
                  figsize=(SINGLE_COLUMN, 4.6)) -> Figure:
    """Coverage vs credibility level α per method, with the diagonal (perfect calibration),
    in the paper style (single column by default; the legend below the axes, or to their
    right when the figure is wider than high).

    Args:
        df_by_method: {method: DataFrame from central_interval_coverage}, or one DataFrame with
            a ``method`` column (e.g. coverage.csv). Needs columns ``alpha`` and ``coverage``;
            rows are filtered to ``coordinate`` when a ``coordinate`` column exists, and
            repeated (method, alpha) rows (several tasks/budgets) are averaged.
    """
    if isinstance(df_by_method, pd.DataFrame):
        if "method" not in df_by_method:
            raise ValueError("df_by_method: a single DataFrame needs a 'method' column")
        df = df_by_method.copy()
    elif isinstance(df_by_method, Mapping):
        if not df_by_method:
            raise ValueError("df_by_method: empty mapping")
        parts = []
        for m, d in df_by_method.items():
            if not isinstance(d, pd.DataFrame):
                raise TypeError(f"df_by_method: value for {m!r} is {type(d).__name__}, expected a DataFrame")
            parts.append(d.assign(method=str(m)))
        df = pd.concat(parts, ignore_index=True)
    else:
        raise TypeError(f"df_by_method: expected a dict of DataFrames or a DataFrame, got {type(df_by_method).__name__}")
    missing = {"alpha", "coverage"} - set(df.columns)
    if missing:
        raise ValueError(f"df_by_method: missing columns {sorted(missing)}")
    if "coordinate" in df:
        df = df[df["coordinate"].astype(str) == coordinate]
        if df.empty:
            raise ValueError(f"coordinate: no rows with coordinate == {coordinate!r}")
    agg = df.groupby(["method", "alpha"], sort=True)["coverage"].agg(["mean", "min", "max"]).reset_index()
    fig = Figure(figsize=figsize, layout="constrained")
    ax = fig.subplots()
    ax.plot([0, 1], [0, 1], ls="--", color="0.6", lw=1, label="calibrated (diagonal)")
    spread = False
    for m in method_order(agg["method"].astype(str)):
        g = agg[agg["method"].astype(str) == m]
        st = method_style(m)
        ax.plot(g["alpha"], g["mean"], ms=3, lw=1.3, label=m, **st.line_kwargs())
        if (g["max"] > g["min"]).any():
            spread = True
            ax.fill_between(g["alpha"], g["min"], g["max"], color=st.color, alpha=0.15, lw=0)
    ax.set(xlim=(0, 1), ylim=(0, 1), xlabel="credibility level α (central interval)",
           ylabel="empirical coverage", aspect="equal")
    ax.set_title(title or f"Coverage ({coordinate})", wrap=True)
    ax.text(0.97, 0.03, "below diagonal:\nover-confident", ha="right", va="bottom",
            transform=ax.transAxes, fontsize=MIN_FONT_PT, color="0.4")
    wide = fig.get_figwidth() > fig.get_figheight()
    where = {"loc": "upper left", "bbox_to_anchor": (1.02, 1.0)} if wide else \
        {"loc": "upper left", "bbox_to_anchor": (0.0, -0.16), "ncols": 2}
    ax.legend(fontsize=MIN_FONT_PT, frameon=False, title_fontsize=MIN_FONT_PT,
              title="band: min–max over tasks/budgets" if spread else None, **where)
    return fig
