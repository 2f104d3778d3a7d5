"""Test oracle: the textbook DTW of one pair, independent of the numba kernels.

Usage from any test module::

    from tests._dtw_reference import dtw_reference
    assert dtw_distances(a, b[None])[0] == pytest.approx(dtw_reference(a, b))
"""

from __future__ import annotations

import numpy as np

__all__ = ["dtw_reference"]


def dtw_reference(a, b) -> float:
    """Plain O(n m) DTW of one pair in numpy: the sum of Euclidean point distances.

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
