"""Issue 33: the onset share (`camo_sbi.diagnostics.misspecification.onset_share`: the share of
its peak step speed at which a reach sets off) of the controller's reaches, under prior draws
and under the subjects' true limits, and of the human-like generators' reaches.

    python benchmarks/measure_onset.py --model panda [--recordings 4 --prior-draws 50]

Per recording: one of the model's informative subjects (alternating), 10 noise-free reaches to
nominal-workspace goals; the controller's reaches under ``--prior-draws`` prior draws on the same
goals and starts. Prints the median and the 1 % quantile (the maximum for the generators) of the
share per kind of reach (the guide's table in docs/guide/misspecification.md).
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from camo_sbi._validation import derive_seed
from camo_sbi.diagnostics.misspecification import onset_share
from camo_sbi.evaluation.evaluate import predictive_trajectories
from camo_sbi.scenarios.generators import make_generator, misspecified_observations
from camo_sbi.scenarios.reaching import make_reaching_task
from camo_sbi.simulators import registry


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", default="panda")
    p.add_argument("--recordings", type=int, default=4)
    p.add_argument("--reaches", type=int, default=10)
    p.add_argument("--prior-draws", type=int, default=50)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    d = registry.get_model(args.model)
    sim = d.build()
    subjects = list(d.informative)
    shares: dict[str, list[float]] = {"controller, prior draws": [], "controller, true limits": [],
                                      "minimum-jerk": [], "via-point": []}
    for run in range(args.recordings):
        theta = d.informative[subjects[run % len(subjects)]](sim)
        task = make_reaching_task(sim, theta, n_train=args.reaches, n_test=1, seed=derive_seed(args.seed, run),
                                  workspace="nominal")
        obs = task.observations
        shares["controller, true limits"] += [onset_share(o.ee) for o in obs]
        starts = torch.stack([o.start.to(torch.float64) for o in obs])
        goals = torch.stack([o.goal.to(torch.float64) for o in obs])
        draws = task.prior.sample(args.prior_draws, derive_seed(args.seed, run, 7)).numpy()
        pred = predictive_trajectories(task.simulator, draws, starts, goals)
        shares["controller, prior draws"] += [onset_share(pred.trimmed(s * len(obs) + i, "cartesian"))
                                              for s in range(args.prior_draws) for i in range(len(obs))]
        for g in ("minimum-jerk", "via-point"):
            t, _ = misspecified_observations(task, make_generator(sim, g, seed=derive_seed(args.seed, run, 5)))
            shares[g] += [onset_share(o.ee) for o in t.observations]
    print(f"{args.model}: onset share (first step / peak step speed), {args.recordings} recordings x {args.reaches} reaches")
    for kind, v in shares.items():
        v = np.asarray(v)
        tail = f"1% quantile {np.quantile(v, 0.01):.3f}" if kind.startswith("controller") else f"max {v.max():.3f}"
        print(f"  {kind:26s} n={v.size:5d}  median {np.median(v):.3f}  {tail}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
