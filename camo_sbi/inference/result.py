"""`PosteriorResult`: the one type every inference method returns."""

from __future__ import annotations

import numbers
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["ROUNDING_TOL", "STATUS_OK", "PosteriorResult", "check_sample_shape", "check_status",
           "failed_at_prior_centre", "order_rounded_bounds", "weighted_median", "weighted_quantile"]

STATUS_OK = "ok"
_STATUS_PREFIXES = ("fallback: ", "failed: ")


def check_status(status) -> str:
    """Validate a result status: ``"ok"``, ``"fallback: <reason>"`` or ``"failed: <reason>"``."""
    if not isinstance(status, str):
        raise TypeError(f"status: expected a str, got {type(status).__name__}")
    if status != STATUS_OK and not (status.startswith(_STATUS_PREFIXES) and status.split(": ", 1)[1].strip()):
        raise ValueError(f"status: expected 'ok', 'fallback: <reason>' or 'failed: <reason>', got {status!r}")
    return status


@dataclass(frozen=True)
class PosteriorResult:
    """Outcome of ``run(task, observations, budget=..., seed=..., config=...)``.

    Attributes:
        method: registry name of the method ("camo", "naive", "abc-smc", "npe", ...).
        samples: (N, 2n) float64 posterior samples laid out [lo_1, hi_1, ..., lo_n, hi_n].
        weights: (N,) non-negative weights summing to 1, or None for equally weighted draws.
        estimate: (2n,) float64 point estimate (CAMO: the argmax of the joint density).
        n_simulations: simulations actually consumed, as counted by the budget wrapper.
        wall_time: seconds spent in ``run``, without JIT compilation (``compile_time``) or
            imports (``import_time``), plus the recorded seconds of work read back from an
            earlier, killed run's checkpoints (``extras["resumed_seconds"]``: the per-task
            networks of npe, nle and tsnpe), so that resuming never makes a method look faster.
        n_tasks: number of observed tasks the posterior conditions on.
        extras: method-specific data (e.g. per-task acceptance counts, epsilons).
        status: ``"ok"``; ``"fallback: <reason>"`` when the method could not do what it
            names and did something weaker instead (CAMO keeping its best k when nothing
            met epsilon, ABC-SMC stopping at its prior population, NPE with a degenerate
            importance sample); ``"failed: <reason>"`` when it produced no usable answer.
            Tables carry it in a ``status`` column; a non-ok status is also warned about.
        compile_time: seconds of numba compilation (or loading compiled code from its cache)
            during ``run``, measured by the registry and never counted in ``wall_time``: the
            first run in a process pays it, later ones do not.
        import_time: seconds of importing the method's libraries before ``run`` (its module,
            e.g. pyabc, and its ``setup``: NPE's sbi and scikit-learn), measured by the registry
            and never counted in ``wall_time``: the first run in a process pays it.
        density: ``theta (B, 2n) -> (B,)`` unnormalised log density of the posterior, for
            the methods that have one (NPE: the combined flows; CAMO: the product of its
            per-task KDEs); None otherwise. Read through `log_prob`; not compared, not
            pickled (it may hold trained networks), not written to files.

    Like sbi's posteriors, ``sample(sample_shape, seed=None)`` draws from the result and
    ``log_prob(theta)`` evaluates its density where one exists.
    """

    method: str
    samples: np.ndarray
    weights: np.ndarray | None
    estimate: np.ndarray
    n_simulations: int
    wall_time: float
    n_tasks: int
    extras: dict[str, Any] = field(default_factory=dict)
    status: str = STATUS_OK
    compile_time: float = 0.0
    import_time: float = 0.0
    density: Callable[[Any], Any] | None = field(default=None, compare=False, repr=False)

    def __getstate__(self):
        state = dict(self.__dict__)
        state.pop("density", None)  # a closure over trained networks: never pickled
        return state

    def __post_init__(self):
        check_status(self.status)
        s = np.asarray(self.samples, dtype=np.float64)
        if s.ndim != 2 or s.shape[1] % 2:
            raise ValueError(f"samples: expected shape (N, 2n), got {s.shape}")
        object.__setattr__(self, "samples", s)
        e = np.asarray(self.estimate, dtype=np.float64)
        if e.shape != (s.shape[1],):
            raise ValueError(f"estimate: expected shape ({s.shape[1]},), got {e.shape}")
        e = order_rounded_bounds(e)
        object.__setattr__(self, "estimate", e)
        if self.weights is not None:
            w = np.asarray(self.weights, dtype=np.float64)
            if w.shape != (s.shape[0],):
                raise ValueError(f"weights: expected shape ({s.shape[0]},), got {w.shape}")
            if not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
                raise ValueError("weights: must be finite, non-negative and not all zero")
            object.__setattr__(self, "weights", w / w.sum())

    @property
    def n_joints(self) -> int:
        return self.samples.shape[1] // 2

    def normalized_weights(self) -> np.ndarray:
        """(N,) weights summing to one (uniform when ``weights`` is None)."""
        if self.weights is None:
            return np.full(self.samples.shape[0], 1.0 / self.samples.shape[0])
        return self.weights

    def mean(self) -> np.ndarray:
        """(2n,) weighted posterior mean."""
        return self.normalized_weights() @ self.samples

    @property
    def ess(self) -> float:
        """Effective sample size implied by the weights, (sum w)^2 / sum w^2 (N when unweighted)."""
        w = self.normalized_weights()
        return float(1.0 / np.sum(w**2))

    def systematic(self, n: int) -> np.ndarray:
        """(n, 2n) deterministic equally weighted draws: systematic resampling at offsets (i + 0.5) / n.

        No random numbers, so a posterior-predictive metric computed from these draws does
        not change from one evaluation to the next.
        """
        cw = np.cumsum(self.normalized_weights())
        idx = np.searchsorted(cw, (np.arange(n) + 0.5) / n * cw[-1], side="right")
        return self.samples[np.minimum(idx, self.samples.shape[0] - 1)]

    def sample(self, sample_shape=(), seed=None):
        """Draws from the posterior as a float64 torch tensor of shape (*sample_shape, 2n), like sbi's
        ``posterior.sample(sample_shape)``: multinomial resampling of ``samples`` by ``weights``
        (a point estimate, one sample, gives that point every time).

        ``seed``: an int or a numpy Generator; None draws from a fresh, nondeterministic
        Generator (never the global random state).
        """
        import torch  # not at import time: reading results needs no torch

        shape = check_sample_shape(sample_shape)
        rng = np.random.default_rng() if seed is None else _generator(seed)
        n = int(np.prod(shape, dtype=np.int64))
        draws = self.resample(n, rng) if n else np.empty((0, self.samples.shape[1]))
        return torch.from_numpy(np.ascontiguousarray(draws.reshape(*shape, self.samples.shape[1])))

    def log_prob(self, theta):
        """(B,) unnormalised log posterior density at ``theta`` (B, 2n) or (2n,), as a torch tensor.

        Raises NotImplementedError naming the method when it returns no density (a point
        estimate such as naive or nominal, or samples without a density, such as ABC-SMC's).
        """
        if self.density is None:
            kind = "a point estimate" if self.samples.shape[0] == 1 else "samples without a density"
            raise NotImplementedError(f"log_prob: method {self.method!r} returns {kind}; no density to evaluate "
                                      "(use sample() for draws)")
        return self.density(theta)

    def resample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """(n, 2n) equally weighted draws (multinomial resampling by ``weights``)."""
        idx = rng.choice(self.samples.shape[0], size=n, replace=True, p=self.normalized_weights())
        return self.samples[idx]


def check_sample_shape(sample_shape) -> tuple[int, ...]:
    """``sample_shape`` (an int, or a sequence of non-negative ints such as ``(100,)`` or a
    torch.Size) as a tuple of ints."""
    if isinstance(sample_shape, numbers.Integral) and not isinstance(sample_shape, bool):
        sample_shape = (sample_shape,)
    try:
        shape = tuple(sample_shape)
    except TypeError:
        raise TypeError(f"sample_shape: expected a tuple of ints such as (100,), got {type(sample_shape).__name__}") \
            from None
    if not all(isinstance(d, numbers.Integral) and not isinstance(d, bool) and d >= 0 for d in shape):
        raise ValueError(f"sample_shape: expected non-negative ints, got {sample_shape!r}")
    return tuple(int(d) for d in shape)


def _generator(seed) -> np.random.Generator:
    if isinstance(seed, np.random.Generator):
        return seed
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral):
        raise TypeError(f"seed: expected a non-negative int, a numpy Generator or None, got {type(seed).__name__}")
    if seed < 0:
        raise ValueError(f"seed: must be >= 0, got {seed}")
    return np.random.default_rng(int(seed))


ROUNDING_TOL = 1e-9
"""A lower bound above its upper bound by at most this much (radians or metres) is rounding."""


def failed_at_prior_centre(method: str, prior, n_tasks: int, reason: str, *, n_simulations: int = 0,
                           wall_time: float = 0.0, extras: dict | None = None) -> PosteriorResult:
    """A result that failed: status ``"failed: <reason>; the result is the prior's centre"``, its
    estimate and its one draw the centre of ``prior``'s box (known coordinates kept), said in the
    status and never passed off as a posterior."""
    centre = prior.with_known((prior.low + prior.high) / 2).numpy()
    return PosteriorResult(method=method, samples=centre[None, :], weights=None, estimate=centre,
                           n_simulations=n_simulations, wall_time=wall_time, n_tasks=n_tasks, extras=extras or {},
                           status=f"failed: {reason}; the result is the prior's centre")


def order_rounded_bounds(estimate: np.ndarray) -> np.ndarray:
    """``estimate`` (2n,) with each pair lo > hi by at most `ROUNDING_TOL` set to their midpoint.

    A mean or median of draws that each satisfy lo <= hi satisfies it too, but not always in
    floating point: where lo == hi in (nearly) every draw (a joint pinned at its start), the two
    sums round differently, and an estimate lo = 0.785 > hi = 0.785 then stopped a whole
    comparison in `task.predict`. A larger violation is left as it is (and refused downstream).
    """
    e = np.array(estimate, dtype=np.float64)
    lo, hi = e[0::2], e[1::2]
    fix = (lo > hi) & (lo - hi <= ROUNDING_TOL)
    if fix.any():
        mid = 0.5 * (lo[fix] + hi[fix])
        lo[fix], hi[fix] = mid, mid
        e[0::2], e[1::2] = lo, hi
    return e


def weighted_quantile(x: np.ndarray, w: np.ndarray | None, q) -> np.ndarray:
    """Weighted quantiles of each coordinate of ``x`` (N, D) (or (N,)) at level(s) ``q``.

    The toolkit's one definition: point estimates (medians), limits.csv's intervals and the
    calibration's central intervals all use it, so the intervals written are the ones whose
    coverage is measured. Hazen's rule: the CDF places each sample's mass at its midpoint and
    is linear in between (flat beyond the extreme samples); with equal weights this equals
    ``np.quantile(x, q, axis=0, method="hazen")``. Zero-weight samples are dropped.

    Args:
        x: (N, D) samples, or (N,) for one coordinate.
        w: (N,) non-negative weights with a positive sum, or None for equal weights.
        q: a level in [0, 1], or (Q,) levels.

    Returns:
        (D,) for a scalar ``q``, (Q, D) for Q levels.
    """
    x = np.asarray(x, dtype=np.float64)
    if x.ndim == 1:
        x = x[:, None]
    if x.ndim != 2 or x.shape[0] == 0:
        raise ValueError(f"x: expected (N, D) samples with N >= 1, got shape {x.shape}")
    qa = np.asarray(q, dtype=np.float64)
    levels = np.atleast_1d(qa)
    if levels.ndim != 1 or not np.all((levels >= 0) & (levels <= 1)):
        raise ValueError(f"q: expected a level or levels in [0, 1], got {q!r}")
    if w is None:
        out = np.quantile(x, levels, axis=0, method="hazen")
    else:
        w = np.asarray(w, dtype=np.float64)
        if w.shape != (x.shape[0],) or not np.all(np.isfinite(w)) or np.any(w < 0) or not w.sum() > 0:
            raise ValueError(f"w: expected {x.shape[0]} finite non-negative weights with a positive sum")
        keep = w > 0
        xs, ws = x[keep], w[keep] / w[keep].sum()
        order = np.argsort(xs, axis=0, kind="stable")
        xs = np.take_along_axis(xs, order, axis=0)
        ws = ws[order]
        cdf = np.cumsum(ws, axis=0) - 0.5 * ws
        out = np.stack([np.interp(levels, cdf[:, d], xs[:, d]) for d in range(x.shape[1])], axis=1)
    return out[0] if qa.ndim == 0 else out


def weighted_median(x: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Coordinate-wise weighted median of ``x`` (N, D) with weights ``w`` (N,) -> (D,)."""
    return weighted_quantile(x, w, 0.5)
