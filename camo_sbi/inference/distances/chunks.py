"""What one thread does with its chunk of lane blocks: bounds, thresholds and the DP.

Each kernel takes (c, n_chunks, ...) and handles blocks c, c + n_chunks, c + 2 n_chunks, ... of
the candidates ``ids`` (int64, in the order the caller chose), so its work and results depend
only on (c, n_chunks), never on thread timing; `camo_sbi._threads` runs the chunks. Shapes: the
observed ``x`` (n, D) float64; ``sim`` (B, T, D) float32 or float64 with ``lengths`` (B,)
int64; per-candidate outputs (B,) float64 indexed by candidate; ``bad`` (1,) int64 (see
`blocks.record_nonfinite`).

The cascade (UCR suite style, adapted to no band and unequal lengths), driven by `api`:

1. `coarse_chunk`: coarse LB (one box per trajectory) and UB of every candidate (cheap);
2. with ``keep_best``: the k candidates of smallest UB are computed first; the k-th smallest UB
   and then the k-th best exact value so far are thresholds (per-thread max-heaps);
3. the others in ascending coarse LB (`dtw_chunk`, mode 2): a candidate whose coarse, then
   fine, LB exceeds the threshold never reaches the DP, and a thread stops at its first block
   whose coarse bounds all exceed it;
4. inside the DP (`kernels`): cells that cannot lie on a path of cost <= the threshold are
   skipped. Even without pruning options the threshold is the candidate's own UB, which skips
   cells without changing any result.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from camo_sbi.inference.distances.blocks import LANES, MIN_CELLS_FOR_LANES, SEG, gather_block
from camo_sbi.inference.distances.bounds import (
    box_rows_bound,
    cols_bound,
    combine_bounds,
    rows_bound,
    seg_boxes,
    upper_bound,
)
from camo_sbi.inference.distances.kernels import dtw_block, dtw_scalar

__all__ = ["coarse_chunk", "dtw_chunk", "fine_bounds", "scalar_chunk"]


@njit(cache=True, nogil=True)
def _bound_scratch(n, D, T):
    """Scratch arrays of the block bounds: Yf, mlen, box, acc_r, best_r, acc_c, best_c, scol,
    suffix_blk, rows, cols, lbb (shapes as the kernels of `blocks` and `bounds` take them)."""
    L = LANES
    return (
        np.empty((D, T * L)),
        np.empty(L, dtype=np.int64),
        np.empty((2, D, L)),
        np.empty(n),
        np.empty(n),
        np.empty(T * L),
        np.empty(T * L),
        np.empty((T + 1) * L),
        np.empty((n + 1, L)),
        np.empty(L),
        np.empty(L),
        np.empty(L),
    )


@njit(cache=True, nogil=True)
def scalar_chunk(c, n_chunks, x, sim, lengths, thr, out, bad):
    """The plain recursion one candidate at a time (`kernels.dtw_scalar`), no bounds, no lanes:
    candidates c, c + n_chunks, ... of sim (B, T, D). out[b] = the exact DTW if it is <= thr
    (+inf: always), else +inf: the values of `dtw_chunk`, bit for bit.

    A few small kernels, so compiling it costs a fraction of the lane machinery's compile; `api`
    sends small calls here (see ``api.SMALL_CALL_CELLS``).
    """
    T = sim.shape[1]
    prev = np.empty(T + 1)
    cur = np.empty(T + 1)
    for b in range(c, sim.shape[0], n_chunks):
        out[b] = dtw_scalar(x, sim, b, lengths[b], thr, prev, cur, bad)


@njit(cache=True, nogil=True)
def coarse_chunk(c, n_chunks, x, sim, lengths, ids, lb, ub, bad):
    """Cheap lower bound (one box per trajectory, LB_Kim ends) and upper bound of candidates
    ``ids`` (sorted by length for short blocks), written to lb[b], ub[b]; blocks c,
    c + n_chunks, ... here."""
    n, D = x.shape
    T = sim.shape[1]
    n_ids = ids.shape[0]
    xT = np.ascontiguousarray(x.T)
    olo, ohi = seg_boxes(xT, n)
    Yf, mlen, box, acc_r, _, acc_c, best_c, scol, _, rows, cols, lbb = _bound_scratch(n, D, T)
    ubb = np.empty(LANES)
    for start in range(c * LANES, n_ids, n_chunks * LANES):
        count = min(LANES, n_ids - start)
        mmax = gather_block(sim, lengths, ids, start, count, Yf, mlen, box, True, bad)
        box_rows_bound(xT, box, acc_r, rows)
        cols_bound(olo, ohi, Yf, mlen, mmax, acc_c, best_c, cols, scol)
        combine_bounds(x, Yf, mlen, rows, cols, lbb)
        upper_bound(x, Yf, mlen, ubb, cols)
        for lane in range(count):
            b = ids[start + lane]
            lb[b] = lbb[lane]
            ub[b] = ubb[lane]


@njit(cache=True)
def fine_bounds(x, sim, lengths, seg, lb, ub, suffix, col_suffix):
    """Fine lower bounds lb, upper bounds ub (B,), row suffix bounds suffix (B, n+1) and column
    suffix bounds col_suffix (B, T+1) of every candidate, as `dtw_chunk` uses them."""
    n, D = x.shape
    B, T = sim.shape[0], sim.shape[1]
    xT = np.ascontiguousarray(x.T)
    olo, ohi = seg_boxes(xT, seg)
    Yf, mlen, box, acc_r, best_r, acc_c, best_c, scol, suffix_blk, rows, cols, lbb = (
        _bound_scratch(n, D, T)
    )
    ubb = np.empty(LANES)
    ids = np.arange(B)
    bad = np.full(1, -1)
    for start in range(0, B, LANES):
        count = min(LANES, B - start)
        mmax = gather_block(sim, lengths, ids, start, count, Yf, mlen, box, False, bad)
        rows_bound(xT, Yf, mlen, seg, acc_r, best_r, suffix_blk, rows)
        cols_bound(olo, ohi, Yf, mlen, mmax, acc_c, best_c, cols, scol)
        combine_bounds(x, Yf, mlen, rows, cols, lbb)
        upper_bound(x, Yf, mlen, ubb, cols)
        for lane in range(count):
            lb[start + lane] = lbb[lane]
            ub[start + lane] = ubb[lane]
            for i in range(n + 1):
                suffix[start + lane, i] = suffix_blk[i, lane]
            for j in range(mmax + 1):
                col_suffix[start + lane, j] = scol[j * LANES + lane]


@njit(cache=True, nogil=True)
def sift_down(heap, i, v):
    """Max-heap: put v at position i and move it down to its place."""
    k = heap.shape[0]
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
def dtw_chunk(c, n_chunks, x, sim, lengths, ids, mode, lb0, ub, thr0, heap0, out, bad):
    """DTW of candidates ``ids`` in blocks of ``LANES``: blocks c, c + n_chunks, ... here.

    mode 0 (all exact): each lane's threshold is its own upper bound, so every result is exact
        and cells that cannot lie on an optimal path are skipped; ids sorted by length.
    mode 1 / 2 (pruned): a chunk's threshold is tau = min(thr0, top of its max-heap); the heap
        starts from heap0, values known for k *other* candidates (exact, or +inf above the
        threshold they were computed with), and takes in the exact values the chunk computes,
        so its top always bounds the global k-th best from above (k = 0: no heap). A lane's
        threshold is min(tau, its upper bound); a lane whose fine lower bound exceeds tau is
        dead from the start and a block without live lanes skips the DP. In mode 2 ids are in
        ascending coarse bound lb0 and a chunk stops at its first block whose bounds all exceed
        tau.
    Blocks whose tables are below ``MIN_CELLS_FOR_LANES`` cells use `kernels.dtw_scalar` instead
    (threshold: +inf in mode 0, min(tau, upper bound) otherwise; the coarse bound decides).
    out[b] = exact DTW if <= the lane's threshold, else +inf.
    """
    n, D = x.shape
    T = sim.shape[1]
    n_ids = ids.shape[0]
    k = heap0.shape[0]
    xT = np.ascontiguousarray(x.T)
    olo, ohi = seg_boxes(xT, SEG)
    n_blocks = (n_ids + LANES - 1) // LANES
    Yf, mlen, box, acc_r, best_r, acc_c, best_c, scol, suffix_blk, rows, cols, lbb = (
        _bound_scratch(n, D, T)
    )
    prev = np.empty((T + 2) * LANES)
    cur = np.empty((T + 2) * LANES)
    cost = np.empty(T * LANES)
    thr = np.empty(LANES)
    thr_eff = np.empty(LANES)
    res = np.empty(LANES)
    heap = heap0.copy()
    for h in range(k // 2 - 1, -1, -1):
        sift_down(heap, h, heap[h])
    for blk in range(c, n_blocks, n_chunks):
        start = blk * LANES
        count = min(LANES, n_ids - start)
        tau = thr0
        if k > 0 and heap[0] < tau:
            tau = heap[0]
        if mode == 2 and lb0[ids[start]] > tau:
            # every later block of the chunk has larger coarse bounds: all out
            for b2 in range(blk, n_blocks, n_chunks):
                s2 = b2 * LANES
                for lane in range(min(LANES, n_ids - s2)):
                    out[ids[s2 + lane]] = np.inf
            break
        mmax = 1
        for lane in range(count):
            mmax = max(mmax, lengths[ids[start + lane]])
        if n * mmax < MIN_CELLS_FOR_LANES:
            # small tables: one candidate at a time, no gather, no bounds
            for lane in range(count):
                b = ids[start + lane]
                t_b = np.inf if mode == 0 else min(tau, ub[b])
                v = np.inf
                if mode == 0 or lb0[b] <= t_b:
                    v = dtw_scalar(x, sim, b, lengths[b], t_b, prev, cur, bad)
                out[b] = v
                if k > 0 and v < heap[0]:
                    sift_down(heap, 0, v)
                    if heap[0] < tau:
                        tau = heap[0]
            continue
        mmax = gather_block(sim, lengths, ids, start, count, Yf, mlen, box, False, bad)
        rows_bound(xT, Yf, mlen, SEG, acc_r, best_r, suffix_blk, rows)
        cols_bound(olo, ohi, Yf, mlen, mmax, acc_c, best_c, cols, scol)
        if mode == 0:
            upper_bound(x, Yf, mlen, thr, cols)
        else:
            for lane in range(LANES):
                u = ub[ids[start + (lane if lane < count else 0)]]
                thr[lane] = u if u < tau else tau
        for lane in range(count, LANES):
            thr[lane] = -1.0  # padding lane
        if mode != 0:
            combine_bounds(x, Yf, mlen, rows, cols, lbb)
            for lane in range(LANES):
                if lbb[lane] > thr[lane]:
                    thr[lane] = -1.0  # dead from the start
        alive = False
        for lane in range(LANES):
            if thr[lane] >= 0.0:
                alive = True
        if alive:
            dtw_block(x, Yf, mlen, mmax, thr, suffix_blk, scol, prev, cur, cost, thr_eff, res)
        else:
            for lane in range(LANES):
                res[lane] = np.inf
        for lane in range(count):
            v = res[lane]
            out[ids[start + lane]] = v
            if k > 0 and v < heap[0]:
                sift_down(heap, 0, v)
