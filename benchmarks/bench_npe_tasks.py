"""Per-task NPE: the time each added task costs, today's settings against the previous code path.

    python benchmarks/bench_npe_tasks.py [--tasks 3] [--budget 500] [--seed 0] [--repeats 1]
        [--arms before,now,warm] [--arm NAME=JSON ...]

The quickstart's problem (`camo-sbi compare --seeds 1`: the Panda, its first subject, the
comparison's task seed and method seed for seed 0), run with `npe.run_sequence` in this one
process by two arms, each on the same simulations:

- "before": ``warm_start=False, reuse_mixture_draws=False`` (every task's flow trained from
  fresh weights with ``stop_after_epochs`` patience; every importance-sampling round draws its
  own flow-mixture draws, round 0 ``n_posterior_samples`` of them), the code path of the
  previous release;
- "now": `npe.NpeConfig`'s defaults (the adaptive importance-sampling rounds reuse round 0's
  flow draws, ``reuse_mixture_draws``);
- "warm": the defaults with ``warm_start=True`` (task i's flow trained from task i - 1's
  weights), the faster option that is not the default (its calibration: docs/guide/performance.md).

Per arm it prints each result's cumulative ``wall_time`` (what results.csv records) and
process CPU time, the per-task breakdown (simulation, training and its epochs, sampling, ESS),
and the cost per ADDED task, (t_K - t_1) / (K - 1), in wall and CPU seconds, and the ratios
before / arm (or, without the before arm, first arm run / arm). sbi is imported and the simulator's kernel loaded before any clock starts (as the
registry does: ``import_time`` is apart from ``wall_time``). The load average is printed: other
jobs on the machine inflate wall times; CPU seconds are the better guide to a quiet machine.
With ``--repeats`` > 1 the arms alternate and the minimum per arm is kept. ``--arms`` picks the
built-in arms to run; ``--arm NAME=JSON`` (repeatable) adds an arm of `npe.NpeConfig` overrides,
e.g. ``--arm 'p10={"stop_after_epochs": 10}'``, timed in the same run as the others.
"""

from __future__ import annotations

import argparse
import json
import os
import time

ARMS = {"before": {"warm_start": False, "reuse_mixture_draws": False}, "now": {}, "warm": {"warm_start": True}}


def _problem(tasks: int, seed: int):
    from camo_sbi._validation import derive_seed
    from camo_sbi.experiments.subjects import build_model, subject_names, subject_theta
    from camo_sbi.scenarios.reaching import make_reaching_task

    sim = build_model("panda")
    theta = subject_theta(sim, "panda", subject_names("panda")[0])
    task = make_reaching_task(sim, theta, n_train=tasks, n_test=10, seed=derive_seed(seed, 0), name="panda",
                              subject=subject_names("panda")[0])
    return task, derive_seed(seed, 0, "method")


def _run_arm(task, budget: int, seed: int, overrides: dict) -> list[dict]:
    from camo_sbi.inference import npe

    config = npe.NpeConfig(**overrides)
    rows, c0 = [], time.process_time()
    for res in npe.run_sequence(task, task.observations, budget=budget, seed=seed, config=config):
        t = res.extras["tasks"][-1]
        rows.append({"k": res.n_tasks, "wall": res.wall_time, "cpu": time.process_time() - c0,
                     "simulate": t["time_simulate"], "train": t["time_train"], "epochs": t["epochs"],
                     "sample": res.extras["time_sample"], "ess": res.extras["ess"]})
    return rows


def _per_added(rows: list[dict], key: str) -> float:
    return (rows[-1][key] - rows[0][key]) / (len(rows) - 1)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tasks", type=int, default=3, help="observed tasks K (>= 2)")
    p.add_argument("--budget", type=int, default=500)
    p.add_argument("--seed", type=int, default=0, help="the comparison's base seed")
    p.add_argument("--repeats", type=int, default=1)
    p.add_argument("--arms", default=",".join(ARMS), help=f"built-in arms to run, of {','.join(ARMS)}")
    p.add_argument("--arm", action="append", default=[], metavar="NAME=JSON",
                   help="an extra arm: npe.NpeConfig overrides as a JSON object (repeatable)")
    args = p.parse_args()
    if args.tasks < 2:
        p.error("--tasks: at least 2 (the cost of an added task)")
    arms = {}
    for name in filter(None, args.arms.split(",")):
        if name not in ARMS:
            p.error(f"--arms: unknown arm {name!r} (of {', '.join(ARMS)})")
        arms[name] = ARMS[name]
    for spec in args.arm:
        name, sep, text = spec.partition("=")
        try:
            overrides = json.loads(text) if sep else None
        except json.JSONDecodeError as exc:
            p.error(f"--arm {spec!r}: {exc}")
        if not name or not isinstance(overrides, dict):
            p.error(f"--arm {spec!r}: expected NAME=JSON object")
        arms[name] = overrides
    if not arms:
        p.error("no arm to run")

    from camo_sbi.inference import sbi_adapter

    sbi_adapter.import_sbi()
    task, seed = _problem(args.tasks, args.seed)
    _run_arm(task, 200, seed, {"max_epochs": 2, "n_posterior_samples": 200})  # kernels and lazy imports, untimed
    print(f"per-task NPE, panda, budget {args.budget}, {args.tasks} tasks, seed {args.seed}; "
          f"load average before: {os.getloadavg()[0]:.2f}")
    best: dict[str, list[dict]] = {}
    for rep in range(args.repeats):
        for name, overrides in arms.items():
            rows = _run_arm(task, args.budget, seed, overrides)
            print(f"\n{name} (repeat {rep + 1}, load {os.getloadavg()[0]:.2f})")
            print("  k  wall_time    CPU  simulate  train (epochs)  sample     ESS")
            for r in rows:
                print(f"  {r['k']}  {r['wall']:8.2f}  {r['cpu']:6.2f}  {r['simulate']:8.2f}  "
                      f"{r['train']:5.2f} ({r['epochs']:3d})  {r['sample']:6.2f}  {r['ess']:6.0f}")
            print(f"  per added task: {_per_added(rows, 'wall'):.2f} s wall, {_per_added(rows, 'cpu'):.2f} s CPU")
            if name not in best or _per_added(rows, "cpu") < _per_added(best[name], "cpu"):
                best[name] = rows
    ref = "before" if "before" in best else next(iter(best))  # the ratios' reference arm
    b = best[ref]
    print("\nper added task (min over repeats):")
    for name, rows in best.items():
        print(f"  {name:6s} {_per_added(rows, 'wall'):5.2f} s wall, {_per_added(rows, 'cpu'):5.2f} s CPU; "
              f"ratio {ref} / {name}: {_per_added(b, 'wall') / _per_added(rows, 'wall'):.2f}x wall, "
              f"{_per_added(b, 'cpu') / _per_added(rows, 'cpu'):.2f}x CPU; first task {rows[0]['wall']:.2f} s wall")
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
