"""The limits of a `camo-sbi infer` run: limits.csv (`limits_table`: per method, joint and bound
the estimate, the observed range, the 90% interval, identifiability, exercised, calibration
(overall and on the bounds no reach touched) and status) and the same limits as a person reads
them (`wide_limits`: one row per joint, one column per method, with the marks of
`WIDE_LIMITS_KEY`).
"""

from __future__ import annotations

__all__ = ["EXERCISED_MARGIN_DEG", "EXERCISED_MARGIN_M", "FALLBACK_MARK", "INTERVAL", "NARROWED",
           "OBSERVED_RANGE_METHODS", "OVERCONFIDENT_MARK", "WIDE_LIMITS_KEY", "limits_table", "wide_limits"]

NARROWED = 0.5
"""`limits_table`: on end-effector-only data a bound is exercised when its 90% interval is below this
fraction of the prior's."""
INTERVAL = 0.90
"""The central interval of ``lower_90_deg`` .. ``upper_90_deg`` and of ``identifiability``."""
EXERCISED_MARGIN_DEG = 2.0
"""`limits_table`: a bound is exercised when a recorded angle came within this margin (plus the noise
allowance, `K_SIGMA` sigma) of the bound's estimate (prismatic joints: `EXERCISED_MARGIN_M`)."""
EXERCISED_MARGIN_M = 0.005
OBSERVED_RANGE_METHODS = ("naive",)
"""Methods whose estimate is the observed extreme itself: exercised by construction, so their
``exercised`` is left empty (the observed range is the range used in the task, never a limit)."""


def limits_table(results: dict, sim, task=None, clipped=()):
    """One row per method, joint and bound: estimate [rad], [deg], the joint's observed range
    [deg], posterior median [deg], the 90% central interval [deg], identifiability, exercised,
    the calibration verdicts and the status.

    Point methods (one sample) have both interval ends and the median at the estimate, and no
    identifiability. Prismatic joints: ``estimate_rad`` holds metres and the degree columns are
    empty. With ``task`` (its prior and observations):

    * ``observed_min_deg``, ``observed_max_deg``: the joint's recorded range over every reach
      (empty without joint columns), beside every method's estimate.
    * ``identifiability``: the 90% interval's width over the prior's 90% width for this bound
      (1: the data taught nothing; a bound fixed by the prior: empty).
    * ``margin_deg``: `EXERCISED_MARGIN_DEG` plus the noise allowance (`K_SIGMA` sigma).
    * ``reaches_at_bound``: reaches whose recorded extreme on this side came within
      ``margin_deg`` of the bound's ESTIMATE (not of its interval: a wide interval that begins
      at the observed extreme would always pass).
    * ``exercised``: the recorded extreme on this side (the lowest angle of every reach for a
      lower bound, the highest for an upper one) lies within ``margin_deg`` of the estimate. An
      estimate short of the recorded extreme (the data went past it) is not exercised either. A method whose estimate is the observed
      extreme itself (naive, `OBSERVED_RANGE_METHODS`) is exercised by construction, which says
      nothing about a limit: its ``exercised`` is empty. With no joint columns (end-effector-only
      data, nothing to come close with) instead: the posterior narrowed the bound below
      `NARROWED` of the prior width. With joint columns narrowing alone does not count: an
      over-confident posterior (CAMO's, see ``calibration``) narrows bounds no reach touched,
      which is exactly the misreading "not exercised" guards against. An unexercised bound is
      not evidence of an impairment: the data say nothing about it.
    * ``clipped_samples``, ``beyond_range``: from ``clipped`` (`Recording.clipped`): how many
      recorded samples went past the model's range on this side and were clipped onto it, and
      the most beyond (degrees; metres for a prismatic joint); 0 and empty otherwise. Such a
      bound's estimate is the model's range, not the person's (the wide table marks it "!").

    Without ``task`` too, per method (the same on each of its rows): ``calibration``, the measured
    verdict of its intervals pooled over every coordinate (`calibration_verdict`), and
    ``untouched_coverage_90`` with ``untouched_calibration``, the measured coverage of its 90%
    intervals on the binding bounds no reach touched and its verdict (`untouched_verdict`, from
    docs/studies/exact_binding). A method calibrated overall can be over-confident exactly there:
    an unexercised bound's narrow interval is not evidence (the wide table marks such a method with
    `OVERCONFIDENT_MARK`).
    """
    import numpy as np
    import pandas as pd

    from camo_sbi.diagnostics.verdicts import calibration_verdict, untouched_verdict
    from camo_sbi.inference.result import weighted_quantile
    from camo_sbi.io.schema import BOUND_SLACK, K_SIGMA

    a = (1.0 - INTERVAL) / 2
    types = getattr(getattr(sim, "spec", None), "joint_types", ("revolute",) * sim.n_joints)
    model = "" if task is None else str(task.name)
    q_lo = q_hi = None
    allow = BOUND_SLACK
    if task is not None:
        qs = [o.q.numpy() for o in task.observations if o.q is not None]
        if qs:
            q_lo = np.stack([q.min(axis=0) for q in qs])  # (reaches, n)
            q_hi = np.stack([q.max(axis=0) for q in qs])
        allow += K_SIGMA * task.noise.sigma("joint") if task.noise is not None else 0.0
        prior_w = INTERVAL * (task.prior.high - task.prior.low).numpy()
    past = {(c["joint"], c["bound"]): c for c in clipped}
    rows = []
    for name, res in results.items():
        w = res.normalized_weights()
        lo, med, hi = weighted_quantile(res.samples, w, [a, 0.5, 1.0 - a])  # one sort per coordinate
        point = res.samples.shape[0] <= 1
        verdict = calibration_verdict(name, model)  # measured: camo_sbi.diagnostics.verdicts
        untouched_cov, untouched = untouched_verdict(name, model)  # measured: docs/studies/exact_binding
        for j, joint in enumerate(sim.joint_names):
            rev = types[j] == "revolute"
            deg = (lambda v: float(np.degrees(v))) if rev else (lambda v: float("nan"))
            margin = (np.radians(EXERCISED_MARGIN_DEG) if rev else EXERCISED_MARGIN_M) + allow
            seen = (deg(q_lo[:, j].min()), deg(q_hi[:, j].max())) if q_lo is not None else (float("nan"),) * 2
            for b, bound in enumerate(("lower", "upper")):
                k = 2 * j + b
                ident = touching = float("nan")
                exercised = None
                if task is not None:
                    if not point:
                        ident = float((hi[k] - lo[k]) / prior_w[k]) if prior_w[k] > 0 else float("nan")
                    touching, near = 0, False
                    if q_lo is not None:
                        x = q_lo[:, j] if b == 0 else q_hi[:, j]
                        gap = np.abs(x - float(res.estimate[k]))
                        touching = int((gap <= margin).sum())
                        extreme = x.min() if b == 0 else x.max()  # the recorded extreme on this side
                        near = bool(abs(extreme - float(res.estimate[k])) <= margin)
                    narrowed = q_lo is None and bool(np.isfinite(ident) and ident < NARROWED)
                    exercised = bool(near or narrowed)
                    if name in OBSERVED_RANGE_METHODS and q_lo is not None:
                        exercised = None
                rows.append({"method": name, "joint": joint, "bound": bound,
                             "estimate_rad": float(res.estimate[k]), "estimate_deg": deg(res.estimate[k]),
                             "observed_min_deg": seen[0], "observed_max_deg": seen[1],
                             "median_deg": deg(res.estimate[k] if point else med[k]),
                             "lower_90_deg": deg(lo[k]), "upper_90_deg": deg(hi[k]), "identifiability": ident,
                             "margin_deg": deg(margin) if task is not None else float("nan"),
                             "reaches_at_bound": touching, "exercised": exercised, "calibration": verdict,
                             "untouched_coverage_90": untouched_cov, "untouched_calibration": untouched,
                             "clipped_samples": int(past[(joint, bound)]["samples"]) if (joint, bound) in past else 0,
                             "beyond_range": float(past[(joint, bound)]["beyond"]) if (joint, bound) in past
                             else float("nan"), "status": res.status})
    return pd.DataFrame(rows, columns=["method", "joint", "bound", "estimate_rad", "estimate_deg",
                                       "observed_min_deg", "observed_max_deg", "median_deg", "lower_90_deg",
                                       "upper_90_deg", "identifiability", "margin_deg", "reaches_at_bound",
                                       "exercised", "calibration", "untouched_coverage_90", "untouched_calibration",
                                       "clipped_samples", "beyond_range", "status"])


FALLBACK_MARK = "\u2020"
"""A method whose status is not "ok" (it fell back or failed) carries this mark in the wide table."""
OVERCONFIDENT_MARK = "\u2021"
"""A method measured over-confident on the bounds no reach touched (limits.csv:
``untouched_calibration``) carries this mark in the wide table."""
WIDE_LIMITS_KEY = ("lower .. upper [deg] of the model's joint angles (not ISB clinical angles); observed = the "
                   "range recorded in these reaches (the functional range of the task, not the person's maximal "
                   "range; naive is that range); * = not exercised: no recorded angle came within the margin "
                   "(limits.csv: margin_deg) of the estimate, so the data say nothing about that bound; "
                   "\u2020 = the method fell back or failed (its status in limits.csv); ! = the recording went "
                   "past the model's range on this side and was clipped onto it (--out-of-range; limits.csv: "
                   "clipped_samples, beyond_range): that estimate is the model's range, not the person's; "
                   "\u2021 = this method's 90% intervals were measured over-confident on binding bounds no reach "
                   "touched, in synthetic studies (limits.csv: untouched_calibration): its interval on a * bound may "
                   "well miss the true limit")


def _past_mark(row) -> str:
    """"!" for a bound the recording went past (clipped onto the model's range), else ""."""
    n = row.get("clipped_samples", 0)
    return "!" if n == n and int(n or 0) > 0 else ""  # n == n: not NaN


def wide_limits(table):
    """The limits as a person reads them: one row per joint, the observed range first (when the
    recording has joint angles), then one column per method, each cell "lower .. upper" in degrees
    with 1 decimal; a bound no reach exercised is marked "*", a bound the recording went past (its
    samples clipped onto the model's range, ``clipped_samples``) "!", a method whose status is
    not "ok" carries `FALLBACK_MARK` after its name, and one measured over-confident on untouched
    bounds (``untouched_calibration``) `OVERCONFIDENT_MARK`."""
    import numpy as np
    import pandas as pd

    def cell(g) -> str:
        parts = []
        for bound in ("lower", "upper"):
            r = g[g["bound"] == bound].iloc[0]
            v = r["estimate_deg"] if np.isfinite(r["estimate_deg"]) else r["estimate_rad"]
            ex = r["exercised"]
            mark = "*" if ex is not None and not (isinstance(ex, float) and np.isnan(ex)) and not bool(ex) else ""
            parts.append(f"{v:.1f}{mark}{_past_mark(r)}")
        return " .. ".join(parts)

    joints = list(dict.fromkeys(table["joint"]))
    out = {}
    if "observed_min_deg" in table and table["observed_min_deg"].notna().any():
        first = table.drop_duplicates(["joint", "bound"]).set_index(["joint", "bound"])
        out["observed"] = [f"{first.loc[(j, 'lower'), 'observed_min_deg']:.1f}{_past_mark(first.loc[(j, 'lower')])} .. "
                           f"{first.loc[(j, 'upper'), 'observed_max_deg']:.1f}{_past_mark(first.loc[(j, 'upper')])}"
                           for j in joints]
    for m in dict.fromkeys(table["method"]):
        t = table[table["method"] == m]
        ok = (t["status"].astype(str) == "ok").all() if "status" in t else True
        over = "untouched_calibration" in t and t["untouched_calibration"].astype(str).str.startswith(
            "over-confident").any()
        marks = ("" if ok else FALLBACK_MARK) + (OVERCONFIDENT_MARK if over else "")
        out[f"{m} {marks}" if marks else m] = [cell(t[t["joint"] == j]) for j in joints]
    return pd.DataFrame(out, index=pd.Index(joints, name="joint"))
