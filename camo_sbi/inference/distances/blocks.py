"""The lane block: candidates copied side by side, one per SIMD lane, and its constants.

A block holds ``LANES`` candidates. ``Yf`` (D, T * LANES) float64 holds coordinate k of point
j of a lane's candidate at ``Yf[k, j * LANES + lane]``; ``mlen`` (LANES,) int64 holds the
lanes' valid lengths. Steps beyond a lane's length repeat its last valid point, and lanes
beyond the block's ``count`` candidates replicate the first one, so every kernel can run all
lanes without branches. DP rows are flat arrays indexed ``(j + 1) * LANES + lane``, the first
``LANES`` entries holding the virtual column -1.

Exactness margins: every lower bound is multiplied by ``SHRINK`` and every threshold by
``SLACK`` before a comparison, so floating-point rounding of sums taken in a different order
(relative errors ~(n + m) * 1.1e-16) can never prune a cell or a candidate that the plain
recursion would keep.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = [
    "EXTEND",
    "LANES",
    "MIN_CELLS_FOR_LANES",
    "SEG",
    "SHRINK",
    "SLACK",
    "gather_block",
    "record_nonfinite",
]

# Candidates computed together, one per SIMD lane: their independent recursions fill the vector
# registers and hide the latency of the D(i, j-1) -> D(i, j) dependency.
LANES = 16
# Points per segment of the piecewise bounding-box envelope of the fine lower bounds.
SEG = 20
# Relative shrink of every lower bound, relative slack of every threshold (see the docstring).
SHRINK = 1.0 - 1e-9
SLACK = 1.0 + 1e-10
# Columns added at a time when a DP row extends beyond the previous row's alive window.
EXTEND = 8
# Blocks whose DP tables (n x longest candidate) are smaller than this go through a scalar
# recursion one candidate at a time: for them, gathering lanes and bounds costs more than it saves.
MIN_CELLS_FOR_LANES = 1024


@njit(cache=True, nogil=True)
def record_nonfinite(sim, b, m, bad):
    """bad[0] = b * T + j for the first step j < m of sim[b] (B, T, D) holding NaN or inf,
    unless bad[0] is already set (>= 0). The caller raises; bad (1,) int64."""
    for j in range(m):
        for k in range(sim.shape[2]):
            if not np.isfinite(sim[b, j, k]) and bad[0] < 0:
                bad[0] = b * sim.shape[1] + j


@njit(cache=True, nogil=True)
def gather_block(sim, lengths, ids, start, count, Yf, mlen, box, want_box, bad):
    """Copy candidates ``ids[start:start+count]`` of sim (B, T, D) into the lane block Yf.

    Points j < the block's largest length (returned) are written; mlen receives the lanes'
    lengths. With ``want_box``, box[0, k, lane] / box[1, k, lane] ((2, D, LANES)) receive the
    lane's bounding box. A NaN/inf among the valid points is recorded in bad[0] (as b * T + step,
    see `record_nonfinite`) and replaced by 0 in Yf (the caller raises).
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
            record_nonfinite(sim, ids[start + lane], mlen[lane], bad)
            for k in range(D):
                for j in range(mmax):
                    if not np.isfinite(Yf[k, j * nl + lane]):
                        Yf[k, j * nl + lane] = 0.0
    return mmax
