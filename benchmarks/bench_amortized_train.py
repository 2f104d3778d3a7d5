"""Amortized training: today's settings vs the faster ones, on the same data, at equal validation loss.

    python benchmarks/bench_amortized_train.py [--model panda] [--simulations 50000] [--seed 0]
        [--out DIR]   # also saves both estimators there, for `camo-sbi calibrate --amortized FILE`
        [--now KEY=VALUE ...]   # the "now" arm: TrainConfig's defaults with these optimiser settings

Both arms call `amortized.train` with the same seed, so they simulate the same training set,
hold out the same validation sets and differ only in the optimiser settings:

- "before": `TrainConfig()`'s defaults (batches of 512 reaches, i.e. 51 sets of 10, Adam at a
  constant 1e-3, at most 40 epochs);
- "now": `amortized.FAST_SET_TRAINING` (2048 reaches, 3e-3 on a cosine schedule, 30 epochs),
  the faster alternative; not the default, because its calibration was worse (README).
  ``--now-threads N`` also gives it N torch threads (both arms default to TrainConfig's one
  thread); CPU seconds then stop being the guide, wall seconds on a quiet machine are.
  ``--now KEY=VALUE`` (repeatable; KEY one of training_batch_size, learning_rate, lr_schedule,
  max_epochs) makes the "now" arm TrainConfig's defaults with those settings instead, e.g.
  ``--now training_batch_size=1024`` (the same rate, schedule and epochs, twice the batch).

The comparison is at EQUAL VALIDATION LOSS: for each arm, the training seconds (process CPU
and wall, per epoch from `fit_density_estimator`'s clocks) until its validation loss first
reaches the higher of the two arms' best losses (the level both reach); the ratio before / now
of those times is the speed-up. The script also prints both best losses, the ratio of the whole
trainings, each arm's per-epoch validation losses, and the load average (other jobs on the
machine inflate wall times; CPU seconds are the better guide to a quiet machine).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
from pathlib import Path

BEFORE = ("training_batch_size", "learning_rate", "lr_schedule", "max_epochs")


def _time_to_reach(info: dict, target: float, clock: str) -> float | None:
    for loss, t in zip(info["validation_loss"], info[clock], strict=True):
        if loss <= target:
            return t
    return None


def _overrides(items: list[str]) -> dict:
    """``["training_batch_size=1024", "lr_schedule=cosine"]`` -> {"training_batch_size": 1024, ...}."""
    types = {"training_batch_size": int, "learning_rate": float, "lr_schedule": str, "max_epochs": int}
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or key not in types:
            raise SystemExit(f"--now: expected KEY=VALUE with KEY one of {', '.join(types)}, got {item!r}")
        out[key] = types[key](value)
    return out


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--model", default="panda")
    p.add_argument("--simulations", type=int, default=50_000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--now-threads", type=int, default=None,
                   help="torch threads of the 'now' arm (default: TrainConfig's, 1, as 'before')")
    p.add_argument("--now", action="append", default=[], metavar="KEY=VALUE",
                   help=f"the 'now' arm: TrainConfig's defaults with these settings ({', '.join(BEFORE)}) "
                        "instead of FAST_SET_TRAINING (repeatable)")
    args = p.parse_args()

    from camo_sbi.experiments.subjects import build_model
    from camo_sbi.inference.amortized import FAST_SET_TRAINING, TrainConfig, train

    before = TrainConfig(simulations=args.simulations)
    now = dataclasses.replace(before, **(_overrides(args.now) if args.now else FAST_SET_TRAINING))
    if args.now_threads is not None:
        now = dataclasses.replace(now, n_threads=args.now_threads)
    changed = {k: (getattr(before, k), getattr(now, k)) for k in (*BEFORE, "n_threads")
               if getattr(before, k) != getattr(now, k)}
    print(f"model {args.model}, {args.simulations} simulations, seed {args.seed}; settings before -> now: {changed}")
    print(f"load average at start: {os.getloadavg()}")
    sim = build_model(args.model)
    infos = {}
    for name, cfg in (("before", before), ("now", now)):
        c0, w0 = time.process_time(), time.perf_counter()
        est = train(sim, model=args.model, config=cfg, seed=args.seed)
        info = est.metadata["training"]["joint"]
        info["cpu"], info["wall"] = time.process_time() - c0, time.perf_counter() - w0
        infos[name] = info
        if args.out is not None:
            args.out.mkdir(parents=True, exist_ok=True)
            est.save(args.out / f"{args.model}-{args.simulations}-{name}.pt")
        print(f"{name:>6}: best validation loss {info['best_validation_loss']:.3f} after {info['epochs']} epochs "
              f"({info['stopped']}); training {info['time_train']:.1f} s wall, arm {info['wall']:.1f} s wall / "
              f"{info['cpu']:.1f} s CPU; load {os.getloadavg()[0]:.1f}", flush=True)
        print("        validation loss per epoch: " + " ".join(f"{v:.2f}" for v in info["validation_loss"]))
    best = {k: v["best_validation_loss"] for k, v in infos.items()}
    # equal validation loss: the first epoch at which each arm reaches the level both reach
    level = max(best.values())
    print(f"best validation loss: before {best['before']:.3f}, now {best['now']:.3f}; common level {level:.3f}")
    for clock, label in (("epoch_cpu_seconds", "CPU"), ("epoch_seconds", "wall")):
        tb, tn = (_time_to_reach(infos[k], level, clock) for k in ("before", "now"))
        print(f"  training {label} seconds to validation loss <= {level:.3f}: before {tb:.1f}, now {tn:.1f}: "
              f"ratio {tb / tn:.2f}x")
    for clock, label in (("epoch_cpu_seconds", "CPU"), ("epoch_seconds", "wall")):
        tb, tn = infos["before"][clock][-1], infos["now"][clock][-1]
        print(f"  whole training, {label} seconds: before {tb:.1f}, now {tn:.1f}: ratio {tb / tn:.2f}x")


if __name__ == "__main__":
    main()
