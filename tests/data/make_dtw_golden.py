"""Writes dtw_golden.npz: inputs and outputs of the DTW code, frozen as golden values.

Run once, on commit c375cd7 (``camo_sbi/inference/distances.py`` as one 1,130-line module,
before it became a package), with ``python tests/data/make_dtw_golden.py``. The test
``tests/test_distances.py::test_golden_values_are_unchanged`` compares today's code with these
values to a relative tolerance of 1e-12 (numba compiles for the CPU at hand, so the last bits
may differ on another CPU; docs/guide/reproducibility.md). Do not rerun it to make that test
pass: a difference beyond the tolerance is a change in the numbers, to be explained, not
re-frozen.

Cases cover the code paths: SIMD lane blocks (D = 3, 7, 9: 1 to 3 passes of `_acc_dims`),
the scalar path of small tables, blocks of both kinds in one call, D = 1, float32 input,
NaN in the padding, an observation padded beyond ``observed_length``; for each, the full DTW
with 1 and 2 threads, ``keep_best`` and ``epsilon`` and both, the bounds of
``_candidate_bounds`` for three segment sizes (the row and column suffix bounds for the
kernels' segment size only), and Eq. 2 on equal lengths.
"""

from __future__ import annotations

import os

import numpy as np

from camo_sbi.inference.distances import _candidate_bounds, dtw_distances, l2_distance

# name: (B, T, D, observed points n, observed padding, min length, generator, dtype)
CASES = {
    "lanes_d3": (80, 40, 3, 36, 4, 16, "reaches", np.float64),
    "lanes_d7": (64, 32, 7, 32, 0, 10, "reaches", np.float64),
    "lanes_d9": (34, 36, 9, 36, 3, 1, "walks", np.float64),
    "scalar_d2": (70, 20, 2, 12, 2, 1, "walks", np.float64),
    "mixed_d5": (64, 40, 5, 32, 0, 1, "reaches", np.float64),
    "d1": (48, 50, 1, 30, 5, 1, "walks", np.float64),
    "f32_d3": (64, 40, 3, 36, 0, 5, "reaches", np.float32),
}
SEGS = (20, 3, 1000)


def reaches(rng, B, T, D, min_len):
    """Minimum-jerk reaches towards nearby goals with a wiggle; padding repeats the end."""
    start = rng.normal(size=D)
    goal = start + rng.normal(size=D)
    lens = rng.integers(min_len, T + 1, size=B)
    out = np.empty((B, T, D))
    for b in range(B):
        s = np.clip(np.arange(T) / max(lens[b] - 1, 1), 0.0, 1.0)
        prof = 10 * s**3 - 15 * s**4 + 6 * s**5
        g = goal + 0.3 * rng.normal(size=D)
        wiggle = 0.05 * rng.normal(size=D) * np.sin(np.pi * s)[:, None]
        out[b] = start + prof[:, None] * (g - start) + wiggle
    return out, lens


def walks(rng, B, T, D, min_len):
    """Gaussian random walks; padding is whatever the walk did."""
    return rng.normal(size=(B, T, D)).cumsum(axis=1) * 0.3, rng.integers(min_len, T + 1, size=B)


def options(full, B):
    """Name -> keyword arguments of the calls recorded for a case (epsilons from ``full``)."""
    q10, q50 = (float(np.quantile(full, q)) for q in (0.1, 0.5))
    return {
        "full_w1": {"workers": 1},
        "full_w2": {"workers": 2},
        "keep1": {"keep_best": 1},
        "keep7_w1": {"keep_best": 7, "workers": 1},
        "keep_third_w2": {"keep_best": max(1, B // 3), "workers": 2},
        "eps_q10": {"epsilon": q10},
        "eps_q50_keep5": {"epsilon": q50, "keep_best": 5},
        "eps_min": {"epsilon": float(np.sort(full)[3])},  # attained value: DTW >= eps is out
    }


def main():
    out = {}
    for c, (name, (B, T, D, n, pad, min_len, gen, dtype)) in enumerate(CASES.items()):
        rng = np.random.default_rng(1000 + c)
        make = reaches if gen == "reaches" else walks
        sim, lens = make(rng, B, T, D, min_len)
        obs = make(rng, 1, n + pad, D, n + pad)[0][0]
        if name == "mixed_d5":  # the padding is never read
            for b in range(B):
                sim[b, lens[b] :] = np.nan
        sim, obs = sim.astype(dtype), obs.astype(dtype)
        out[f"{name}/sim"], out[f"{name}/lens"], out[f"{name}/obs"] = sim, lens, obs
        out[f"{name}/n"] = np.int64(n)
        full = dtw_distances(obs, sim, lens, observed_length=n).numpy()
        for opt, kw in options(full, B).items():
            d = dtw_distances(obs, sim, lens, observed_length=n, **kw)
            out[f"{name}/dtw/{opt}"] = d.numpy()
            for key, v in kw.items():
                out[f"{name}/kw/{opt}/{key}"] = np.asarray(v)
        for seg in SEGS:
            x = np.asarray(obs[:n], dtype=np.float64)
            s64 = np.where(np.isnan(sim), 0.0, sim).astype(np.float64)
            for key, v in _candidate_bounds(x, s64, lens, seg=seg).items():
                if seg == SEGS[0] or key not in ("row_suffix", "col_suffix"):
                    out[f"{name}/bounds/{seg}/{key}"] = v
        eq = sim[:, :n] if not np.isnan(sim[:, :n]).any() else np.nan_to_num(sim[:, :n])
        out[f"{name}/l2"] = l2_distance(obs[:n], eq).numpy()
    path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "dtw_golden.npz")
    np.savez_compressed(path, **out)
    print(f"wrote {path}: {len(out)} arrays, {os.path.getsize(path) / 1024:.0f} KiB")


if __name__ == "__main__":
    main()
