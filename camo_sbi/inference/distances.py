"""Batched trajectory distances: exact Dynamic Time Warping with exact pruning, and Eq. 2's L2.

Definitions (one observed trajectory ``x`` of ``n`` points, one simulated ``y`` of ``m`` points,
points in R^D: joint space D = n_joints, Cartesian space D = 3)::

    c(i, j)   = ||x_i - y_j||_2                                   (Euclidean local cost)
    DTW(x, y) = min over warping paths P of  sum_{(i, j) in P} c(i, j)

A warping path goes from (0, 0) to (n-1, m-1) with steps (1, 0), (0, 1), (1, 1), so the
classic recursion ``D(i, j) = c(i, j) + min(D(i-1, j), D(i, j-1), D(i-1, j-1))`` gives
``DTW = D(n-1, m-1)``. No band (window) constrains the paths: this is the full DTW. The
paper's Eq. 2 (`l2_distance`) is the L2 norm of the point differences of two trajectories of
the same length; DTW generalises the comparison to trajectories of different lengths
(section IV-A). For equal lengths the diagonal path is one of the candidates, so
DTW <= sum_t ||x_t - y_t|| (a sum of point distances, not Eq. 2's root of summed squares).

`dtw_distances` compares one observed trajectory with a batch of simulated ones with numba
(float64 throughout): candidates are processed in blocks of ``_LANES``, one candidate per SIMD
lane (small tables: one candidate at a time with the scalar recursion). The blocks are dealt
round-robin to ``workers`` chunks run by ``nogil`` kernels on a thread pool (rather than a
``parallel=True`` prange, whose compilation alone took ~20 s here, against ~12 s for everything
else). Every value it reports is the exact DTW, computed with the operations of the plain
recursion, so results do not depend on pruning, ordering or the number of threads (bit for
bit). Optional pruning reports +inf for candidates whose value is not needed:

* ``epsilon``: candidates with DTW >= epsilon are +inf (ABC acceptance ``L < epsilon`` only
  needs the others);
* ``keep_best=k``: all but the k smallest values (ties: lower index first) are +inf.

Bounds (all true bounds for non-negative local costs; ``_candidate_bounds`` exposes them):

* rows: every warping path visits every row, in cells that differ from row to row, so
  ``DTW >= sum_i min_j c(i, j)``; columns alike. ``min_j c(i, j) >= r_i = min_s dist(x_i,
  box_s(y))`` where box_s(y) is the bounding box of the s-th segment of ``_SEG`` consecutive
  points of y (the distance to a box never exceeds the distance to a point inside it): this is
  LB_Keogh with the whole candidate as envelope (no band), tightened by piecewise envelopes;
* LB_Kim: every path contains (0, 0) and (n-1, m-1): row 0 costs at least c(0, 0), row n-1
  at least c(n-1, m-1); these replace the first and last rows' (columns') terms;
* lower bound LB = max(row bound, column bound); the coarse LB uses one box per trajectory;
* upper bound UB: the cost of the straight path from (0, 0) to (n-1, m-1), summed in the DP's
  order, so the DP's result never exceeds it.

The cascade (UCR suite style, adapted to no band and unequal lengths):

1. coarse LB and UB of every candidate (cheap);
2. with ``keep_best``: the k candidates of smallest UB are computed first; the k-th smallest UB
   and then the k-th best exact value so far are thresholds (per-thread max-heaps);
3. the others in ascending coarse LB: a candidate whose coarse, then fine, LB exceeds the
   threshold never reaches the DP, and a thread stops at its first block whose coarse bounds
   all exceed it;
4. inside the DP (PrunedDTW, Silva & Batista 2016; EAPrunedDTW, Herrmann & Webb 2021): a cell
   with ``D(i, j) + max(S_rows(i+1), S_cols(j+1)) > threshold`` (S = sums of the row / column
   bounds still to visit) cannot lie on a path of cost <= threshold; each row is computed only
   between its first and last live columns and the candidate is abandoned when a whole row is
   dead. Even without pruning options the threshold is the candidate's own UB, which skips
   cells without changing any result.

Every lower bound is shrunk by a relative 1e-9 and every threshold widened by 1e-10 before a
comparison, so floating-point reassociation can never prune a cell or a candidate that the
plain recursion would keep.
"""

from __future__ import annotations

import numbers
import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch
from numba import njit

from camo_sbi._validation import as_tensor, check_finite, check_positive_float, check_positive_int

__all__ = ["dtw_distances", "dtw_reference", "l2_distance"]

# Candidates computed together, one per SIMD lane: their independent recursions fill the vector
# registers and hide the latency of the D(i, j-1) -> D(i, j) dependency.
_LANES = 16
# Points per segment of the piecewise bounding-box envelope of the fine lower bounds.
_SEG = 20
# Relative shrink applied to every lower bound, relative slack added to every threshold: float
# rounding of sums taken in a different order can then never prune a cell or a candidate that
# the plain recursion would keep (their rounding errors are ~(n + m) * 1.1e-16 relative).
_SHRINK = 1.0 - 1e-9
_SLACK = 1.0 + 1e-10
# Columns added at a time when a row extends beyond the previous row's alive window.
_EXTEND = 8
# Blocks whose DP tables (n x longest candidate) are smaller than this go through a scalar
# recursion one candidate at a time: for them, gathering lanes and bounds costs more than it saves.
_MIN_CELLS_FOR_LANES = 1024


# ----------------------------------------------------------------------------------------------
# numba kernels. A block holds _LANES candidates: Yf[k, j * _LANES + lane] (D, T * _LANES) is
# coordinate k of point j of a lane's candidate. DP rows are flat arrays indexed
# (j + 1) * _LANES + lane, the first _LANES entries holding the virtual column -1.
# ----------------------------------------------------------------------------------------------


@njit(cache=True, nogil=True)
def _gather_block(sim, lengths, ids, start, count, Yf, mlen, box, want_box, bad):
    """Copy candidates ``ids[start:start+count]`` into the lane block Yf.

    Points j < the block's largest length (returned) are written; steps >= a candidate's length
    repeat its last valid point whatever the input padding holds; unused lanes replicate the
    first one. With ``want_box``, box[0, k, lane] / box[1, k, lane] receive the lane's
    bounding box. A NaN/inf
    among the valid points is recorded in bad[0] (as b * T + step) and replaced by 0 (the
    caller raises).
    """
    D = Yf.shape[0]
    T = sim.shape[1]
    nl = mlen.shape[0]
    mmax = 1
    for lane in range(nl):
        m = lengths[ids[start + (lane if lane < count else 0)]]
        mlen[lane] = m
        if m > mmax:
            mmax = m
    flat = sim.reshape(sim.size)
    base = np.empty(nl, dtype=np.int64)  # offset of each lane's candidate in flat
    off = np.empty(nl, dtype=np.int64)  # offset of its point j
    for lane in range(nl):
        base[lane] = ids[start + (lane if lane < count else 0)] * (T * D)
    for k in range(D):
        for lane in range(nl):
            v = flat[base[lane] + k]
            box[0, k, lane] = v
            box[1, k, lane] = v
    chk = np.zeros(nl)
    for j in range(mmax):
        for lane in range(nl):
            m = mlen[lane]
            off[lane] = base[lane] + (j if j < m else m - 1) * D
        t = j * nl
        for k in range(D):
            Yk = Yf[k, t : t + nl]
            for lane in range(nl):
                v = flat[off[lane] + k]
                Yk[lane] = v
                chk[lane] += v * 0.0  # NaN as soon as one value is NaN or inf
            if want_box:
                lo = box[0, k]
                hi = box[1, k]
                for lane in range(nl):
                    v = Yk[lane]
                    lo[lane] = v if v < lo[lane] else lo[lane]
                    hi[lane] = v if v > hi[lane] else hi[lane]
    for lane in range(count):
        if chk[lane] != 0.0:
            b = ids[start + lane]
            for j in range(mlen[lane]):
                for k in range(D):
                    if not np.isfinite(sim[b, j, k]) and bad[0] < 0:
                        bad[0] = b * T + j
            for k in range(D):
                for j in range(mmax):
                    if not np.isfinite(Yf[k, j * nl + lane]):
                        Yf[k, j * nl + lane] = 0.0
    return mmax


@njit(cache=True, nogil=True)
def _box_rows_bound(xT, box, acc_r, inner):
    """Row bounds against one box per lane (the whole candidate): inner[lane] = r_1+...+r_{n-2}."""
    D, n = xT.shape
    for lane in range(_LANES):
        for k in range(D):
            lo = box[0, k, lane]
            hi = box[1, k, lane]
            xk = xT[k]
            if k == 0:
                for i in range(n):
                    d1 = lo - xk[i]
                    d2 = xk[i] - hi
                    d = d1 if d1 > d2 else d2
                    d = d if d > 0.0 else 0.0
                    acc_r[i] = d * d
            else:
                for i in range(n):
                    d1 = lo - xk[i]
                    d2 = xk[i] - hi
                    d = d1 if d1 > d2 else d2
                    d = d if d > 0.0 else 0.0
                    acc_r[i] += d * d
        for i in range(n):
            acc_r[i] = np.sqrt(acc_r[i])
        mid = 0.0
        for i in range(1, n - 1):
            mid += acc_r[i]
        inner[lane] = mid


@njit(cache=True, nogil=True)
def _seg_boxes(x, seg):
    """Bounding boxes lo, hi (D, n_seg) of consecutive segments of ``seg`` points of x (n, D)."""
    n, D = x.shape
    n_seg = (n + seg - 1) // seg
    lo = np.empty((D, n_seg))
    hi = np.empty((D, n_seg))
    for s in range(n_seg):
        a = s * seg
        e = min(a + seg, n)
        for k in range(D):
            vlo = x[a, k]
            vhi = vlo
            for j in range(a + 1, e):
                v = x[j, k]
                vlo = v if v < vlo else vlo
                vhi = v if v > vhi else vhi
            lo[k, s] = vlo
            hi[k, s] = vhi
    return lo, hi


@njit(cache=True, nogil=True)
def _cell_cost(x, i, Yf, j, lane):
    """c(i, j) for one lane, summing squares in the same order as the DP kernel."""
    t = j * _LANES + lane
    d = x[i, 0] - Yf[0, t]
    acc = d * d
    for k in range(1, x.shape[1]):
        d = x[i, k] - Yf[k, t]
        acc += d * d
    return np.sqrt(acc)


@njit(cache=True, nogil=True)
def _rows_bound(xT, Yf, mlen, seg, acc_r, best_r, suffix_blk, inner):
    """Row bounds: r_i = min over the lane's segments s of dist(x_i, box_s(y)) <= min_j c(i, j).

    Every warping path visits every row, in cells that differ from row to row, so any sum of
    r_i over distinct rows is a lower bound of the cost of the path's cells in those rows.
    suffix_blk[i, lane] = (r_i + ... + r_{n-1}) * _SHRINK (suffix_blk[n] = 0);
    inner[lane] = r_1 + ... + r_{n-2}.
    """
    D, n = xT.shape
    L = _LANES
    inf = np.inf
    for lane in range(L):
        m = mlen[lane]
        for i in range(n):
            best_r[i] = inf
        for s in range((m + seg - 1) // seg):
            a = s * seg
            e = min(a + seg, m)
            for k in range(D):
                lo = Yf[k, a * L + lane]
                hi = lo
                for j in range(a + 1, e):
                    v = Yf[k, j * L + lane]
                    lo = v if v < lo else lo
                    hi = v if v > hi else hi
                xk = xT[k]
                if k == 0:
                    for i in range(n):
                        d1 = lo - xk[i]
                        d2 = xk[i] - hi
                        d = d1 if d1 > d2 else d2
                        d = d if d > 0.0 else 0.0
                        acc_r[i] = d * d
                else:
                    for i in range(n):
                        d1 = lo - xk[i]
                        d2 = xk[i] - hi
                        d = d1 if d1 > d2 else d2
                        d = d if d > 0.0 else 0.0
                        acc_r[i] += d * d
            for i in range(n):
                v = acc_r[i]
                best_r[i] = v if v < best_r[i] else best_r[i]
        tot = 0.0
        mid = 0.0
        suffix_blk[n, lane] = 0.0
        for i in range(n - 1, -1, -1):
            r = np.sqrt(best_r[i])
            tot += r
            suffix_blk[i, lane] = tot * _SHRINK
            if 0 < i < n - 1:
                mid += r
        inner[lane] = mid


@njit(cache=True, nogil=True)
def _cols_bound(olo, ohi, Yf, mlen, mmax, acc_c, best_c, inner, scol):
    """Column bounds c_j = min_s dist(y_j, box_s(x)) <= min_i c(i, j).

    inner[lane] = c_1 + ... + c_{m-2}; scol (flat, (T+1) * L): suffix sums of c_j, shrunk.
    """
    D = Yf.shape[0]
    L = _LANES
    W = mmax * L
    bc = best_c[:W]
    ac = acc_c[:W]
    for t in range(W):
        bc[t] = np.inf
    for s in range(olo.shape[1]):
        for k in range(D):
            lo = olo[k, s]
            hi = ohi[k, s]
            Yk = Yf[k, :W]
            if k == 0:
                for t in range(W):
                    d1 = lo - Yk[t]
                    d2 = Yk[t] - hi
                    d = d1 if d1 > d2 else d2
                    d = d if d > 0.0 else 0.0
                    ac[t] = d * d
            else:
                for t in range(W):
                    d1 = lo - Yk[t]
                    d2 = Yk[t] - hi
                    d = d1 if d1 > d2 else d2
                    d = d if d > 0.0 else 0.0
                    ac[t] += d * d
        for t in range(W):
            v = ac[t]
            bc[t] = v if v < bc[t] else bc[t]
    for t in range(W):
        bc[t] = np.sqrt(bc[t])
    for lane in range(L):
        inner[lane] = 0.0
    for j in range(1, mmax - 1):
        for lane in range(L):
            if j < mlen[lane] - 1:
                inner[lane] += bc[j * L + lane]
    # column suffix: scol[j * L + lane] = (c_j + ... + c_{m-1}) * _SHRINK, 0 from column m on
    nl = mlen.shape[0]
    for lane in range(nl):
        scol[mmax * nl + lane] = 0.0
    for j in range(mmax - 1, -1, -1):
        t = j * nl
        for lane in range(nl):
            v = bc[t + lane] if j < mlen[lane] else 0.0
            scol[t + lane] = scol[t + nl + lane] + v
    for t in range((mmax + 1) * nl):
        scol[t] *= _SHRINK


@njit(cache=True, nogil=True)
def _combine_bounds(x, Yf, mlen, rows_inner, cols_inner, lb):
    """lb = max(row bound, column bound) * _SHRINK, each with its LB_Kim end cells.

    Every path contains (0, 0) and (n-1, m-1): row 0 (column 0) costs at least c(0, 0) and row
    n-1 (column m-1) at least c(n-1, m-1); the inner rows (columns) add their own bounds.
    """
    n = x.shape[0]
    for lane in range(_LANES):
        m = mlen[lane]
        first = _cell_cost(x, 0, Yf, 0, lane)
        if n == 1:
            rows = first + (_cell_cost(x, 0, Yf, m - 1, lane) if m > 1 else 0.0)
        else:
            rows = first + rows_inner[lane] + _cell_cost(x, n - 1, Yf, m - 1, lane)
        if m == 1:
            cols = first + (_cell_cost(x, n - 1, Yf, 0, lane) if n > 1 else 0.0)
        else:
            cols = first + cols_inner[lane] + _cell_cost(x, n - 1, Yf, m - 1, lane)
        lb[lane] = (rows if rows > cols else cols) * _SHRINK


@njit(cache=True, nogil=True)
def _upper_bound(x, Yf, mlen, ub, acc):
    """Cost of the straight warping path from (0, 0) to (n-1, m-1), summed in path order.

    The longer side advances at every step, the other by 0 or 1. Summed along the path exactly
    as the DP accumulates, so the DP's result never exceeds it, even in floating point.
    acc: (L,) scratch.
    """
    n, D = x.shape
    nl = mlen.shape[0]
    m = mlen[0]
    same = True
    for lane in range(nl):
        if mlen[lane] != m:
            same = False
    if not same:
        for lane in range(nl):
            m = mlen[lane]
            K = n if n > m else m
            tot = _cell_cost(x, 0, Yf, 0, lane)
            for t in range(1, K):
                i = (t * (n - 1) + (K - 1) // 2) // (K - 1)
                j = (t * (m - 1) + (K - 1) // 2) // (K - 1)
                tot = _cell_cost(x, i, Yf, j, lane) + tot
            ub[lane] = tot
        return
    # every lane has the same length: one path for all, vectorised across lanes
    K = n if n > m else m
    for t in range(K):
        i = 0 if K == 1 else (t * (n - 1) + (K - 1) // 2) // (K - 1)
        j = 0 if K == 1 else (t * (m - 1) + (K - 1) // 2) // (K - 1)
        for k in range(D):
            xk = x[i, k]
            Yk = Yf[k, j * nl : (j + 1) * nl]
            if k == 0:
                for lane in range(nl):
                    d = xk - Yk[lane]
                    acc[lane] = d * d
            else:
                for lane in range(nl):
                    d = xk - Yk[lane]
                    acc[lane] += d * d
        if t == 0:
            for lane in range(nl):
                ub[lane] = np.sqrt(acc[lane])
        else:
            for lane in range(nl):
                ub[lane] = np.sqrt(acc[lane]) + ub[lane]


@njit(cache=True, nogil=True)
def _acc_dims(x, i, Yf, t0, t1, cst, k0, cnt, first):
    """cst[t] (+)= sum of (x[i, k] - Yf[k, t0 + t])^2 for k in k0..k0+cnt-1 (cnt <= 4).

    Adds left to right like ``acc += d * d`` coordinate after coordinate (same rounding), with
    several coordinates per pass over memory.
    """
    w = t1 - t0
    a0 = x[i, k0]
    y0 = Yf[k0, t0:t1]
    if cnt == 1:
        if first:
            for t in range(w):
                d0 = a0 - y0[t]
                cst[t] = d0 * d0
        else:
            for t in range(w):
                d0 = a0 - y0[t]
                cst[t] = cst[t] + d0 * d0
        return
    a1 = x[i, k0 + 1]
    y1 = Yf[k0 + 1, t0:t1]
    if cnt == 2:
        if first:
            for t in range(w):
                d0 = a0 - y0[t]
                d1 = a1 - y1[t]
                cst[t] = d0 * d0 + d1 * d1
        else:
            for t in range(w):
                d0 = a0 - y0[t]
                d1 = a1 - y1[t]
                cst[t] = cst[t] + d0 * d0 + d1 * d1
        return
    a2 = x[i, k0 + 2]
    y2 = Yf[k0 + 2, t0:t1]
    if cnt == 3:
        if first:
            for t in range(w):
                d0 = a0 - y0[t]
                d1 = a1 - y1[t]
                d2 = a2 - y2[t]
                cst[t] = d0 * d0 + d1 * d1 + d2 * d2
        else:
            for t in range(w):
                d0 = a0 - y0[t]
                d1 = a1 - y1[t]
                d2 = a2 - y2[t]
                cst[t] = cst[t] + d0 * d0 + d1 * d1 + d2 * d2
        return
    a3 = x[i, k0 + 3]
    y3 = Yf[k0 + 3, t0:t1]
    if first:
        for t in range(w):
            d0 = a0 - y0[t]
            d1 = a1 - y1[t]
            d2 = a2 - y2[t]
            d3 = a3 - y3[t]
            cst[t] = d0 * d0 + d1 * d1 + d2 * d2 + d3 * d3
    else:
        for t in range(w):
            d0 = a0 - y0[t]
            d1 = a1 - y1[t]
            d2 = a2 - y2[t]
            d3 = a3 - y3[t]
            cst[t] = cst[t] + d0 * d0 + d1 * d1 + d2 * d2 + d3 * d3


@njit(cache=True, nogil=True)
def _row_pass(x, i, Yf, prev, cur, cost, c0, c1):
    """Cells (i, c0..c1) of every lane: cost, then min over above / diagonal, then left.

    Reads prev columns c0-1..c1 and cur column c0-1. Slices starting at 0 let LLVM prove the
    accesses disjoint and vectorise every loop. Per cell this is exactly
    D(i, j) = c(i, j) + min(D(i-1, j-1), D(i-1, j), D(i, j-1)), since rounding is monotone:
    c + min(a, b, e) == min(c + min(a, b), c + e) in floating point.
    """
    L = _LANES
    D = x.shape[1]
    t0 = c0 * L
    t1 = (c1 + 1) * L
    w = t1 - t0
    cst = cost[t0:t1]
    for k0 in range(0, D, 4):
        _acc_dims(x, i, Yf, t0, t1, cst, k0, min(4, D - k0), k0 == 0)
    up_left = prev[t0:t1]
    up = prev[t0 + L : t1 + L]
    here = cur[t0 + L : t1 + L]
    for t in range(w):
        c = np.sqrt(cst[t])
        cst[t] = c
        p = up_left[t]
        q = up[t]
        here[t] = c + (p if p < q else q)
    # flat loop with a dependence distance of _LANES: still vectorises across lanes
    row = cur[t0 : t1 + L]
    for t in range(w):
        v = row[t + L]
        v2 = cst[t] + row[t]
        row[t + L] = v if v < v2 else v2


@njit(cache=True, nogil=True)
def _dtw_scalar(x, sim, b, m, thr, prev, cur, bad):
    """DTW of x against sim[b, :m] if it is <= thr, else +inf (abandoned when a row is dead).

    The plain recursion with the operations of `_row_pass` (same values, bit for bit).
    prev, cur: scratch of at least m + 1. Records a NaN/inf in a valid step in bad[0].
    """
    n, D = x.shape
    inf = np.inf
    chk = 0.0
    for j in range(m):
        for k in range(D):
            chk += sim[b, j, k] * 0.0
    if chk != 0.0:
        if bad[0] < 0:
            for j in range(m):
                for k in range(D):
                    if not np.isfinite(sim[b, j, k]) and bad[0] < 0:
                        bad[0] = b * sim.shape[1] + j
        return inf
    thr_eff = thr * _SLACK
    for j in range(m + 1):
        prev[j] = inf
    prev[0] = 0.0
    for i in range(n):
        cur[0] = inf
        rmin = inf
        for j in range(m):
            d = x[i, 0] - sim[b, j, 0]
            acc = d * d
            for k in range(1, D):
                d = x[i, k] - sim[b, j, k]
                acc += d * d
            p = prev[j]
            q = prev[j + 1]
            e = cur[j]
            mn = p if p < q else q
            mn = mn if mn < e else e
            v = np.sqrt(acc) + mn
            cur[j + 1] = v
            rmin = v if v < rmin else rmin
        if not rmin <= thr_eff:
            return inf
        prev, cur = cur, prev
    v = prev[m]
    return v if v <= thr else inf


@njit(cache=True, nogil=True)
def _dtw_block(x, Yf, mlen, mmax, thr, suffix_blk, scol, prev, cur, cost, thr_eff, out):
    """Exact DTW of the observed ``x`` (n, D) against the ``_LANES`` candidates of a block.

    thr[lane]: threshold; out[lane] = the exact DTW if it is <= thr[lane], else +inf. Cells
    (i, j) are computed only inside a window of columns outside of which every lane's cell
    provably has ``D(i, j) + suffix_blk[i+1] > thr`` (PrunedDTW, Silva & Batista 2016, with the
    bounds of the remaining rows as in EAPrunedDTW, Herrmann & Webb 2021): such cells cannot lie
    on an optimal path of cost <= thr, and every cell that can is computed with exactly the
    operations of the plain recursion. A column j >= mlen[lane] is dead for that lane. The
    block stops as soon as a whole row is dead. Returns True if the block ran to its last row.
    """
    n = x.shape[0]
    L = _LANES
    inf = np.inf
    for lane in range(L):
        thr_eff[lane] = thr[lane] * _SLACK
        prev[lane] = 0.0  # virtual cell (-1, -1)
        prev[L + lane] = inf  # virtual cell (-1, 0)
    a = -1  # first and last alive columns of the previous row
    b = -1
    s = 0
    e = 0
    for i in range(n):
        i1 = i + 1
        s = a if a > 0 else 0
        e = b + 1 if b + 1 < mmax else mmax - 1
        for lane in range(L):
            cur[s * L + lane] = inf  # column s-1
        c0 = s
        while True:
            _row_pass(x, i, Yf, prev, cur, cost, c0, e)
            if e + 1 >= mmax:
                break
            # beyond the previous row's alive columns only the left neighbour can be alive
            base = (e + 1) * L
            alive = False
            for lane in range(L):
                r = suffix_blk[i1, lane]
                r2 = scol[base + lane]
                r = r if r > r2 else r2
                if e < mlen[lane] and cur[base + lane] + r <= thr_eff[lane]:
                    alive = True
            if not alive:
                break
            c0 = e + 1
            e = min(e + _EXTEND, mmax - 1)
            for t in range((c0 + 1) * L, (e + 2) * L):
                prev[t] = inf
        for lane in range(L):
            cur[(e + 2) * L + lane] = inf  # column e+1
        a = -1
        b = -1
        for j in range(s, e + 1):
            base = (j + 1) * L
            for lane in range(L):
                r = suffix_blk[i1, lane]
                r2 = scol[base + lane]
                r = r if r > r2 else r2
                if j < mlen[lane] and cur[base + lane] + r <= thr_eff[lane]:
                    a = j
            if a >= 0:
                break
        if a < 0:
            for lane in range(L):
                out[lane] = inf
            return False
        for j in range(e, a - 1, -1):
            base = (j + 1) * L
            for lane in range(L):
                r = suffix_blk[i1, lane]
                r2 = scol[base + lane]
                r = r if r > r2 else r2
                if j < mlen[lane] and cur[base + lane] + r <= thr_eff[lane]:
                    b = j
            if b >= 0:
                break
        prev, cur = cur, prev
    for lane in range(L):
        col = mlen[lane] - 1
        v = prev[(col + 1) * L + lane] if s <= col <= e else inf
        out[lane] = v if v <= thr[lane] else inf
    return True


@njit(cache=True, nogil=True)
def _coarse_chunk(c, n_chunks, x, sim, lengths, ids, lb, ub, bad):
    """Cheap lower bound (one box per trajectory, LB_Kim ends) and upper bound of candidates
    ``ids`` (sorted by length for short blocks), written to lb[b], ub[b]; blocks c,
    c + n_chunks, ... here."""
    n, D = x.shape
    T = sim.shape[1]
    n_ids = ids.shape[0]
    xT = np.ascontiguousarray(x.T)
    olo, ohi = _seg_boxes(x, n)
    Yf = np.empty((D, T * _LANES))
    mlen = np.empty(_LANES, dtype=np.int64)
    box = np.empty((2, D, _LANES))
    acc_r = np.empty(n)
    acc_c = np.empty(T * _LANES)
    best_c = np.empty(T * _LANES)
    scol = np.empty((T + 1) * _LANES)
    rows = np.empty(_LANES)
    cols = np.empty(_LANES)
    lbb = np.empty(_LANES)
    ubb = np.empty(_LANES)
    for start in range(c * _LANES, n_ids, n_chunks * _LANES):
        count = min(_LANES, n_ids - start)
        mmax = _gather_block(sim, lengths, ids, start, count, Yf, mlen, box, True, bad)
        _box_rows_bound(xT, box, acc_r, rows)
        _cols_bound(olo, ohi, Yf, mlen, mmax, acc_c, best_c, cols, scol)
        _combine_bounds(x, Yf, mlen, rows, cols, lbb)
        _upper_bound(x, Yf, mlen, ubb, cols)
        for lane in range(count):
            b = ids[start + lane]
            lb[b] = lbb[lane]
            ub[b] = ubb[lane]


@njit(cache=True)
def _fine_bounds(x, sim, lengths, seg, lb, ub, suffix, col_suffix):
    """Fine lower bounds, upper bounds, row and column suffix bounds of every candidate."""
    n, D = x.shape
    B, T = sim.shape[0], sim.shape[1]
    xT = np.ascontiguousarray(x.T)
    olo, ohi = _seg_boxes(x, seg)
    Yf = np.empty((D, T * _LANES))
    mlen = np.empty(_LANES, dtype=np.int64)
    box = np.empty((2, D, _LANES))
    acc_r = np.empty(n)
    best_r = np.empty(n)
    acc_c = np.empty(T * _LANES)
    best_c = np.empty(T * _LANES)
    scol = np.empty((T + 1) * _LANES)
    suffix_blk = np.empty((n + 1, _LANES))
    rows = np.empty(_LANES)
    cols = np.empty(_LANES)
    lbb = np.empty(_LANES)
    ubb = np.empty(_LANES)
    ids = np.arange(B)
    bad = np.full(1, -1)
    for start in range(0, B, _LANES):
        count = min(_LANES, B - start)
        mmax = _gather_block(sim, lengths, ids, start, count, Yf, mlen, box, False, bad)
        _rows_bound(xT, Yf, mlen, seg, acc_r, best_r, suffix_blk, rows)
        _cols_bound(olo, ohi, Yf, mlen, mmax, acc_c, best_c, cols, scol)
        _combine_bounds(x, Yf, mlen, rows, cols, lbb)
        _upper_bound(x, Yf, mlen, ubb, cols)
        for lane in range(count):
            lb[start + lane] = lbb[lane]
            ub[start + lane] = ubb[lane]
            for i in range(n + 1):
                suffix[start + lane, i] = suffix_blk[i, lane]
            for j in range(mmax + 1):
                col_suffix[start + lane, j] = scol[j * _LANES + lane]


@njit(cache=True, nogil=True)
def _sift_down(heap, i, v):
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
def _dtw_chunk(c, n_chunks, x, sim, lengths, ids, mode, lb0, ub, thr0, heap0, out, bad):
    """DTW of candidates ``ids`` in blocks of ``_LANES``: blocks c, c + n_chunks, ... here.

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
    Blocks whose tables are below ``_MIN_CELLS_FOR_LANES`` cells use `_dtw_scalar` instead
    (threshold: +inf in mode 0, min(tau, upper bound) otherwise; the coarse bound decides).
    out[b] = exact DTW if <= the lane's threshold, else +inf.
    """
    n, D = x.shape
    T = sim.shape[1]
    n_ids = ids.shape[0]
    k = heap0.shape[0]
    xT = np.ascontiguousarray(x.T)
    olo, ohi = _seg_boxes(x, _SEG)
    n_blocks = (n_ids + _LANES - 1) // _LANES
    Yf = np.empty((D, T * _LANES))
    mlen = np.empty(_LANES, dtype=np.int64)
    box = np.empty((2, D, _LANES))
    acc_r = np.empty(n)
    best_r = np.empty(n)
    acc_c = np.empty(T * _LANES)
    best_c = np.empty(T * _LANES)
    scol = np.empty((T + 1) * _LANES)
    suffix_blk = np.empty((n + 1, _LANES))
    rows = np.empty(_LANES)
    cols = np.empty(_LANES)
    lbb = np.empty(_LANES)
    prev = np.empty((T + 2) * _LANES)
    cur = np.empty((T + 2) * _LANES)
    cost = np.empty(T * _LANES)
    thr = np.empty(_LANES)
    thr_eff = np.empty(_LANES)
    res = np.empty(_LANES)
    heap = heap0.copy()
    for h in range(k // 2 - 1, -1, -1):
        _sift_down(heap, h, heap[h])
    for blk in range(c, n_blocks, n_chunks):
        start = blk * _LANES
        count = min(_LANES, n_ids - start)
        tau = thr0
        if k > 0 and heap[0] < tau:
            tau = heap[0]
        if mode == 2 and lb0[ids[start]] > tau:
            # every later block of the chunk has larger coarse bounds: all out
            for b2 in range(blk, n_blocks, n_chunks):
                s2 = b2 * _LANES
                for lane in range(min(_LANES, n_ids - s2)):
                    out[ids[s2 + lane]] = np.inf
            break
        mmax = 1
        for lane in range(count):
            mmax = max(mmax, lengths[ids[start + lane]])
        if n * mmax < _MIN_CELLS_FOR_LANES:
            # small tables: one candidate at a time, no gather, no bounds
            for lane in range(count):
                b = ids[start + lane]
                t_b = np.inf if mode == 0 else min(tau, ub[b])
                v = np.inf
                if mode == 0 or lb0[b] <= t_b:
                    v = _dtw_scalar(x, sim, b, lengths[b], t_b, prev, cur, bad)
                out[b] = v
                if k > 0 and v < heap[0]:
                    _sift_down(heap, 0, v)
                    if heap[0] < tau:
                        tau = heap[0]
            continue
        mmax = _gather_block(sim, lengths, ids, start, count, Yf, mlen, box, False, bad)
        _rows_bound(xT, Yf, mlen, _SEG, acc_r, best_r, suffix_blk, rows)
        _cols_bound(olo, ohi, Yf, mlen, mmax, acc_c, best_c, cols, scol)
        if mode == 0:
            _upper_bound(x, Yf, mlen, thr, cols)
        else:
            for lane in range(_LANES):
                u = ub[ids[start + (lane if lane < count else 0)]]
                thr[lane] = u if u < tau else tau
        for lane in range(count, _LANES):
            thr[lane] = -1.0  # padding lane
        if mode != 0:
            _combine_bounds(x, Yf, mlen, rows, cols, lbb)
            for lane in range(_LANES):
                if lbb[lane] > thr[lane]:
                    thr[lane] = -1.0  # dead from the start
        alive = False
        for lane in range(_LANES):
            if thr[lane] >= 0.0:
                alive = True
        if alive:
            _dtw_block(x, Yf, mlen, mmax, thr, suffix_blk, scol, prev, cur, cost, thr_eff, res)
        else:
            for lane in range(_LANES):
                res[lane] = np.inf
        for lane in range(count):
            v = res[lane]
            out[ids[start + lane]] = v
            if k > 0 and v < heap[0]:
                _sift_down(heap, 0, v)


# ----------------------------------------------------------------------------------------------
# input handling
# ----------------------------------------------------------------------------------------------


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


_POOL: ThreadPoolExecutor | None = None
_POOL_SIZE = 0
_POOL_LOCK = threading.Lock()


def _default_workers() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def _run_chunks(fn, n_chunks: int, *args) -> None:
    """fn(c, n_chunks, *args) for c in range(n_chunks), chunk 0 in the calling thread.

    The kernels are ``nogil``: the chunks run truly in parallel on a shared thread pool. Each
    chunk's work depends only on (c, n_chunks), never on thread timing.
    """
    global _POOL, _POOL_SIZE
    if n_chunks > 1:
        with _POOL_LOCK:
            if _POOL is None or _POOL_SIZE < n_chunks - 1:
                if _POOL is not None:
                    _POOL.shutdown(wait=False)
                _POOL = ThreadPoolExecutor(max_workers=n_chunks - 1, thread_name_prefix="dtw")
                _POOL_SIZE = n_chunks - 1
            pool = _POOL
        futures = [pool.submit(fn, c, n_chunks, *args) for c in range(1, n_chunks)]
    fn(0, n_chunks, *args)
    if n_chunks > 1:
        for f in futures:
            f.result()


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
        workers: threads to use (default: the CPUs this process may run on). Each thread
            takes a fixed share of the blocks, so the values never depend on it.

    Returns:
        (B,) float64 CPU tensor: DTW = min over warping paths of the sum of Euclidean point
        distances (see the module docstring), or +inf where pruned as described above. The
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
    n_threads = _default_workers() if workers is None else check_positive_int(workers, "workers")
    x = np.ascontiguousarray(obs[:n], dtype=np.float64)
    if not np.isfinite(x).all():
        raise ValueError("observed: contains NaN or inf values")
    out = np.empty(B, dtype=np.float64)
    bad = np.full(1, -1, dtype=np.int64)  # set by the kernels on NaN/inf in a valid step

    if eps is None and (k is None or k >= B):
        ids = np.argsort(lens, kind="stable").astype(np.int64)
        none = np.empty(0)
        n_chunks = max(1, min(n_threads, -(-B // _LANES)))
        _run_chunks(_dtw_chunk, n_chunks, x, sim, lens, ids, 0, none, none, np.inf, none, out, bad)
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
    """The pruned pipeline (see the module docstring); out[b] = exact DTW or +inf."""
    B = sim.shape[0]
    lb0 = np.empty(B)
    ub = np.empty(B)
    by_length = np.argsort(lens, kind="stable").astype(np.int64)
    n_chunks = max(1, min(n_threads, -(-B // _LANES)))
    _run_chunks(_coarse_chunk, n_chunks, x, sim, lens, by_length, lb0, ub, bad)
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
        _run_chunks(_dtw_chunk, n_chunks, x, sim, lens, first, 1, lb0, ub, thr0, heap0, out, bad)
        heap0 = np.ascontiguousarray(out[first])
        todo[first] = False
    # phase 2: the others by ascending coarse bound; those above the threshold never get there
    rest = np.flatnonzero(todo & (lb0 <= thr0))
    rest = rest[np.argsort(lb0[rest], kind="stable")].astype(np.int64)
    if rest.size:
        _run_chunks(_dtw_chunk, n_chunks, x, sim, lens, rest, 2, lb0, ub, thr0, heap0, out, bad)


def _candidate_bounds(observed, simulated, lengths=None, *, seg=_SEG):
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
    _fine_bounds(x, sim, lens, seg, lb, ub, suffix, col_suffix)
    coarse = np.empty(B)
    ub2 = np.empty(B)
    ids = np.argsort(lens, kind="stable").astype(np.int64)
    _coarse_chunk(0, 1, x, sim, lens, ids, coarse, ub2, np.full(1, -1, dtype=np.int64))
    return {"lb": lb, "coarse_lb": coarse, "ub": ub, "row_suffix": suffix, "col_suffix": col_suffix}


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
