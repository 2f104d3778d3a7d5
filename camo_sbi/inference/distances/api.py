"""The public functions `dtw_distances` and `l2_distance`, and the checks of their inputs.

Shapes: ``observed`` (T_o, D) and ``simulated`` (B, T, D), tensors or arrays (float32 and
float64 are read as they are, anything else is converted to float64); ``lengths`` (B,)
integers in [1, T]. Results are (B,) float64 CPU tensors. Input errors are ValueError or
TypeError whose message starts with the argument's name (``"lengths: ..."``).

`dtw_distances` validates, then runs the chunk kernels of `chunks` on threads (`camo_sbi._threads`):
one pass of exact DTW without pruning options, else the pruned cascade of `_dtw_with_pruning`.
`_candidate_bounds` exposes the bounds of `bounds` for tests and diagnostics.
"""

from __future__ import annotations

import numbers

import numpy as np
import torch

from camo_sbi._threads import default_workers, run_chunks
from camo_sbi._validation import as_tensor, check_finite, check_positive_float, check_positive_int
from camo_sbi.inference.distances.blocks import LANES, SEG
from camo_sbi.inference.distances.chunks import coarse_chunk, dtw_chunk, fine_bounds, scalar_chunk

__all__ = ["SMALL_CALL_CELLS", "dtw_distances", "l2_distance"]

SMALL_CALL_CELLS = 5_000_000
"""A call whose DP tables hold at most this many cells in all (observed length x the sum of the
candidates' lengths) runs the plain recursion one candidate at a time (`chunks.scalar_chunk`):
at most a few tens of milliseconds per call at this size (slower per cell than the cascade),
and its kernels compile in about a second, where the
lane blocks, bounds and pruned cascade of larger calls take most of a first run's compile
(docs/guide/performance.md, section 1). The values are the same bit for bit either way."""


def _as_points(x, name: str, ndim: int) -> np.ndarray:
    """A C-contiguous float32/float64 numpy view of x (no copy when it already is one)."""
    if isinstance(x, torch.Tensor):
        t = x.detach()
        if t.device.type != "cpu":
            t = t.cpu()
        if t.dtype not in (torch.float32, torch.float64):
            t = as_tensor(t, name).to(torch.float64)
        a = t.numpy()
    elif isinstance(x, np.ndarray) and x.dtype in (np.float32, np.float64):
        a = x
    else:
        a = as_tensor(x, name).numpy()
    if a.ndim != ndim:
        want = "(T, D)" if ndim == 2 else "(B, T, D)"
        raise ValueError(f"{name}: expected shape {want}, got {tuple(a.shape)}")
    if a.shape[-2] < 1 or a.shape[-1] < 1 or (ndim == 3 and a.shape[0] < 1):
        raise ValueError(f"{name}: expected non-empty dimensions, got shape {tuple(a.shape)}")
    return np.ascontiguousarray(a)


def _check_lengths(lengths, B: int, T: int) -> np.ndarray:
    if lengths is None:
        return np.full(B, T, dtype=np.int64)
    if isinstance(lengths, torch.Tensor):
        if lengths.dtype.is_floating_point or lengths.dtype == torch.bool or lengths.is_complex():
            raise TypeError(f"lengths: expected an integer tensor, got dtype {lengths.dtype}")
        arr = lengths.detach().cpu().numpy()
    else:
        arr = np.asarray(lengths)
        if arr.dtype.kind not in "iu":
            raise TypeError(f"lengths: expected integers, got dtype {arr.dtype}")
    if arr.shape != (B,):
        raise ValueError(f"lengths: expected shape ({B},), got {tuple(arr.shape)}")
    arr = arr.astype(np.int64)
    if B and (arr.min() < 1 or arr.max() > T):
        bad = int(np.flatnonzero((arr < 1) | (arr > T))[0])
        raise ValueError(f"lengths: must lie in [1, {T}], got {int(arr[bad])} at index {bad}")
    return np.ascontiguousarray(arr)


def _check_observed_length(observed_length, T_o: int) -> int:
    if observed_length is None:
        return T_o
    if isinstance(observed_length, torch.Tensor):
        if observed_length.numel() != 1 or observed_length.dtype.is_floating_point:
            raise TypeError("observed_length: expected an integer")
        observed_length = int(observed_length.item())
    if isinstance(observed_length, bool) or not isinstance(observed_length, numbers.Integral):
        raise TypeError(
            f"observed_length: expected an integer, got {type(observed_length).__name__}"
        )
    if not 1 <= int(observed_length) <= T_o:
        raise ValueError(f"observed_length: must lie in [1, {T_o}], got {observed_length}")
    return int(observed_length)


def _raise_nonfinite(sim: np.ndarray, lengths: np.ndarray, name: str) -> None:
    """Raise ValueError naming the first sample/step holding NaN or inf among valid steps."""
    T = sim.shape[1]
    valid = np.arange(T)[None, :] < lengths[:, None]
    bad = ~np.isfinite(sim).all(axis=-1) & valid
    b, t = np.argwhere(bad)[0]
    raise ValueError(f"{name}: contains NaN or inf values (sample {int(b)}, step {int(t)})")


def dtw_distances(
    observed,
    simulated,
    lengths=None,
    *,
    observed_length=None,
    epsilon=None,
    keep_best=None,
    workers=None,
) -> torch.Tensor:
    """Exact DTW between one observed trajectory and every simulated trajectory.

    Args:
        observed: (T_o, D) observed trajectory (tensor or array); steps >= ``observed_length``
            are ignored.
        simulated: (B, T, D) simulated trajectories, same D; steps >= ``lengths[b]`` are padding
            and are never read.
        lengths: (B,) integer valid lengths in [1, T]; None means all T.
        observed_length: valid length of ``observed`` in [1, T_o]; None means T_o.
        epsilon: if given (> 0), candidates with DTW >= epsilon are returned as +inf; all others
            are exact.
        keep_best: if given (k >= 1), only the k smallest distances (ties: lower index first) are
            returned exactly, all other entries are +inf. With ``epsilon`` too, the k best among
            those < epsilon.
        workers: threads to use (default: the CPUs this process may run on). Each thread
            takes a fixed share of the blocks, so the values never depend on it.

    Returns:
        (B,) float64 CPU tensor: DTW = min over warping paths of the sum of Euclidean point
        distances (see the package docstring), or +inf where pruned as described above. The
        values do not depend on ``workers`` or on the pruning options (bit-for-bit).

    Raises:
        ValueError/TypeError whose message starts with the offending argument's name.
    """
    obs = _as_points(observed, "observed", 2)
    sim = _as_points(simulated, "simulated", 3)
    B, T, D = sim.shape
    if obs.shape[1] != D:
        raise ValueError(f"simulated: point dimension {D} differs from observed's {obs.shape[1]}")
    n = _check_observed_length(observed_length, obs.shape[0])
    lens = _check_lengths(lengths, B, T)
    eps = None if epsilon is None else check_positive_float(epsilon, "epsilon")
    k = None if keep_best is None else check_positive_int(keep_best, "keep_best")
    n_threads = default_workers() if workers is None else check_positive_int(workers, "workers")
    x = np.ascontiguousarray(obs[:n], dtype=np.float64)
    if not np.isfinite(x).all():
        raise ValueError("observed: contains NaN or inf values")
    out = np.empty(B, dtype=np.float64)
    bad = np.full(1, -1, dtype=np.int64)  # set by the kernels on NaN/inf in a valid step

    if n * int(lens.sum()) <= SMALL_CALL_CELLS:
        thr = np.inf if eps is None else float(np.nextafter(eps, 0.0))  # "< eps" is "<= thr"
        run_chunks(scalar_chunk, max(1, min(n_threads, B)), x, sim, lens, thr, out, bad)
        if bad[0] >= 0:
            _raise_nonfinite(sim, lens, "simulated")
    elif eps is None and (k is None or k >= B):
        ids = np.argsort(lens, kind="stable").astype(np.int64)
        none = np.empty(0)
        n_chunks = max(1, min(n_threads, -(-B // LANES)))
        run_chunks(dtw_chunk, n_chunks, x, sim, lens, ids, 0, none, none, np.inf, none, out, bad)
        if bad[0] >= 0:
            _raise_nonfinite(sim, lens, "simulated")
    else:
        _dtw_with_pruning(x, sim, lens, eps, k, n_threads, out, bad)

    if eps is not None:
        out[out >= eps] = np.inf
    if k is not None and k < B:
        best = np.argsort(out, kind="stable")[:k]
        keep = np.full(B, np.inf)
        keep[best] = out[best]
        out = keep
    return torch.from_numpy(out)


def _dtw_with_pruning(x, sim, lens, eps, k, n_threads, out, bad) -> None:
    """The pruned cascade (see the `chunks` docstring); out[b] = exact DTW or +inf."""
    B = sim.shape[0]
    lb0 = np.empty(B)
    ub = np.empty(B)
    by_length = np.argsort(lens, kind="stable").astype(np.int64)
    n_chunks = max(1, min(n_threads, -(-B // LANES)))
    run_chunks(coarse_chunk, n_chunks, x, sim, lens, by_length, lb0, ub, bad)
    if bad[0] >= 0:
        _raise_nonfinite(sim, lens, "simulated")
    out[:] = np.inf
    # "DTW >= epsilon" is "DTW > prev_float(epsilon)": the threshold for epsilon
    thr0 = np.inf if eps is None else float(np.nextafter(eps, 0.0))
    heap0 = np.empty(0)
    todo = np.ones(B, dtype=bool)
    if k is not None and k < B:
        # phase 1: the k smallest upper bounds; the k-th of them bounds the k-th best DTW, and
        # these candidates are likely among the best: their exact values start the heap
        first = np.argsort(ub, kind="stable")[:k]
        thr0 = min(thr0, float(ub[first[-1]]))
        first = first[np.argsort(lens[first], kind="stable")].astype(np.int64)
        run_chunks(dtw_chunk, n_chunks, x, sim, lens, first, 1, lb0, ub, thr0, heap0, out, bad)
        heap0 = np.ascontiguousarray(out[first])
        todo[first] = False
    # phase 2: the others by ascending coarse bound; those above the threshold never get there
    rest = np.flatnonzero(todo & (lb0 <= thr0))
    rest = rest[np.argsort(lb0[rest], kind="stable")].astype(np.int64)
    if rest.size:
        run_chunks(dtw_chunk, n_chunks, x, sim, lens, rest, 2, lb0, ub, thr0, heap0, out, bad)


def _candidate_bounds(observed, simulated, lengths=None, *, seg=SEG):
    """Bounds of every candidate, for tests and diagnostics (float64 numpy arrays).

    Returns a dict: ``lb`` the fine lower bound (segments of ``seg`` points), ``coarse_lb`` the
    one-box-per-trajectory lower bound that orders the candidates, ``ub`` the straight path's
    cost, ``row_suffix`` (B, n+1) the bounds S(i) of rows i..n-1 and ``col_suffix`` (B, T+1)
    the bounds of columns j..m-1 (0 from m on), all as used by the kernels (shrunk).
    """
    x = np.ascontiguousarray(np.asarray(observed, dtype=np.float64))
    sim = np.ascontiguousarray(np.asarray(simulated, dtype=np.float64))
    B, T = sim.shape[:2]
    n = x.shape[0]
    lens = _check_lengths(lengths, B, T)
    lb = np.empty(B)
    ub = np.empty(B)
    suffix = np.empty((B, n + 1))
    col_suffix = np.zeros((B, T + 1))
    fine_bounds(x, sim, lens, seg, lb, ub, suffix, col_suffix)
    coarse = np.empty(B)
    ub2 = np.empty(B)
    ids = np.argsort(lens, kind="stable").astype(np.int64)
    coarse_chunk(0, 1, x, sim, lens, ids, coarse, ub2, np.full(1, -1, dtype=np.int64))
    return {"lb": lb, "coarse_lb": coarse, "ub": ub, "row_suffix": suffix, "col_suffix": col_suffix}


def l2_distance(observed, simulated) -> torch.Tensor:
    """Eq. 2 of the paper: L2 norm of the point differences, for equal-length trajectories.

    observed: (T, D); simulated: (B, T, D) (or (T, D) for one). Returns (B,) float64:
    ``sqrt(sum_t ||observed_t - simulated_b,t||^2)``. ValueError if the lengths differ.
    """
    obs_t = torch.from_numpy(_as_points(observed, "observed", 2)).to(torch.float64)
    sim_t = as_tensor(simulated, "simulated").detach().cpu().to(torch.float64)
    if sim_t.dim() == 2:
        sim_t = sim_t.unsqueeze(0)
    if sim_t.dim() != 3:
        raise ValueError(f"simulated: expected shape (B, T, D), got {tuple(sim_t.shape)}")
    if sim_t.shape[2] != obs_t.shape[1]:
        raise ValueError(
            f"simulated: point dimension {int(sim_t.shape[2])} differs from observed's "
            f"{int(obs_t.shape[1])}"
        )
    if sim_t.shape[1] != obs_t.shape[0]:
        raise ValueError(
            f"simulated: length {int(sim_t.shape[1])} differs from observed's "
            f"{int(obs_t.shape[0])}; Eq. 2 needs equal lengths (use dtw_distances)"
        )
    check_finite(obs_t, "observed")
    check_finite(sim_t, "simulated")
    return torch.sqrt(((sim_t - obs_t.unsqueeze(0)) ** 2).sum(dim=(1, 2)))
