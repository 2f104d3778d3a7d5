"""``camo-sbi warmup``: compile camo_sbi's numba kernels (and build matplotlib's font cache) now.

What a first run would otherwise compile while the user waits: the package's DTW and KDE
kernels, the generated kernels of each body model in float32 (CAMO's candidates, the report's
predictive draws) and float64 (predictions of held-out reaches), and the kernels numba compiles
for arviz when a posterior file is written. They are compiled by running the same code a
comparison runs, on a tiny grid (camo and abc-smc plus the baselines, one task, one test goal,
150 simulations) in a temporary directory that is deleted afterwards: the argument types, hence
the compiled signatures, are exactly those of a real run, never a guessed list.

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

__all__ = ["WARMUP_METHODS", "add_arguments", "main", "warm"]

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


def main(args) -> int:
    models = _models(args.models)
    import matplotlib.font_manager  # noqa: F401  (builds matplotlib's font cache once, ~1 s)

    for model in models:
        wall, cpu = warm(model)
        print(f"warmup {model}: kernels compiled or loaded from the cache in {wall:.1f} s ({cpu:.1f} s CPU)")
    return 0
