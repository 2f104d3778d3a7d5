"""Amortized training: today's settings vs the faster ones, on the same data, at equal validation loss.

    python benchmarks/bench_amortized_train.py [--model panda] [--simulations 50000] [--seed 0]
        [--out DIR]   # also saves both estimators there, for `camo-sbi calibrate --amortized FILE`

Both arms call `amortized.train` with the same seed, so they simulate the same training set,
hold out the same validation sets and differ only in the optimiser settings:

- "before": the settings `TrainConfig` had until this benchmark (batches of 512 reaches,
  i.e. 51 sets of 10, Adam at a constant 1e-3, at most 40 epochs);
- "now": `TrainConfig()`'s current defaults.

The comparison is at EQUAL VALIDATION LOSS: for each arm, the training seconds (wall and,
per epoch, from `fit_density_estimator`'s clock) until its validation loss first reaches the
"before" arm's best; the ratio before / now of those times is the speed-up. The script also
prints each arm's best validation loss, epochs and total training time, the CPU seconds of the
process during each arm, and the load average (other jobs on the machine inflate wall times).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
from pathlib import Path

BEFORE = {"training_batch_size": 512, "learning_rate": 1e-3, "lr_schedule": "constant", "max_epochs": 40,
          "stop_after_epochs": 8}


def _time_to_reach(info: dict, target: float) -> float | None:
    for loss, t in zip(info["validation_loss"], info["epoch_seconds"], strict=True):
        if loss <= target:
            return t
    return None


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--model", default="panda")
    p.add_argument("--simulations", type=int, default=50_000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args()

    from camo_sbi.experiments.subjects import build_model
    from camo_sbi.inference.amortized import TrainConfig, train

    now = TrainConfig(simulations=args.simulations)
    before = dataclasses.replace(now, **BEFORE)
    changed = {k: (getattr(before, k), getattr(now, k)) for k in BEFORE if getattr(before, k) != getattr(now, k)}
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
    target = infos["before"]["best_validation_loss"]
    t_before = _time_to_reach(infos["before"], target)
    t_now = _time_to_reach(infos["now"], target)
    cpu_per_s = {k: v["cpu"] / v["wall"] for k, v in infos.items()}
    if t_now is None:
        print(f"now never reached the before arm's best validation loss {target:.3f} "
              f"(its best: {infos['now']['best_validation_loss']:.3f}): no speed-up at equal loss")
        return
    print(f"to validation loss {target:.3f} (before's best): before {t_before:.1f} s, now {t_now:.1f} s: "
          f"ratio {t_before / t_now:.2f}x (wall; CPU share of the wall time: before {cpu_per_s['before']:.2f}, "
          f"now {cpu_per_s['now']:.2f})")
    print(f"full runs: before {infos['before']['time_train']:.1f} s, now {infos['now']['time_train']:.1f} s: "
          f"ratio {infos['before']['time_train'] / infos['now']['time_train']:.2f}x; best loss now "
          f"{infos['now']['best_validation_loss']:.3f} vs before {target:.3f}")


if __name__ == "__main__":
    main()
