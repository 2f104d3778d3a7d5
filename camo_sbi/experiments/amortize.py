"""`camo-sbi amortize`: train an amortized estimator once per body model and save it.

    camo-sbi amortize (--model panda|human | --urdf PATH --ee LINK ...) --simulations 200000 --out panda.pt
                      [--space joint,cartesian] [--noise-joint-deg S --noise-ee-mm S] [--seed S]

The file (state dict + JSON metadata, loaded with ``weights_only=True``) is then used by
``compare --methods npe-amortized --amortized FILE`` and by
``run_method("npe-amortized", task, ..., config={"estimator_path": FILE})``; inferring a person's
limits from it simulates nothing. `ensure_estimator` is what compare and calibrate call when
no file is given: it trains one under the run directory once and reuses it.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from camo_sbi._io import atomic_write_text
from camo_sbi.experiments.models import ModelSpec, add_model_arguments, model_from_args

__all__ = ["add_arguments", "cost_table", "ensure_estimator", "estimator_for_run", "load_cli_estimator", "main",
           "parse_spaces",
           "train_config", "write_cost_table"]


def parse_spaces(text: str) -> tuple[str, ...]:
    from camo_sbi.task import SPACES

    items = tuple(t.strip() for t in str(text).split(",") if t.strip())
    bad = [s for s in items if s not in SPACES]
    if not items or bad or len(set(items)) != len(items):
        raise ValueError(f"--space: expected distinct values of {', '.join(SPACES)} separated by commas, got {text!r}")
    return items


def train_config(*, simulations: int, spaces, noise_joint_deg: float = 0.0, noise_ee_mm: float = 0.0,
                 max_epochs: int | None = None, form: str | None = None, flow: str | None = None,
                 fast: bool = False, threads: int | None = None, batch_size: int | None = None):
    """The `TrainConfig` of the CLI options (ValueError naming the option otherwise).

    ``fast``: `amortized.FAST_SET_TRAINING`'s optimiser settings (set form only);
    ``threads``: torch threads while training (TrainConfig.n_threads);
    ``batch_size``: reaches per training batch (TrainConfig.training_batch_size; wins over ``fast``'s).
    """
    from camo_sbi.inference.amortized import FAST_SET_TRAINING, TrainConfig
    from camo_sbi.task import NoiseModel

    try:
        noise = NoiseModel(joint_deg=noise_joint_deg, ee_mm=noise_ee_mm)
    except ValueError as exc:
        raise ValueError(f"--noise-{str(exc).split(':')[0].replace('_', '-')}: {str(exc).split(': ', 1)[1]}") from exc
    extra = {}
    if fast:
        if form not in (None, "set"):
            raise ValueError(f"--fast: its settings are the set form's, not --form {form}'s")
        extra.update(FAST_SET_TRAINING)
    if max_epochs is not None:
        extra["max_epochs"] = max_epochs
    if batch_size is not None:
        extra["training_batch_size"] = batch_size
    if threads is not None:
        if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
            raise ValueError(f"--threads: expected an integer >= 1, got {threads!r}")
        extra["n_threads"] = threads
    if form is not None:
        extra["form"] = form
    if flow is not None:
        extra["density_estimator"] = flow
    try:
        return TrainConfig(simulations=simulations, spaces=tuple(spaces), noise=noise, **extra)
    except (TypeError, ValueError) as exc:
        field = str(exc).split(":")[0]
        name = {"density_estimator": "flow", "training_batch_size": "batch_size"}.get(field, field).replace("_", "-")
        raise ValueError(f"--{name}: {str(exc).split(': ', 1)[-1]}") from exc


def ensure_estimator(path: Path, *, model: ModelSpec, config, seed: int, progress: bool = True):
    """The estimator at ``path``, trained (and saved atomically) first if the file does not exist.

    An existing file is reused only if it was trained for ``model`` with exactly ``config``
    and ``seed``; otherwise ValueError (choose another path or delete it).
    Returns (estimator, trained_now: bool).
    """
    from camo_sbi.inference.amortized import load_estimator, train

    path = Path(path)
    if path.is_file():
        est = load_estimator(path)
        if est.model != model.name or est.metadata["settings"] != config.to_json() or est.metadata["seed"] != seed:
            raise ValueError(f"--amortized: {path} exists but was trained with other settings "
                             f"(model {est.model!r}, seed {est.metadata['seed']}); delete it or choose another path")
        return est, False
    est = train(model.build(), model=model.name, config=config, seed=seed, progress=progress)
    est.save(path)
    return load_estimator(path), True


def estimator_for_run(methods, *, model: ModelSpec, path, out, simulations: int, space: str,
                      seed: int, tasks: int | None = None) -> Path | None:
    """The estimator file a run of ``methods`` uses: None without an amortized method; ``path``
    (``--amortized``, must exist) if given; otherwise one trained here, ONCE, in the calling
    (parent) process before any cell runs, at OUT/work/amortized/<model>-<space>-n<N>-seed<S>.pt,
    and reused by every cell and by a resumed run (its cost is recorded once, in the file).
    ``tasks``: the most reaches a cell will pass; a set-form estimator trained on fewer is
    refused here, naming --tasks, before any cell runs (not by a cell, mid-grid)."""
    from camo_sbi.inference.registry import capabilities

    if not any(capabilities(m).amortized for m in methods):
        return None
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise ValueError(f"--amortized: no such file {str(path)!r}")
        _check_set_size(path, tasks)
        return path
    cfg = train_config(simulations=simulations, spaces=(space,))
    if cfg.form == "set":
        _refuse_set_size(tasks, cfg.max_set, "this run would train")
    path = Path(out) / "work" / "amortized" / f"{model.name}-{space}-n{simulations}-seed{seed}.pt"
    print(f"amortized estimator: {path}")
    _, trained = ensure_estimator(path, model=model, config=cfg, seed=seed)
    print(("trained " if trained else "reused ") + str(path))
    return path


def load_cli_estimator(path):
    """`load_estimator` for a file named by ``--amortized``: its errors name the flag."""
    from camo_sbi.inference.amortized import load_estimator

    try:
        return load_estimator(path)
    except ValueError as exc:
        raise ValueError(f"--amortized: {exc}") from exc


def _check_set_size(path: Path, tasks: int | None) -> None:
    if tasks is None:
        return
    est = load_cli_estimator(path)
    if est.form == "set":
        _refuse_set_size(tasks, est.settings.max_set, str(path))


def _refuse_set_size(tasks: int | None, max_set: int, which: str) -> None:
    if tasks is not None and tasks > max_set:
        raise ValueError(f"--tasks: {tasks} reaches, but the set-form estimator {which} takes at most "
                         f"max_set={max_set}; use --tasks {max_set} or less, or a per-reach estimator "
                         f"(`camo-sbi amortize --form per-reach`, then --amortized FILE)")


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_model_arguments(p, limits=False)
    p.add_argument("--simulations", type=int, default=200_000, help="training simulations (one reach each)")
    p.add_argument("--out", type=Path, required=True, help="estimator file to write (e.g. panda.pt)")
    p.add_argument("--space", default="joint", help="joint, cartesian or joint,cartesian (one flow each, same "
                                                    "simulations)")
    p.add_argument("--noise-joint-deg", type=float, default=0.0, help="observation noise on joint angles [deg]")
    p.add_argument("--noise-ee-mm", type=float, default=0.0, help="observation noise on end-effector positions [mm]")
    p.add_argument("--max-epochs", type=int, default=None, help="training epochs at most (default: TrainConfig's)")
    p.add_argument("--form", default=None, help="set (default: one flow q(theta | set of 1..10 reaches)) or "
                                                "per-reach (one flow per reach, combined by the i.i.d. rule)")
    p.add_argument("--flow", default=None, help="nsf (default: neural spline flow) or maf")
    p.add_argument("--fast", action="store_true",
                   help="the faster optimiser settings (2048 reaches a batch, 3e-3 on a cosine schedule, 30 "
                        "epochs); their speed-up and calibration are measured in the documentation "
                        "(Measured performance)")
    p.add_argument("--batch-size", type=int, default=None,
                   help="reaches per training batch (default: TrainConfig's, 512); the rate, schedule and "
                        "epochs stay. 2048 trains about twice as fast; its calibration is measured in the "
                        "documentation (first-run performance, amortized training)")
    p.add_argument("--threads", type=int, default=None,
                   help="torch threads while training (default: 1; what more threads gain is measured in the "
                        "documentation, Measured performance)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--force", action="store_true", help="overwrite --out if it exists")


def main(args) -> int:
    from camo_sbi.inference.amortized import train

    if args.seed < 0:
        raise ValueError(f"--seed: must be >= 0, got {args.seed}")
    cfg = train_config(simulations=args.simulations, spaces=parse_spaces(args.space),
                       noise_joint_deg=args.noise_joint_deg, noise_ee_mm=args.noise_ee_mm,
                       max_epochs=args.max_epochs, form=args.form, flow=args.flow, fast=args.fast,
                       threads=args.threads, batch_size=args.batch_size)
    out = Path(args.out)
    if out.exists() and not args.force:
        raise ValueError(f"--out: {out} exists (use --force to overwrite)")
    t0 = time.perf_counter()
    model = model_from_args(args)
    est = train(model.build(), model=model.name, config=cfg, seed=args.seed, progress=True)
    est.save(out)
    print(est.describe())
    atomic_write_text(out.with_suffix(out.suffix + ".json"), json.dumps(est.metadata, indent=2, sort_keys=True))
    print(f"estimator: {out} (metadata copy: {out}.json)  wall time: {time.perf_counter() - t0:.1f} s")
    return 0


def cost_table(df, estimator_path):
    """Honest cost of the amortized estimator against every simulating method of a comparison.

    ``df``: compare's tidy table. Per (method, budget) at the largest number of observed tasks K:
    simulations and wall time per person (one cell = one person observed on K reaches; the
    mean over cells). The amortized method's one-off ``training_simulations`` and
    ``training_time`` come from its file. Break-even persons: the smallest P with
    training + P x (amortized cost per person) <= P x (the other method's cost per person),
    i.e. ceil(training / (other - amortized)); empty where the other method is not dearer.
    """
    import math

    import pandas as pd

    from camo_sbi.inference.amortized import load_estimator
    from camo_sbi.inference.registry import capabilities

    est = load_estimator(estimator_path)
    last = df[df["n_tasks"] == df["n_tasks"].max()]
    per = (last[last["metric"].isin(["n_simulations", "wall_time"])]
           .pivot_table(index=["method", "budget"], columns="metric", values="value", aggfunc="mean")
           .reset_index())
    amort = per[[capabilities(m).amortized for m in per["method"]]]
    others = per[[capabilities(m).simulates and not capabilities(m).amortized for m in per["method"]]]
    rows = []
    for _, a in amort.groupby("method", sort=True).mean(numeric_only=True).reset_index().iterrows():
        for _, o in others.iterrows():
            ds = o["n_simulations"] - a["n_simulations"]
            dt = o["wall_time"] - a["wall_time"]
            rows.append({
                "amortized": a["method"], "method": o["method"], "budget": int(o["budget"]),
                "n_tasks": int(last["n_tasks"].max()),
                "simulations_per_person": o["n_simulations"], "wall_time_per_person_s": o["wall_time"],
                "amortized_simulations_per_person": a["n_simulations"],
                "amortized_wall_time_per_person_s": a["wall_time"],
                "training_simulations": est.training_simulations, "training_time_s": est.training_time,
                "break_even_persons_simulations": math.ceil(est.training_simulations / ds) if ds > 0 else None,
                "break_even_persons_wall_time": math.ceil(est.training_time / dt) if dt > 0 else None,
            })
    return pd.DataFrame(rows)


def write_cost_table(df, estimator_path, out) -> Path:
    """`cost_table` as OUT/amortized_cost.csv, and printed."""
    table = cost_table(df, estimator_path)
    path = Path(out) / "amortized_cost.csv"
    atomic_write_text(path, table.to_csv(index=False))
    if len(table):
        t = table.iloc[0]
        print(f"amortized cost: {t['training_simulations']} training simulations, {t['training_time_s']:.1f} s to "
              f"train (once per body model); per person {t['amortized_simulations_per_person']:.0f} simulations, "
              f"{t['amortized_wall_time_per_person_s']:.2f} s")
        cols = ["method", "budget", "simulations_per_person", "wall_time_per_person_s",
                "break_even_persons_simulations", "break_even_persons_wall_time"]
        print(table[cols].to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    print(f"cost table: {path}")
    return path
