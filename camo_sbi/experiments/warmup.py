"""``camo-sbi warmup``: compile camo_sbi's numba kernels (and build matplotlib's font cache) now.

What a first run would otherwise compile while the user waits: the package's DTW and KDE
kernels, the generated kernels of each body model in float32 (CAMO's candidates, the report's
predictive draws) and float64 (predictions of held-out reaches), and the kernels numba compiles
for arviz when a posterior file is written. They are compiled by running the same code a
comparison runs, on a tiny grid (camo and abc-smc plus the baselines, one task, one test goal,
150 simulations) in a temporary directory that is deleted afterwards: the argument types, hence
the compiled signatures, are exactly those of a real run, never a guessed list. A tiny grid's
distance calls are small enough for the DTW of small calls; `warm_distances` then compiles the
pruned cascade of larger calls through the public `dtw_distances`, on a synthetic batch just
above ``SMALL_CALL_CELLS`` in both precisions a simulator returns.

Everything lands in the per-user caches (``$XDG_CACHE_HOME/camo_sbi``, ``~/.cache/camo_sbi`` by
default; see `camo_sbi.inference.distances.numba_cache` and `camo_sbi.simulators.kernel`), which
every later run, and every other clone or install of the same sources in this user account,
loads in a fraction of a second. A second ``warmup`` finds everything cached and returns quickly.
Prints one line per model with the time it took (wall and CPU).
"""

from __future__ import annotations

import argparse
import tempfile
import time
import warnings

__all__ = ["WARMUP_METHODS", "add_arguments", "main", "warm", "warm_distances"]

WARMUP_METHODS = "camo,abc-smc"
"""The methods whose runs compile numba kernels (the baselines are added by `compare`; NPE's and
the amortized methods' work is torch, compiled by nobody)."""
_BUDGET = 150  # abc-smc needs a first population of 100 particles


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--models", default="panda",
                   help="comma-separated registered body models whose kernels to compile (panda, human)")


def _models(text: str) -> list[str]:
    from camo_sbi.simulators.registry import model_names

    names = [m.strip() for m in text.split(",") if m.strip()]
    if not names:
        raise ValueError("--models: give at least one model name")
    bad = [m for m in names if m not in model_names()]
    if bad:
        raise ValueError(f"--models: unknown model {bad[0]!r} (registered: {', '.join(model_names())})")
    return list(dict.fromkeys(names))


def warm(model: str) -> tuple[float, float]:
    """Run the tiny grid of `model` once (results discarded); returns (wall s, CPU s)."""
    from camo_sbi.experiments import compare

    t0, c0 = time.perf_counter(), time.process_time()
    parser = argparse.ArgumentParser()
    compare.add_arguments(parser)
    args = parser.parse_args(["--model", model, "--methods", WARMUP_METHODS, "--budgets", str(_BUDGET),
                              "--seeds", "1", "--tasks", "1", "--test-goals", "1"])
    with tempfile.TemporaryDirectory(prefix="camo_warmup_") as tmp, warnings.catch_warnings():
        # a 150-simulation run may warn about its own accuracy; only the compiled code matters here
        warnings.simplefilter("ignore")
        for cell in compare.grid_cells(args):
            compare.run_cell(cell, tmp)
    return time.perf_counter() - t0, time.process_time() - c0


def warm_distances() -> tuple[float, float]:
    """Compile (or load) the pruned DTW cascade: every pruning mode, float32 and float64 candidates;
    returns (wall s, CPU s)."""
    import numpy as np

    from camo_sbi.inference.distances import dtw_distances
    from camo_sbi.inference.distances.api import SMALL_CALL_CELLS

    t0, c0 = time.perf_counter(), time.process_time()
    T = 100
    B = SMALL_CALL_CELLS // (T * T) + 16  # one call just above the small-call size
    steps = np.linspace(0.0, 1.0, T)[None, :, None]
    ends = np.random.default_rng(0).normal(size=(B, 1, 3))
    observed = steps[0] * ends[0]
    for dtype in (np.float32, np.float64):
        sim = (steps * ends).astype(dtype)
        for kw in ({}, {"keep_best": 10}, {"epsilon": 1.0}):
            dtw_distances(observed, sim, **kw)
    return time.perf_counter() - t0, time.process_time() - c0


def main(args) -> int:
    models = _models(args.models)
    import matplotlib.font_manager  # noqa: F401  (builds matplotlib's font cache once, ~1 s)

    for model in models:
        wall, cpu = warm(model)
        print(f"warmup {model}: kernels compiled or loaded from the cache in {wall:.1f} s ({cpu:.1f} s CPU)")
    wall, cpu = warm_distances()
    print(f"warmup DTW of large batches: compiled or loaded from the cache in {wall:.1f} s ({cpu:.1f} s CPU)")
    return 0
