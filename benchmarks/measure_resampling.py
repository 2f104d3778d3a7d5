"""Why the loader resamples recordings in normalised time: CAMO-CS on 1x vs faster recordings.

For 6 Panda subjects (shoulder / elbow / wrist restricted, cycled), 5 observed reaches and 10
held-out goals each: the exact 1x observations, the same reaches recorded R times as fast
(linear interpolation in time, as `simulate-observations --rate-multiplier R` writes them), then
Gaussian noise on the end-effector positions. CAMO-CS (budget 1000, keep 50) runs on

    1x, Rx raw (no resampling), Rx -> time, Rx -> arclength, 1x -> time, 1x -> arclength

with the rate estimated from the file (`estimate_rate`), and the held-out Cartesian error per
point [mm] of its estimate is printed (mean over subjects and per subject).

    python benchmarks/measure_resampling.py [R=3] [ee noise mm=0]
"""

from __future__ import annotations

import sys
import warnings

import numpy as np
import torch

from camo_sbi.evaluation.evaluate import evaluate_result, true_test_trajectories
from camo_sbi.experiments.subjects import subject_theta
from camo_sbi.inference.registry import run_method
from camo_sbi.io.resample import estimate_rate, resample_to_controller
from camo_sbi.scenarios.reaching import make_reaching_task
from camo_sbi.simulators import panda
from camo_sbi.task import NoiseModel, Observation

SUBJECTS = ("shoulder_restricted", "elbow_restricted", "wrist_restricted")


def main(rate: float = 3.0, ee_mm: float = 0.0, seeds: int = 6) -> None:
    warnings.filterwarnings("ignore", category=RuntimeWarning)
    sim = panda()
    noise = NoiseModel(ee_mm=ee_mm)
    errors: dict[str, list[float]] = {}
    estimated = []
    tag = f"{rate:g}x"
    for seed in range(seeds):
        task = make_reaching_task(sim, subject_theta(sim, "panda", SUBJECTS[seed % 3]), n_train=5, n_test=10,
                                  seed=seed)
        truth = true_test_trajectories(task)

        def noisy(obs, seed=seed):
            g = torch.Generator().manual_seed(seed + 100)
            return tuple(Observation(o.start, o.goal, o.q, noise.perturb(o.ee, "cartesian", g)) for o in obs)

        fast = tuple(resample_to_controller(o, sim, mode="time", rate=1 / rate) for o in task.observations)
        variants = {"1x": noisy(task.observations), f"{tag} raw": noisy(fast)}
        r_fast, r_one = estimate_rate(variants[f"{tag} raw"], sim), estimate_rate(variants["1x"], sim)
        estimated.append((r_one, r_fast))
        for mode in ("time", "arclength"):
            variants[f"{tag} -> {mode}"] = tuple(resample_to_controller(o, sim, mode=mode, rate=r_fast)
                                                 for o in variants[f"{tag} raw"])
            variants[f"1x -> {mode}"] = tuple(resample_to_controller(o, sim, mode=mode, rate=r_one)
                                              for o in variants["1x"])
        for name, obs in variants.items():
            t = task.with_observations(obs)
            res = run_method("camo-cs", t, budget=1000, seed=seed, config={"keep_best": 50})
            errors.setdefault(name, []).append(evaluate_result(t, res, truth)["cartesian_error_mm"])
    print(f"R = {rate:g}, end-effector noise {ee_mm:g} mm; estimated rates (1x file, {tag} file): {estimated}")
    for name, v in errors.items():
        print(f"{name:18s} held-out Cartesian error {np.mean(v):6.1f} mm   per subject {np.round(v, 1).tolist()}")


if __name__ == "__main__":
    main(*(float(a) for a in sys.argv[1:3]))
