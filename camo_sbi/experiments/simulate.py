"""`camo-sbi simulate-observations`: synthetic recordings of a subject.

A synthetic subject with the ``--limits`` file's limits reaches ``--reaches`` goals sampled as
the experiments sample them (`reachable_goals`: joint configurations uniform inside the true
limits, through FK, kept if the subject's controller reaches them), from the model's start
posture. ``--rate-multiplier R`` resamples each reach to R times as fast a recorder
(round(R (L - 1)) + 1 samples, linear interpolation in time); then `NoiseModel.perturb` adds
the noise (seeded) to every recorded value, the start included. Written in the recording
format (`camo_sbi.io.recordings`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from tqdm import tqdm

from camo_sbi.experiments.models import add_model_arguments, model_from_args, subject_limits
from camo_sbi.experiments.recording_args import add_noise_arguments, noise_from_args

__all__ = ["add_arguments", "main", "simulate_recordings"]


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
    from camo_sbi.io.resample import resample_to_controller
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


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_model_arguments(p)
    p.add_argument("--reaches", type=int, default=10, help="number of reaches")
    p.add_argument("--seed", type=int, default=0)
    add_noise_arguments(p)
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


def main(args) -> int:
    import numpy as np
    import torch

    from camo_sbi._validation import derive_seed
    from camo_sbi.evaluation.claims import FEW_REACHES
    from camo_sbi.io.schema import save_recordings
    from camo_sbi.scenarios.generators import make_generator
    from camo_sbi.scenarios.reaching import binding_reaches
    from camo_sbi.task import Observation

    if args.reaches < 1:
        raise ValueError("--reaches: must be >= 1")
    if not (np.isfinite(args.rate_multiplier) and args.rate_multiplier > 0):
        raise ValueError(f"--rate-multiplier: must be > 0, got {args.rate_multiplier}")
    if args.seed < 0:
        raise ValueError("--seed: must be >= 0")
    noise = noise_from_args(args)
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
