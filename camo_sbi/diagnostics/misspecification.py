"""Does the posterior reproduce what was observed? A posterior-predictive check per reach (issue 33).

For a result with posterior draws and each observed reach ``y`` (start, goal, the recorded path
in the space it was recorded in: end effector if present, else joint angles), ``S`` draws
``theta_s`` are taken from the posterior (multinomial resampling, seeded) and simulated on the
same start and goal with the task's simulator: ``Y_1 .. Y_S`` (plus the task's recorder noise,
`NoiseModel.perturb`, when it has one). Each member ``Z_k`` of ``{y, Y_1, ..., Y_S}`` gets a
statistic ``T(Z_k)`` and the reach's p-value is the rank of ``T(y)`` among the S + 1 statistics,
ties broken at random (seeded)::

    p = (#{s: T(Y_s) > T(y)} + U (#{s: T(Y_s) = T(y)} + 1)) / (S + 1),   U ~ U(0, 1)

When ``y`` is exchangeable with the replicates, every ordering is equally likely and ``p`` is
exactly uniform on (0, 1); a reach the model cannot produce lies beyond every replicate,
``p = U / (S + 1)``.

Two statistics, two questions:

* ``statistic="onset"`` (the default: the model check). The share of its peak speed at which the
  reach sets off, ``o(Z) = |Z(1) - Z(0)| / max_t |Z(t+1) - Z(t)|``, and
  ``T(Z_k) = |o(Z_k) - mean_{j != k} o(Z_j)| / sd`` (sd over the members, floored). The
  differential-kinematics controller takes its first step at (nearly) full speed whatever the
  limits; a person, and the minimum-jerk and via-point generators, set off from rest (the
  measured shares are in docs/guide/misspecification.md).
  Because the share barely depends on the limits, the check does not depend on the posterior
  being calibrated: it tests the reach law, not the fit of the limits. Every member's share gets
  the same N(0, ``onset_tolerance``^2) jitter first (`ONSET_TOLERANCE`, 0.1), so a few hundredths
  between the truth's limits and the posterior's do not decide it, and a quarter of the
  replicates come from prior draws (`ONSET_PRIOR_SHARE`): a posterior too sure of a bound that
  slows the first step is not read as a wrong reach law. (With prior draws the observed reach
  is no longer exchangeable with every replicate: the test is then conservative, not exact.)
* ``statistic="path"`` (the fit). The mean distance per step of the path (held at its final
  point, jittered by ``tolerance_mm``) to the mean path of the other members. It also detects a
  wrong posterior: an over-confident posterior does not reproduce reaches that bind, so on
  exact-model data it raises false alarms (measured in docs/guide/misspecification.md).

Per recording: the reach p-values are Holm-adjusted (valid under any dependence between reaches,
which share one posterior); the recording's p-value is the smallest adjusted one (= Bonferroni's
``m min_i p_i``), and the reaches flagged are those with an adjusted p below ``alpha`` (0.05).

``test="mmd"``: sbi's ``calc_misspecification_mmd`` (x-space, RBF kernel, median heuristic,
permutation baseline) on the flattened paths, through the sbi adapter: the comparison the
issue asks for; the default is the rank test above (see the guide for which measures better).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

__all__ = ["ALPHA", "CHECK_DRAWS", "STATISTIC", "ReproductionCheck", "check_metrics", "check_reproduction", "column_text", "holm",
           "ONSET_PRIOR_SHARE", "ONSET_TOLERANCE", "onset_share", "rank_p_values",
           "reach_rows", "verdict_lines"]

CHECK_DRAWS = 399
"""Posterior draws simulated per reach (the smallest reach p-value is 1/400: with 10 reaches the
Holm-adjusted floor is 0.025, below ``ALPHA``)."""

ALPHA = 0.05
"""A recording (and a reach, Holm-adjusted) is flagged when its p-value is below this."""

TESTS = ("rank", "mmd")
STATISTICS = ("onset", "timing", "path")
STATISTIC = "onset"
"""The default statistic (module docstring): the reach law, not the fit of the limits."""
PRIOR_SHARE = 0.0
"""Share of the reference draws taken from the prior instead of the posterior for the ``path``
and ``timing`` statistics (0: a pure posterior-predictive check; 1: a prior-predictive check,
Box 1980)."""

ONSET_PRIOR_SHARE = 0.25
"""The same share for the ``onset`` statistic (the default). The onset share barely depends on
the limits, so prior draws cost the check little power against a person who sets off from rest,
while they keep a posterior that is too sure of a bound near the start posture (which can slow
the controller's first step) from being read as a wrong reach law."""

PROFILE_POINTS = 20
"""Points of the normalized speed profile (`timing_features`)."""
FEATURE_SD_FLOOR = 0.05
"""Floor of a feature's spread in the standardization of `timing_features` (a reach whose replicates
all move alike does not turn a numerical difference into a large statistic)."""

TOLERANCE_MM = 10.0
"""Jitter sd (per coordinate and step, mm) added to the observed path AND to every replicate before
the rank test: the same for all S + 1 members, so exchangeability (and the p-value's uniformity
under it) is kept, while a misfit well below it (a slightly over-confident posterior) barely
moves the statistic and one well above it (another timing, a via point) dominates it."""

ONSET_TOLERANCE = 0.1
"""Jitter sd added to every member's onset share (the observed reach's and each replicate's, the
same law for all, so exchangeability and uniformity are kept) before the onset statistic: a
difference of a few hundredths between the truth's limits and the posterior's (noise-free data,
a posterior that is slightly off) does not decide the test; setting off from rest (share ~0.0
against the controller's ~1.0) still does."""

TOLERANCE_DEG = 2.0
"""The jitter in joint space (degrees), for reaches recorded as joint angles only."""


def holm(p) -> np.ndarray:
    """Holm's step-down adjusted p-values of ``p`` (m,), in the input order."""
    p = np.asarray(p, dtype=np.float64)
    m = p.shape[0]
    order = np.argsort(p, kind="stable")
    adj = np.minimum(1.0, np.maximum.accumulate((m - np.arange(m)) * p[order]))
    out = np.empty(m)
    out[order] = adj
    return out


def _held(paths: list[torch.Tensor], steps: int) -> torch.Tensor:
    """(K, steps, d): each (L, d) path held at its final point."""
    out = []
    for z in paths:
        z = z.to(torch.float64)
        if z.shape[0] < steps:
            z = torch.cat([z, z[-1:].expand(steps - z.shape[0], -1)])
        out.append(z[:steps])
    return torch.stack(out)


def timing_features(path: torch.Tensor) -> np.ndarray:
    """(PROFILE_POINTS + 1,) the timing of one trimmed path (L, d): its speed profile over
    normalized time (speed per step divided by the mean speed, linearly interpolated at
    PROFILE_POINTS points of [0, 1]) and log(L). Scale-free, and nearly free of the limits: the
    controller's profile (fast start, exponential approach) and a person's (a bell, two bells
    through a via point) differ whatever the limits."""
    z = path.to(torch.float64).numpy()
    L = z.shape[0]
    if L < 3:
        return np.concatenate([np.zeros(PROFILE_POINTS), [np.log(L)]])
    v = np.linalg.norm(np.diff(z, axis=0), axis=-1)
    mean = v.mean()
    v = v / mean if mean > 0 else np.zeros_like(v)
    t = (np.arange(v.shape[0]) + 0.5) / v.shape[0]
    prof = np.interp((np.arange(PROFILE_POINTS) + 0.5) / PROFILE_POINTS, t, v)
    return np.concatenate([prof, [np.log(L)]])


SHAPE_POINTS = 50
"""Points of a path resampled over its own duration (`ReproductionCheck.shape_error_mm`)."""


def _normalised_time(path: torch.Tensor, points: int = SHAPE_POINTS) -> torch.Tensor:
    """(points, d): the (L, d) path linearly interpolated at ``points`` equally spaced fractions of
    its own duration (first and last samples kept)."""
    z = path.to(torch.float64)
    L = z.shape[0]
    if L == 1:
        return z.expand(points, -1).clone()
    t = torch.linspace(0.0, L - 1.0, points, dtype=torch.float64)
    i0 = t.floor().long().clamp(max=L - 2)
    w = (t - i0).unsqueeze(-1)
    return (1 - w) * z[i0] + w * z[i0 + 1]


def onset_share(path: torch.Tensor) -> float:
    """The share of its peak step speed at which the (L, d) path sets off: |Z(1) - Z(0)| / max_t
    |Z(t+1) - Z(t)|, in [0, 1] (1.0 for a path that never moves or has one point)."""
    z = path.to(torch.float64)
    if z.shape[0] < 2:
        return 1.0
    v = (z[1:] - z[:-1]).norm(dim=-1)
    peak = float(v.max())
    return float(v[0]) / peak if peak > 0 else 1.0


def _feature_statistics(f: np.ndarray) -> np.ndarray:
    """T_k = || (f_k - mean of the others) / sd || over features (sd over all members, floored)."""
    k = f.shape[0]
    sd = np.maximum(f.std(axis=0), FEATURE_SD_FLOOR)
    others = (f.sum(axis=0, keepdims=True) - f) / (k - 1)
    return np.linalg.norm((f - others) / sd, axis=-1)


def _rank(stat: np.ndarray, rng: np.random.Generator, tol: float) -> float:
    greater = int((stat[1:] > stat[0] + tol).sum())
    equal = int((np.abs(stat[1:] - stat[0]) <= tol).sum())
    return (greater + rng.uniform() * (equal + 1)) / stat.shape[0]


def rank_p_values(z: torch.Tensor, rng: np.random.Generator) -> tuple[float, np.ndarray]:
    """The rank test of the module docstring on a stack ``z`` (S + 1, T, d), row 0 the observed
    path: returns (p, the S + 1 statistics)."""
    k = z.shape[0]
    total = z.sum(dim=0)
    others = (total.unsqueeze(0) - z) / (k - 1)
    stat = (z - others).norm(dim=-1).mean(dim=-1).numpy()
    return _rank(stat, rng, 1e-12 * max(1.0, float(np.abs(stat).max()))), stat


@dataclass(frozen=True)
class ReproductionCheck:
    """The per-reach verdict of one result (`check_reproduction`).

    Attributes:
        method: the result's method name.  status: "checked" or "not checked: <reason>".
        test: "rank" or "mmd".  spaces: per reach the space compared ("cartesian" / "joint").
        p_reach: (m,) raw p-values per reach.  p_adjusted: (m,) Holm-adjusted.
        p_recording: the recording's p-value (the smallest adjusted one).  alpha: the level.
        n_draws: posterior draws per reach.  n_simulations: simulations the check ran.
        distance_mm: per reach the observed path's distance to the posterior-predictive mean
            (mm in Cartesian space, degrees in joint space) and ``replicate_mm`` the replicates'
            median distance (reported whatever the statistic; posterior draws only, never the
            reference's prior draws, as for the errors below).  statistic: "onset", "timing" or
            "path".  onset_observed / onset_replicates: per reach the observed path's onset share
            (`onset_share`) and the replicates' median one.  predictive_error_mm: per reach the
            posterior-predictive Cartesian error: the mean over the draws of the mean distance per
            step (mm) between the observed hand path (forward kinematics of the joint angles when
            no end effector was recorded) and the draw's simulated one, both held at their end,
            without recorder noise.  shape_error_mm: the same with every path resampled over its
            own duration to `SHAPE_POINTS` points (normalised time): the path's shape without
            its timing.
    """

    method: str
    status: str
    test: str = "rank"
    spaces: tuple[str, ...] = ()
    p_reach: np.ndarray = field(default_factory=lambda: np.zeros(0))
    p_adjusted: np.ndarray = field(default_factory=lambda: np.zeros(0))
    p_recording: float = float("nan")
    alpha: float = ALPHA
    n_draws: int = 0
    n_simulations: int = 0
    distance_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    replicate_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    p_pooled: float = float("nan")
    statistic: str = STATISTIC
    onset_observed: np.ndarray = field(default_factory=lambda: np.zeros(0))
    onset_replicates: np.ndarray = field(default_factory=lambda: np.zeros(0))
    predictive_error_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    shape_error_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def checked(self) -> bool:
        return self.status == "checked"

    @property
    def flagged(self) -> bool:
        """The recording is not reproduced (its p-value is below ``alpha``)."""
        return self.checked and self.p_recording < self.alpha

    @property
    def flagged_reaches(self) -> list[int]:
        """0-based indices of the reaches whose Holm-adjusted p-value is below ``alpha``."""
        return [int(i) for i in np.nonzero(self.p_adjusted < self.alpha)[0]] if self.checked else []

    def verdicts(self) -> list[str]:
        """Per reach a one-word verdict: "reproduced", "not reproduced" or the status."""
        if not self.checked:
            return [self.status] * max(1, len(self.p_reach))
        bad = set(self.flagged_reaches)
        return ["not reproduced" if i in bad else "reproduced" for i in range(len(self.p_reach))]


def _p_text(p: float) -> str:
    return "p < 0.01" if p < 0.01 else f"p = {p:.2f}"


def verdict_lines(check: ReproductionCheck) -> list[str]:
    """The warnings a run prints and writes: one per flagged reach (0-based, as the report's
    figures), e.g. "abc-smc: the model does not reproduce reach 2 (p < 0.01, ...): read these
    limits with care"."""
    if not check.flagged:
        return []
    m = len(check.p_reach)
    units = ["mm" if sp == "cartesian" else "deg" for sp in check.spaces]
    lines = []
    for i in check.flagged_reaches:
        why = (f"it sets off at {100 * check.onset_observed[i]:.0f}% of its peak speed, the model's reaches at "
               f"{100 * check.onset_replicates[i]:.0f}%; " if check.statistic == "onset" and len(check.onset_observed) else "")
        lines.append(f"{check.method}: the model does not reproduce reach {i} ({_p_text(float(check.p_adjusted[i]))}, "
                     f"Holm over {m} reaches; {why}the observed path lies {check.distance_mm[i]:.0f} {units[i]} from "
                     f"the posterior-predictive mean, its replicates {check.replicate_mm[i]:.0f} {units[i]}): read "
                     f"these limits with care")
    return lines


def check_reproduction(task, result, *, seed: int, n_draws: int = CHECK_DRAWS, alpha: float = ALPHA,
                       test: str = "rank", statistic: str = STATISTIC, tolerance_mm: float = TOLERANCE_MM,
                       tolerance_deg: float = TOLERANCE_DEG, prior_share: float | None = None,
                       onset_tolerance: float = ONSET_TOLERANCE) -> ReproductionCheck:
    """Per reach of ``task.observations``, can the posterior of ``result`` reproduce it? (module docstring).

    A point estimate (one sample), a failed result or a task without observations is "not
    checked" (its status says why), never a silent pass. ``seed``: the draws, the recorder noise
    on the replicates and the tie-breaks. ``prior_share``: None takes `ONSET_PRIOR_SHARE` for the
    onset statistic and `PRIOR_SHARE` for the others.
    """
    from camo_sbi._validation import check_positive_int, derive_seed, torch_generator
    from camo_sbi.evaluation.evaluate import predictive_trajectories

    n_draws = check_positive_int(n_draws, "n_draws")
    if n_draws < 19:
        raise ValueError(f"n_draws: expected >= 19 (a p-value below 0.05 needs 19 replicates), got {n_draws}")
    for tol_name, tol in (("tolerance_mm", tolerance_mm), ("tolerance_deg", tolerance_deg),
                          ("onset_tolerance", onset_tolerance)):
        if not (isinstance(tol, (int, float)) and np.isfinite(tol) and tol >= 0):
            raise ValueError(f"{tol_name}: expected a number >= 0, got {tol!r}")
    if prior_share is None:
        prior_share = ONSET_PRIOR_SHARE if statistic == "onset" else PRIOR_SHARE
    if not (isinstance(prior_share, (int, float)) and 0 <= prior_share <= 1):
        raise ValueError(f"prior_share: expected a share in [0, 1], got {prior_share}")
    if test not in TESTS:
        raise ValueError(f"test: expected one of {TESTS}, got {test!r}")
    if statistic not in STATISTICS:
        raise ValueError(f"statistic: expected one of {STATISTICS}, got {statistic!r}")
    if not 0 < alpha < 1:
        raise ValueError(f"alpha: expected a level in (0, 1), got {alpha}")
    name = getattr(result, "method", "method")
    obs = task.observations
    if not obs:
        return ReproductionCheck(name, "not checked: no observed reaches", test, alpha=alpha)
    if str(getattr(result, "status", "ok")).startswith("failed"):
        return ReproductionCheck(name, f"not checked: the method failed ({result.status})", test, alpha=alpha)
    if np.unique(np.asarray(result.samples), axis=0).shape[0] <= 1:
        return ReproductionCheck(name, "not checked: a point estimate has no posterior predictive", test,
                                 alpha=alpha)
    rng = np.random.default_rng(derive_seed(seed, 0))
    n_prior = int(round(prior_share * n_draws))
    n_post = n_draws - n_prior  # the reported distances and predictive errors use these draws only
    draws = result.sample((n_draws - n_prior,), seed=rng).numpy()
    if n_prior:
        draws = np.concatenate([draws, task.prior.sample(n_prior, derive_seed(seed, 3)).numpy()])
    starts = torch.stack([o.start.to(torch.float64) for o in obs])
    goals = torch.stack([(o.goal if o.goal is not None else o.ee[-1]).to(torch.float64) for o in obs])
    pred = predictive_trajectories(task.simulator, draws, starts, goals)
    noise_gen = torch_generator(derive_seed(seed, 1))
    m = len(obs)
    p, dist, rep, spaces = np.empty(m), np.empty(m), np.empty(m), []
    onset_obs, onset_rep, pred_err, shape_err = np.empty(m), np.empty(m), np.empty(m), np.empty(m)
    member_stats = []
    for i, o in enumerate(obs):
        space = "cartesian" if o.ee is not None else "joint"
        spaces.append(space)
        y = o.ee if space == "cartesian" else o.q
        reps = [task.noise.perturb(pred.trimmed(s * m + i, space).to(torch.float64), space, noise_gen)
                for s in range(n_draws)]
        steps = max(y.shape[0], max(r.shape[0] for r in reps))
        z = _held([y, *reps], steps)
        scale = 1e3 if space == "cartesian" else 180.0 / np.pi
        jitter = (tolerance_mm if space == "cartesian" else tolerance_deg) / scale
        if jitter > 0:
            z = z + jitter * torch.randn(z.shape, generator=noise_gen, dtype=torch.float64)
        hand = (o.ee if o.ee is not None else task.simulator.forward_kinematics(o.q)).to(torch.float64)
        hands = [pred.trimmed(s * m + i, "cartesian").to(torch.float64) for s in range(n_post)]  # posterior only
        held = _held([hand, *hands], max(hand.shape[0], max(h.shape[0] for h in hands)))
        pred_err[i] = 1e3 * float((held[1:] - held[:1]).norm(dim=-1).mean())
        shaped = torch.stack([_normalised_time(h) for h in (hand, *hands)])
        shape_err[i] = 1e3 * float((shaped[1:] - shaped[:1]).norm(dim=-1).mean())
        onsets = np.array([onset_share(y)] + [onset_share(r) for r in reps])
        onset_obs[i], onset_rep[i] = onsets[0], float(np.median(onsets[1:]))
        if test == "rank" and statistic == "onset":
            jittered = onsets + onset_tolerance * rng.standard_normal(onsets.shape[0])
            stat = _feature_statistics(jittered[:, None])
            p[i] = _rank(stat, rng, 1e-9)
            member_stats.append(stat)
            stat = rank_p_values(z[:1 + n_post], rng)[1]  # the reported distances: the posterior's paths'
        elif test == "rank" and statistic == "timing":
            f = np.stack([timing_features(y.to(torch.float64))] + [timing_features(r) for r in reps])
            stat = _feature_statistics(f)
            p[i] = _rank(stat, rng, 1e-6)
            member_stats.append(stat)
            stat = rank_p_values(z[:1 + n_post], rng)[1]  # the reported distances: the posterior's paths'
        elif test == "rank":
            p[i], stat = rank_p_values(z, rng)
            member_stats.append(stat)
        else:
            from camo_sbi.inference.sbi_adapter import mmd_misspecification_p

            p[i] = mmd_misspecification_p(z[:1].flatten(1), z[1:].flatten(1), seed=derive_seed(seed, 2, i))
            stat = rank_p_values(z[:1 + n_post], rng)[1]
        dist[i], rep[i] = stat[0] * scale, float(np.median(stat[1:])) * scale
    adj = holm(p)
    pooled = _pooled_p(np.stack(member_stats), rng) if member_stats else float("nan")
    return ReproductionCheck(name, "checked", test, tuple(spaces), p, adj, float(adj.min()), alpha, n_draws,
                             n_draws * m, dist, rep, pooled, statistic, onset_obs, onset_rep, pred_err, shape_err)


def _pooled_p(stats: np.ndarray, rng: np.random.Generator) -> float:
    """The recording's pooled rank test: ``stats`` (m, S + 1) per reach the members' statistics,
    member k of every reach simulated from the same draw (member 0: the observed recording). Each
    member's per-reach tail share q_i(k) (average ranks) is pooled as sum_i -log q_i(k) (Fisher's
    form), and the observed recording is ranked among the S + 1 pooled values: exchangeable
    recordings give a uniform p-value whatever the dependence between reaches."""
    from scipy.stats import rankdata

    k = stats.shape[1]
    q = (k + 1 - rankdata(stats, axis=1)) / k  # share of members at least as extreme, in (0, 1]
    pooled = -np.log(q).sum(axis=0)
    return _rank(pooled, rng, 1e-9)


def column_text(check: ReproductionCheck) -> str:
    """The limits.csv ``model_check`` cell of a method: "not reproduced: reaches 0, 2 (p < 0.01)",
    "reproduced (p = 0.43 over 5 reaches)" or the status ("not checked: ...")."""
    if not check.checked:
        return check.status
    m = len(check.p_reach)
    if check.flagged:
        bad = ", ".join(str(i) for i in check.flagged_reaches)
        return f"not reproduced: reach{'es' if len(check.flagged_reaches) > 1 else ''} {bad} " \
               f"({_p_text(check.p_recording)}, Holm over {m} reaches)"
    return f"reproduced ({_p_text(check.p_recording)}, Holm over {m} reaches)"


def reach_rows(checks: dict) -> list[dict]:
    """One row per method and reach: the p-values, the verdict, the distances, the onset shares
    (observed, model's median) and the posterior-predictive Cartesian error (the report's table and
    ``model_check.csv``; ``checks``: {method: ReproductionCheck})."""
    rows = []
    for name, c in checks.items():
        if not c.checked:
            rows.append({"method": name, "reach": "", "verdict": c.status})
            continue
        for i, v in enumerate(c.verdicts()):
            unit = "mm" if c.spaces[i] == "cartesian" else "deg"
            rows.append({"method": name, "reach": i, "verdict": v, "p": round(float(c.p_reach[i]), 4),
                         "p_holm": round(float(c.p_adjusted[i]), 4),
                         "observed_from_mean": f"{c.distance_mm[i]:.1f} {unit}",
                         "replicates_from_mean": f"{c.replicate_mm[i]:.1f} {unit}",
                         "onset_observed": round(float(c.onset_observed[i]), 3),
                         "onset_model": round(float(c.onset_replicates[i]), 3),
                         "predictive_error_mm": round(float(c.predictive_error_mm[i]), 1),
                         "shape_error_mm": round(float(c.shape_error_mm[i]), 1)})
    return rows


def check_metrics(task, result, *, seed: int) -> dict[str, float]:
    """The results.csv rows of the check for the grid commands: ``model_check_p`` (the recording's
    Holm-adjusted p-value) and ``model_check_flagged`` (1.0 / 0.0); {} when not checked."""
    c = check_reproduction(task, result, seed=seed)
    if not c.checked:
        return {}
    return {"model_check_p": c.p_recording, "model_check_flagged": float(c.flagged)}
