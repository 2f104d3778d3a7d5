"""Local costs c(i, j) = ||x_i - y_j||_2 of lane-block cells, always computed one way.

The squares are added coordinate after coordinate, k = 0 first (``acc = d0 * d0; acc += d1 *
d1; ...``), by the DP (`kernels`, through `sq_costs`; `kernels.dtw_scalar` inline) and by the
straight-path upper bound (`bounds.upper_bound`, through `cell_cost`, and a lane-vectorised loop
of its own for blocks of equal lengths), so they round a cell's cost identically and the DP's
result never exceeds the upper bound, even in floating point.

Shapes: the observed ``x`` (n, D) float64; a lane block ``Yf`` (D, T * LANES) as in `blocks`
(flat column t = j * LANES + lane); ``cst`` a (t1 - t0,) slice of a flat row.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from camo_sbi.inference.distances.blocks import LANES

__all__ = ["cell_cost", "sq_costs"]


@njit(cache=True, nogil=True)
def cell_cost(x, i, Yf, j, lane):
    """c(i, j) for one lane: the square root of `sq_costs`'s sum, for a single cell."""
    t = j * LANES + lane
    d = x[i, 0] - Yf[0, t]
    acc = d * d
    for k in range(1, x.shape[1]):
        d = x[i, k] - Yf[k, t]
        acc += d * d
    return np.sqrt(acc)


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


@njit(cache=True, nogil=True, inline="always")
def sq_costs(x, i, Yf, t0, t1, cst):
    """cst[t] = ||x_i - Yf[:, t0 + t]||^2 for t < t1 - t0: squared costs of flat columns t0..t1-1.

    Four coordinates per pass over memory (`_acc_dims`), the same sums as one at a time.
    """
    D = x.shape[1]
    for k0 in range(0, D, 4):
        _acc_dims(x, i, Yf, t0, t1, cst, k0, min(4, D - k0), k0 == 0)
