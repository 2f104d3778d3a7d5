"""Batched trajectory distances: exact Dynamic Time Warping with exact pruning, and Eq. 2's L2.

Definitions (one observed trajectory ``x`` of ``n`` points, one simulated ``y`` of ``m`` points,
points in R^D, joint space D = n_joints or Cartesian D = 3)::

    c(i, j)  = ||x_i - y_j||_2                                   (Euclidean local cost)
    DTW(x, y) = min over warping paths P of  sum_{(i, j) in P} c(i, j)

A warping path goes from (0, 0) to (n-1, m-1) with steps (1, 0), (0, 1), (1, 1), so the
classic recursion ``D(i, j) = c(i, j) + min(D(i-1, j), D(i, j-1), D(i-1, j-1))`` gives
``DTW = D(n-1, m-1)``. No band (window) is used: this is the full, unconstrained DTW.
For equal lengths the diagonal path is one of the candidates, so DTW <= sum_t ||x_t - y_t||,
a sum of point distances; the paper's Eq. 2 (`l2_distance`, the L2 norm of the stacked point
differences) compares equal-length trajectories only, DTW generalises the comparison to
trajectories of different lengths (section IV-A).

`dtw_distances` computes DTW between one observed trajectory and a batch of simulated ones with
numba, in parallel over candidates, several candidates per SIMD register. Two optional prunings
return values that are *exact for every candidate they report*:

* ``epsilon``: a candidate whose DTW is >= epsilon is reported as +inf (ABC acceptance
  ``L < epsilon`` only needs the accepted ones), every candidate with DTW < epsilon is exact;
* ``keep_best=k``: the k smallest DTW values are exact (ties broken by the lower index), every
  other candidate is reported as +inf.

The pruning cascade (as in the UCR suite, adapted to unequal lengths and no band):

1. a per-candidate lower bound ``LB`` (below), candidates processed in ascending ``LB`` order so
   that a good threshold (the k-th best exact value so far) is found early, and every candidate
   whose bound already exceeds the threshold is skipped without any DP;
2. early abandoning inside the DP: after row ``i`` of the DP, ``min_j D(i, j) + S(i+1)`` is a
   lower bound on DTW, where ``S(i+1)`` bounds the cost of the rows still to come; the DP stops
   as soon as that exceeds the threshold.

Lower bound used (all terms are true lower bounds of DTW with non-negative local costs):

* every warping path visits every row ``i`` at least once, in cells that differ from row to row,
  so ``DTW >= sum_i min_j c(i, j)``; symmetrically ``DTW >= sum_j min_i c(i, j)``;
* ``min_j c(i, j) >= min_s dist(x_i, box_s(y))`` where ``box_s(y)`` is the axis-aligned bounding
  box of the s-th segment of consecutive points of ``y`` (``dist`` to a box is the distance to
  the nearest point of the box, which never exceeds the distance to a point inside it). This is
  LB_Keogh with the whole candidate as envelope (no band), made tighter by piecewise envelopes;
* LB_Kim: every path contains (0, 0) and (n-1, m-1), so row 0 costs at least c(0, 0) and row
  n-1 at least c(n-1, m-1); these replace the box terms of the first and last rows (columns).

``LB = max(row bound, column bound)``. ``S(i)`` is the row bound restricted to rows >= i. Bounds are
shrunk by a relative 1e-9 before any comparison so floating-point reassociation can never
prune a candidate whose computed exact value would have been kept. Exact values do not depend on
the pruning, on the processing order or on the number of threads (each candidate's recursion
runs the same floating-point operations), so results are bit-for-bit reproducible.
"""

from __future__ import annotations

import numbers

import numba
import numpy as np
import torch
from numba import njit, prange

from camo_sbi._validation import as_tensor, check_finite, check_positive_float, check_positive_int

__all__ = ["dtw_distances", "dtw_reference", "l2_distance"]

# Candidates computed together, one per SIMD lane (2 x 8 float64 lanes with AVX-512, 4 x 4 with
# AVX2): independent recursions interleave and hide the latency of the D(i, j-1) dependency.
_LANES = 16
# Points per segment of the piecewise bounding-box envelope used by the lower bound.
_SEG = 8
# Relative shrink applied to every lower bound before comparing it with a threshold.
_SHRINK = 1.0 - 1e-9


# ----------------------------------------------------------------------------------------------
# numba kernels
# ----------------------------------------------------------------------------------------------


@njit(cache=True, nogil=True)
def _gather_block(sim, lengths, ids, start, count, Y, mlen):
    """Copy candidates ``ids[start:start+count]`` into the lane block ``Y`` (D, T, L).

    Steps >= length repeat the last valid point whatever the input padding holds; unused lanes
    replicate the first lane. Returns the largest length in the block.
    """
    T = Y.shape[1]
    D = Y.shape[0]
    mmax = 1
    for lane in range(_LANES):
        b = ids[start + (lane if lane < count else 0)]
        m = lengths[b]
        mlen[lane] = m
        if m > mmax:
            mmax = m
        for j in range(T):
            jj = j if j < m else m - 1
            for k in range(D):
                Y[k, j, lane] = sim[b, jj, k]
    return mmax


@njit(cache=True, nogil=True)
def _dtw_block(x, Y, mlen, mmax, thr, suffix_blk, prev, cur, cost, rmin, out):
    """DTW of the observed ``x`` (n, D) against the ``_LANES`` candidates of block ``Y``.

    thr: (L,) abandon threshold per lane (+inf: never abandon); a lane is abandoned when
    ``(min_j D(i, j) + suffix_blk[i+1, lane]) * _SHRINK > thr[lane]``; the block stops when all
    of its lanes are abandoned. out[lane] receives the exact DTW or +inf when abandoned.
    Returns True when the block ran to the end.
    """
    n = x.shape[0]
    D = x.shape[1]
    inf = np.inf
    check = False
    for lane in range(_LANES):
        if thr[lane] < inf:
            check = True
    for j in range(mmax + 1):
        for lane in range(_LANES):
            prev[j, lane] = inf
    for lane in range(_LANES):
        prev[0, lane] = 0.0
    for i in range(n):
        for lane in range(_LANES):
            cur[0, lane] = inf
        # squared distances of x_i to every point of every lane
        x0 = x[i, 0]
        for j in range(mmax):
            for lane in range(_LANES):
                d = x0 - Y[0, j, lane]
                cost[j, lane] = d * d
        for k in range(1, D):
            xk = x[i, k]
            for j in range(mmax):
                for lane in range(_LANES):
                    d = xk - Y[k, j, lane]
                    cost[j, lane] += d * d
        for lane in range(_LANES):
            rmin[lane] = inf
        for j in range(mmax):
            for lane in range(_LANES):
                a = prev[j, lane]
                b = prev[j + 1, lane]
                e = cur[j, lane]
                mn = a if a < b else b
                mn = mn if mn < e else e
                v = np.sqrt(cost[j, lane]) + mn
                cur[j + 1, lane] = v
                r = v if j < mlen[lane] else inf
                rmin[lane] = r if r < rmin[lane] else rmin[lane]
        if check and i + 1 < n:
            alive = False
            for lane in range(_LANES):
                if (rmin[lane] + suffix_blk[i + 1, lane]) * _SHRINK <= thr[lane]:
                    alive = True
            if not alive:
                for lane in range(_LANES):
                    out[lane] = inf
                return False
        prev, cur = cur, prev
    for lane in range(_LANES):
        out[lane] = prev[mlen[lane], lane]
    return True


@njit(cache=True, parallel=True)
def _dtw_all(x, sim, lengths, ids, n_chunks, out):
    """Exact DTW for candidates ``ids`` (ideally sorted by length), no pruning.

    Blocks of ``_LANES`` consecutive ids are dealt round-robin to ``n_chunks`` chunks (one per
    thread) so that each thread sees a similar mix of lengths.
    """
    n_ids = ids.shape[0]
    T = sim.shape[1]
    D = sim.shape[2]
    n_blocks = (n_ids + _LANES - 1) // _LANES
    for c in prange(n_chunks):
        Y = np.empty((D, T, _LANES))
        prev = np.empty((T + 1, _LANES))
        cur = np.empty((T + 1, _LANES))
        cost = np.empty((T, _LANES))
        rmin = np.empty(_LANES)
        mlen = np.empty(_LANES, dtype=np.int64)
        thr = np.full(_LANES, np.inf)
        suffix_blk = np.zeros((1, _LANES))
        res = np.empty(_LANES)
        for blk in range(c, n_blocks, n_chunks):
            start = blk * _LANES
            count = min(_LANES, n_ids - start)
            mmax = _gather_block(sim, lengths, ids, start, count, Y, mlen)
            _dtw_block(x, Y, mlen, mmax, thr, suffix_blk, prev, cur, cost, rmin, res)
            for lane in range(count):
                out[ids[start + lane]] = res[lane]


@njit(cache=True, nogil=True)
def _seg_boxes(pts, m, seg, lo, hi):
    """Bounding boxes of consecutive segments of ``seg`` points of pts[:m]; returns their count."""
    D = pts.shape[1]
    n_seg = (m + seg - 1) // seg
    for s in range(n_seg):
        a = s * seg
        e = min(a + seg, m)
        for k in range(D):
            v = pts[a, k]
            lo[s, k] = v
            hi[s, k] = v
        for j in range(a + 1, e):
            for k in range(D):
                v = pts[j, k]
                if v < lo[s, k]:
                    lo[s, k] = v
                if v > hi[s, k]:
                    hi[s, k] = v
    return n_seg


@njit(cache=True, nogil=True)
def _box_dist2(p, lo, hi, n_seg):
    """Squared distance from point p (D,) to the nearest of ``n_seg`` boxes."""
    D = p.shape[0]
    best = np.inf
    for s in range(n_seg):
        acc = 0.0
        for k in range(D):
            v = p[k]
            if v < lo[s, k]:
                d = lo[s, k] - v
                acc += d * d
            elif v > hi[s, k]:
                d = v - hi[s, k]
                acc += d * d
        if acc < best:
            best = acc
    return best


@njit(cache=True, nogil=True)
def _point_dist(p, q):
    acc = 0.0
    for k in range(p.shape[0]):
        d = p[k] - q[k]
        acc += d * d
    return np.sqrt(acc)


@njit(cache=True, parallel=True)
def _lower_bounds(x, sim, lengths, seg, lb, suffix):
    """Lower bounds of DTW(x, sim[b, :lengths[b]]) for every candidate b.

    lb: (B,) receives max(row bound, column bound), shrunk by ``_SHRINK``.
    suffix: (B, n+1) receives S(i) = bound on the cost of rows i..n-1 (S(n) = 0).
    """
    n = x.shape[0]
    D = x.shape[1]
    B = sim.shape[0]
    T = sim.shape[1]
    max_seg_obs = (n + seg - 1) // seg
    olo = np.empty((max_seg_obs, D))
    ohi = np.empty((max_seg_obs, D))
    n_seg_obs = _seg_boxes(x, n, seg, olo, ohi)
    max_seg = (T + seg - 1) // seg
    for b in prange(B):
        y = sim[b]
        m = lengths[b]
        ylo = np.empty((max_seg, D))
        yhi = np.empty((max_seg, D))
        n_seg = _seg_boxes(y, m, seg, ylo, yhi)
        # rows (observed points)
        first = _point_dist(x[0], y[0])
        suffix[b, n] = 0.0
        if n == 1:
            last_row = _point_dist(x[0], y[m - 1]) if m > 1 else 0.0
            rows = first + last_row
            suffix[b, 0] = rows
        else:
            acc = _point_dist(x[n - 1], y[m - 1])
            suffix[b, n - 1] = acc
            for i in range(n - 2, 0, -1):
                acc += np.sqrt(_box_dist2(x[i], ylo, yhi, n_seg))
                suffix[b, i] = acc
            acc += first
            suffix[b, 0] = acc
            rows = acc
        # columns (simulated points)
        if m == 1:
            cols = first + (_point_dist(x[n - 1], y[0]) if n > 1 else 0.0)
        else:
            cols = first + _point_dist(x[n - 1], y[m - 1])
            for j in range(1, m - 1):
                cols += np.sqrt(_box_dist2(y[j], olo, ohi, n_seg_obs))
        best = rows if rows > cols else cols
        lb[b] = best * _SHRINK
        for i in range(n + 1):
            suffix[b, i] = suffix[b, i] * _SHRINK


@njit(cache=True, nogil=True)
def _heap_replace_top(heap, v):
    """Max-heap: replace the largest element with v and restore the heap."""
    k = heap.shape[0]
    i = 0
    while True:
        left = 2 * i + 1
        if left >= k:
            break
        right = left + 1
        c = left
        if right < k and heap[right] > heap[left]:
            c = right
        if heap[c] <= v:
            break
        heap[i] = heap[c]
        i = c
    heap[i] = v


@njit(cache=True, nogil=True)
def _heapify(heap):
    k = heap.shape[0]
    for start in range(k // 2 - 1, -1, -1):
        v = heap[start]
        i = start
        while True:
            left = 2 * i + 1
            if left >= k:
                break
            right = left + 1
            c = left
            if right < k and heap[right] > heap[left]:
                c = right
            if heap[c] <= v:
                break
            heap[i] = heap[c]
            i = c
        heap[i] = v


@njit(cache=True, parallel=True)
def _dtw_pruned(x, sim, lengths, ids, lb, suffix, thr0, heap0, n_chunks, out):
    """DTW with pruning for candidates ``ids`` sorted by ascending lower bound.

    thr0: initial abandon threshold (a candidate is dropped when its bound is > thr0).
    heap0: (k,) exact values already known (k = 0: the threshold stays thr0); each chunk keeps
    its own max-heap of the k best values it has seen, whose top is an upper bound of the global
    k-th best, and tightens its threshold with it. out[b] = exact DTW or +inf (pruned).
    """
    n_ids = ids.shape[0]
    n = x.shape[0]
    T = sim.shape[1]
    D = sim.shape[2]
    k = heap0.shape[0]
    n_blocks = (n_ids + _LANES - 1) // _LANES
    for c in prange(n_chunks):
        Y = np.empty((D, T, _LANES))
        prev = np.empty((T + 1, _LANES))
        cur = np.empty((T + 1, _LANES))
        cost = np.empty((T, _LANES))
        rmin = np.empty(_LANES)
        mlen = np.empty(_LANES, dtype=np.int64)
        thr = np.empty(_LANES)
        suffix_blk = np.empty((n + 1, _LANES))
        res = np.empty(_LANES)
        heap = heap0.copy()
        if k > 0:
            _heapify(heap)
        for blk in range(c, n_blocks, n_chunks):
            tau = thr0
            if k > 0 and heap[0] < tau:
                tau = heap[0]
            start = blk * _LANES
            count = min(_LANES, n_ids - start)
            if lb[ids[start]] > tau:
                # ids are sorted by bound: this block and every later one are pruned
                for b2 in range(blk, n_blocks, n_chunks):
                    s2 = b2 * _LANES
                    for lane in range(min(_LANES, n_ids - s2)):
                        out[ids[s2 + lane]] = np.inf
                break
            mmax = _gather_block(sim, lengths, ids, start, count, Y, mlen)
            for lane in range(_LANES):
                b = ids[start + (lane if lane < count else 0)]
                thr[lane] = tau
                for i in range(n + 1):
                    suffix_blk[i, lane] = suffix[b, i]
            _dtw_block(x, Y, mlen, mmax, thr, suffix_blk, prev, cur, cost, rmin, res)
            for lane in range(count):
                v = res[lane]
                out[ids[start + lane]] = v
                if k > 0 and v < heap[0]:
                    _heap_replace_top(heap, v)


# ----------------------------------------------------------------------------------------------
# input handling
# ----------------------------------------------------------------------------------------------


def _as_points(x, name: str, ndim: int) -> torch.Tensor:
    t = as_tensor(x, name)
    if t.dim() != ndim:
        want = "(T, D)" if ndim == 2 else "(B, T, D)"
        raise ValueError(f"{name}: expected shape {want}, got {tuple(t.shape)}")
    if t.shape[-2] < 1 or t.shape[-1] < 1 or (ndim == 3 and t.shape[0] < 1):
        raise ValueError(f"{name}: expected non-empty dimensions, got shape {tuple(t.shape)}")
    return t


def _to_numpy(t: torch.Tensor) -> np.ndarray:
    t = t.detach()
    if t.device.type != "cpu":
        t = t.cpu()
    if t.dtype not in (torch.float32, torch.float64):
        t = t.to(torch.float64)
    return np.ascontiguousarray(t.numpy())


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
        raise TypeError(f"observed_length: expected an integer, got {type(observed_length).__name__}")
    if not 1 <= int(observed_length) <= T_o:
        raise ValueError(f"observed_length: must lie in [1, {T_o}], got {observed_length}")
    return int(observed_length)


def _check_valid_finite(sim: torch.Tensor, lengths: np.ndarray, name: str) -> None:
    T = sim.shape[1]
    if bool(torch.isfinite(sim).all()):
        return
    valid = torch.arange(T)[None, :] < torch.from_numpy(lengths)[:, None]
    bad = ~torch.isfinite(sim).all(dim=-1) & valid
    if bool(bad.any()):
        b, t = (int(v) for v in torch.nonzero(bad)[0])
        raise ValueError(f"{name}: contains NaN or inf values (sample {b}, step {t})")


class _Threads:
    """Context manager setting numba's thread count for one call."""

    def __init__(self, workers):
        self.workers = workers
        self.old = None

    def __enter__(self):
        if self.workers is not None:
            self.old = numba.get_num_threads()
            numba.set_num_threads(self.workers)
        return numba.get_num_threads()

    def __exit__(self, *exc):
        if self.old is not None:
            numba.set_num_threads(self.old)
        return False


# ----------------------------------------------------------------------------------------------
# public API
# ----------------------------------------------------------------------------------------------


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
        workers: numba threads to use (default: numba's current setting).

    Returns:
        (B,) float64 CPU tensor: DTW = min over warping paths of the sum of Euclidean point
        distances (see the module docstring), or +inf where pruned as described above. The
        values do not depend on ``workers`` or on the pruning options (bit-for-bit).

    Raises:
        ValueError/TypeError whose message starts with the offending argument's name.
    """
    obs_t = _as_points(observed, "observed", 2)
    sim_t = _as_points(simulated, "simulated", 3)
    B, T, D = (int(s) for s in sim_t.shape)
    if obs_t.shape[1] != D:
        raise ValueError(
            f"simulated: point dimension {D} differs from observed's {int(obs_t.shape[1])}"
        )
    n = _check_observed_length(observed_length, int(obs_t.shape[0]))
    lens = _check_lengths(lengths, B, T)
    eps = None if epsilon is None else check_positive_float(epsilon, "epsilon")
    k = None if keep_best is None else check_positive_int(keep_best, "keep_best")
    if workers is not None:
        workers = check_positive_int(workers, "workers")
        if workers > numba.config.NUMBA_NUM_THREADS:
            raise ValueError(
                f"workers: must be <= {numba.config.NUMBA_NUM_THREADS} (numba's thread pool), "
                f"got {workers}"
            )
    obs_t = obs_t[:n]
    check_finite(obs_t, "observed")
    _check_valid_finite(sim_t, lens, "simulated")

    sim = _to_numpy(sim_t)
    x = np.ascontiguousarray(_to_numpy(obs_t).astype(sim.dtype, copy=False))
    out = np.empty(B, dtype=np.float64)

    with _Threads(workers) as n_threads:
        if eps is None and (k is None or k >= B):
            ids = np.argsort(lens, kind="stable").astype(np.int64)
            _dtw_all(x, sim, lens, ids, n_threads, out)
        else:
            _dtw_with_pruning(x, sim, lens, eps, k, n_threads, out)

    if eps is not None:
        out[out >= eps] = np.inf
    if k is not None and k < B:
        best = np.argsort(out, kind="stable")[:k]
        keep = np.full(B, np.inf)
        keep[best] = out[best]
        out = keep
    return torch.from_numpy(out)


def _dtw_with_pruning(x, sim, lens, eps, k, n_threads, out) -> None:
    B = sim.shape[0]
    n = x.shape[0]
    lb = np.empty(B)
    suffix = np.empty((B, n + 1))
    _lower_bounds(x, sim, lens, _SEG, lb, suffix)
    order = np.argsort(lb, kind="stable").astype(np.int64)
    # candidates with bound >= epsilon are > prev_float(epsilon): abandon threshold
    thr0 = np.inf if eps is None else float(np.nextafter(eps, 0.0))
    if k is None or k >= B:
        heap0 = np.empty(0)
        rest = order
    else:
        # phase 1: the k most promising candidates exactly (abandoning only at epsilon)
        first = order[:k]
        _dtw_pruned(x, sim, lens, first, lb, suffix, thr0, np.empty(0), n_threads, out)
        heap0 = np.ascontiguousarray(out[first])
        rest = order[k:]
        thr0 = min(thr0, float(heap0.max()))
        out[rest] = np.inf
        # drop everything whose bound already exceeds the k-th best known value
        rest = rest[: int(np.searchsorted(lb[rest], thr0, side="right"))]
    if rest.size:
        _dtw_pruned(x, sim, lens, rest, lb, suffix, thr0, heap0, n_threads, out)


def dtw_reference(a, b) -> float:
    """Plain O(n m) DTW of one pair in numpy (for tests): sum of Euclidean point distances.

    a: (n, D), b: (m, D). Builds the full cost matrix and the accumulated-cost table.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.ndim != 2 or a.shape[0] < 1:
        raise ValueError(f"a: expected shape (n, D), got {a.shape}")
    if b.ndim != 2 or b.shape[0] < 1 or b.shape[1] != a.shape[1]:
        raise ValueError(f"b: expected shape (m, {a.shape[1]}), got {b.shape}")
    cost = np.sqrt(((a[:, None, :] - b[None, :, :]) ** 2).sum(axis=-1))
    n, m = cost.shape
    acc = np.full((n + 1, m + 1), np.inf)
    acc[0, 0] = 0.0
    for i in range(1, n + 1):
        for j in range(1, m + 1):
            acc[i, j] = cost[i - 1, j - 1] + min(acc[i - 1, j], acc[i, j - 1], acc[i - 1, j - 1])
    return float(acc[n, m])


def l2_distance(observed, simulated) -> torch.Tensor:
    """Eq. 2 of the paper: L2 norm of the point differences, for equal-length trajectories.

    observed: (T, D); simulated: (B, T, D) (or (T, D) for one). Returns (B,) float64:
    ``sqrt(sum_t ||observed_t - simulated_b,t||^2)``. ValueError if the lengths differ.
    """
    obs_t = _as_points(observed, "observed", 2).detach().cpu().to(torch.float64)
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
