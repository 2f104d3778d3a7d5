"""Input checks shared by every public entry point.

Every check raises ``ValueError`` or ``TypeError`` whose message starts with the
name of the offending argument, never an ``assert``.
"""

from __future__ import annotations

import functools
import numbers
import os
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # torch is imported by the checks that use it: numpy-only callers never load it
    import torch


class InputError(ValueError):
    """Bad input found only inside a method's run (an estimator file that does not fit the task,
    a config field the run alone can judge). A ValueError like every other input check, but one
    a grid never records as the method's failure: ``run_method(..., errors="record")`` lets it
    propagate, so the CLI exits 2 naming the argument."""


__all__ = [
    "InputError",
    "as_tensor",
    "check_finite",
    "check_point_estimate",
    "check_positive_int",
    "check_positive_float",
    "check_theta",
    "cpu_array",
    "SEED_STREAMS",
    "derive_seed",
    "numpy_generator",
    "renamed_fields",
    "torch_generator",
]


def as_tensor(x, name: str, *, dtype=None, device=None) -> torch.Tensor:
    """Convert ``x`` (tensor, array, list) to a floating tensor; TypeError naming ``name``."""
    import torch

    if isinstance(x, torch.Tensor):
        t = x
    elif isinstance(x, (np.ndarray, list, tuple, numbers.Real)):
        try:
            a = np.asarray(x, dtype=np.float64)
            t = torch.from_numpy(a if a.flags.writeable else a.copy())
        except (TypeError, ValueError) as exc:
            raise TypeError(f"{name}: cannot convert to a float tensor ({exc})") from exc
    else:
        raise TypeError(f"{name}: expected a torch.Tensor or array-like, got {type(x).__name__}")
    if not (t.is_floating_point()):
        t = t.to(torch.get_default_dtype() if dtype is None else dtype)
    if dtype is not None or device is not None:
        t = t.to(dtype=dtype or t.dtype, device=device or t.device)
    return t


def cpu_array(t: torch.Tensor) -> np.ndarray | None:
    """A numpy view of ``t`` (no copy) when it is a CPU tensor of a numpy dtype, else None.

    Checks on CPU tensors run on this view, in numpy, single-threaded: a torch elementwise op
    on more than ``at::internal::GRAIN_SIZE`` (32768) elements runs on torch's OpenMP threads,
    which then spin-wait for some milliseconds and take the cores from the numba kernel that a
    simulator starts right after its checks (`benchmarks/bench_simulator.py --joints`).
    """
    try:
        return t.detach().numpy()
    except (TypeError, RuntimeError):  # a GPU tensor, bfloat16, a conjugate view, ...
        return None


def check_finite(t: torch.Tensor, name: str) -> torch.Tensor:
    """Raise ValueError naming ``name`` if ``t`` holds NaN or inf."""
    import torch

    a = cpu_array(t)
    ok = bool(np.isfinite(a).all()) if a is not None else bool(torch.isfinite(t).all())
    if not ok:
        raise ValueError(f"{name}: contains NaN or inf values")
    return t


def check_bool(x, name: str) -> bool:
    """Validate a bool (TypeError naming ``name`` otherwise; 0/1 are not bools)."""
    if not isinstance(x, bool):
        raise TypeError(f"{name}: expected a bool, got {type(x).__name__}")
    return x


def check_choice(x, choices, name: str):
    """Validate that ``x`` is one of ``choices`` (ValueError naming ``name`` and listing them)."""
    if x not in choices:
        raise ValueError(f"{name}: expected one of {tuple(choices)}, got {x!r}")
    return x


#: The one name of the mode, whatever a method used to call it (docs/architecture.md, "Vocabulary").
_OLD_MODE_NAMES = ("argmax", "best", "map")


def check_point_estimate(x, choices) -> str:
    """Validate a ``point_estimate`` (ValueError naming it); an old name of the mode
    ("argmax", "best", "map") is refused with its new name, "mode"."""
    if x in _OLD_MODE_NAMES and x not in choices:
        raise ValueError(f"point_estimate: {x!r} is now called 'mode'; expected one of {tuple(choices)}")
    return check_choice(x, choices, "point_estimate")


def renamed_fields(**old_to_new: str):
    """Class decorator for a config dataclass whose fields were renamed: an old name given to
    its constructor is a TypeError naming the new one (``RENAMED`` on the class lists them;
    `registry.make_config` reads it for dict configs and ``--config``)."""

    def decorate(cls):
        init = cls.__init__

        @functools.wraps(init)
        def __init__(self, *args, **kwargs):
            for old, new in old_to_new.items():
                if old in kwargs:
                    raise TypeError(f"{old}: renamed {new!r}; use {new}=")
            init(self, *args, **kwargs)

        cls.__init__ = __init__
        cls.RENAMED = dict(old_to_new)
        return cls

    return decorate


def check_workdir(x, name: str = "workdir"):
    """A config's artefact folder: None or a path (TypeError naming ``name`` otherwise)."""
    if x is not None and not isinstance(x, (str, os.PathLike)):
        raise TypeError(f"{name}: expected a path or None, got {type(x).__name__}")
    return x


def check_positive_int(x, name: str, *, minimum: int = 1) -> int:
    """Validate an integer >= ``minimum`` (bools rejected)."""
    if isinstance(x, bool) or not isinstance(x, numbers.Integral):
        raise TypeError(f"{name}: expected an integer, got {type(x).__name__}")
    if int(x) < minimum:
        raise ValueError(f"{name}: must be >= {minimum}, got {x}")
    return int(x)


def check_positive_float(x, name: str, *, allow_zero: bool = False) -> float:
    """Validate a finite real > 0 (or >= 0 with ``allow_zero``)."""
    if isinstance(x, bool) or not isinstance(x, numbers.Real):
        raise TypeError(f"{name}: expected a real number, got {type(x).__name__}")
    v = float(x)
    if not np.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        raise ValueError(f"{name}: must be {'>= 0' if allow_zero else '> 0'} and finite, got {x}")
    return v


def check_theta(theta: torch.Tensor, n_joints: int, name: str = "theta") -> torch.Tensor:
    """Validate a batch of limit vectors laid out ``[lo_1, hi_1, ..., lo_n, hi_n]``.

    theta: (B, 2n) or (2n,) -> returned as (B, 2n).
    Raises ValueError naming ``name`` on a wrong shape, NaN/inf or ``lo > hi``.
    """
    if theta.dim() == 1:
        theta = theta.unsqueeze(0)
    if theta.dim() != 2 or theta.shape[1] != 2 * n_joints:
        raise ValueError(
            f"{name}: expected shape (B, {2 * n_joints}) laid out [lo_1, hi_1, ..., lo_n, hi_n], "
            f"got {tuple(theta.shape)}"
        )
    check_finite(theta, name)
    lo, hi = theta[:, 0::2], theta[:, 1::2]
    a = cpu_array(theta)
    bad = (a[:, 0::2] > a[:, 1::2]) if a is not None else (lo > hi).cpu().numpy()
    if bad.any():
        b, j = (int(v) for v in np.argwhere(bad)[0])
        raise ValueError(
            f"{name}: lower limit exceeds upper limit (sample {b}, joint {j}: "
            f"lo={float(lo[b, j]):.4g} > hi={float(hi[b, j]):.4g})"
        )
    return theta


def numpy_generator(seed_or_gen, name: str = "seed") -> np.random.Generator:
    """An explicit numpy Generator from an int seed or a Generator (never global state)."""
    if isinstance(seed_or_gen, np.random.Generator):
        return seed_or_gen
    if isinstance(seed_or_gen, bool) or not isinstance(seed_or_gen, numbers.Integral):
        raise TypeError(f"{name}: expected an int seed or numpy.random.Generator, got {type(seed_or_gen).__name__}")
    return np.random.default_rng(int(seed_or_gen))


def torch_generator(seed_or_gen, name: str = "seed", device="cpu") -> torch.Generator:
    """An explicit torch Generator from an int seed or a Generator (never global state)."""
    import torch

    if isinstance(seed_or_gen, torch.Generator):
        return seed_or_gen
    if isinstance(seed_or_gen, bool) or not isinstance(seed_or_gen, numbers.Integral):
        raise TypeError(f"{name}: expected an int seed or torch.Generator, got {type(seed_or_gen).__name__}")
    g = torch.Generator(device=device)
    g.manual_seed(int(seed_or_gen))
    return g


#: Named seed streams: what each stream seeds, once for every command. Each name stands for
#: the integer the commands used before they had names, so every number stays the same.
SEED_STREAMS = {
    "observation-noise": 5,  # noise added to synthetic recordings (robustness)
    "method": 7,  # a method's run on a cell's task
    "sbc": 11,  # SBC ranks' posterior draws (calibrate)
    "posterior-file": 13,  # resampling and prior draws of a saved netCDF posterior
    "suggest-candidates": 23,  # candidate goals for infer --suggest
    "suggest-ranking": 24,  # their ranking
}


def derive_seed(*parts: int | str) -> int:
    """A 63-bit integer seed derived from ``parts`` (numpy SeedSequence): non-negative integers
    and names of `SEED_STREAMS` (e.g. ``derive_seed(base, run, "method")``).

    Distinct part tuples give independent streams; used to give every run, cell and method
    its own seed from one base seed. An unknown stream name is a ValueError naming ``parts``.
    """
    ints = []
    for p in parts:
        if isinstance(p, str):
            if p not in SEED_STREAMS:
                raise ValueError(f"parts: unknown seed stream {p!r}; expected one of {sorted(SEED_STREAMS)}")
            p = SEED_STREAMS[p]
        ints.append(int(p))
    return int(np.random.SeedSequence(ints).generate_state(2, np.uint64)[0] >> 1)
