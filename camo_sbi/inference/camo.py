"""CAMO (Algorithm 1 of the paper), continual and paper-faithful.

For each observed task n (start, goal, trajectory):

1. REJECTIONSAMPLE: draw b limit vectors from the prior (uniform or Latin hypercube),
   simulate them to the task's goal from its start, and keep those whose DTW distance
   to the observed trajectory is below epsilon and/or the best k (Q_n).
2. Fit a Gaussian KDE P_n over Q_n with kernel H = diag(h) (Eq. 3-4).
3. The joint density of every kept vector is the product over tasks (Eq. 5), kept as
   a sum of logs, and the estimate is its argmax over all kept vectors Q_all (Eq. 6).

The joint log-density table is updated incrementally: a new task only evaluates its
own KDE at the old kept vectors and every KDE at its new vectors (matrix products),
so earlier tasks are never re-simulated and task n costs O(|Q_n| * |Q_all|).

Step 1 runs in fixed-size chunks (``CamoConfig.chunk_size``): chunk c of task n draws from
``default_rng([seed, n, c])`` and is simulated and scored on its own, in-process or on Dask
workers (``CamoConfig.scheduler``), so the result never depends on the number of workers.
Each chunk scores its own best k exactly, and the task's best k are among those.

The authors' published code differs from Algorithm 1 as written in ways selectable here
(see ``REFERENCE_SETTING.md``): ``distance="euclidean"`` (Eq. 2's plain L2 norm instead of
DTW), acceptance by ``epsilon`` alone (``keep_best=None``), ``sampling="grid"`` (their
5-level grid prior) and ``proposal="sequential"`` (task n > 1 draws from task n-1's KDE,
clipped to the observed hull in joint space). The registry's ``camo-seq`` is CAMO-JS with
sequential proposals (the authors' "JS"), ``camo-seq-cs`` scores Cartesian observations on
candidates from that JS chain (``proposal="sequential-js"``, the authors' "CS"); ``camo-js`` and
``camo-cs`` are Algorithm 1 as the paper writes it.

A candidate whose simulation is not finite (NaN/inf) is rejected and counted: a failure of
the method's own simulations, reported in the result's status (``fallback: ...``, or
``failed: ...`` when no task had a finite candidate), never an error about the input.

One opt-in extension, not in the paper (``CamoConfig.contain_observed``, joint space):
step 1 draws from the prior conditioned on every posture observed so far lying inside
the limits (`BoxPrior.containing`), and step 3 gives zero density to kept vectors that
exclude a posture observed later. The default is the paper's algorithm.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass

import numpy as np
import torch

from camo_sbi._validation import (
    as_tensor,
    check_bool,
    check_choice,
    check_finite,
    check_point_estimate,
    check_positive_float,
    check_positive_int,
    renamed_fields,
)
from camo_sbi.distributed import parse_scheduler, run_chunks
from camo_sbi.inference.contract import check_run_args
from camo_sbi.inference.distances import dtw_distances, l2_distance
from camo_sbi.inference.kde import GaussianKDE, scott_bandwidth
from camo_sbi.inference.result import STATUS_OK, PosteriorResult, weighted_quantile
from camo_sbi.priors import BoxPrior
from camo_sbi.task import SPACES, NoiseModel, Observation, contain

__all__ = ["Camo", "CamoConfig", "KdeProposal", "TaskRecord", "run", "run_sequence"]

_BANDWIDTH_MODES = ("fixed", "scott")
_SAMPLINGS = ("uniform", "lhs", "grid")
_DISTANCES = ("dtw", "euclidean")
_PROPOSALS = ("prior", "sequential", "sequential-js")
_POINT_ESTIMATES = ("mode", "mean", "median", "outer")
_DTYPES = {"float32": torch.float32, "float64": torch.float64}


@renamed_fields(estimator="point_estimate")
@dataclass(frozen=True)
class CamoConfig:
    """Every CAMO hyperparameter.

    The number of prior draws per task (the paper's b: 2000; 5000 in the HRC scenario) is
    the run's ``budget`` (`Camo` takes it as ``n_samples``), not a config field.

    Attributes:
        epsilon: keep vectors with DTW distance < epsilon (None: no threshold).
        keep_best: keep at most the k best vectors (None: no cap). The paper keeps at most
            500 of 5000. At least one of epsilon / keep_best must be set.
        fallback_keep: when a task accepts nothing under epsilon, keep its best k instead
            (warns; recorded in the task record and the result's extras).
        bandwidth: kernel variance h in rad^2 for H = diag(h) ("fixed" mode).
        bandwidth_mode: "fixed" (scalar h, as the paper) or "scott" (per-dimension, per task).
        space: "joint" (CAMO-JS) or "cartesian" (CAMO-CS) observations.
        sampling: "uniform", "lhs" (Latin hypercube) or "grid" (the authors' 5-level grid
            per bound, `BoxPrior`) prior draws.
        distance: "dtw" (dynamic time warping, the paper's text) or "euclidean" (the plain
            L2 norm of the stacked difference, Eq. 2, as the authors' code; the observed
            trajectory holds its final point up to the simulations' horizon).
        proposal: "prior" (Algorithm 1 as written: every task draws from the prior) or
            "sequential" (the authors' code: task n > 1 draws from task n-1's KDE, a kept
            vector plus Gaussian noise of variance h, clipped in joint space to the observed
            hull (lo_i <= min observed q_i, hi_i >= max observed q_i) and in Cartesian space to
            the prior box), or "sequential-js" (Cartesian space only; the authors' CS,
            ``camo-seq-cs``): the candidates come from the JS chain's sequential proposal (the
            last task's joint-space acceptances, epsilon ``js_epsilon``, clipped to the observed
            joint hull), so it reads the joint observations for its proposals as their code
            does; each candidate is simulated once and scored in both spaces (the JS score
            only feeds the next proposal; a task where JS accepts nothing keeps the last bank,
            as theirs). One difference: their CS at task n scores draws from the JS KDE after
            task n, ours the bank JS scores at task n (after task n-1), so that one simulation
            per candidate serves both and the budget stays b per task.
        js_epsilon: the JS chain's joint-space epsilon for ``proposal="sequential-js"``
            (the authors' ``THRESH`` 0.02); the chain keeps at most ``keep_best`` of those (None:
            its best ``keep_best``).
        point_estimate: "mode" (Eq. 6's argmax, the paper), "mean" (weighted by the
            joint density), "median" (coordinate-wise weighted median) or "outer" (each lower
            bound at its ``outer_quantile`` weighted quantile, each upper bound at 1 -
            ``outer_quantile``: identified bounds stay where the posterior puts them,
            unidentified ones are left wide). Not in the paper except "mode". (Its old name,
            ``estimator``, and the mode's, "argmax", are refused naming these.)
        outer_quantile: the level of the "outer" point estimate, in (0, 0.5].
        sim_dtype: "float32" or "float64" for the candidate simulations.
        chunk_size: candidates per chunk. Chunk c of task n draws its candidates from
            ``numpy.random.default_rng([seed, n, c])`` and is simulated and scored on its own,
            in-process or on a Dask worker, so the numbers never depend on the number of
            workers. A constant: changing it changes the draws (as does ``sampling="lhs"``,
            which stratifies per chunk).
        scheduler: None (in-process), "local:N" (a Dask LocalCluster with N workers) or a
            Dask scheduler address ("tcp://host:8786"); see `camo_sbi.distributed`.
        contain_observed: joint space only; not in the paper. The controller clamps to the
            limits, so every observed posture lies inside them. When True, task n draws
            its candidates from the prior conditioned on that (`BoxPrior.containing` the
            postures of tasks 1..n) and kept vectors of earlier tasks that exclude a
            posture observed later get zero joint density. False: the paper's algorithm.
    """

    epsilon: float | None = None
    keep_best: int | None = 100
    fallback_keep: int = 20
    bandwidth: float = 0.2
    bandwidth_mode: str = "fixed"
    space: str = "joint"
    sampling: str = "uniform"
    sim_dtype: str = "float32"
    chunk_size: int = 1000
    scheduler: str | None = None
    contain_observed: bool = False
    distance: str = "dtw"
    proposal: str = "prior"
    point_estimate: str = "mode"
    outer_quantile: float = 0.05
    js_epsilon: float | None = None

    def __post_init__(self):
        if self.epsilon is None and self.keep_best is None:
            raise ValueError("epsilon: at least one of epsilon and keep_best must be set")
        if self.epsilon is not None:
            check_positive_float(self.epsilon, "epsilon")
        if self.keep_best is not None:
            check_positive_int(self.keep_best, "keep_best")
        check_positive_int(self.fallback_keep, "fallback_keep")
        check_positive_float(self.bandwidth, "bandwidth")
        check_choice(self.bandwidth_mode, _BANDWIDTH_MODES, "bandwidth_mode")
        check_choice(self.space, SPACES, "space")
        check_choice(self.sampling, _SAMPLINGS, "sampling")
        check_choice(self.distance, _DISTANCES, "distance")
        check_choice(self.proposal, _PROPOSALS, "proposal")
        if self.proposal == "sequential-js":
            if self.space != "cartesian":
                raise ValueError("proposal: 'sequential-js' scores Cartesian observations; needs space='cartesian'")
            if self.js_epsilon is None and self.keep_best is None:
                raise ValueError("js_epsilon: proposal='sequential-js' with keep_best=None needs the JS "
                                 "chain's epsilon")
        if self.js_epsilon is not None:
            check_positive_float(self.js_epsilon, "js_epsilon")
        check_point_estimate(self.point_estimate, _POINT_ESTIMATES)
        check_positive_float(self.outer_quantile, "outer_quantile")
        if self.outer_quantile > 0.5:
            raise ValueError(f"outer_quantile: must be in (0, 0.5], got {self.outer_quantile}")
        check_choice(self.sim_dtype, _DTYPES, "sim_dtype")
        check_positive_int(self.chunk_size, "chunk_size")
        parse_scheduler(self.scheduler)
        check_bool(self.contain_observed, "contain_observed")
        if self.contain_observed and self.space != "joint":
            raise ValueError("contain_observed: needs space='joint' (Cartesian observations do not "
                             "show the joint postures)")


@dataclass(frozen=True)
class TaskRecord:
    """What one observed task contributed: Q_n, its distances and timings (seconds)."""

    index: int
    kept: torch.Tensor  # (|Q_n|, 2n)
    distances: torch.Tensor  # (|Q_n|,)
    n_accepted_epsilon: int | None
    fallback: bool
    bandwidth: torch.Tensor  # (d_free,)
    time_simulate: float
    time_distance: float
    time_kde: float
    n_nonfinite: int = 0  # candidates whose simulation held NaN/inf (rejected)


class Camo:
    """Continual CAMO: ``observe`` tasks one at a time, ``estimate`` after any of them.

    Args:
        simulator: a `Simulator` (possibly a budget-counting wrapper).
        prior: `BoxPrior`; fixed (known) coordinates are excluded from the KDE.
        config: `CamoConfig`.
        n_samples: b, the prior draws simulated per task.
        noise: the observation-noise model (`NoiseModel`; default none). With noise, every
            simulated candidate trajectory is perturbed by the same model before its distance
            to the observation is computed (noisy ABC: like is compared with like), and
            camo-hull's containment tolerates ``NOISE_K`` sigma (`BoxPrior.containing`).
        seed: int; chunk c of task n draws from ``numpy.random.default_rng([seed, n, c])``
            so each task's stream is independent of how many tasks came before it and of
            where (which worker) its chunks run.
    """

    def __init__(self, simulator, prior: BoxPrior, config: CamoConfig = CamoConfig(), *, n_samples: int = 2000,
                 seed: int, noise: NoiseModel | None = None):
        if not isinstance(prior, BoxPrior):
            raise TypeError(f"prior: expected a BoxPrior, got {type(prior).__name__}")
        if prior.n_joints != simulator.n_joints:
            raise ValueError(f"prior: has {prior.n_joints} joints, simulator has {simulator.n_joints}")
        if not isinstance(config, CamoConfig):
            raise TypeError(f"config: expected CamoConfig, got {type(config).__name__}")
        self.simulator, self.config, self.seed = simulator, config, check_positive_int(seed, "seed", minimum=0)
        self.n_samples = check_positive_int(n_samples, "n_samples")
        self.noise = NoiseModel() if noise is None else noise
        if not isinstance(self.noise, NoiseModel):
            raise TypeError(f"noise: expected a NoiseModel, got {type(self.noise).__name__}")
        self.prior = prior if prior.sampling == config.sampling else prior.with_sampling(config.sampling)
        self._free = self.prior.free_mask
        self._draw_prior = self.prior  # conditioned on the observed postures (contain_observed)
        self._hull = self.prior  # the prior box split at the hull of every posture seen (joint space)
        self.records: list[TaskRecord] = []
        self._kdes: list[GaussianKDE] = []
        self._kept = torch.empty(0, self.prior.dim, dtype=torch.float64)  # Q_all (M, 2n)
        self._logp = torch.empty(0, dtype=torch.float64)  # (M,) sum_n log P_n(Q_all)
        self._js_bank: tuple[torch.Tensor, torch.Tensor] | None = None  # sequential-js: (kept, h)

    @property
    def n_tasks(self) -> int:
        return len(self.records)

    @property
    def kept(self) -> torch.Tensor:
        """(M, 2n) all kept vectors Q_all, in the order tasks arrived."""
        return self._kept

    @property
    def joint_log_density(self) -> torch.Tensor:
        """(M,) sum over observed tasks of log P_n at each kept vector (Eq. 6)."""
        return self._logp

    def observe(self, start, goal, trajectory, joint_trajectory=None) -> TaskRecord:
        """Add one observed task.

        start: (n,) start posture; goal: (3,); trajectory: (L, n) joint or (L, 3) Cartesian
        observations (``config.space``), valid steps only; joint_trajectory: (L, n), needed
        (only) by ``proposal="sequential-js"``.
        """
        cfg, n = self.config, self.simulator.n_joints
        start = as_tensor(start, "start", dtype=torch.float64).cpu()
        goal = as_tensor(goal, "goal", dtype=torch.float64).cpu()
        traj = as_tensor(trajectory, "trajectory", dtype=torch.float64).cpu()
        if start.shape != (n,):
            raise ValueError(f"start: expected shape ({n},), got {tuple(start.shape)}")
        if goal.shape != (3,):
            raise ValueError(f"goal: expected shape (3,), got {tuple(goal.shape)}")
        dim = n if cfg.space == "joint" else 3
        if traj.dim() != 2 or traj.shape[1] != dim or traj.shape[0] < 1:
            raise ValueError(f"trajectory: expected shape (L, {dim}) for space={cfg.space!r}, got {tuple(traj.shape)}")
        for t, name in ((start, "start"), (goal, "goal"), (traj, "trajectory")):
            check_finite(t, name)
        js_traj = None
        if cfg.proposal == "sequential-js":
            if joint_trajectory is None:
                raise ValueError("joint_trajectory: proposal='sequential-js' reads the joint observations")
            js_traj = as_tensor(joint_trajectory, "joint_trajectory", dtype=torch.float64).cpu()
            if js_traj.dim() != 2 or js_traj.shape[1] != n or js_traj.shape[0] < 1:
                raise ValueError(f"joint_trajectory: expected shape (L, {n}), got {tuple(js_traj.shape)}")
            check_finite(js_traj, "joint_trajectory")
        return self._add(start, goal, traj, js_traj)

    def _add(self, start, goal, traj, js_traj) -> TaskRecord:
        """One observed task whose arrays are already checked: float64 CPU tensors, ``start``
        (n,), ``goal`` (3,), ``traj`` (L, n or 3 for ``config.space``), ``js_traj`` (L, n) or None."""
        sim, cfg = self.simulator, self.config
        idx = self.n_tasks
        hull_traj = traj if cfg.space == "joint" else js_traj
        if hull_traj is not None and (cfg.contain_observed or cfg.proposal != "prior"):
            k_sigma = self.noise.tolerance("joint")
            self._hull = self._hull.containing(torch.cat([start.unsqueeze(0), hull_traj]), tol=max(1e-5, k_sigma),
                                               margin=k_sigma)
        if cfg.contain_observed:
            self._draw_prior = self._hull
        proposal = self._draw_prior
        last = next((r for r in reversed(self.records) if r.kept.shape[0]), None)
        bank = (last.kept, last.bandwidth) if cfg.proposal == "sequential" and last is not None else None
        if cfg.proposal == "sequential-js":
            bank = self._js_bank
        if bank is not None:
            sd = torch.zeros(self.prior.dim, dtype=torch.float64)
            sd[self._free] = bank[1].sqrt()
            box = self._hull if cfg.space == "joint" or cfg.proposal == "sequential-js" else self.prior
            proposal = KdeProposal(bank[0], sd, box.low, box.high)

        t0 = time.perf_counter()
        b_total = self.n_samples
        sizes = [min(cfg.chunk_size, b_total - c) for c in range(0, b_total, cfg.chunk_size)]
        jobs = [(self.seed, idx, c, b) for c, b in enumerate(sizes)]
        parts = run_chunks(_candidate_chunk, jobs, simulator=sim, n_simulations=b_total, scheduler=cfg.scheduler,
                           prior=proposal, start=start, goal=goal, trajectory=traj, config=cfg, noise=self.noise,
                           js_trajectory=js_traj)
        theta = torch.cat([p["theta"] for p in parts])
        dist = torch.cat([p["dist"] for p in parts])
        n_nonfinite = sum(p["n_nonfinite"] for p in parts)
        if n_nonfinite:
            warnings.warn(f"task {idx}: {n_nonfinite} of {b_total} candidate simulations were not finite "
                          f"(NaN/inf); rejected", RuntimeWarning, stacklevel=2)
        if js_traj is not None:  # the JS chain: its acceptances are the next task's bank
            d_js = torch.cat([p["dist_js"] for p in parts])
            js_keep = torch.argsort(d_js, stable=True)
            js_keep = js_keep[torch.isfinite(d_js[js_keep])]
            if cfg.js_epsilon is not None:
                js_keep = js_keep[: int((d_js < cfg.js_epsilon).sum())]
            if cfg.keep_best is not None:
                js_keep = js_keep[: cfg.keep_best]
            if js_keep.numel():  # none accepted: the last bank stays (as the authors' code)
                js_free = theta[js_keep][:, self._free]
                self._js_bank = (theta[js_keep], scott_bandwidth(js_free) if cfg.bandwidth_mode == "scott"
                                 else torch.full((js_free.shape[1],), cfg.bandwidth, dtype=torch.float64))
        t_sim = sum(p["time_simulate"] for p in parts)
        t_dist = sum(p["time_distance"] for p in parts)
        # wall-clock split in proportion to the chunks' own timings
        wall = time.perf_counter() - t0
        share = t_sim / (t_sim + t_dist) if t_sim + t_dist > 0 else 1.0
        t1 = t0 + wall * share
        t2 = t0 + wall

        order = torch.argsort(dist, stable=True)
        fallback, n_eps = False, None
        if cfg.epsilon is not None:
            n_eps = int((dist < cfg.epsilon).sum())
            keep = order[:n_eps]
            if cfg.keep_best is not None:
                keep = keep[: cfg.keep_best]
            if n_eps == 0:
                fallback = True
                warnings.warn(
                    f"task {idx}: no sample within epsilon={cfg.epsilon:.4g} "
                    f"(best distance {float(dist[order[0]]):.4g}); keeping the best {cfg.fallback_keep}",
                    RuntimeWarning, stacklevel=2,
                )
                # pruned distances beyond epsilon are +inf: each chunk (none of which accepted
                # anything) also scored its best k exactly; the global best k are among them
                dist = torch.cat([p["dist_fallback"] for p in parts])
                keep = torch.argsort(dist, stable=True)[: cfg.fallback_keep]
        else:
            keep = order[: cfg.keep_best]
        if not bool(torch.isfinite(dist[keep]).all()):
            # pruned distances are +inf only beyond epsilon / the k-th best, or for candidates
            # whose simulation was not finite: keep the finite ones
            keep = keep[torch.isfinite(dist[keep])]
        if keep.numel() == 0:  # no finite candidate at all: the task contributes nothing (failed)
            h = torch.full((int(self._free.sum()),), cfg.bandwidth, dtype=torch.float64)
            rec = TaskRecord(idx, theta[:0], dist[:0], n_eps, True, h, t1 - t0, t2 - t1, 0.0, n_nonfinite)
            self.records.append(rec)
            return rec
        q_new = theta[keep]
        free_new = q_new[:, self._free]
        h = (scott_bandwidth(free_new) if cfg.bandwidth_mode == "scott"
             else torch.full((free_new.shape[1],), cfg.bandwidth, dtype=torch.float64))
        kde = GaussianKDE(free_new, h)
        # incremental joint density: new KDE at old vectors, all KDEs at new vectors
        old_free = self._kept[:, self._free]
        if old_free.shape[0]:
            self._logp = self._logp + kde.log_density(old_free)
            if cfg.contain_observed:  # vectors that exclude a posture seen now are impossible
                self._logp[~self._draw_prior.contains(self._kept)] = -torch.inf
        self._kdes.append(kde)
        logp_new = torch.zeros(free_new.shape[0], dtype=torch.float64)
        for k in self._kdes:
            logp_new += k.log_density(free_new)
        self._kept = torch.cat([self._kept, q_new])
        self._logp = torch.cat([self._logp, logp_new])
        t3 = time.perf_counter()

        rec = TaskRecord(idx, q_new, dist[keep].clone(), n_eps, fallback, h, t1 - t0, t2 - t1, t3 - t2,
                         n_nonfinite)
        self.records.append(rec)
        return rec

    def observe_all(self, observations) -> Camo:
        """Observe a sequence of `Observation` in order (in ``config.space``); returns self.

        An `Observation` checked its arrays when it was made (float64, finite, shapes (n,), (3,),
        (L, n) and (L, 3)), so they are not checked again; only its joint count against the model.
        """
        n = self.simulator.n_joints
        for i, obs in enumerate(observations):
            if not isinstance(obs, Observation) or obs.start.shape != (n,):
                raise ValueError(f"observations: item {i} is not an Observation of {n} joints")
            js = obs.trajectory("joint").cpu() if self.config.proposal == "sequential-js" else None
            self._add(obs.start.cpu(), obs.goal.cpu(), obs.trajectory(self.config.space).cpu(), js)
        return self

    def estimate(self) -> np.ndarray:
        """(2n,) the point estimate (``config.point_estimate``; default: the kept vector with the
        highest joint density over the tasks so far, Eq. 6)."""
        if not self.records:
            raise RuntimeError("estimate: no task observed yet; call observe() first")
        if self._kept.shape[0] == 0:  # every task failed (no finite candidate): the prior's centre
            return self.prior.with_known(0.5 * (self.prior.low + self.prior.high)).numpy()
        est = self.config.point_estimate
        if est == "mode":
            return self._kept[int(torch.argmax(self._logp))].numpy().copy()
        kept, w = self._kept.numpy(), self.posterior_weights()
        if est == "mean":
            value = w @ kept
        else:
            a = 0.5 if est == "median" else self.config.outer_quantile
            qs = weighted_quantile(kept, w, [a, 1.0 - a])  # (2, 2n): a for lower bounds, 1 - a for upper
            value = np.where(np.arange(kept.shape[1]) % 2 == 0, qs[0], qs[1])
        return self.prior.with_known(torch.from_numpy(value)).numpy()

    def density(self):
        """``theta (B, 2n) or (2n,) -> (B,)``: the unnormalised log joint density of the tasks so
        far, sum_n log P_n(theta) over the free coordinates (Eq. 6), -inf outside the prior box
        (and, with ``contain_observed``, outside what the observed postures allow). A snapshot:
        later tasks do not change it."""
        kdes, free, support, dim = list(self._kdes), self._free, self._draw_prior, self.prior.dim

        def log_prob(theta) -> torch.Tensor:
            t = as_tensor(theta, "theta", dtype=torch.float64).cpu()
            t = t.unsqueeze(0) if t.dim() == 1 else t
            if t.dim() != 2 or t.shape[1] != dim:
                raise ValueError(f"theta: expected shape (B, {dim}), got {tuple(t.shape)}")
            lp = torch.zeros(t.shape[0], dtype=torch.float64)
            for kde in kdes:
                lp += kde.log_density(t[:, free])
            return torch.where(support.contains(t), lp, torch.full_like(lp, -torch.inf))

        return log_prob

    def posterior_weights(self) -> np.ndarray:
        """(M,) kept vectors' weights, proportional to their joint density."""
        w = torch.softmax(self._logp, dim=0)
        return w.numpy().copy()

    def result(self, method: str = "camo", *, n_simulations: int = 0, wall_time: float = 0.0) -> PosteriorResult:
        """The posterior so far: kept vectors weighted by their joint density, and the argmax."""
        w = self.posterior_weights()
        samples = self._kept.numpy().copy()
        empty = [r.index for r in self.records if r.kept.shape[0] == 0]
        fallback = [r.index for r in self.records if r.fallback and r.index not in empty]
        nonfinite = {r.index: r.n_nonfinite for r in self.records if r.n_nonfinite}
        reasons = []
        if fallback:
            reasons.append(f"task(s) {fallback} accepted nothing within epsilon={self.config.epsilon:.4g}; "
                           f"kept their best {self.config.fallback_keep}")
        if nonfinite:
            reasons.append(f"non-finite (NaN/inf) candidate simulations rejected, per task {nonfinite}")
        if empty:
            reasons.append(f"task(s) {empty} had no finite candidate and contribute nothing")
        status = STATUS_OK if not reasons else "fallback: " + "; ".join(reasons)
        if samples.shape[0] == 0:
            status = "failed: " + "; ".join(reasons) + "; the result is the prior's centre"
            samples, w = self.estimate()[None], np.ones(1)
        return PosteriorResult(
            method=method, samples=samples, weights=w, estimate=self.estimate(),
            n_simulations=n_simulations, wall_time=wall_time, n_tasks=self.n_tasks, status=status,
            density=self.density(),
            extras={
                "kept_per_task": [int(r.kept.shape[0]) for r in self.records],
                "fallback_tasks": [r.index for r in self.records if r.fallback],
                "nonfinite_candidates": [r.n_nonfinite for r in self.records],
                "accepted_epsilon": [r.n_accepted_epsilon for r in self.records],
                "ess": float(1.0 / np.sum(w**2)),
                "time_simulate": sum(r.time_simulate for r in self.records),
                "time_distance": sum(r.time_distance for r in self.records),
                "time_kde": sum(r.time_kde for r in self.records),
            },
        )


@dataclass(frozen=True)
class KdeProposal:
    """The authors' sequential proposal: a Gaussian KDE over the last task's kept vectors.

    points: (m, 2n) kept vectors; sd: (2n,) kernel standard deviations (0 on fixed
    coordinates); low, high: (2n,) the box every draw is clipped to.
    """

    points: torch.Tensor
    sd: torch.Tensor
    low: torch.Tensor
    high: torch.Tensor

    def sample(self, n: int, rng: np.random.Generator) -> torch.Tensor:
        """(n, 2n) draws: a uniformly chosen kept vector plus N(0, sd^2) noise, clipped to the box."""
        idx = torch.from_numpy(rng.integers(0, self.points.shape[0], size=n))
        noise = torch.from_numpy(rng.standard_normal((n, self.points.shape[1])))
        return torch.clamp(self.points[idx] + noise * self.sd, min=self.low, max=self.high)


def _distances(trajectory, sim_traj, lengths, config: CamoConfig, *, keep_best, epsilon=None) -> torch.Tensor:
    """(b,) distances of the simulations to the observed trajectory (``config.distance``)."""
    if config.distance == "dtw":
        return dtw_distances(trajectory, sim_traj, lengths, epsilon=epsilon, keep_best=keep_best)
    T = sim_traj.shape[1]
    if trajectory.shape[0] > T:
        raise ValueError(f"trajectory: {trajectory.shape[0]} points, more than the simulations' horizon {T}; "
                         f"the euclidean distance needs equal lengths (use distance='dtw')")
    held = torch.cat([trajectory, trajectory[-1:].expand(T - trajectory.shape[0], -1)])
    return l2_distance(held, sim_traj)


def _candidate_chunk(job, *, simulator, prior, start, goal, trajectory, config: CamoConfig,
                     noise: NoiseModel, js_trajectory=None) -> dict:
    """One chunk of one task's candidates: draw, simulate, score (runs in-process or on a worker).

    ``job`` = (seed, task index, chunk index, size); the draws come from
    ``default_rng([seed, task, chunk])`` only. Returns theta (b, 2n) float64, dist (b,)
    (exact for the chunk's best ``keep_best`` / those < ``epsilon``, else +inf), dist_fallback
    (exact for the chunk's best ``fallback_keep``, only when ``epsilon`` accepted none of
    the chunk, else None) and the chunk's simulate / distance times.
    """
    seed, task_index, chunk_index, b = job
    cfg = config
    rng = np.random.default_rng([seed, task_index, chunk_index])
    t0 = time.perf_counter()
    theta = contain(prior.sample(b, rng), start)  # this task's start is observed
    dtype = _DTYPES[cfg.sim_dtype]
    sims = simulator.simulate(theta.to(dtype), goal.to(dtype), start.to(dtype))
    t1 = time.perf_counter()
    # a candidate whose simulation is not finite (NaN/inf: a failure of this method's own
    # simulations, not of the user's data) is rejected: distance +inf, counted
    finite = torch.isfinite(sims.q).flatten(1).all(1) & torch.isfinite(sims.ee).flatten(1).all(1)
    n_nonfinite = int((~finite).sum())
    ok = torch.ones_like(finite) if n_nonfinite == 0 else finite
    dist, dist_fallback = _scores(trajectory, sims, ok, cfg.space, cfg, cfg.epsilon, noise, rng)
    dist_js = None
    if js_trajectory is not None:  # camo-seq-cs: the same candidates scored by the JS chain
        dist_js, _ = _scores(js_trajectory, sims, ok, "joint", cfg, cfg.js_epsilon, noise, rng)
    return {"theta": theta, "dist": dist, "dist_fallback": dist_fallback, "dist_js": dist_js,
            "n_nonfinite": n_nonfinite, "time_simulate": t1 - t0, "time_distance": time.perf_counter() - t1}


def _scores(trajectory, sims, ok, space, cfg: CamoConfig, epsilon, noise: NoiseModel, rng):
    """(dist (b,), dist_fallback (b,) or None) of the simulations ``ok`` (the rest: +inf) in ``space``."""
    sim_traj = (sims.q if space == "joint" else sims.ee)[ok]
    lengths = sims.length[ok]
    dist = torch.full((ok.shape[0],), torch.inf, dtype=torch.float64)
    dist_fallback = None
    if sim_traj.shape[0] == 0:
        return dist, (dist.clone() if epsilon is not None else None)
    if noise.sigma(space) > 0:  # compare like with like: the candidates seen through the same noise
        sim_traj = noise.perturb(sim_traj, space, rng)
    dist[ok] = _distances(trajectory, sim_traj, lengths, cfg, keep_best=cfg.keep_best, epsilon=epsilon)
    if epsilon is not None and not bool((dist < epsilon).any()):
        dist_fallback = torch.full_like(dist, torch.inf)
        dist_fallback[ok] = (dist[ok] if cfg.distance == "euclidean"
                             else dtw_distances(trajectory, sim_traj, lengths, keep_best=cfg.fallback_keep))
    return dist, dist_fallback


def _camo_for(task, observations, budget, seed, config) -> tuple[Camo, tuple]:
    config, budget, seed, observations, prior = check_run_args(task, observations, budget, seed, config,
                                                               CamoConfig)
    return Camo(task.simulator, prior, config, n_samples=budget, seed=seed, noise=task.noise), observations


def run_sequence(task, observations, *, budget: int, seed: int, config: CamoConfig | None = None):
    """Yield the result after each observed task (continual: nothing is re-simulated).

    The ``n_simulations`` / ``wall_time`` fields are placeholders: `run_method_sequence`
    fills them from the budget counter and its own clock.
    """
    camo, observations = _camo_for(task, observations, budget, seed, config)
    for obs in observations:
        camo.observe_all([obs])
        yield camo.result()


def run(task, observations, *, budget: int, seed: int, config: CamoConfig | None = None) -> PosteriorResult:
    """The run contract: CAMO on ``observations`` with ``budget`` prior draws per task."""
    camo, observations = _camo_for(task, observations, budget, seed, config)
    return camo.observe_all(observations).result()
