"""`camo-sbi simulate-observations` and `camo-sbi infer`: synthetic recordings, and inference on recordings.

simulate-observations: a synthetic subject with the ``--limits`` file's limits reaches
``--reaches`` goals sampled as the experiments sample them (`reachable_goals`: joint
configurations uniform inside the true limits, through FK, kept if the subject's controller
reaches them), from the model's start posture. ``--rate-multiplier R`` resamples each reach
to R times as fast a recorder (round(R (L - 1)) + 1 samples, linear interpolation in time);
then `NoiseModel.perturb` adds the noise (seeded) to every recorded value, the start
included. Written in the recording format (`camo_sbi.io.recordings`).

infer: the recordings of one person or robot, the model, and the methods. The `Task` has no
test goals and no truth; its prior is the model's range split at the first reach's start
and conditioned on every reach's start lying inside the limits (`BoxPrior.containing`):
each start is an observed posture. Its noise model is ``--noise-joint-deg`` /
``--noise-ee-mm`` (carried in the task for the methods; the loader's range tolerance uses it).
Recordings from a lab (`add_recording_arguments`, `load_from_args`): C3D markers and BVH
channels, units, a lab frame, ``--goal final``, starts by IK, ``--body-scale free`` (the
methods then run on ``model.scaled(s)``); the loader's warnings are printed and go in the
report. The report and the summary open with the limits (`wide_limits`, `plot_limits`);
limits.csv adds median, identifiability, exercised and calibration (`limits_table`).
``--observations DIR/`` runs every recording of the folder (`infer_folder`).
Methods that need the truth (oracle) are skipped with a note. A method that cannot use the
file's space is an error naming ``space`` when it is the only method asked for, and skipped
with a printed reason when several are.
"""

from __future__ import annotations

import argparse
import json
import time
import urllib.parse
from pathlib import Path
from typing import TYPE_CHECKING

from tqdm import tqdm

from camo_sbi._io import atomic_write_text
from camo_sbi.experiments.figure_options import add_figure_format_argument, figure_formats
from camo_sbi.experiments.models import add_model_arguments, model_from_args, subject_limits

# only light modules at import time: the CLI builds its parser from the add_*_arguments functions
# (numpy and torch are imported by the functions that use them)
if TYPE_CHECKING:
    import numpy as np
    import torch

    from camo_sbi.diagnostics.pages import Markup

__all__ = ["add_infer_arguments", "add_recording_arguments", "add_simulate_arguments",
           "infer_main", "limits_table", "load_from_args", "simulate_main",
           "simulate_recordings", "wide_limits", "write_starts"]

PPC_DRAWS = 50
NARROWED = 0.5
"""`limits_table`: on end-effector-only data a bound is exercised when its 90% interval is below this
fraction of the prior's."""
MAX_REPORT_REACHES = 12
INTERVAL = 0.90


def _noise(args):
    from camo_sbi.task import NoiseModel

    try:
        return NoiseModel(joint_deg=args.noise_joint_deg, ee_mm=args.noise_ee_mm)
    except ValueError as exc:
        flag = "--noise-joint-deg" if str(exc).startswith("joint_deg") else "--noise-ee-mm"
        raise ValueError(f"{flag}: {str(exc).split(': ', 1)[1]}") from exc


def _add_noise_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--noise-joint-deg", type=float, default=0.0, help="noise sd per joint angle [deg]")
    p.add_argument("--noise-ee-mm", type=float, default=0.0, help="noise sd per end-effector coordinate [mm]")


# ----------------------------------------------------------------------------- simulate-observations


def simulate_recordings(sim, theta, n_reaches: int, *, seed: int, noise=None, rate_multiplier: float = 1.0,
                        generator: str = "controller", tremor_mm: float = 0.0):
    """Synthetic recorded reaches of a subject with limits ``theta`` (2n,): a tuple of `Observation`.

    Goals from `reachable_goals` (seed ``derive_seed(seed, 0)``); the subject moves by
    ``generator`` (`camo_sbi.scenarios.generators.make_generator`, nuisances seeded by
    ``derive_seed(seed, 2)``; "controller": the model itself); each reach resampled to
    ``rate_multiplier`` times as many samples (linear interpolation in time); noise from
    ``noise.perturb`` (seed ``derive_seed(seed, 1)``) on every value, start included.
    """
    import numpy as np
    import torch

    from camo_sbi._validation import derive_seed, torch_generator
    from camo_sbi.io.recordings import resample_to_controller
    from camo_sbi.scenarios.generators import make_generator
    from camo_sbi.scenarios.reaching import observe, reachable_goals
    from camo_sbi.task import NoiseModel, Observation

    noise = NoiseModel() if noise is None else noise
    if not (isinstance(rate_multiplier, (int, float)) and np.isfinite(rate_multiplier) and rate_multiplier > 0):
        raise ValueError(f"rate_multiplier: expected a number > 0, got {rate_multiplier!r}")
    theta = torch.as_tensor(theta, dtype=torch.float64)
    goals = reachable_goals(sim, theta, n_reaches, torch_generator(derive_seed(seed, 0)))
    exact = observe(make_generator(sim, generator, seed=derive_seed(seed, 2), tremor_mm=tremor_mm), theta, goals)
    if rate_multiplier != 1:
        exact = tuple(resample_to_controller(o, sim, mode="time", rate=1.0 / rate_multiplier) for o in exact)
    gen = torch_generator(derive_seed(seed, 1))
    out = []
    for o in exact:
        q = noise.perturb(o.q, "joint", gen)
        ee = noise.perturb(o.ee, "cartesian", gen)
        out.append(Observation(q[0].clone(), o.goal, q, ee))
    return tuple(out)


def add_simulate_arguments(p: argparse.ArgumentParser) -> None:
    add_model_arguments(p)
    p.add_argument("--reaches", type=int, default=10, help="number of reaches")
    p.add_argument("--seed", type=int, default=0)
    _add_noise_arguments(p)
    p.add_argument("--rate-multiplier", type=float, default=1.0,
                   help="the recorder samples R times per controller step (default 1)")
    p.add_argument("--generator", choices=("controller", "minimum-jerk", "via-point"), default="controller",
                   help="how the subject moves: the model's controller (default) or human-like paths the methods "
                        "do not assume (camo_sbi.scenarios.generators)")
    p.add_argument("--tremor-mm", type=float, default=0.0,
                   help="physiological tremor sd per coordinate [mm] on minimum-jerk / via-point paths")
    p.add_argument("--scale", type=float, default=1.0,
                   help="the subject's segments are F times as long as the model's (default 1; 0.85-1.15)")
    p.add_argument("--space", choices=("both", "joint", "cartesian"), default="both",
                   help="columns written: joint angles, end-effector positions or both")
    p.add_argument("--out", type=Path, required=True, help="recording file to write (.csv or .npz)")


def simulate_main(args) -> int:
    import numpy as np
    import torch

    from camo_sbi._validation import derive_seed
    from camo_sbi.evaluation.claims import FEW_REACHES
    from camo_sbi.io.recordings import save_recordings
    from camo_sbi.scenarios.generators import make_generator
    from camo_sbi.scenarios.reaching import binding_reaches
    from camo_sbi.task import Observation

    if args.reaches < 1:
        raise ValueError("--reaches: must be >= 1")
    if not (np.isfinite(args.rate_multiplier) and args.rate_multiplier > 0):
        raise ValueError(f"--rate-multiplier: must be > 0, got {args.rate_multiplier}")
    if args.seed < 0:
        raise ValueError("--seed: must be >= 0")
    noise = _noise(args)
    tremor = getattr(args, "tremor_mm", 0.0)
    generator = getattr(args, "generator", "controller")
    if not (np.isfinite(tremor) and tremor >= 0):
        raise ValueError(f"--tremor-mm: must be >= 0, got {tremor}")
    if tremor and generator == "controller":
        raise ValueError("--tremor-mm: tremor needs --generator minimum-jerk or via-point")
    model = model_from_args(args)
    if model.limits is None:
        raise ValueError("--limits: simulate-observations needs the subject's true limits (--limits FILE.json)")
    if not (np.isfinite(args.scale) and 0.85 <= args.scale <= 1.15):
        raise ValueError(f"--scale: must lie in [0.85, 1.15], got {args.scale}")
    sim = model.build()
    theta = subject_limits(model, sim, model.limits_name)
    body = sim if args.scale == 1.0 else sim.scaled(args.scale)
    with tqdm(total=1, desc="simulate-observations", unit="file") as bar:
        obs = simulate_recordings(body, theta, args.reaches, seed=args.seed, noise=noise,
                                  rate_multiplier=args.rate_multiplier, generator=generator, tremor_mm=tremor)
        if args.space != "both":
            obs = tuple(Observation(o.start, o.goal, o.q if args.space == "joint" else None,
                                    o.ee if args.space == "cartesian" else None) for o in obs)
        path = save_recordings(args.out, obs, sim)
        bar.update()
    n = sum(o.length for o in obs)
    print(f"{model.name}: {len(obs)} reaches, {n} samples ({generator}) -> {path}")
    mover = sim if generator == "controller" else make_generator(body, generator, seed=derive_seed(args.seed, 2),
                                                                 tremor_mm=tremor)
    hit = binding_reaches(mover, theta, sim.bounds.reshape(-1), torch.stack([o.start for o in obs]),
                          torch.stack([o.goal for o in obs]))
    print(f"binding_train_fraction {float(hit.double().mean()):.2f}: {int(hit.sum())} of {len(obs)} reaches move "
          f"> 1 mm when the limits are relaxed to the nominal range"
          + (f" (fewer than {FEW_REACHES}: the data says little about the limits)" if int(hit.sum()) < FEW_REACHES
             else ""))
    return 0


# ----------------------------------------------------------------------------- infer


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
    the calibration verdict and the status.

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
    """
    import numpy as np
    import pandas as pd

    from camo_sbi.diagnostics.verdicts import calibration_verdict
    from camo_sbi.inference.result import weighted_quantile
    from camo_sbi.io.recordings import BOUND_SLACK, K_SIGMA

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
                             "clipped_samples": int(past[(joint, bound)]["samples"]) if (joint, bound) in past else 0,
                             "beyond_range": float(past[(joint, bound)]["beyond"]) if (joint, bound) in past
                             else float("nan"), "status": res.status})
    return pd.DataFrame(rows, columns=["method", "joint", "bound", "estimate_rad", "estimate_deg",
                                       "observed_min_deg", "observed_max_deg", "median_deg", "lower_90_deg",
                                       "upper_90_deg", "identifiability", "margin_deg", "reaches_at_bound",
                                       "exercised", "calibration", "clipped_samples", "beyond_range", "status"])


FALLBACK_MARK = "\u2020"
"""A method whose status is not "ok" (it fell back or failed) carries this mark in the wide table."""
WIDE_LIMITS_KEY = ("lower .. upper [deg] of the model's joint angles (not ISB clinical angles); observed = the "
                   "range recorded in these reaches (the functional range of the task, not the person's maximal "
                   "range; naive is that range); * = not exercised: no recorded angle came within the margin "
                   "(limits.csv: margin_deg) of the estimate, so the data say nothing about that bound; "
                   "\u2020 = the method fell back or failed (its status in limits.csv); ! = the recording went "
                   "past the model's range on this side and was clipped onto it (--out-of-range; limits.csv: "
                   "clipped_samples, beyond_range): that estimate is the model's range, not the person's")


def _past_mark(row) -> str:
    """"!" for a bound the recording went past (clipped onto the model's range), else ""."""
    n = row.get("clipped_samples", 0)
    return "!" if n == n and int(n or 0) > 0 else ""  # n == n: not NaN


def wide_limits(table):
    """The limits as a person reads them: one row per joint, the observed range first (when the
    recording has joint angles), then one column per method, each cell "lower .. upper" in degrees
    with 1 decimal; a bound no reach exercised is marked "*", a bound the recording went past (its
    samples clipped onto the model's range, ``clipped_samples``) "!", and a method whose status is
    not "ok" carries `FALLBACK_MARK` after its name."""
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
        out[m if ok else f"{m} {FALLBACK_MARK}"] = [cell(t[t["joint"] == j]) for j in joints]
    return pd.DataFrame(out, index=pd.Index(joints, name="joint"))


def _recorded_task(model, sim, obs, noise):
    import torch

    from camo_sbi.priors import BoxPrior
    from camo_sbi.task import Task

    prior = BoxPrior(sim.bounds, obs[0].start)
    if len(obs) > 1:
        prior = prior.containing(torch.stack([o.start for o in obs[1:]]))
    return Task(name=model.name, subject="recorded", simulator=sim, prior=prior, observations=obs, noise=noise)


def _plan(methods: list[str], task, space_arg: str | None, file_name: str) -> tuple[list, list[str]]:
    """(runnable [(method, space or None)], notes) for the methods asked for."""
    from camo_sbi.inference.registry import capabilities, get_method

    available = task.spaces
    if space_arg is not None and space_arg not in available:
        raise ValueError(f"--space: {file_name} has no {space_arg} trajectories (it has: {', '.join(available)})")
    plan, notes = [], []
    for m in methods:
        spec = get_method(m)
        cap = capabilities(m)
        if cap.needs_truth:
            notes.append(f"{m}: skipped (needs the true limits, which recorded data does not have)")
            continue
        if not cap.spaces:
            plan.append((m, None))
            continue
        if "space" in spec.defaults or len(cap.spaces) == 1:
            want = spec.defaults.get("space", cap.spaces[0])
        else:
            want = space_arg or available[0]
        if want not in available:
            reason = (f"space: method {m!r} needs {want} observations; {file_name} has only "
                      f"{' and '.join(available)} ones")
            if len(methods) == 1:
                raise ValueError(reason)
            notes.append(f"{m}: skipped ({reason})")
            continue
        plan.append((m, want if len(cap.spaces) > 1 and "space" not in spec.defaults else None))
    return plan, notes


def _check_amortized(plan: list, notes: list[str], task, obs, overrides: dict, path, only: bool) -> list:
    """Point amortized methods at ``--amortized`` and check, before anything runs, that the
    estimator fits this recording (model, noise, start, number of reaches); one that does not is
    skipped with a note (or refused, naming the reason, when it is the only method)."""
    from camo_sbi.experiments.amortize import load_cli_estimator
    from camo_sbi.inference.amortized import load_estimator
    from camo_sbi.inference.registry import capabilities

    kept = []
    for name, space in plan:
        if not capabilities(name).amortized:
            kept.append((name, space))
            continue
        cfg = overrides.get(name) or {}
        if path is not None:
            cfg = overrides[name] = {**cfg, "estimator_path": str(path)}
        if cfg.get("estimator_path") is None:
            raise ValueError(f"--amortized: {name} needs a trained estimator file (train one with "
                             f"`camo-sbi amortize --model M --out FILE`)")
        try:  # a file given by --config keeps load_estimator's own message
            est = (load_cli_estimator if path is not None else load_estimator)(cfg["estimator_path"])
            est.check_task(task, obs, space or cfg.get("space", "joint"))
        except ValueError as exc:
            if only:
                raise
            notes.append(f"{name}: skipped ({exc})")
            continue
        kept.append((name, space))
    return kept


def _limits_html(table, sim) -> Markup:
    """The limits figure (model range, estimates, 90% intervals, "not exercised") and the wide table."""
    import numpy as np

    from camo_sbi.diagnostics.figures import plot_limits
    from camo_sbi.diagnostics.pages import join, part
    from camo_sbi.diagnostics.report import figure_html, table_html

    types = getattr(getattr(sim, "spec", None), "joint_types", ("revolute",) * sim.n_joints)
    b = np.degrees(sim.bounds.double().numpy())
    ranges = {j: (float(b[i, 0]), float(b[i, 1])) for i, j in enumerate(sim.joint_names) if types[i] == "revolute"}
    parts = []
    if ranges:
        parts.append(figure_html(plot_limits(table, ranges),
                                 "Inferred joint limits [deg]: the model's range (grey), each method's estimate "
                                 "(marker) and 90% interval (line); hollow markers: bounds no reach exercised (not "
                                 "an impairment: the data say nothing about them)", alt="limits figure"))
    parts.append(part("meta", WIDE_LIMITS_KEY) + part("wide", table_html(wide_limits(table), index=True)))
    return join(parts)


def _shown_limits(table):
    """The limits table as a person reads it: degrees only (radians stay in limits.csv),
    unless a prismatic joint (metres, no degree column) needs ``estimate_rad``."""
    if table["estimate_deg"].notna().all():
        return table.drop(columns=["estimate_rad"])
    return table


def _ee_of(traj_ee: torch.Tensor, length: torch.Tensor, b: int) -> np.ndarray:
    import torch

    return traj_ee[b, : int(length[b])].to(torch.float64).numpy()


def method_title(name: str, status: str) -> str:
    """A panel title: the method's name, with `FALLBACK_MARK` when its status is not "ok" (the
    status itself, often a long sentence, goes into the caption, never into a title)."""
    return name if status == "ok" else f"{name} {FALLBACK_MARK}"


def reach_figure(sim, o, results: dict, draws: dict):
    """One reach: per method (columns) the end-effector path from above (top) and the distance
    to the goal per step (bottom): observed, the estimate's prediction, the posterior draws."""
    import numpy as np
    import torch
    from matplotlib.figure import Figure

    from camo_sbi.diagnostics.style import DOUBLE_COLUMN
    from camo_sbi.task import contain

    methods = list(results)
    seen = (o.ee if o.ee is not None else sim.forward_kinematics(o.q)).to(torch.float64).numpy()
    fig = Figure(figsize=(max(DOUBLE_COLUMN, 1.75 * len(methods)), 4.4), constrained_layout=True)
    axes = fig.subplots(2, len(methods), squeeze=False)
    for c, m in enumerate(methods):
        # float32, as CAMO's candidates: a new chain's float64 kernel is not compiled for a figure
        th = contain(draws[m], o.start).to(torch.float32)
        pred = sim.simulate(th, o.goal, o.start)
        est = sim.simulate(contain(torch.as_tensor(results[m].estimate), o.start).to(torch.float32), o.goal,
                           o.start)
        top, side = axes[0, c], axes[1, c]
        for b in range(th.shape[0]):
            e = _ee_of(pred.ee, pred.length, b)
            top.plot(e[:, 0], e[:, 1], color="C0", alpha=0.15, lw=0.8)
            side.plot(np.arange(e.shape[0]), np.linalg.norm(e - o.goal.numpy(), axis=1), color="C0",
                      alpha=0.15, lw=0.8)
        e = _ee_of(est.ee, est.length, 0)
        top.plot(e[:, 0], e[:, 1], color="C3", ls="--", lw=1.2, label="estimate")
        side.plot(np.arange(e.shape[0]), np.linalg.norm(e - o.goal.numpy(), axis=1), color="C3", ls="--",
                  lw=1.2)
        top.plot(seen[:, 0], seen[:, 1], color="k", lw=1.8, label="observed")
        side.plot(np.arange(seen.shape[0]), np.linalg.norm(seen - o.goal.numpy(), axis=1), color="k", lw=1.8)
        top.plot(*o.goal.numpy()[:2], marker="*", color="k", ms=10, ls="none")
        top.set_title(method_title(m, results[m].status))
        top.set_xlabel("x [m]")
        top.set_ylabel("y [m]")
        top.set_aspect("equal", adjustable="datalim")
        side.set_xlabel("controller step")
        side.set_ylabel("distance to goal [m]")
        if c == 0:
            top.legend()
    return fig


MODEL_CHECK_STREAM = 33
"""Seed stream of the reproduction check (`derive_seed(seed, MODEL_CHECK_STREAM)`)."""


def _model_checks(task, results: dict, seed: int) -> dict:
    """{method: `ReproductionCheck`}: does each posterior reproduce each observed reach (issue 33)?"""
    from camo_sbi._validation import derive_seed
    from camo_sbi.diagnostics.misspecification import check_reproduction

    return {name: check_reproduction(task, res, seed=derive_seed(seed, MODEL_CHECK_STREAM))
            for name, res in results.items()}


def _check_html(checks: dict):
    """The report's opening section: the warnings of the check, then its per-reach table."""
    import pandas as pd

    from camo_sbi.diagnostics.misspecification import reach_rows, verdict_lines
    from camo_sbi.diagnostics.pages import join, part
    from camo_sbi.diagnostics.report import table_html

    lines = [w for c in checks.values() for w in verdict_lines(c)]
    head = part("items", lines) if lines else part(
        "meta", "every posterior checked reproduces every reach (Holm-adjusted p >= 0.05)")
    return join([head, table_html(pd.DataFrame(reach_rows(checks)))])


def _report(out: Path, task, results: dict, notes: list[str], table, settings: dict, seed: int,
            formats=None, speed: dict | None = None, checks: dict | None = None) -> Path:
    """report.html: the model check (``checks``: does each posterior reproduce each reach?), the
    limits table (degrees) and, per reach, observed vs posterior-predictive paths (``speed``: the
    hand speed with the reach cuts); with ``formats`` (``--figure-format``) the figures also as
    files in ``out/report_figures``."""
    from camo_sbi.diagnostics.report import figure_files
    from camo_sbi.diagnostics.style import paper_style

    with paper_style(), figure_files(out / "report_figures", formats):
        return _report_page(out, task, results, notes, table, settings, seed, speed, checks)


def _report_page(out: Path, task, results: dict, notes: list[str], table, settings: dict, seed: int,
                 speed: dict | None = None, checks: dict | None = None) -> Path:
    import pandas as pd
    import torch

    from camo_sbi.diagnostics.pages import join, part
    from camo_sbi.diagnostics.report import figure_html, table_html, write_page

    sim = task.simulator
    obs = task.observations[:MAX_REPORT_REACHES]
    methods = list(results)
    reach_html = []
    # per method: PPC_DRAWS systematic posterior draws (deterministic), simulated once per reach
    draws = {m: torch.as_tensor(r.systematic(PPC_DRAWS if r.samples.shape[0] > 1 else 1), dtype=torch.float64)
             for m, r in results.items()}
    for i, o in enumerate(tqdm(obs, desc="report", unit="reach")):
        fig = reach_figure(sim, o, results, draws)
        fallback = [m for m in methods if results[m].status != "ok"]
        reach_html.append(figure_html(
            fig, f"reach {i}: observed (black), the estimate's prediction (red dashed) and "
                 f"{PPC_DRAWS} posterior-predictive draws per method (blue; point methods: one); "
                 f"top: end-effector path seen from above, bottom: distance to the goal per step"
                 + (f"; {FALLBACK_MARK}: fell back or failed ({'; '.join(f'{m}: {results[m].status}' for m in fallback)})"
                    if fallback else ""),
            alt=f"reach {i}"))
    more = len(task.observations) - len(obs)
    if more > 0:
        reach_html.append(part("meta", f"{more} more reaches not shown"))
    settings_html = part("wide", table_html(pd.DataFrame([{"setting": k, "value": str(v)}
                                                          for k, v in settings.items()])))
    sections = ([("model-check", "Does the model reproduce the recording?", _check_html(checks))] if checks else []) + [
        ("limits", "Estimated limits", _limits_html(table, sim)),
        ("settings", "Settings", settings_html + (part("items", notes) if notes else "")),
        ("limits-table", "All columns of limits.csv",
         part("meta", "degrees (limits.csv also holds radians, estimate_rad)")
         + part("wide", table_html(_shown_limits(table), float_format="{:.4g}"))),
        ("reaches", "Observed vs posterior-predictive reaches", join(reach_html)),
    ]
    if speed is not None:
        from camo_sbi.diagnostics.figures import plot_speed

        sections.insert(2, ("reaches-found", "Reaches found", figure_html(
            plot_speed(speed["time"], speed["speed"], speed["cuts"]),
            f"hand speed ({speed['source']}) and the {len(speed['cuts'])} reaches found (shaded, numbered as in "
            f"reaches.csv); rule: {speed['rule']}", alt="hand speed with the cuts")))
    return write_page(out / "report.html", f"camo_sbi infer: {settings['observations']}", sections,
                      meta=f"model {task.name}, {len(task.observations)} reaches, seed {seed}")


def add_infer_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--observations", type=Path, required=True,
                   help="recording file (.csv, .npz, .c3d, .bvh, or an OpenSim .mot/.sto of joint angles), or a folder "
                        "of them (one subject per file)")
    add_model_arguments(p, limits=False)
    p.add_argument("--methods", default="camo,camo-hull,naive,nominal", help="comma-separated method names")
    p.add_argument("--budget", type=int, default=500, help="simulations per observed reach")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--space", choices=("joint", "cartesian"), default=None,
                   help="space for methods that can use either (default: joint when the file has joint columns)")
    _add_noise_arguments(p)
    p.add_argument("--degrees", action="store_true", help="the recording's revolute joint columns are in degrees")
    p.add_argument("--resample", choices=("time", "arclength", "none"), default="time",
                   help="resample the recording to the controller's step (default: time)")
    p.add_argument("--rate", type=float, default=None,
                   help="recorded samples per controller step (default: estimated from the file)")
    add_recording_arguments(p)
    p.add_argument("--amortized", type=Path, default=None,
                   help="trained estimator file for npe-amortized (`camo-sbi amortize`)")
    p.add_argument("--predict-goals", type=Path, default=None,
                   help="CSV of goal_x,goal_y,goal_z[,start joint columns] to predict reaches for")
    p.add_argument("--config", action="append", default=[], metavar="METHOD=JSON",
                   help='per-method config overrides, e.g. --config \'npe={"max_epochs": 20}\' (repeatable)')
    p.add_argument("--suggest", type=int, default=0, metavar="N",
                   help=f"rank {SUGGEST_CANDIDATES} goals from the model's nominal workspace by what a reach to each "
                        "would tell about the limits (camo_sbi.design, the first posterior method's draws) and write "
                        "the best N to next_goals.csv")
    add_figure_format_argument(p)
    p.add_argument("--reach-model", choices=("controller", "minimum-jerk"), default="controller",
                   help="the reach law every method conditions on and predicts with: the differential-kinematics "
                        "controller (the paper's) or a human-like minimum-jerk reach (bell-shaped speed, duration "
                        "normalised; camo_sbi.scenarios.generators.reach_model); amortized estimators are skipped "
                        "with minimum-jerk (trained on the controller)")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--force", action="store_true",
                   help="--out holds an infer run with other settings: replace it (its limits, posteriors, "
                        "predictions and report are removed first)")
    p.add_argument("--wait", action="store_true", help="wait for another camo-sbi run holding --out")


#: what an infer run writes into --out (removed when --force replaces a run of other settings)
_INFER_OUTPUTS = ("limits.csv", "model_check.csv", "report.html", "config.json", "posteriors", "estimates",
                  "predictions", "work", "figures", "starts.csv", "next_goals.csv", "subjects", "reaches.csv")


def _infer_settings(args, model, overrides: dict) -> dict:
    """The settings that determine an infer run's results (its manifest): every option but the
    runtime ones, the model's full specification (URDF sha256, --ee, --start, joints) and the
    recording's and goal file's sha256."""
    import hashlib

    from camo_sbi.experiments.rundir import run_settings

    def digest(path):
        try:
            return None if path is None else hashlib.sha256(Path(path).read_bytes()).hexdigest()
        except OSError:
            return None  # reported by the loader, naming the file

    return run_settings(args, ignore=("config", "max_reaches"), model_spec=json.loads(model.to_json()),
                        config=json.dumps(overrides, sort_keys=True),
                        observations_sha256=digest(args.observations),
                        predict_goals_sha256=digest(args.predict_goals),
                        amortized_sha256=digest(getattr(args, "amortized", None)))


def _clear_infer_outputs(out: Path) -> None:
    import shutil

    for name in _INFER_OUTPUTS:
        p = out / name
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        elif p.exists() or p.is_symlink():
            p.unlink()


SUGGEST_CANDIDATES = 200
MAX_REACHES = 2000  # --max-reaches: a light copy of camo_sbi.io.recordings.MAX_REACHES (--help needs no torch)
SUGGEST_DRAWS = 100


def _returns_draws(name: str) -> bool:
    from camo_sbi.inference.registry import capabilities

    cap = capabilities(name)
    return cap.posterior and not cap.baseline


def _suggest_method(results: dict) -> str | None:
    """The first method run whose result holds posterior draws (not a baseline, not failed)."""
    import numpy as np

    for name, res in results.items():
        if (_returns_draws(name) and not res.status.startswith("failed")
                and np.unique(res.samples, axis=0).shape[0] > 1):
            return name
    return None


def _suggest(out: Path, task, results: dict, n: int, seed: int) -> None:
    """Rank nominal-workspace goals with the first posterior method's draws; write next_goals.csv; print them."""
    import pandas as pd

    from camo_sbi._validation import derive_seed
    from camo_sbi.design import rank_goals
    from camo_sbi.scenarios.reaching import nominal_workspace_goals

    name = _suggest_method(results)
    if name is None:
        raise ValueError(f"--suggest: none of the methods run ({', '.join(results)}) returned posterior draws; "
                         "add one that does (e.g. camo, abc-smc, npe)")
    cands = nominal_workspace_goals(task.simulator, SUGGEST_CANDIDATES, derive_seed(seed, "suggest-candidates"))
    info = rank_goals(task, results[name], cands, seed=derive_seed(seed, "suggest-ranking"),
                      budget=SUGGEST_CANDIDATES * SUGGEST_DRAWS)
    table = pd.DataFrame({"rank": range(1, n + 1), "goal_x": info.goals[:n, 0], "goal_y": info.goals[:n, 1],
                          "goal_z": info.goals[:n, 2], "score": info.scores[:n], "criterion": info.criterion,
                          "method": name})
    atomic_write_text(out / "next_goals.csv", table.to_csv(index=False))
    print(f"next reaches ({info.criterion}: expected reduction of the limits' posterior variance, rad^2; "
          f"{name}'s draws, {info.n_draws} per goal, {info.n_simulations} design simulations, "
          f"{info.wall_time:.1f} s; model base frame, m):")
    print(table[["rank", "goal_x", "goal_y", "goal_z", "score"]].to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    if info.status != "ok":
        print(f"suggest: {info.status}")


def infer_main(args) -> int:
    import numpy as np

    from camo_sbi.budget import announce_simulation_time, check_budget_fits
    from camo_sbi.experiments.compare import grid_methods
    from camo_sbi.experiments.method_configs import parse_configs
    from camo_sbi.experiments.rundir import RunDirectory
    from camo_sbi.io.recordings import load_goals

    if Path(args.observations).is_dir():
        return infer_folder(args)
    t0 = time.perf_counter()
    formats = figure_formats(args)
    if args.budget < 1:
        raise ValueError("--budget: must be >= 1")
    if args.seed < 0:
        raise ValueError("--seed: must be >= 0")
    if not 0 <= args.suggest <= SUGGEST_CANDIDATES:
        raise ValueError(f"--suggest: must be between 0 and {SUGGEST_CANDIDATES}, got {args.suggest}")
    if args.rate is not None and not (np.isfinite(args.rate) and args.rate > 0):
        raise ValueError(f"--rate: must be > 0, got {args.rate}")
    methods = [m.strip() for m in str(args.methods).split(",") if m.strip()]
    grid_methods(",".join(methods) or ",")  # validates names and duplicates (--methods: ...)
    overrides = parse_configs(args.config, methods)
    noise = _noise(args)
    _height_from_file(args)
    model = model_from_args(args)
    sim = model.build()
    check_budget_fits(args.budget, n_joints=sim.n_joints, flag="--budget")
    start = list(model.start) if model.start is not None else None
    recording = load_from_args(args, args.observations, sim, noise, start)
    obs = recording.observations
    if recording.scale != 1.0:
        sim = sim.scaled(recording.scale)
        lo, hi = recording.info["body_scale_90"]
        print(f"body scale s = {recording.scale:.3f} (90% interval {lo:.3f}-{hi:.3f}; least squares of ee_* on the "
              f"model's FK, bootstrap over reaches); every method runs on the scaled body")
    for w in recording.warnings:
        print(f"warning: {w}")
    goals = starts = None
    if args.predict_goals is not None:
        goals, starts = load_goals(args.predict_goals, sim, degrees=args.degrees, noise=noise)
    task = _recorded_task(model, sim, obs, noise)
    reach_law = getattr(args, "reach_model", "controller")
    if reach_law != "controller":  # every method conditions on, and predicts with, a human-like reach law
        from camo_sbi.scenarios.generators import reach_model

        task = task.with_simulator(reach_model(sim, reach_law))
    plan, notes = _plan(methods, task, args.space, str(args.observations))
    if reach_law != "controller":
        from camo_sbi.inference.registry import capabilities

        for name, _ in [p for p in plan if capabilities(p[0]).amortized]:
            notes.append(f"{name}: skipped (trained on the controller's reaches, not on --reach-model {reach_law})")
        plan = [p for p in plan if not capabilities(p[0]).amortized]
    if recording.scale != 1.0:  # an amortized estimator was trained on the model's own size
        from camo_sbi.inference.registry import capabilities

        for name, _ in [p for p in plan if capabilities(p[0]).amortized]:
            if len(methods) == 1:
                raise ValueError(f"--body-scale: {name} was trained on the model's own size; with --body-scale free "
                                 f"use a per-task method (camo, abc-smc, npe)")
            notes.append(f"{name}: skipped (trained on the model's own size, not on the scaled body of "
                         f"--body-scale free)")
        plan = [p for p in plan if not capabilities(p[0]).amortized]
    plan = _check_amortized(plan, notes, task, obs, overrides, getattr(args, "amortized", None), len(methods) == 1)
    for n in notes:
        print(n)
    if not plan:
        raise ValueError("--methods: none of the methods can run on this recording (see the notes above)")
    if args.suggest and not any(_returns_draws(name) for name, _ in plan):
        raise ValueError("--suggest: needs a method that returns posterior draws in --methods (e.g. camo, abc-smc, npe)")
    announce_simulation_time(sim, args.budget * len(obs) * len(plan), what="infer")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out}: exists and is not a directory")
    with RunDirectory(out, "infer", _infer_settings(args, model, overrides), wait=getattr(args, "wait", False),
                      force=getattr(args, "force", False), with_store=False) as run:
        if run.replaced:  # --force: nothing of the replaced run stays beside the new limits.csv
            _clear_infer_outputs(out)
        _infer_into(out, args, model, sim, task, obs, goals, starts, plan, notes, overrides, formats, noise,
                    recording, reach_law)
    print(f"wall time: {time.perf_counter() - t0:.1f} s")
    return 0


def _infer_into(out: Path, args, model, sim, task, obs, goals, starts, plan, notes, overrides, formats,
                noise, recording, reach_law: str = "controller") -> None:
    """Run the planned methods and write limits.csv, model_check.csv (per method and reach: the
    reproduction check), posteriors, predictions, starts.csv, config.json, the report and
    (--suggest) next_goals.csv."""
    import pandas as pd
    import torch

    import camo_sbi
    from camo_sbi._validation import derive_seed
    from camo_sbi.diagnostics.arviz_io import observed_arrays, save_in_run, to_inference_data
    from camo_sbi.diagnostics.misspecification import column_text, reach_rows, verdict_lines
    from camo_sbi.experiments.method_configs import method_config
    from camo_sbi.inference.registry import run_method
    from camo_sbi.io.recordings import save_recordings
    from camo_sbi.task import Observation, predict

    results = {}
    observed, observed_dims = observed_arrays(task)  # the recorded reaches, in every posterior file
    bar = tqdm(plan, desc="infer", unit="method")
    for name, space in bar:
        bar.set_postfix_str(name)
        cfg = method_config(name, budget=args.budget, space=space, workdir=out / "work" / name,
                            overrides=overrides.get(name))
        res = run_method(name, task, budget=args.budget, seed=args.seed, config=cfg)
        results[name] = res
        idata = to_inference_data(res, sim.joint_names, prior=task.prior, seed=derive_seed(args.seed, "posterior-file"),
                                  budget=args.budget, observed=observed, observed_dims=observed_dims,
                                  attrs={"task": model.name, "observations": str(args.observations),
                                         "model_spec": model.to_json()})
        save_in_run(idata, out, name)  # posteriors/, or estimates/ for a point estimate
    bar.close()
    checks = _model_checks(task, results, args.seed)
    table = limits_table(results, sim, task, recording.clipped)
    table["model_check"] = [column_text(checks[m]) for m in table["method"]]
    atomic_write_text(out / "limits.csv", table.to_csv(index=False))
    atomic_write_text(out / "model_check.csv", pd.DataFrame(reach_rows(checks)).to_csv(index=False))
    if goals is not None:
        s = obs[0].start if starts is None else starts
        for name, res in results.items():
            traj = predict(task.simulator, res.estimate, s, goals)  # the reach law the methods assumed
            pred = [Observation((s if s.dim() == 1 else s[i]), goals[i], traj.trimmed(i, "joint").to(torch.float64),
                                traj.trimmed(i, "cartesian").to(torch.float64)) for i in range(goals.shape[0])]
            save_recordings(out / "predictions" / f"{name}.csv", pred, sim)
    settings = {"observations": str(args.observations), "model": model.name, "reaches": len(obs),
                "samples": sum(o.length for o in obs), "spaces": ",".join(task.spaces),
                "methods": ",".join(results), "budget": args.budget, "seed": args.seed,
                "noise_joint_deg": noise.joint_deg, "noise_ee_mm": noise.ee_mm, "resample": args.resample,
                "config": json.dumps(overrides, sort_keys=True), "suggest": args.suggest, "reach_model": reach_law, **recording.info,
                "warnings": list(recording.warnings) + [w for c in checks.values() for w in verdict_lines(c)]}
    atomic_write_text(out / "config.json", json.dumps({"experiment": "infer", "camo_sbi_version": camo_sbi.__version__,
                                                       **settings, "model_spec": json.loads(model.to_json())},
                                                      indent=2))
    write_starts(out / "starts.csv", obs, sim)
    if recording.segments:
        atomic_write_text(out / "reaches.csv", pd.DataFrame(list(recording.segments)).to_csv(index=False))
        print(f"reaches: {len(recording.segments)} found ({recording.speed['rule']}) -> {out / 'reaches.csv'}")
    notes = notes + [f"warning: {w}" for w in recording.warnings]
    report = _report(out, task, results, notes, table, settings, args.seed,
                     formats=None if formats == ("png",) else formats, speed=recording.speed,
                     checks=checks)
    print("model check (does each posterior reproduce each reach? camo_sbi.diagnostics.misspecification):")
    for name, c in checks.items():
        print(f"  {name}: {column_text(c)}"
              + ("" if not c.checked else "; per reach: " + ", ".join(
                  f"{i} {v} (p={c.p_adjusted[i]:.3f})" for i, v in enumerate(c.verdicts()))))
    for c in checks.values():
        for w in verdict_lines(c):
            print(f"warning: {w}")
    print("limits [deg], " + WIDE_LIMITS_KEY.replace(" [deg]", "", 1))
    print(wide_limits(table).to_string())
    for name, res in results.items():
        if res.status != "ok":
            print(f"{name}: {res.status}")
    if args.suggest:
        _suggest(out, task, results, args.suggest, args.seed)
    print(f"limits: {out / 'limits.csv'}  posteriors: {out / 'posteriors'}  report: {report}")


# ----------------------------------------------------------------------------- recordings from a lab


def add_recording_arguments(p: argparse.ArgumentParser) -> None:
    """Units, frames, markers and goals of a recording (CSV, NPZ or C3D)."""
    p.add_argument("--ee-units", choices=("m", "mm"), default=None,
                   help="unit of the ee_* and goal_* columns (default m; a C3D file's POINT:UNITS is used)")
    p.add_argument("--goal", choices=("columns", "final"), default="columns",
                   help="columns: the goal_* columns; final: each reach's last end-effector position (free reaching)")
    p.add_argument("--frame", type=Path, default=None,
                   help="JSON rigid transform lab -> model base: rotation (3x3) or quaternion [w,x,y,z], "
                        "translation [m]")
    p.add_argument("--frame-from-markers", default=None, metavar="A,B,C",
                   help="estimate the frame from these C3D markers (positions in --marker-positions)")
    p.add_argument("--marker-positions", type=Path, default=None,
                   help='JSON {"marker": [x, y, z]} model-frame positions [m] for --frame-from-markers')
    p.add_argument("--ee-marker", default=None, metavar="NAME[,NAME...]",
                   help="C3D marker(s) of the end effector (several: their mean)")
    p.add_argument("--bvh-map", type=Path, default=None,
                   help="JSON mapping of a BVH file's channels to the model's joints (signs, offsets, reaches)")
    p.add_argument("--max-reaches", type=int, default=MAX_REACHES, metavar="N",
                   help="refuse a recording of more reaches (each is a task of every method; a larger one "
                        "runs with a larger N)")
    p.add_argument("--reaches", default=None, metavar="auto|events|A-B,C-D",
                   help="find the reaches in a recording with time (C3D, BVH, or a time column): auto (by hand "
                        "speed), events (the C3D file's events), or inclusive frame ranges; each reach's goal is "
                        "where it ends; DIR/reaches.csv lists them (default: the file's own reaches)")
    p.add_argument("--side", choices=("right", "left"), default=None,
                   help="the recorded arm (--markers isb mirrors a left arm onto the right-arm model; default "
                        "right) and the events' context with --reaches events")
    p.add_argument("--markers", choices=("isb",), default=None,
                   help="isb: the human model's joint angles per frame from a C3D's ISB upper-limb landmarks "
                        "(thorax, humerus, forearm, hand; angles relative to the thorax); needs --marker-map")
    p.add_argument("--marker-map", type=Path, default=None,
                   help='JSON {"IJ": "<label>", "PX": ..., "C7": ..., "T8": ..., "AC": ..., "EL": ..., "EM": ..., '
                        '"RS": ..., "US": ..., "MC2": ..., "MC5": ...}: the file\'s marker for each ISB landmark')
    p.add_argument("--out-of-range", choices=("auto", "clip", "error"), default="auto",
                   help="a joint angle beyond the model's range (more than the noise allowance): clip = clip it onto "
                        "the range with a warning per joint and mark the bound (!) in limits.csv and the report; "
                        "error = exit 2 naming it; auto = clip the angles of --markers isb (a person beyond the "
                        "model's normative range), error for every other file (a BVH map, a unit, a sign)")
    p.add_argument("--body-scale", choices=("fixed", "free"), default="fixed",
                   help="free: estimate the body's segment-length scale s in [0.85, 1.15] from the joint and "
                        "end-effector columns and infer on the scaled body")


def load_from_args(args, path, sim, noise, start):
    """`load_recording` of ``path`` with the recording flags of ``args``."""
    from camo_sbi.io.frames import load_frame, load_marker_positions
    from camo_sbi.io.recordings import load_recording

    frame = load_frame(args.frame) if args.frame is not None else None
    markers = None
    if args.frame_from_markers is not None:
        names = [m.strip() for m in str(args.frame_from_markers).split(",") if m.strip()]
        if len(names) < 3:
            raise ValueError(f"--frame-from-markers: needs three or more marker names, got {args.frame_from_markers!r}")
        if frame is not None:
            raise ValueError("--frame-from-markers: give --frame or --frame-from-markers, not both")
        if args.marker_positions is None:
            raise ValueError("--frame-from-markers: needs --marker-positions FILE.json (the markers' model-frame "
                             "positions)")
        markers = load_marker_positions(args.marker_positions, names)
    ee_markers = None
    if args.ee_marker is not None:
        ee_markers = [m.strip() for m in str(args.ee_marker).split(",") if m.strip()]
        if not ee_markers:
            raise ValueError("--ee-marker: expected one or more marker names")
    return load_recording(path, sim, degrees=args.degrees, noise=noise, start=start,
                          resample=None if args.resample == "none" else args.resample, rate=args.rate,
                          ee_units=args.ee_units, goal=args.goal, frame=frame, ee_markers=ee_markers,
                          frame_markers=markers, body_scale=getattr(args, "body_scale", "fixed"),
                          bvh_map=getattr(args, "bvh_map", None),
                          max_reaches=getattr(args, "max_reaches", MAX_REACHES), reaches=getattr(args, "reaches", None),
                          side=getattr(args, "side", None), markers=getattr(args, "markers", None),
                          marker_map=getattr(args, "marker_map", None),
                          out_of_range=getattr(args, "out_of_range", "auto"))


def _height_from_file(args) -> None:
    """``--markers isb`` on a C3D with ``--model human`` and no ``--height``: the subject's height from
    the file (PROCESSING:Height) when it has one (printed)."""
    if getattr(args, "markers", None) is None or getattr(args, "height", None) is not None:
        return
    if getattr(args, "model", None) != "human" or Path(args.observations).suffix.lower() != ".c3d":
        return
    from camo_sbi.io.c3d import c3d_subject_height

    h = c3d_subject_height(args.observations)
    if h is not None:
        args.height = h
        print(f"subject height {h:.3f} m (the C3D file's PROCESSING:Height): the model is built for it")


def write_starts(path: Path, obs, sim) -> Path:
    """starts.csv: each reach's start posture (radians) and where it came from: "observed" (the
    first joint sample), "model" (the start posture) or "IK" (estimated from the first
    end-effector sample, `estimate_starts`)."""
    import pandas as pd
    import torch

    model_start = torch.as_tensor(sim.start, dtype=torch.float64)
    rows = []
    for i, o in enumerate(obs):
        source = "observed" if o.q is not None else "model" if torch.equal(o.start, model_start) else "IK"
        rows.append({"reach": i, "source": source, **{j: float(v) for j, v in zip(sim.joint_names, o.start,
                                                                                 strict=True)}})
    return atomic_write_text(path, pd.DataFrame(rows).to_csv(index=False))


RECORDING_SUFFIXES = (".csv", ".npz", ".c3d", ".bvh", ".mot", ".sto")


def infer_folder(args) -> int:
    """``infer --observations DIR/``: one subject per recording file in DIR (sorted by name). Every
    file is loaded and checked first (a bad file stops the run before any method runs, naming
    it); then each subject is inferred into ``out/subjects/<file stem>/`` as a single file would
    be, and ``out/limits.csv`` (every subject, a ``subject`` column first) and one
    ``out/report.html`` (per subject: its limits figure, its table, its warnings and a link to
    its own report) are written."""
    import argparse as _argparse

    import pandas as pd

    from camo_sbi.diagnostics.pages import part
    from camo_sbi.diagnostics.report import write_page

    folder = Path(args.observations)
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in RECORDING_SUFFIXES)
    if not files:
        raise ValueError(f"--observations: {folder} holds no recording ({', '.join(RECORDING_SUFFIXES)} files)")
    stems = [p.stem for p in files]
    dup = sorted({x for x in stems if stems.count(x) > 1})
    if dup:
        raise ValueError(f"--observations: {folder} holds two recordings of subject {dup[0]!r} (one file per subject)")
    model = model_from_args(args)
    sim = model.build()
    start = list(model.start) if model.start is not None else None
    noise = _noise(args)
    for p in tqdm(files, desc="check recordings", unit="file"):
        load_from_args(args, p, sim, noise, start)
    out = Path(args.out)
    tables, sections = [], []
    for p in files:
        print(f"subject {p.stem}: {p}")
        sub = _argparse.Namespace(**{**vars(args), "observations": p, "out": out / "subjects" / p.stem})
        infer_main(sub)
        t = pd.read_csv(sub.out / "limits.csv")
        t.insert(0, "subject", p.stem)
        tables.append(t)
        cfg = json.loads((sub.out / "config.json").read_text())
        warnings = cfg.get("warnings", [])
        # the link: a relative URL of the subject's folder, its name quoted as a path segment
        href = f"subjects/{urllib.parse.quote(p.stem)}/report.html"
        sections.append((f"subject-{len(sections)}", f"Subject {p.stem}",
                         part("subject_line", str(p), cfg["reaches"], href)
                         + (part("items", warnings) if warnings else "")
                         + _limits_html(t.drop(columns="subject"), sim)))
    table = pd.concat(tables, ignore_index=True)
    atomic_write_text(out / "limits.csv", table.to_csv(index=False))
    from camo_sbi.diagnostics.style import paper_style

    with paper_style():
        report = write_page(out / "report.html", f"camo_sbi infer: {folder}", sections,
                            meta=f"model {model.name}, {len(files)} subjects, seed {args.seed}")
    print(f"{len(files)} subjects: limits {out / 'limits.csv'}  report: {report}")
    return 0
