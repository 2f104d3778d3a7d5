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

`dtw_distances` compares one observed trajectory (T_o, D) with a batch of simulated ones
(B, T, D) with numba (float64 throughout) and returns (B,) float64: candidates are processed
in blocks of 16, one candidate per SIMD lane (small tables: one candidate at a time with the
scalar recursion; a whole call of at most ``api.SMALL_CALL_CELLS`` cells: the scalar recursion
only, whose kernels compile in a fraction of the cascade's time). The blocks are dealt round-robin to ``workers`` chunks run by ``nogil``
kernels on a thread pool (rather than a ``parallel=True`` prange, whose compilation costs more
than everything else together: docs/studies/design_measurements.md). Every value it reports is the exact DTW,
computed with the operations of the plain recursion, so results do not depend on pruning,
ordering or the number of threads (bit for bit). Optional pruning reports +inf for candidates
whose value is not needed:

* ``epsilon``: candidates with DTW >= epsilon are +inf (ABC acceptance ``L < epsilon`` only
  needs the others);
* ``keep_best=k``: all but the k smallest values (ties: lower index first) are +inf.

Modules, each with its own docstring (shapes, invariants):

* `api`: `dtw_distances`, `l2_distance`, input checks, the pruned cascade's phases;
* `camo_sbi._threads`: `ChunkRunner` (owns a thread pool) and the shared default runner;
* `chunks`: what one thread does with its chunk of blocks (bounds, thresholds, DP);
* `kernels`: the DP of a lane block (pruned, exact) and of one candidate;
* `bounds`: LB_Keogh-style envelope bounds with LB_Kim ends, the straight-path upper bound;
* `costs`: the local cost of a cell, computed one way for the DP and the upper bound;
* `blocks`: the lane block layout, its constants and the exactness margins;
* `numba_cache`: keeps numba's on-disk cache of the kernels in step with all their modules.
"""

from __future__ import annotations

from camo_sbi._threads import ChunkRunner
from camo_sbi.inference.distances import blocks, bounds, chunks, costs, kernels, numba_cache
from camo_sbi.inference.distances.api import _candidate_bounds as _candidate_bounds  # tests
from camo_sbi.inference.distances.api import dtw_distances, l2_distance

__all__ = ["ChunkRunner", "dtw_distances", "l2_distance"]

# The modules of numba kernels. Before any kernel runs: numba alone would not see an edit of
# one of them in the on-disk cache of a kernel of another.
KERNEL_MODULES = (blocks, costs, bounds, kernels, chunks)
numba_cache.use_private_cache(KERNEL_MODULES)  # never the package's __pycache__, never a shared directory
numba_cache.flush_if_changed(KERNEL_MODULES)
