"""Lower and upper bounds of the DTW of a lane block's candidates (numba kernels).

Shapes: the observed ``x`` (n, D) float64 and ``xT`` = its transpose (D, n), C-contiguous; a
lane block ``Yf`` (D, T * LANES), ``mlen`` (LANES,) as in `blocks`; per-lane outputs (LANES,).
All are true bounds for non-negative local costs c(i, j) = ||x_i - y_j||:

* rows: every warping path visits every row, in cells that differ from row to row, so
  ``DTW >= sum_i min_j c(i, j)``; columns alike. ``min_j c(i, j) >= r_i = min_s dist(x_i,
  box_s(y))`` where box_s(y) is the bounding box of the s-th segment of ``SEG`` consecutive
  points of y (the distance to a box never exceeds the distance to a point inside it): this is
  LB_Keogh with the whole candidate as envelope (no band), tightened by piecewise envelopes
  (`rows_bound`, `cols_bound`; `box_rows_bound` uses one box per candidate);
* LB_Kim: every path contains (0, 0) and (n-1, m-1): row 0 costs at least c(0, 0), row n-1
  at least c(n-1, m-1); these replace the first and last rows' (columns') terms
  (`combine_bounds`: LB = max(row bound, column bound));
* upper bound UB (`upper_bound`): the cost of the straight path from (0, 0) to (n-1, m-1),
  with the DP's cell costs (`costs`) summed in the DP's order, so the DP's result never
  exceeds it.

Every point-to-box distance goes through `box_dist2`.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from camo_sbi.inference.distances.blocks import LANES, SHRINK
from camo_sbi.inference.distances.costs import cell_cost

__all__ = [
    "box_dist2",
    "box_rows_bound",
    "cols_bound",
    "combine_bounds",
    "rows_bound",
    "seg_box",
    "seg_boxes",
    "upper_bound",
]


@njit(cache=True, nogil=True, inline="always")
def _gap2(v, lo, hi):
    """Squared distance from v to the interval [lo, hi] (0 inside)."""
    d1 = lo - v
    d2 = v - hi
    d = d1 if d1 > d2 else d2
    d = d if d > 0.0 else 0.0
    return d * d


@njit(cache=True, nogil=True, inline="always")
def box_dist2(acc, P, lo, hi):
    """acc[t] = squared distance from point P[:, t] to the box [lo, hi], for t < len(acc).

    P (D, >= len(acc)) C-contiguous, lo and hi (D,). The squares are added coordinate after
    coordinate, k = 0 first, in every caller the same way.
    """
    N = acc.shape[0]
    for k in range(P.shape[0]):
        Pk = P[k, :N]
        lk = lo[k]
        hk = hi[k]
        if k == 0:
            for t in range(N):
                acc[t] = _gap2(Pk[t], lk, hk)
        else:
            for t in range(N):
                acc[t] += _gap2(Pk[t], lk, hk)


@njit(cache=True, nogil=True, inline="always")
def seg_box(P, a, e, step, off, lo, hi):
    """lo[k], hi[k] = min, max of P[k, off + j * step] over points j in [a, e) (e > a)."""
    for k in range(P.shape[0]):
        vlo = P[k, off + a * step]
        vhi = vlo
        for j in range(a + 1, e):
            v = P[k, off + j * step]
            vlo = v if v < vlo else vlo
            vhi = v if v > vhi else vhi
        lo[k] = vlo
        hi[k] = vhi


@njit(cache=True, nogil=True)
def seg_boxes(xT, seg):
    """Bounding boxes lo, hi (D, n_seg) of consecutive segments of ``seg`` points of xT (D, n)."""
    D, n = xT.shape
    n_seg = (n + seg - 1) // seg
    lo = np.empty((D, n_seg))
    hi = np.empty((D, n_seg))
    for s in range(n_seg):
        a = s * seg
        seg_box(xT, a, min(a + seg, n), 1, 0, lo[:, s], hi[:, s])
    return lo, hi


@njit(cache=True, nogil=True)
def box_rows_bound(xT, box, acc_r, inner):
    """Row bounds against one box per lane (the whole candidate): inner[lane] = r_1+...+r_{n-2}.

    box (2, D, LANES) from `gather_block`; acc_r (n,) scratch.
    """
    n = xT.shape[1]
    for lane in range(LANES):
        box_dist2(acc_r, xT, box[0, :, lane], box[1, :, lane])
        for i in range(n):
            acc_r[i] = np.sqrt(acc_r[i])
        mid = 0.0
        for i in range(1, n - 1):
            mid += acc_r[i]
        inner[lane] = mid


@njit(cache=True, nogil=True)
def rows_bound(xT, Yf, mlen, seg, acc_r, best_r, suffix_blk, inner):
    """Row bounds: r_i = min over the lane's segments s of dist(x_i, box_s(y)) <= min_j c(i, j).

    Every warping path visits every row, in cells that differ from row to row, so any sum of
    r_i over distinct rows is a lower bound of the cost of the path's cells in those rows.
    suffix_blk (n+1, LANES): suffix_blk[i, lane] = (r_i + ... + r_{n-1}) * SHRINK, suffix_blk[n]
    = 0; inner[lane] = r_1 + ... + r_{n-2}. acc_r, best_r: (n,) scratch.
    """
    D, n = xT.shape
    L = LANES
    inf = np.inf
    lo = np.empty(D)
    hi = np.empty(D)
    for lane in range(L):
        m = mlen[lane]
        for i in range(n):
            best_r[i] = inf
        for s in range((m + seg - 1) // seg):
            a = s * seg
            seg_box(Yf, a, min(a + seg, m), L, lane, lo, hi)
            box_dist2(acc_r, xT, lo, hi)
            for i in range(n):
                v = acc_r[i]
                best_r[i] = v if v < best_r[i] else best_r[i]
        tot = 0.0
        mid = 0.0
        suffix_blk[n, lane] = 0.0
        for i in range(n - 1, -1, -1):
            r = np.sqrt(best_r[i])
            tot += r
            suffix_blk[i, lane] = tot * SHRINK
            if 0 < i < n - 1:
                mid += r
        inner[lane] = mid


@njit(cache=True, nogil=True)
def cols_bound(olo, ohi, Yf, mlen, mmax, acc_c, best_c, inner, scol):
    """Column bounds c_j = min_s dist(y_j, box_s(x)) <= min_i c(i, j).

    olo, ohi (D, n_seg): the observed's segment boxes (`seg_boxes`); mmax: the block's largest
    length. inner[lane] = c_1 + ... + c_{m-2}; scol ((T+1) * LANES, flat like a DP row without
    its virtual column): scol[j * LANES + lane] = (c_j + ... + c_{m-1}) * SHRINK, 0 from column
    m on. acc_c, best_c: (T * LANES,) scratch.
    """
    L = LANES
    W = mmax * L
    bc = best_c[:W]
    ac = acc_c[:W]
    for t in range(W):
        bc[t] = np.inf
    for s in range(olo.shape[1]):
        box_dist2(ac, Yf, olo[:, s], ohi[:, s])
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
    nl = mlen.shape[0]
    for lane in range(nl):
        scol[mmax * nl + lane] = 0.0
    for j in range(mmax - 1, -1, -1):
        t = j * nl
        for lane in range(nl):
            v = bc[t + lane] if j < mlen[lane] else 0.0
            scol[t + lane] = scol[t + nl + lane] + v
    for t in range((mmax + 1) * nl):
        scol[t] *= SHRINK


@njit(cache=True, nogil=True)
def combine_bounds(x, Yf, mlen, rows_inner, cols_inner, lb):
    """lb = max(row bound, column bound) * SHRINK, each with its LB_Kim end cells.

    Every path contains (0, 0) and (n-1, m-1): row 0 (column 0) costs at least c(0, 0) and row
    n-1 (column m-1) at least c(n-1, m-1); the inner rows (columns) add their own bounds.
    """
    n = x.shape[0]
    for lane in range(LANES):
        m = mlen[lane]
        first = cell_cost(x, 0, Yf, 0, lane)
        if n == 1:
            rows = first + (cell_cost(x, 0, Yf, m - 1, lane) if m > 1 else 0.0)
        else:
            rows = first + rows_inner[lane] + cell_cost(x, n - 1, Yf, m - 1, lane)
        if m == 1:
            cols = first + (cell_cost(x, n - 1, Yf, 0, lane) if n > 1 else 0.0)
        else:
            cols = first + cols_inner[lane] + cell_cost(x, n - 1, Yf, m - 1, lane)
        lb[lane] = (rows if rows > cols else cols) * SHRINK


@njit(cache=True, nogil=True, inline="always")
def _straight(t, K, n):
    """Row (or column) of step t of the straight path of K steps through n rows (columns)."""
    return 0 if K == 1 else (t * (n - 1) + (K - 1) // 2) // (K - 1)


@njit(cache=True, nogil=True)
def upper_bound(x, Yf, mlen, ub, acc):
    """Cost of the straight warping path from (0, 0) to (n-1, m-1), summed in path order.

    The longer side advances at every step, the other by 0 or 1. Summed along the path exactly
    as the DP accumulates, so the DP's result never exceeds it, even in floating point.
    ub (LANES,) output, acc (LANES,) scratch.
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
            tot = cell_cost(x, 0, Yf, 0, lane)
            for t in range(1, K):
                tot = cell_cost(x, _straight(t, K, n), Yf, _straight(t, K, m), lane) + tot
            ub[lane] = tot
        return
    # every lane has the same length: one path for all, vectorised across lanes (the sums of
    # costs.sq_costs, written out: calling it per step made the coarse bounds 10% slower)
    K = n if n > m else m
    for t in range(K):
        i = _straight(t, K, n)
        j = _straight(t, K, m)
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
