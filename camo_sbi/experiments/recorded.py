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
Methods that need the truth (oracle) are skipped with a note. A method that cannot use the
file's space is an error naming ``space`` when it is the only method asked for, and skipped
with a printed reason when several are.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import TYPE_CHECKING

from tqdm import tqdm

from camo_sbi._io import atomic_write_text
from camo_sbi.experiments.figure_options import add_figure_format_argument, figure_formats
from camo_sbi.experiments.models import add_model_arguments, model_from_args, true_limits

# only light modules at import time: the CLI builds its parser from the add_*_arguments functions
# (numpy and torch are imported by the functions that use them)
if TYPE_CHECKING:
    import numpy as np
    import torch

__all__ = ["add_infer_arguments", "add_simulate_arguments", "infer_main", "limits_table", "simulate_main",
           "simulate_recordings"]

PPC_DRAWS = 50
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


def simulate_recordings(sim, theta, n_reaches: int, *, seed: int, noise=None, rate_multiplier: float = 1.0):
    """Synthetic recorded reaches of a subject with limits ``theta`` (2n,): a tuple of `Observation`.

    Goals from `reachable_goals` (seed ``derive_seed(seed, 0)``); each reach resampled to
    ``rate_multiplier`` times as many samples (linear interpolation in time); noise from
    ``noise.perturb`` (seed ``derive_seed(seed, 1)``) on every value, start included.
    """
    import numpy as np
    import torch

    from camo_sbi._validation import derive_seed, torch_generator
    from camo_sbi.io.recordings import resample_to_controller
    from camo_sbi.scenarios.reaching import observe, reachable_goals
    from camo_sbi.task import NoiseModel, Observation

    noise = NoiseModel() if noise is None else noise
    if not (isinstance(rate_multiplier, (int, float)) and np.isfinite(rate_multiplier) and rate_multiplier > 0):
        raise ValueError(f"rate_multiplier: expected a number > 0, got {rate_multiplier!r}")
    theta = torch.as_tensor(theta, dtype=torch.float64)
    goals = reachable_goals(sim, theta, n_reaches, torch_generator(derive_seed(seed, 0)))
    exact = observe(sim, theta, goals)
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
    p.add_argument("--space", choices=("both", "joint", "cartesian"), default="both",
                   help="columns written: joint angles, end-effector positions or both")
    p.add_argument("--out", type=Path, required=True, help="recording file to write (.csv or .npz)")


def simulate_main(args) -> int:
    import numpy as np

    from camo_sbi.io.recordings import save_recordings
    from camo_sbi.task import Observation

    if args.reaches < 1:
        raise ValueError("--reaches: must be >= 1")
    if not (np.isfinite(args.rate_multiplier) and args.rate_multiplier > 0):
        raise ValueError(f"--rate-multiplier: must be > 0, got {args.rate_multiplier}")
    if args.seed < 0:
        raise ValueError("--seed: must be >= 0")
    noise = _noise(args)
    model = model_from_args(args)
    if model.limits is None:
        raise ValueError("--limits: simulate-observations needs the subject's true limits (--limits FILE.json)")
    sim = model.build()
    theta = true_limits(model, sim, model.limits_name)
    with tqdm(total=1, desc="simulate-observations", unit="file") as bar:
        obs = simulate_recordings(sim, theta, args.reaches, seed=args.seed, noise=noise,
                                  rate_multiplier=args.rate_multiplier)
        if args.space != "both":
            obs = tuple(Observation(o.start, o.goal, o.q if args.space == "joint" else None,
                                    o.ee if args.space == "cartesian" else None) for o in obs)
        path = save_recordings(args.out, obs, sim)
        bar.update()
    n = sum(o.length for o in obs)
    print(f"{model.name}: {len(obs)} reaches, {n} samples -> {path}")
    return 0


# ----------------------------------------------------------------------------- infer


def limits_table(results: dict, sim):
    """One row per method, joint and bound: estimate [rad], [deg] and the 90% central interval [deg].

    Point methods (one sample) have both interval ends at the estimate. Prismatic joints:
    ``estimate_rad`` holds metres and the degree columns are empty.
    """
    import numpy as np
    import pandas as pd

    from camo_sbi.inference.result import weighted_quantile

    a = (1.0 - INTERVAL) / 2
    types = getattr(getattr(sim, "spec", None), "joint_types", ("revolute",) * sim.n_joints)
    rows = []
    for name, res in results.items():
        w = res.normalized_weights()
        lo, hi = weighted_quantile(res.samples, w, a), weighted_quantile(res.samples, w, 1.0 - a)
        for j, joint in enumerate(sim.joint_names):
            for b, bound in enumerate(("lower", "upper")):
                k = 2 * j + b
                deg = (lambda v: float(np.degrees(v))) if types[j] == "revolute" else (lambda v: float("nan"))
                rows.append({"method": name, "joint": joint, "bound": bound,
                             "estimate_rad": float(res.estimate[k]), "estimate_deg": deg(res.estimate[k]),
                             "lower_90_deg": deg(lo[k]), "upper_90_deg": deg(hi[k]), "status": res.status})
    return pd.DataFrame(rows, columns=["method", "joint", "bound", "estimate_rad", "estimate_deg",
                                       "lower_90_deg", "upper_90_deg", "status"])


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
            cfg = overrides[name] = {**cfg, "estimator": str(path)}
        if cfg.get("estimator") is None:
            raise ValueError(f"--amortized: {name} needs a trained estimator file (train one with "
                             f"`camo-sbi amortize --model M --out FILE`)")
        try:  # a file given by --config keeps load_estimator's own message
            est = (load_cli_estimator if path is not None else load_estimator)(cfg["estimator"])
            est.check_task(task, obs, space or cfg.get("space", "joint"))
        except ValueError as exc:
            if only:
                raise
            notes.append(f"{name}: skipped ({exc})")
            continue
        kept.append((name, space))
    return kept


def _method_config(name: str, space: str | None, budget: int, workdir: Path, overrides: dict | None) -> dict:
    from camo_sbi.experiments.calibrate import method_config
    from camo_sbi.inference.registry import capabilities

    cfg = method_config(name, budget, overrides)
    if space is not None:
        cfg.setdefault("space", space)
    if capabilities(name).workdir:
        cfg.setdefault("workdir", str(workdir / name))
    return cfg


def _shown_limits(table):
    """The limits table as a person reads it: degrees only (radians stay in limits.csv),
    unless a prismatic joint (metres, no degree column) needs ``estimate_rad``."""
    if table["estimate_deg"].notna().all():
        return table.drop(columns=["estimate_rad"])
    return table


def _ee_of(traj_ee: torch.Tensor, length: torch.Tensor, b: int) -> np.ndarray:
    import torch

    return traj_ee[b, : int(length[b])].to(torch.float64).numpy()


def _report(out: Path, task, results: dict, notes: list[str], table, settings: dict, seed: int,
            formats=None) -> Path:
    """report.html: the limits table (degrees) and, per reach, observed vs posterior-predictive
    paths; with ``formats`` (``--figure-format``) the figures also as files in
    ``out/report_figures``."""
    from camo_sbi.diagnostics.report import figure_files
    from camo_sbi.diagnostics.style import paper_style

    with paper_style(), figure_files(out / "report_figures", formats):
        return _report_page(out, task, results, notes, table, settings, seed)


def _report_page(out: Path, task, results: dict, notes: list[str], table, settings: dict, seed: int) -> Path:
    import html

    import numpy as np
    import pandas as pd
    import torch
    from matplotlib.figure import Figure

    from camo_sbi.diagnostics.report import figure_html, table_html, write_page
    from camo_sbi.diagnostics.style import DOUBLE_COLUMN
    from camo_sbi.task import contain

    sim = task.simulator
    obs = task.observations[:MAX_REPORT_REACHES]
    methods = list(results)
    reach_html = []
    # per method: PPC_DRAWS systematic posterior draws (deterministic), simulated once per reach
    draws = {m: torch.as_tensor(r.systematic(PPC_DRAWS if r.samples.shape[0] > 1 else 1), dtype=torch.float64)
             for m, r in results.items()}
    for i, o in enumerate(tqdm(obs, desc="report", unit="reach")):
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
            top.set_title(f"{m} ({results[m].status})")
            top.set_xlabel("x [m]")
            top.set_ylabel("y [m]")
            top.set_aspect("equal", adjustable="datalim")
            side.set_xlabel("controller step")
            side.set_ylabel("distance to goal [m]")
            if c == 0:
                top.legend()
        reach_html.append(figure_html(
            fig, f"reach {i}: observed (black), the estimate's prediction (red dashed) and "
                 f"{PPC_DRAWS} posterior-predictive draws per method (blue; point methods: one); "
                 f"top: end-effector path seen from above, bottom: distance to the goal per step",
            alt=f"reach {i}"))
    more = len(task.observations) - len(obs)
    if more > 0:
        reach_html.append(f'<p class="meta">{more} more reaches not shown</p>')
    esc_notes = "".join(f"<li>{html.escape(n)}</li>" for n in notes)
    settings_html = table_html(pd.DataFrame([{"setting": k, "value": str(v)} for k, v in settings.items()]))
    sections = [
        ("settings", "Settings", settings_html + (f"<ul>{esc_notes}</ul>" if notes else "")),
        ("limits", "Estimated limits", '<p class="meta">degrees (limits.csv also holds radians, '
                                        "estimate_rad)</p>" + table_html(_shown_limits(table), float_format="{:.4g}")),
        ("reaches", "Observed vs posterior-predictive reaches", "".join(reach_html)),
    ]
    return write_page(out / "report.html", f"camo_sbi infer: {settings['observations']}", sections,
                      meta=f"model {task.name}, {len(task.observations)} reaches, seed {seed}")


def add_infer_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--observations", type=Path, required=True, help="recording file (.csv or .npz)")
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
    p.add_argument("--amortized", type=Path, default=None,
                   help="trained estimator file for npe-amortized (`camo-sbi amortize`)")
    p.add_argument("--predict-goals", type=Path, default=None,
                   help="CSV of goal_x,goal_y,goal_z[,start joint columns] to predict reaches for")
    p.add_argument("--config", action="append", default=[], metavar="METHOD=JSON",
                   help='per-method config overrides, e.g. --config \'npe={"max_epochs": 20}\' (repeatable)')
    add_figure_format_argument(p)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--force", action="store_true",
                   help="--out holds an infer run with other settings: replace it (its limits, posteriors, "
                        "predictions and report are removed first)")
    p.add_argument("--wait", action="store_true", help="wait for another camo-sbi run holding --out")


#: what an infer run writes into --out (removed when --force replaces a run of other settings)
_INFER_OUTPUTS = ("limits.csv", "report.html", "config.json", "posteriors", "predictions", "work", "figures")


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

    return run_settings(args, ignore=("config",), model_spec=json.loads(model.to_json()),
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


def infer_main(args) -> int:
    import numpy as np

    from camo_sbi.experiments.compare import grid_methods
    from camo_sbi.experiments.method_configs import parse_configs
    from camo_sbi.io.recordings import load_goals, load_recordings

    t0 = time.perf_counter()
    formats = figure_formats(args)
    if args.budget < 1:
        raise ValueError("--budget: must be >= 1")
    if args.seed < 0:
        raise ValueError("--seed: must be >= 0")
    if args.rate is not None and not (np.isfinite(args.rate) and args.rate > 0):
        raise ValueError(f"--rate: must be > 0, got {args.rate}")
    methods = [m.strip() for m in str(args.methods).split(",") if m.strip()]
    grid_methods(",".join(methods) or ",")  # validates names and duplicates (--methods: ...)
    overrides = parse_configs(args.config, methods)
    noise = _noise(args)
    model = model_from_args(args)
    sim = model.build()
    from camo_sbi.budget import check_budget_fits

    check_budget_fits(args.budget, n_joints=sim.n_joints, flag="--budget")
    start = list(model.start) if model.start is not None else None
    obs = load_recordings(args.observations, sim, degrees=args.degrees, noise=noise, start=start,
                          resample=None if args.resample == "none" else args.resample, rate=args.rate)
    goals = starts = None
    if args.predict_goals is not None:
        goals, starts = load_goals(args.predict_goals, sim, degrees=args.degrees, noise=noise)
    task = _recorded_task(model, sim, obs, noise)
    plan, notes = _plan(methods, task, args.space, str(args.observations))
    plan = _check_amortized(plan, notes, task, obs, overrides, getattr(args, "amortized", None), len(methods) == 1)
    for n in notes:
        print(n)
    if not plan:
        raise ValueError("--methods: none of the methods can run on this recording (see the notes above)")
    from camo_sbi.budget import announce_simulation_time

    announce_simulation_time(sim, args.budget * len(obs) * len(plan), what="infer")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out}: exists and is not a directory")
    from camo_sbi.experiments.rundir import RunDirectory

    with RunDirectory(out, "infer", _infer_settings(args, model, overrides), wait=getattr(args, "wait", False),
                      force=getattr(args, "force", False), with_store=False) as run:
        if run.replaced:  # --force: nothing of the replaced run stays beside the new limits.csv
            _clear_infer_outputs(out)
        _infer_into(out, args, model, sim, task, obs, goals, starts, plan, notes, overrides, formats, noise)
    print(f"wall time: {time.perf_counter() - t0:.1f} s")
    return 0


def _infer_into(out: Path, args, model, sim, task, obs, goals, starts, plan, notes, overrides, formats,
                noise) -> None:
    """Run the planned methods and write limits.csv, posteriors, predictions, config.json and the report."""
    import torch

    import camo_sbi
    from camo_sbi._validation import derive_seed
    from camo_sbi.diagnostics.arviz_io import observed_arrays, save_netcdf, to_inference_data
    from camo_sbi.inference.registry import run_method
    from camo_sbi.io.recordings import save_recordings
    from camo_sbi.task import Observation, predict

    (out / "posteriors").mkdir(parents=True, exist_ok=True)
    results = {}
    observed, observed_dims = observed_arrays(task)  # so `camo-sbi report` can draw the predictive reaches
    bar = tqdm(plan, desc="infer", unit="method")
    for name, space in bar:
        bar.set_postfix_str(name)
        cfg = _method_config(name, space, args.budget, out / "work", overrides.get(name))
        res = run_method(name, task, budget=args.budget, seed=args.seed, config=cfg)
        results[name] = res
        idata = to_inference_data(res, sim.joint_names, prior=task.prior, seed=derive_seed(args.seed, 13),
                                  budget=args.budget, observed=observed, observed_dims=observed_dims,
                                  attrs={"task": model.name, "observations": str(args.observations),
                                         "model_spec": model.to_json()})
        save_netcdf(idata, out / "posteriors" / f"{name}.nc")
    bar.close()
    table = limits_table(results, sim)
    atomic_write_text(out / "limits.csv", table.to_csv(index=False))
    if goals is not None:
        s = obs[0].start if starts is None else starts
        for name, res in results.items():
            traj = predict(sim, res.estimate, s, goals)
            pred = [Observation((s if s.dim() == 1 else s[i]), goals[i], traj.trimmed(i, "joint").to(torch.float64),
                                traj.trimmed(i, "cartesian").to(torch.float64)) for i in range(goals.shape[0])]
            save_recordings(out / "predictions" / f"{name}.csv", pred, sim)
    settings = {"observations": str(args.observations), "model": model.name, "reaches": len(obs),
                "samples": sum(o.length for o in obs), "spaces": ",".join(task.spaces),
                "methods": ",".join(results), "budget": args.budget, "seed": args.seed,
                "noise_joint_deg": noise.joint_deg, "noise_ee_mm": noise.ee_mm, "resample": args.resample,
                "config": json.dumps(overrides, sort_keys=True)}
    atomic_write_text(out / "config.json", json.dumps({"experiment": "infer", "camo_sbi_version": camo_sbi.__version__,
                                                       **settings, "model_spec": json.loads(model.to_json())},
                                                      indent=2))
    report = _report(out, task, results, notes, table, settings, args.seed,
                     formats=None if formats == ("png",) else formats)
    pd_table = table[table.bound.isin(["lower", "upper"])].pivot_table(
        index="joint", columns=["method", "bound"], values="estimate_deg", sort=False)
    print(pd_table.to_string(float_format=lambda v: f"{v:.1f}"))
    for name, res in results.items():
        if res.status != "ok":
            print(f"{name}: {res.status}")
    print(f"limits: {out / 'limits.csv'}  posteriors: {out / 'posteriors'}  report: {report}")
