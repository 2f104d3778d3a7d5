"""Per-task checkpoints of the per-task neural methods: a killed run resumes at its next task.

NPE, NLE and TSNPE train one estimator per observed task, each seeded by (seed, task index)
only (their continual-use contract), so a trained task is a self-contained result. With a
``workdir``, such a method writes each task's estimator here as soon as it is trained, and a
later run with the same settings reads it back instead of simulating and training that task
again: a long run (the human at 10^5 simulations per task, timed in
docs/guide/reference_posteriors.md) survives a kill or a session's end with at most one task's
work lost.

Files: ``workdir/{method}_tasks/task{i:03d}-{key[:16]}.pt`` (tensors: the estimator's state
dict and the observed summary) and ``.pt.json`` (the format, the full key, the weights' sha256,
the sizes, the architecture and the task's training info), written atomically, the metadata
last. The method rebuilds the network from the architecture (``build``) and loads the state
dict, its z-scoring statistics included (they are buffers).

The key is the sha256 of everything the trained estimator depends on: the method, the config
(except ``workdir`` and ``scheduler``, which change where work runs, not what it computes), the
per-task budget, the seed, the task index, the observation (start, goal, trajectory), the body
model's fingerprint, the prior box, the noise model, the torch and sbi versions and, with a
warm start, the previous task's key. A file whose key, digest or shape does not match is
ignored (a RuntimeWarning says why) and the task is trained again. Nothing in a file is run:
weights are read with ``torch.load(weights_only=True)``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from camo_sbi._files import read_json
from camo_sbi._io import atomic_write_bytes, atomic_write_text
from camo_sbi.inference import sbi_adapter

__all__ = ["file_format", "load_task", "resumed_summary", "save_task", "task_key"]

_NOT_IN_KEY = ("workdir", "scheduler")


def file_format(method: str) -> str:
    """The format tag of ``method``'s checkpoints (part of their key)."""
    return f"camo_sbi-{method}-task-v1"


def _digest(a) -> str:
    arr = np.ascontiguousarray(torch.as_tensor(a, dtype=torch.float64).cpu().numpy())
    return hashlib.sha256(repr(arr.shape).encode() + arr.tobytes()).hexdigest()


def task_key(method: str, task, obs, *, index: int, budget: int, seed: int, config,
             previous: str | None = None) -> str:
    """The sha256 (hex) identifying task ``index``'s trained estimator (module docstring)."""
    from camo_sbi.inference.amortized_data import model_fingerprint

    cfg = {k: v for k, v in dataclasses.asdict(config).items() if k not in _NOT_IN_KEY}
    prior = task.prior
    noise = task.noise
    content = {
        "format": file_format(method),
        "config": cfg,
        "budget": int(budget), "seed": int(seed), "index": int(index),
        "observation": {"start": _digest(obs.start), "goal": _digest(obs.goal),
                        "trajectory": _digest(obs.trajectory(config.space))},
        "model": model_fingerprint(task.simulator),
        "prior": {"low": _digest(prior.low), "high": _digest(prior.high),
                  "free": [bool(v) for v in torch.as_tensor(prior.free_mask).tolist()]},
        "noise": dataclasses.asdict(noise) if dataclasses.is_dataclass(noise) else repr(noise),
        "versions": {"torch": torch.__version__, "sbi": ".".join(map(str, sbi_adapter.sbi_version()))},
        "previous": previous,
    }
    text = json.dumps(content, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def _paths(workdir, method: str, index: int, key: str) -> tuple[Path, Path]:
    weights = Path(workdir) / f"{method}_tasks" / f"task{index:03d}-{key[:16]}.pt"
    return weights, weights.with_name(weights.name + ".json")


def save_task(workdir, method: str, index: int, key: str, module: torch.nn.Module, x_obs: torch.Tensor,
              info: dict, *, n_free: int, architecture: dict) -> Path:
    """Write task ``index``'s trained network and observed summary (atomically, metadata last)."""
    weights, meta_path = _paths(workdir, method, index, key)
    buf = io.BytesIO()
    torch.save({"state_dict": {k: t.detach().cpu() for k, t in module.state_dict().items()},
                "x_obs": x_obs.detach().cpu()}, buf)
    data = buf.getvalue()
    meta = {"format": file_format(method), "key": key, "index": int(index),
            "sha256": hashlib.sha256(data).hexdigest(), "n_free": int(n_free), "n_x": int(x_obs.shape[-1]),
            "architecture": architecture, "info": info}
    atomic_write_bytes(weights, data)
    atomic_write_text(meta_path, json.dumps(meta, indent=1, default=str))
    return weights


def load_task(workdir, method: str, index: int, key: str,
              build: Callable[[int, int, dict], torch.nn.Module]) -> tuple[torch.nn.Module, torch.Tensor, dict] | None:
    """(network, observed summary, training info) of a checkpoint with exactly this ``key``, or
    None when there is none; a damaged or mismatched one is ignored with a RuntimeWarning.
    ``build(n_free, n_x, architecture)`` makes the untrained network the state dict fills."""
    weights, meta_path = _paths(workdir, method, index, key)
    if not meta_path.is_file():
        return None
    try:
        meta = read_json(meta_path, "metadata")
        if not isinstance(meta, dict) or meta.get("format") != file_format(method) or meta.get("key") != key:
            raise ValueError("its metadata is not this task's (format or key differs)")
        data = weights.read_bytes()
        if hashlib.sha256(data).hexdigest() != meta.get("sha256"):
            raise ValueError("the weights' sha256 differs from the metadata (damaged or replaced)")
        blob = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
        module = build(int(meta["n_free"]), int(meta["n_x"]), meta["architecture"])
        module.load_state_dict(blob["state_dict"], strict=True)
        x_obs = blob["x_obs"]
        if not isinstance(x_obs, torch.Tensor) or x_obs.shape != (int(meta["n_x"]),):
            raise ValueError("the stored observed summary has the wrong shape")
        info = meta["info"]
        if not isinstance(info, dict):
            raise ValueError("the stored training info is not a JSON object")
    except Exception as exc:  # noqa: BLE001 - any unreadable checkpoint means: train the task again
        msg = str(exc).splitlines()[0] if str(exc) else ""
        warnings.warn(f"{method}: checkpoint {meta_path.name} not used ({type(exc).__name__}: {msg}); "
                      f"task {index} is trained again", RuntimeWarning, stacklevel=3)
        return None
    return module.eval(), x_obs, info


def resumed_summary(infos) -> dict:
    """Which of a run's per-task ``infos`` were read back (``"resumed"``) and their recorded
    simulation and training seconds: a result's ``extras["resumed_tasks"]`` and
    ``extras["resumed_seconds"]`` (added to its wall time, by the registry too, so that
    resuming never makes a method look faster)."""
    back = [t for t in infos if t.get("resumed")]
    return {"resumed_tasks": [t["task"] for t in back],
            "resumed_seconds": sum(t["time_simulate"] + t["time_train"] for t in back)}
