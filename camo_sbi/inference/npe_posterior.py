"""The combined posterior of per-task (or per-reach) flows, and its file format.

`NpePosterior` holds k trained flows q_i(z | x_i) and their observed summaries and is the
target p(theta | x_1..k) ∝ p(theta)^(1-k) ∏_i q_i(theta | x_i) (exact if each q_i is the exact
posterior under the common prior p), in the flow coordinates z of the prior box
(`flow_space`). It is shared by per-task NPE (`npe`, one flow per task) and the per-reach
amortized estimator (`amortized`, the same flow with N conditions). It builds the target and
the flow-mixture proposal and hands them to `samplers` (importance sampling, population MCMC,
tempered SMC): ``sample_is``, ``sample_mcmc``, ``sample_smc`` return `samplers.WeightedDraws`
in theta coordinates. ``save`` writes the flows' weights and a JSON description;
`load_posterior` reloads them without running any code from the files.
"""

from __future__ import annotations

import contextlib
import math
from pathlib import Path

import numpy as np
import torch

from camo_sbi._files import read_json
from camo_sbi._validation import as_tensor, check_choice, check_positive_float, check_positive_int
from camo_sbi.inference import samplers, sbi_adapter
from camo_sbi.inference.flow_space import (
    from_unconstrained,
    logistic_log_prob,
    to_unconstrained,
    torch_threads,
)
from camo_sbi.inference.result import check_sample_shape

__all__ = ["NpePosterior", "load_posterior"]

TRANSFORMS = ("logit", "none")
_FORMAT = "camo_sbi.npe.posterior/2"
# log-prob evaluations per chunk (samples x tasks)
_CHUNK = 8192
# the flow architecture a saved posterior records; defaults for posteriors built without a
# config (they equal `npe.NpeConfig`'s defaults, checked by tests/test_npe.py)
ARCH_DEFAULTS = {"density_estimator": "maf", "hidden_features": 50, "num_transforms": 5, "embedding": "none",
                 "embedding_dim": 32}


class _LastCall:
    """``f(z)`` remembered for the last ``z`` (same tensor object, not modified since): the
    target and the flow-mixture proposal read the same k flow densities, evaluated once."""

    def __init__(self, f):
        self._f, self._key, self._value = f, None, None

    def __call__(self, z):
        if self._key is not None and self._key[0] is z and self._key[1] == z._version:
            return self._value
        value = self._f(z)
        self._key, self._value = (z, z._version), value
        return value


class NpePosterior:
    """p(theta | x_1..k) ∝ p(theta)^(1-k) ∏_i q_i(theta | x_i) from per-task flows.

    Args:
        estimators: k trained sbi density estimators q_i(z | x) over the free coordinates.
        x_obs: k observed summaries (1-D tensors; each estimator's own feature set).
        low, high: (2n,) prior box; coordinates with low == high are fixed.
        theta_transform: "logit" or "none" (coordinates the estimators model).
        info: free-form metadata (config, training summaries) saved along.
        n_threads: torch intra-op threads used by ``log_prob`` and ``sample`` (restored
            afterwards), so results do not depend on the caller's thread setting; None: as is.
    """

    def __init__(self, estimators, x_obs, low, high, *, theta_transform: str = "logit", info=None,
                 n_threads: int | None = 1):
        if len(estimators) != len(x_obs) or not estimators:
            raise ValueError("estimators: need one estimator per observed summary (at least one)")
        check_choice(theta_transform, TRANSFORMS, "theta_transform")
        self.estimators = [e.eval() for e in estimators]
        self.x_obs = [torch.as_tensor(x, dtype=torch.float32).reshape(1, -1) for x in x_obs]
        self.low = torch.as_tensor(low, dtype=torch.float64).cpu()
        self.high = torch.as_tensor(high, dtype=torch.float64).cpu()
        self.free_mask = self.high > self.low
        self.theta_transform = theta_transform
        self.info = dict(info or {})
        self.n_threads = None if n_threads is None else check_positive_int(n_threads, "n_threads")
        self._lo = self.low[self.free_mask]
        self._w = (self.high - self.low)[self.free_mask]

    @property
    def n_tasks(self) -> int:
        return len(self.estimators)

    @property
    def dim(self) -> int:
        return int(self.low.shape[0])

    @property
    def n_free(self) -> int:
        return int(self.free_mask.sum())

    # coordinates -------------------------------------------------------------------------

    def to_unconstrained(self, theta_free: torch.Tensor) -> torch.Tensor:
        """(N, n_free) free coordinates -> (N, n_free) flow coordinates z."""
        return to_unconstrained(theta_free, self._lo, self._w, self.theta_transform)

    def from_unconstrained(self, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """z (N, n_free) -> (free coordinates (N, n_free), log |d theta / d z| (N,))."""
        return from_unconstrained(z, self._lo, self._w, self.theta_transform)

    def _theta(self, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """z (N, n_free) -> (full theta (N, 2n) with the fixed coordinates set, log |d theta / d z| (N,))."""
        theta_free, logdet = self.from_unconstrained(z)
        theta = self.low.repeat(theta_free.shape[0], 1)
        theta[:, self.free_mask] = theta_free
        return theta, logdet

    def _prior_log_prob_z(self, z: torch.Tensor) -> torch.Tensor:
        if self.theta_transform == "none":
            inside = ((z >= self._lo) & (z <= self._lo + self._w)).all(-1)
            lp = torch.full((z.shape[0],), -float(torch.log(self._w).sum()), dtype=torch.float64)
            return torch.where(inside, lp, torch.full_like(lp, -math.inf))
        return logistic_log_prob(z)

    # densities ---------------------------------------------------------------------------

    @torch.no_grad()
    def task_log_probs(self, z: torch.Tensor) -> torch.Tensor:
        """(k, N) log q_i(z | x_i) in flow coordinates (NaN mapped to -inf).

        When every task shares one flow (the amortized estimator), one call per chunk
        evaluates all k conditions at once (input (n, k, d), condition (k, F)).
        """
        z = torch.as_tensor(z, dtype=torch.float32)
        out = torch.empty(self.n_tasks, z.shape[0], dtype=torch.float64)
        k = self.n_tasks
        with torch_threads(self.n_threads):
            if k > 1 and all(e is self.estimators[0] for e in self.estimators) \
                    and len({x.shape for x in self.x_obs}) == 1:
                x = torch.cat(self.x_obs)
                step = max(1, _CHUNK // k)
                for s in range(0, z.shape[0], step):
                    zc = z[s : s + step]
                    lp = self.estimators[0].log_prob(zc.unsqueeze(1).expand(-1, k, -1), condition=x)
                    out[:, s : s + zc.shape[0]] = lp.reshape(zc.shape[0], k).T.double()
                return torch.nan_to_num(out, nan=-math.inf)
            for i, (est, x) in enumerate(zip(self.estimators, self.x_obs, strict=True)):
                for s in range(0, z.shape[0], _CHUNK):
                    zc = z[s : s + _CHUNK]
                    lp = est.log_prob(zc.unsqueeze(1), condition=x).reshape(-1).double()
                    out[i, s : s + zc.shape[0]] = lp
        return torch.nan_to_num(out, nan=-math.inf)

    def _log_target_z(self, z: torch.Tensor, lq: torch.Tensor) -> torch.Tensor:
        lp = self._prior_log_prob_z(z)
        out = lq.sum(0) + (1 - self.n_tasks) * torch.where(torch.isfinite(lp), lp, torch.zeros_like(lp))
        # outside the prior's support the target is zero, whatever the power of the prior
        return torch.where(torch.isfinite(lp), out, torch.full_like(out, -math.inf))

    @torch.no_grad()
    def log_prob(self, theta) -> torch.Tensor:
        """(B,) unnormalised log p(theta | x_1..k) for theta (B, 2n) or (2n,), -inf outside the box.

        Density with respect to the free coordinates; exact normalisation only for k = 1.
        """
        t = as_tensor(theta, "theta", dtype=torch.float64).cpu()
        t = t.unsqueeze(0) if t.dim() == 1 else t
        if t.dim() != 2 or t.shape[1] != self.dim:
            raise ValueError(f"theta: expected shape (B, {self.dim}), got {tuple(t.shape)}")
        inside = ((t >= self.low - 1e-9) & (t <= self.high + 1e-9)).all(-1)
        z = self.to_unconstrained(t[:, self.free_mask])
        _, logdet = self.from_unconstrained(z)
        lp = self._log_target_z(z, self.task_log_probs(z)) - logdet
        return torch.where(inside, lp, torch.full_like(lp, -math.inf))

    # sampling ----------------------------------------------------------------------------

    @torch.no_grad()
    def _sample_flows(self, counts: list[int]) -> torch.Tensor:
        parts = [est.sample((c,), condition=x).reshape(c, -1).double()
                 for est, x, c in zip(self.estimators, self.x_obs, counts, strict=True) if c > 0]
        return torch.cat(parts)

    def target(self):
        """(log_target, mixture) for `samplers`: the combined log density in flow coordinates z,
        (N, n_free) -> (N,), and the equal mixture of the k flows (`samplers.Mixture`, with the
        standard logistic prior's precision 3 / pi^2 taken out of its Gaussian product in logit
        coordinates). Both read one evaluation of the k flows per batch of z."""
        lq = _LastCall(self.task_log_probs)
        prior_precision = 3.0 / math.pi**2 if self.theta_transform == "logit" else 0.0
        mixture = samplers.Mixture(self._sample_flows, lq, self.n_tasks, self.n_free, prior_precision)
        return (lambda z: self._log_target_z(z, lq(z))), mixture

    def _in_theta(self, draws: samplers.WeightedDraws) -> samplers.WeightedDraws:
        theta, logdet = self._theta(draws.samples)
        return draws.mapped(theta, draws.log_density - logdet)

    @contextlib.contextmanager
    def _rng(self, seed: int):
        """Flows sample from the global torch RNG: forked and seeded for the block (and the threads set)."""
        with torch.random.fork_rng(devices=[]), torch_threads(self.n_threads):
            torch.manual_seed(seed)
            yield

    def sample(self, sample_shape=(), seed: int | None = None, *, n_proposals: int | None = None) -> torch.Tensor:
        """Equally weighted draws, shape (*sample_shape, 2n), like sbi's ``posterior.sample``.

        Sampling-importance-resampling: ``sample_is`` draws ``n_proposals`` weighted draws
        (default: max(prod(sample_shape), 1000)) and they are resampled by weight. ``seed``:
        an int; None draws a fresh nondeterministic seed (never the global random state).
        The weighted draws themselves, with their effective sample size, come from ``sample_is``.
        """
        shape = check_sample_shape(sample_shape)
        if seed is None:
            seed = int(np.random.SeedSequence().generate_state(1)[0])
        seed = check_positive_int(seed, "seed", minimum=0)
        n = int(np.prod(shape, dtype=np.int64))
        m = max(n, 1000) if n_proposals is None else check_positive_int(n_proposals, "n_proposals", minimum=2)
        draws = self.sample_is(m, seed)
        w = draws.weights.numpy()
        idx = np.random.default_rng(seed).choice(len(w), size=n, replace=True, p=w)
        return torch.from_numpy(np.ascontiguousarray(draws.samples.numpy()[idx])).reshape(*shape, self.dim)

    def sample_is(self, n: int, seed: int, *, is_rounds: int = 2, defensive_fraction: float = 0.2,
                  reuse_mixture_draws: bool = False) -> samplers.WeightedDraws:
        """``n`` weighted draws per round by importance sampling (`samplers.importance`: round 0
        from the flow mixture, then the Gaussian product and refits, ``is_rounds`` after the
        first); the round with the largest ESS. ``reuse_mixture_draws``: round 0 draws only the
        defensive share from the flows and every later round reuses those draws (fewer flow
        draws and evaluations; `samplers.importance`). Deterministic given ``seed``; the global
        torch RNG is restored afterwards."""
        seed = check_positive_int(seed, "seed", minimum=0)
        n = check_positive_int(n, "n", minimum=2)
        is_rounds = check_positive_int(is_rounds, "is_rounds", minimum=0)
        with self._rng(seed):
            log_target, mixture = self.target()
            try:
                draws = samplers.importance(log_target, mixture, n, seed=seed, rounds=is_rounds,
                                            defensive_fraction=defensive_fraction,
                                            reuse_mixture_draws=reuse_mixture_draws)
            except RuntimeError as exc:
                if not str(exc).startswith("importance: every importance weight is zero"):
                    raise
                raise RuntimeError("sample: every importance weight is zero (the flows put no mass in the box)") \
                    from None
        return self._in_theta(draws)

    def sample_mcmc(self, n: int, seed: int, *, chains: int = 128, steps: int = 100, burn_in: int = 50,
                    init_draws: int = 512, de_fraction: float = 0.2, target_acceptance: float = 0.25,
                    min_acceptance: float = 0.0) -> samplers.WeightedDraws:
        """At most ``n`` equally weighted draws by population MCMC in z (`samplers.mcmc`).

        The ``chains`` start from the Gaussian approximation of the product of the flows
        (`samplers.Mixture.product` of ``init_draws`` flow-mixture draws), or from those draws
        themselves if it is degenerate (or k = 1). Deterministic given ``seed``; the global
        torch RNG is restored afterwards.
        """
        seed = check_positive_int(seed, "seed", minimum=0)
        with self._rng(seed):
            log_target, mixture = self.target()
            pool, product = mixture.pool_and_product(init_draws)
            init = pool if product is None else samplers.Gaussian.from_covariance(*product)
            draws = samplers.mcmc(log_target, init, n, seed=seed, chains=chains, steps=steps, burn_in=burn_in,
                                  de_fraction=de_fraction, target_acceptance=target_acceptance,
                                  min_acceptance=min_acceptance)
        return self._in_theta(draws)

    def sample_smc(self, seed: int, *, particles: int = 512, base: str = "mixture", init_draws: int = 512,
                   inflate: float = 2.0, target_ess: float = 0.5, moves: int = 3, independent_fraction: float = 0.5,
                   max_stages: int = 50, target_acceptance: float = 0.3) -> samplers.WeightedDraws:
        """Weighted draws by tempered SMC in z (`samplers.smc`) from a base to the target.

        Base ``"mixture"`` (default): the equal mixture of the k flows, drawn exactly and
        evaluated from the same k flow densities the target needs; ``"gaussian"``: the
        Gaussian product of ``init_draws`` flow draws (their mean and covariance if it is
        degenerate), covariance x ``inflate``. Deterministic given ``seed``; the global torch
        RNG is restored afterwards.
        """
        seed = check_positive_int(seed, "seed", minimum=0)
        check_choice(base, ("mixture", "gaussian"), "base")
        init_draws = check_positive_int(init_draws, "init_draws", minimum=2)
        inflate = check_positive_float(inflate, "inflate")
        d = self.n_free
        with self._rng(seed):
            log_target, mixture = self.target()
            if base == "mixture":
                start = mixture
            else:
                pool, product = mixture.pool_and_product(init_draws)
                if product is None:
                    product = pool.mean(0), torch.cov(pool.T).reshape(d, d)
                mu, cov = product
                start = samplers.Gaussian.from_covariance(mu, inflate * cov)
            draws = samplers.smc(log_target, start, seed=seed, particles=particles, inflate=inflate,
                                 target_ess=target_ess, moves=moves, independent_fraction=independent_fraction,
                                 max_stages=max_stages, target_acceptance=target_acceptance)
        return self._in_theta(draws)

    # persistence -------------------------------------------------------------------------

    def save(self, path) -> Path:
        """Write the flows' weights (tensors only) to ``path`` and their description to ``path`` + ".json".

        The JSON metadata holds the format, the architecture settings, the sizes, the sampler's
        settings, ``info`` and the sha256 of the weights file; `load_posterior` checks that digest,
        loads the weights with ``torch.load(weights_only=True)`` (no code can run) and rebuilds the
        networks from the metadata. Both files are written atomically, the metadata last.
        """
        import hashlib
        import io
        import json

        from camo_sbi._io import atomic_write_bytes, atomic_write_text

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        buf = io.BytesIO()
        torch.save({"format": _FORMAT,
                    "state_dict": {f"{k}.{name}": t.detach().cpu() for k, e in enumerate(self.estimators)
                                   for name, t in e.state_dict().items()},
                    "x_obs": [x.detach().cpu() for x in self.x_obs],
                    "low": self.low, "high": self.high}, buf)
        data = buf.getvalue()
        config = self.info.get("config", {})
        meta = {"format": _FORMAT, "weights": path.name, "sha256": hashlib.sha256(data).hexdigest(),
                "bytes": len(data), "n_tasks": self.n_tasks, "n_free": self.n_free,
                "n_x": [int(x.shape[1]) for x in self.x_obs],
                "architecture": {k: config.get(k, v) for k, v in ARCH_DEFAULTS.items()},
                "theta_transform": self.theta_transform, "n_threads": self.n_threads, "info": self.info}
        atomic_write_bytes(path, data)
        atomic_write_text(_meta_path(path), json.dumps(meta, indent=1, default=str))
        return path


def _meta_path(path: Path) -> Path:
    return path.with_name(path.name + ".json")

def load_posterior(path) -> NpePosterior:
    """Reload a posterior written by `NpePosterior.save` (no retraining).

    Nothing in the files is run: the weights file must match the sha256 in its metadata
    (``path`` + ".json"), is read with ``torch.load(weights_only=True)`` (tensors only) and the
    networks are rebuilt from the metadata. ValueError ``path: <file>: ...`` naming the file
    for a missing, damaged, foreign or mismatched file (the CLI exits 2).
    """
    import hashlib
    import io

    path = Path(path)
    meta_path = _meta_path(path)
    if not path.is_file():
        raise ValueError(f"path: no such file {str(path)!r}")
    try:
        if not meta_path.exists():
            raise FileNotFoundError(meta_path)
        meta = read_json(meta_path, "metadata")
        if not isinstance(meta, dict):
            raise ValueError("not a JSON object")
    except FileNotFoundError:
        raise ValueError(f"path: {path}: its metadata {meta_path.name} is missing (not a camo_sbi NPE posterior "
                         f"{_FORMAT}); nothing was loaded") from None
    except (OSError, ValueError) as exc:
        raise ValueError(f"path: {meta_path}: unreadable metadata ({exc})") from None
    if meta.get("format") != _FORMAT:
        raise ValueError(f"path: {path}: is not a camo_sbi NPE posterior ({_FORMAT}; found {meta.get('format')!r})")
    data = path.read_bytes()
    if hashlib.sha256(data).hexdigest() != meta.get("sha256"):
        raise ValueError(f"path: {path}: sha256 differs from its metadata {meta_path.name} (damaged or replaced); "
                         "nothing was loaded")
    try:
        blob = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
        arch = meta["architecture"]
        n_x, n_free = [int(v) for v in meta["n_x"]], int(meta["n_free"])
        estimators = []
        for k, nx in enumerate(n_x):
            est = sbi_adapter.new_npe_estimator(
                n_free, nx, density_estimator=arch["density_estimator"], hidden_features=int(arch["hidden_features"]),
                num_transforms=int(arch["num_transforms"]),
                embedding_dim=int(arch["embedding_dim"]) if arch["embedding"] == "mlp" else None)
            prefix = f"{k}."
            est.load_state_dict({name[len(prefix):]: t for name, t in blob["state_dict"].items()
                                 if name.startswith(prefix)}, strict=True)
            estimators.append(est)
        return NpePosterior(estimators, blob["x_obs"], blob["low"], blob["high"],
                            theta_transform=meta["theta_transform"], info=meta.get("info"),
                            n_threads=meta.get("n_threads", 1))
    except Exception as exc:  # noqa: BLE001 - a refused pickle, a missing key, weights that do not fit
        raise ValueError(f"path: {path}: cannot be loaded as a camo_sbi NPE posterior "
                         f"({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})") from None
