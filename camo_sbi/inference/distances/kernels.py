"""The DP kernels: exact DTW of the observed trajectory against one lane block or one candidate.

Shapes: the observed ``x`` (n, D) float64; a lane block ``Yf`` (D, T * LANES) with ``mlen``
(LANES,) as in `blocks`; DP rows ``prev``, ``cur`` ((T + 2) * LANES,) flat, indexed
``(j + 1) * LANES + lane`` (the first LANES entries: the virtual column -1); ``cost`` (T * LANES,)
scratch; per-lane thresholds and outputs (LANES,). `dtw_scalar` reads one candidate sim[b]
of sim (B, T, D) directly, with DP rows of at least m + 1 entries.

Every value computed is the plain recursion ``D(i, j) = c(i, j) + min(D(i-1, j-1), D(i-1, j),
D(i, j-1))`` with the same floating-point operations, whatever the pruning: a cell is either
skipped, when it provably cannot lie on a path of cost <= the lane's threshold (PrunedDTW,
Silva & Batista 2016; EAPrunedDTW, Herrmann & Webb 2021, with the bounds of `bounds`), or
computed exactly.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from camo_sbi.inference.distances.blocks import EXTEND, LANES, SLACK, record_nonfinite
from camo_sbi.inference.distances.costs import sq_costs

__all__ = ["dtw_block", "dtw_scalar", "row_pass"]


@njit(cache=True, nogil=True)
def row_pass(x, i, Yf, prev, cur, cost, c0, c1):
    """Cells (i, c0..c1) of every lane: cost (`costs.sq_costs`), then min over above / diagonal,
    then left.

    Reads prev columns c0-1..c1 and cur column c0-1. Slices starting at 0 let LLVM prove the
    accesses disjoint and vectorise every loop. Per cell this is exactly
    D(i, j) = c(i, j) + min(D(i-1, j-1), D(i-1, j), D(i, j-1)), since rounding is monotone:
    c + min(a, b, e) == min(c + min(a, b), c + e) in floating point.
    """
    L = LANES
    t0 = c0 * L
    t1 = (c1 + 1) * L
    w = t1 - t0
    cst = cost[t0:t1]
    sq_costs(x, i, Yf, t0, t1, cst)
    up_left = prev[t0:t1]
    up = prev[t0 + L : t1 + L]
    here = cur[t0 + L : t1 + L]
    for t in range(w):
        c = np.sqrt(cst[t])
        cst[t] = c
        p = up_left[t]
        q = up[t]
        here[t] = c + (p if p < q else q)
    # flat loop with a dependence distance of LANES: still vectorises across lanes
    row = cur[t0 : t1 + L]
    for t in range(w):
        v = row[t + L]
        v2 = cst[t] + row[t]
        row[t + L] = v if v < v2 else v2


@njit(cache=True, nogil=True)
def dtw_scalar(x, sim, b, m, thr, prev, cur, bad):
    """DTW of x against sim[b, :m] if it is <= thr, else +inf (abandoned when a row is dead).

    The plain recursion with the operations of `row_pass` (same values, bit for bit).
    prev, cur: scratch of at least m + 1. Records a NaN/inf in a valid step in bad[0].
    """
    n, D = x.shape
    inf = np.inf
    chk = 0.0
    for j in range(m):
        for k in range(D):
            chk += sim[b, j, k] * 0.0
    if chk != 0.0:
        record_nonfinite(sim, b, m, bad)
        return inf
    thr_eff = thr * SLACK
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


@njit(cache=True, nogil=True, inline="always")
def _column_alive(cur, j, i1, suffix_blk, scol, mlen, thr_eff):
    """Whether cell (i1 - 1, j) of some lane can lie on a path within the lane's threshold.

    cur: DP row i1 - 1. The cell is dead for a lane if j >= its length, or if its value plus
    the larger of the bounds of the rows below (suffix_blk[i1]) and of the columns to its right
    (scol from column j + 1) exceeds thr_eff.
    """
    base = (j + 1) * LANES
    alive = False
    for lane in range(LANES):
        r = suffix_blk[i1, lane]
        r2 = scol[base + lane]
        r = r if r > r2 else r2
        if j < mlen[lane] and cur[base + lane] + r <= thr_eff[lane]:
            alive = True
    return alive


@njit(cache=True, nogil=True)
def dtw_block(x, Yf, mlen, mmax, thr, suffix_blk, scol, prev, cur, cost, thr_eff, out):
    """Exact DTW of the observed ``x`` (n, D) against the ``LANES`` candidates of a block.

    thr[lane]: threshold; out[lane] = the exact DTW if it is <= thr[lane], else +inf. Cells
    (i, j) are computed only inside a window of columns outside of which every lane's cell
    provably has ``D(i, j) + suffix_blk[i+1] > thr`` (PrunedDTW, Silva & Batista 2016, with the
    bounds of the remaining rows as in EAPrunedDTW, Herrmann & Webb 2021): such cells cannot lie
    on an optimal path of cost <= thr, and every cell that can is computed with exactly the
    operations of the plain recursion. A column j >= mlen[lane] is dead for that lane. The
    block stops as soon as a whole row is dead. Returns True if the block ran to its last row.
    """
    n = x.shape[0]
    L = LANES
    inf = np.inf
    for lane in range(L):
        thr_eff[lane] = thr[lane] * SLACK
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
            row_pass(x, i, Yf, prev, cur, cost, c0, e)
            if e + 1 >= mmax:
                break
            # beyond the previous row's alive columns only the left neighbour can be alive
            if not _column_alive(cur, e, i1, suffix_blk, scol, mlen, thr_eff):
                break
            c0 = e + 1
            e = min(e + EXTEND, mmax - 1)
            for t in range((c0 + 1) * L, (e + 2) * L):
                prev[t] = inf
        for lane in range(L):
            cur[(e + 2) * L + lane] = inf  # column e+1
        a = -1
        b = -1
        for j in range(s, e + 1):
            if _column_alive(cur, j, i1, suffix_blk, scol, mlen, thr_eff):
                a = j
                break
        if a < 0:
            for lane in range(L):
                out[lane] = inf
            return False
        for j in range(e, a - 1, -1):
            if _column_alive(cur, j, i1, suffix_blk, scol, mlen, thr_eff):
                b = j
                break
        prev, cur = cur, prev
    for lane in range(L):
        col = mlen[lane] - 1
        v = prev[(col + 1) * L + lane] if s <= col <= e else inf
        out[lane] = v if v <= thr[lane] else inf
    return True
