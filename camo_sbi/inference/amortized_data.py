"""What an amortized estimator is trained for and on: the body model's identity and the training set.

`model_fingerprint` / `fingerprint_differences`: what identifies a body model (joints,
bounds, start, URDF, controller), stored in an estimator file and checked against every task.
`design_goals` / `simulate_training_set`: the training triples (limits from the box prior,
goals independent of them, one simulated reach each) and their conditions (`conditions`: the
goal, then `flow_space.trajectory_summary` of the trajectory). See `amortized` for why.
"""

from __future__ import annotations

import dataclasses
import hashlib
import time

import numpy as np
import torch

from camo_sbi._validation import check_positive_int
from camo_sbi.budget import unwrap_simulator
from camo_sbi.inference.flow_space import trajectory_summary
from camo_sbi.priors import BoxPrior

__all__ = ["conditions", "design_goals", "fingerprint_differences", "model_fingerprint", "seed_int",
           "simulate_training_set"]

_DTYPES = {"float32": torch.float32, "float64": torch.float64}


def model_fingerprint(simulator) -> dict:
    """What identifies a body model: joint names, bounds, default start, URDF, end effector, controller."""
    sim = unwrap_simulator(simulator)
    cfg = getattr(sim, "config", None)
    if dataclasses.is_dataclass(cfg):
        cfg = {k: (v if isinstance(v, (int, float, str, bool)) or v is None else repr(v))
               for k, v in dataclasses.asdict(cfg).items()}
    elif cfg is not None:
        cfg = repr(cfg)
    urdf = getattr(sim, "urdf", "") or ""
    return {
        "joint_names": list(sim.joint_names),
        "bounds": torch.as_tensor(sim.bounds, dtype=torch.float64).tolist(),
        "start": torch.as_tensor(sim.start, dtype=torch.float64).tolist(),
        "urdf_sha256": hashlib.sha256(urdf.encode()).hexdigest(),
        "end_effector": getattr(sim, "end_effector", None),
        "controller": cfg,
        "max_steps": getattr(sim, "max_steps", None) or (cfg.get("max_steps") if isinstance(cfg, dict) else None),
    }


def _controller_defaults() -> dict:
    from camo_sbi.simulators.controller import ControllerConfig

    return {f.name: f.default for f in dataclasses.fields(ControllerConfig)
            if f.default is not dataclasses.MISSING and isinstance(f.default, (int, float, str, bool))}


def fingerprint_differences(a: dict, b: dict) -> list[str]:
    """Fields of the current fingerprint ``b`` on which the stored fingerprint ``a`` differs.

    A controller setting that a stored file does not name did not exist when the file was
    written; it counts as that setting's default, which is the behaviour the controller had
    before the setting was added (``derivative_gain=0``, ``early_stop=True``).
    """
    out = []
    for k in sorted(b):
        va, vb = a.get(k), b.get(k)
        if k == "controller" and isinstance(va, dict) and isinstance(vb, dict):
            va = {**{n: d for n, d in _controller_defaults().items() if n in vb}, **va}
        if k in ("bounds", "start") and va is not None and vb is not None:
            ta, tb = torch.tensor(va, dtype=torch.float64), torch.tensor(vb, dtype=torch.float64)
            if ta.shape != tb.shape or not torch.allclose(ta, tb, atol=1e-9, rtol=0):
                out.append(k)
        elif va != vb:
            out.append(k)
    return out


def conditions(traj: torch.Tensor, lengths: torch.Tensor, goals: torch.Tensor, settings) -> torch.Tensor:
    """(B, 3 + summary) float64: the goal, then `trajectory_summary` of the trajectory."""
    s = trajectory_summary(traj, lengths, n_points=settings.n_points, include_length=settings.include_length)
    return torch.cat([torch.as_tensor(goals, dtype=torch.float64).reshape(-1, 3), s], dim=1)


def seed_int(seed: int, *key: int) -> int:
    return int(np.random.SeedSequence(seed, spawn_key=key).generate_state(1, np.uint64)[0] >> np.uint64(1))


def design_goals(simulator, prior: BoxPrior, n: int, seed: int) -> torch.Tensor:
    """(n, 3) float64 training goals, independent of the training limits (see the module docstring):
    FK of configurations uniform inside the limits of independent prior draws."""
    sim = unwrap_simulator(simulator)
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(1,)))
    theta_goal = prior.sample(n, rng)
    u = torch.from_numpy(rng.random((n, sim.n_joints)))
    q = theta_goal[:, 0::2] + (theta_goal[:, 1::2] - theta_goal[:, 0::2]) * u
    return torch.cat([sim.forward_kinematics(q[s : s + 20000]).to(torch.float64)
                      for s in range(0, n, 20000)])


def simulate_training_set(simulator, prior: BoxPrior, settings, seed: int, *,
                          n: int | None = None, progress: bool = False) -> dict:
    """Simulate ``n`` (default ``settings.simulations``) training triples; no count is charged.

    Returns {"theta": (n, 2n) float64, "x": {space: (n, D) float64 conditions},
    "time_simulate": seconds (FK of the goals + simulation + summaries)}. Seeded by ``seed``:
    limits, goals and noise come from independent streams. The "set" form simulates
    ``max_set`` reaches (independent goals) of each of n // max_set limit vectors: "theta" is
    (n // max_set, 2n) and "x" (n // max_set, max_set, D).
    """
    from tqdm import tqdm

    sim = unwrap_simulator(simulator)
    n = settings.simulations if n is None else check_positive_int(n, "n")
    r = settings.reaches_per_theta
    m = n // r
    n = m * r
    t0 = time.perf_counter()
    theta_m = prior.sample(m, np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(0,))))
    theta = theta_m.repeat_interleave(r, dim=0)
    goals = design_goals(sim, prior, n, seed)
    start = torch.as_tensor(sim.start, dtype=torch.float64)
    noise_gen = torch.Generator().manual_seed(seed_int(seed, 2))
    dtype = _DTYPES[settings.sim_dtype]
    parts = {s: [] for s in settings.spaces}
    b = settings.chunk_size
    for s in tqdm(range(0, n, b), desc="simulating", unit="batch", disable=not progress, leave=False):
        out = sim.simulate(theta[s : s + b].to(dtype), goals[s : s + b].to(dtype), start.to(dtype))
        for space in settings.spaces:
            traj = out.q if space == "joint" else out.ee
            traj = settings.noise.perturb(traj.to(torch.float64), space, noise_gen)
            parts[space].append(conditions(traj, out.length, goals[s : s + b], settings))
    x = {k: torch.cat(v) for k, v in parts.items()}
    if r > 1:
        x = {k: v.reshape(m, r, -1) for k, v in x.items()}
    return {"theta": theta_m, "x": x, "time_simulate": time.perf_counter() - t0}
