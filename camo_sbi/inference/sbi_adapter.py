"""The only module importing sbi: every use of sbi's public API goes through these functions.

    build_flow(kind, n_inputs, n_conditions, ...)          a conditional flow q(input | condition)
    train_npe(theta, x, ...)                               sbi's NPE trainer (per-task NPE)
    fit_density_estimator(estimator, inputs, conditions)   our seeded loop over ``estimator.loss``
    c2st(a, b, ...)                                        sbi.utils.metrics.c2st
    run_sbc / check_sbc / run_tarp / check_tarp            sbi.diagnostics on an amortized posterior

Public sbi names only (``sbi.inference.NPE``, ``sbi.neural_nets.posterior_nn``,
``ConditionalDensityEstimator.loss/log_prob/sample``, ``NeuralInference.summary``,
``sbi.diagnostics``, ``sbi.utils.metrics.c2st``); sbi is imported inside the functions, so
importing this module is cheap. The installed sbi must satisfy `SBI_SUPPORTED`
(pyproject pins the same range; `check_sbi_version` raises otherwise).

Every function that draws random numbers does so inside ``torch.random.fork_rng`` seeded
from its ``seed`` argument: the caller's global torch RNG is never changed.
"""

from __future__ import annotations

import contextlib
import copy
import io
import math
import time
import warnings

import torch
from torch import nn

from camo_sbi._validation import check_choice, check_positive_float, check_positive_int

__all__ = [
    "FLOW_KINDS",
    "SBI_SUPPORTED",
    "build_flow",
    "c2st",
    "check_sbc",
    "check_sbi_version",
    "check_tarp",
    "fit_density_estimator",
    "run_sbc",
    "run_tarp",
    "sbi_version",
    "train_npe",
]

SBI_SUPPORTED = ((0, 25), (0, 28))
"""Supported sbi versions: [0.25, 0.28), the range pyproject.toml pins."""

FLOW_KINDS = ("maf", "nsf")


def sbi_version() -> tuple[int, ...]:
    import sbi

    return tuple(int(p) for p in sbi.__version__.split("+")[0].split(".")[:3] if p.isdigit())


def check_sbi_version() -> tuple[int, ...]:
    """The installed sbi version, or RuntimeError if it is outside `SBI_SUPPORTED`."""
    v = sbi_version()
    lo, hi = SBI_SUPPORTED
    if not (lo <= v[:2] < hi):
        raise RuntimeError(f"sbi {'.'.join(map(str, v))} is not supported: camo_sbi needs sbi >= "
                           f"{lo[0]}.{lo[1]}, < {hi[0]}.{hi[1]} (see pyproject.toml)")
    return v


class _NullTracker:
    """sbi Tracker that records nothing (sbi's default writes TensorBoard logs to ./sbi-logs)."""

    log_dir = None

    def log_metric(self, name, value, step=None):
        pass

    def log_metrics(self, metrics, step=None):
        pass

    def log_params(self, params):
        pass

    def add_figure(self, name, figure, step=None):
        pass

    def flush(self):
        pass


@contextlib.contextmanager
def _quiet():
    with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
        warnings.simplefilter("ignore")
        yield


# ----------------------------------------------------------------------------------- flows


def build_flow(kind: str, n_inputs: int, n_conditions: int, *, hidden_features: int = 50,
               num_transforms: int = 5, embedding_dim: int | None = None, embedding_hidden: int = 128,
               embedding_layers: int = 3, seed: int = 0) -> nn.Module:
    """A fresh sbi conditional flow q(input | condition) with NO internal z-scoring.

    The architecture depends on the sizes and settings only (never on data), so a flow
    rebuilt with the same arguments accepts the state dict of a trained one: the caller
    standardises inputs and conditions itself and stores those statistics. ``seed`` seeds the
    initial weights (global torch RNG untouched). The module has ``log_prob(input,
    condition)``, ``sample(sample_shape, condition)`` and ``loss(input, condition)``
    (sbi's ``ConditionalDensityEstimator``). ``embedding_dim``: None (conditions fed to the
    flow as they are) or the output size of an sbi ``FCEmbedding`` (``embedding_layers`` layers
    of ``embedding_hidden`` units) trained jointly with the flow.
    """
    check_choice(kind, FLOW_KINDS, "kind")
    n_inputs = check_positive_int(n_inputs, "n_inputs")
    n_conditions = check_positive_int(n_conditions, "n_conditions")
    check_sbi_version()
    from sbi.neural_nets import posterior_nn
    from sbi.neural_nets.embedding_nets import FCEmbedding

    with torch.random.fork_rng(devices=[]), _quiet():
        torch.manual_seed(seed)
        embedding = nn.Identity() if embedding_dim is None else FCEmbedding(
            n_conditions, check_positive_int(embedding_dim, "embedding_dim"),
            num_layers=check_positive_int(embedding_layers, "embedding_layers", minimum=2),
            num_hiddens=check_positive_int(embedding_hidden, "embedding_hidden"))
        builder = posterior_nn(model=kind, z_score_theta="none", z_score_x="none",
                               hidden_features=check_positive_int(hidden_features, "hidden_features"),
                               num_transforms=check_positive_int(num_transforms, "num_transforms"),
                               embedding_net=embedding)
        net = builder(torch.zeros(2, n_inputs), torch.zeros(2, n_conditions))
    return net.to("cpu")


def fit_density_estimator(estimator: nn.Module, inputs: torch.Tensor, conditions: torch.Tensor, *,
                          seed: int, batch_size: int = 256, learning_rate: float = 1e-3,
                          validation_fraction: float = 0.05, stop_after_epochs: int = 10,
                          max_epochs: int = 100, max_seconds: float | None = None,
                          clip_max_norm: float = 5.0, progress: bool = False,
                          desc: str = "training", balance: float = 0.0, prior_log_prob=None) -> dict:
    """Maximum-likelihood training of ``estimator`` on (input, condition) pairs, in place.

    Adam on ``estimator.loss`` (sbi's negative log-likelihood), gradient norms clipped at
    ``clip_max_norm``, a held-out ``validation_fraction`` for early stopping after
    ``stop_after_epochs`` epochs without improvement; the best validation state is restored.
    ``max_seconds`` stops after the epoch that crosses it (None: no limit). ``balance`` > 0 adds
    the balancing penalty of balanced NPE (Delaunoy et al. 2023), balance x (E_joint[s(d)] +
    E_marginal[s(d)] - 1)^2 with d = log q(input | condition) - ``prior_log_prob(input)``, s the
    logistic sigmoid, marginal pairs made by shuffling the inputs within the batch; it pushes
    the estimator toward conservative (not over-confident) posteriors. Seeded: the split,
    the batch order and any dropout come from ``seed`` inside ``fork_rng``. ``progress``: a tqdm
    bar over epochs.

    Returns {"epochs", "best_validation_loss", "training_loss", "stopped" ("converged",
    "max_epochs" or "max_seconds"), "time_train", "n_train", "n_validation"}.
    """
    from tqdm import tqdm

    x = torch.as_tensor(inputs, dtype=torch.float32)
    c = torch.as_tensor(conditions, dtype=torch.float32)
    if x.dim() != 2 or c.dim() != 2 or x.shape[0] != c.shape[0]:
        raise ValueError(f"inputs: expected (N, d) inputs and (N, D) conditions, got {tuple(x.shape)} "
                         f"and {tuple(c.shape)}")
    batch_size = check_positive_int(batch_size, "batch_size", minimum=2)
    check_positive_float(learning_rate, "learning_rate")
    check_positive_float(validation_fraction, "validation_fraction")
    stop_after_epochs = check_positive_int(stop_after_epochs, "stop_after_epochs")
    max_epochs = check_positive_int(max_epochs, "max_epochs")
    if max_seconds is not None:
        check_positive_float(max_seconds, "max_seconds")
    check_positive_float(balance, "balance", allow_zero=True)
    if balance > 0 and not callable(prior_log_prob):
        raise TypeError("prior_log_prob: balance > 0 needs a callable prior log density of the inputs")
    n = x.shape[0]
    n_val = max(1, int(round(validation_fraction * n)))
    if n - n_val < 2:
        raise ValueError(f"inputs: {n} pairs leave too few for training (validation_fraction={validation_fraction})")
    t0 = time.perf_counter()
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        gen = torch.Generator().manual_seed(seed)
        perm = torch.randperm(n, generator=gen)
        val, train = perm[:n_val], perm[n_val:]
        opt = torch.optim.Adam(estimator.parameters(), lr=learning_rate)
        best, best_state, since, stopped = math.inf, None, 0, "max_epochs"
        history = []
        bar = tqdm(range(max_epochs), desc=desc, unit="epoch", disable=not progress, leave=False)
        for _ in bar:
            estimator.train()
            order = train[torch.randperm(train.shape[0], generator=gen)]
            total = 0.0
            for s in range(0, order.shape[0], batch_size):
                idx = order[s : s + batch_size]
                opt.zero_grad()
                nll = estimator.loss(x[idx], condition=c[idx])
                loss = nll.mean()
                if balance > 0:
                    shuffled = x[idx][torch.randperm(idx.shape[0], generator=gen)]
                    d_joint = -nll - prior_log_prob(x[idx])
                    d_marg = -estimator.loss(shuffled, condition=c[idx]) - prior_log_prob(shuffled)
                    gap = torch.sigmoid(d_joint).mean() + torch.sigmoid(d_marg).mean() - 1.0
                    loss = loss + balance * gap**2
                loss.backward()
                nn.utils.clip_grad_norm_(estimator.parameters(), max_norm=clip_max_norm)
                opt.step()
                total += float(loss.detach()) * idx.shape[0]
            estimator.eval()
            with torch.no_grad():
                vl = float(sum(estimator.loss(x[val[s : s + 8192]], condition=c[val[s : s + 8192]]).sum()
                               for s in range(0, n_val, 8192)) / n_val)
            history.append(total / train.shape[0])
            if vl < best:
                best, since = vl, 0
                best_state = copy.deepcopy(estimator.state_dict())
            else:
                since += 1
            bar.set_postfix(train=f"{history[-1]:.3f}", val=f"{vl:.3f}", best=f"{best:.3f}")
            if since >= stop_after_epochs:
                stopped = "converged"
                break
            if max_seconds is not None and time.perf_counter() - t0 > max_seconds:
                stopped = "max_seconds"
                break
        bar.close()
    if best_state is not None:
        estimator.load_state_dict(best_state)
    estimator.eval()
    return {"epochs": len(history), "best_validation_loss": best, "training_loss": history, "stopped": stopped,
            "time_train": time.perf_counter() - t0, "n_train": int(train.shape[0]), "n_validation": n_val}


def train_npe(theta: torch.Tensor, x: torch.Tensor, *, seed: int, density_estimator: str = "maf",
              hidden_features: int = 50, num_transforms: int = 5, embedding_dim: int | None = None,
              training_batch_size: int = 100, learning_rate: float = 1e-3,
              validation_fraction: float = 0.1, stop_after_epochs: int = 20, max_epochs: int = 200,
              device: str = "cpu") -> tuple[nn.Module, dict]:
    """Single-round sbi NPE (maximum likelihood) of q(theta | x), z-scored inside the flow.

    ``embedding_dim``: None (x fed as is) or the output size of an sbi ``FCEmbedding`` trained
    jointly. Returns (estimator on the CPU in eval mode, {"epochs", "best_validation_loss",
    "time_train"}) read from the trainer's public ``summary``. Global torch RNG untouched.
    """
    check_sbi_version()
    from sbi.inference import NPE
    from sbi.neural_nets import posterior_nn
    from sbi.neural_nets.embedding_nets import FCEmbedding

    t0 = time.perf_counter()
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        embedding = nn.Identity() if embedding_dim is None else FCEmbedding(x.shape[1], embedding_dim)
        builder = posterior_nn(model=density_estimator, hidden_features=hidden_features,
                               num_transforms=num_transforms, embedding_net=embedding,
                               z_score_theta="independent", z_score_x="independent")
        trainer = NPE(prior=None, density_estimator=builder, device=device, show_progress_bars=False,
                      tracker=_NullTracker())
        with _quiet():
            trainer.append_simulations(theta.float(), x.float())
            estimator = trainer.train(
                training_batch_size=training_batch_size, learning_rate=learning_rate,
                validation_fraction=validation_fraction, stop_after_epochs=stop_after_epochs,
                max_num_epochs=max_epochs, show_train_summary=False,
            )
    summary = trainer.summary
    info = {"epochs": int(summary["epochs_trained"][-1]),
            "best_validation_loss": float(summary["best_validation_loss"][-1]),
            "time_train": time.perf_counter() - t0}
    return estimator.to("cpu").eval(), info


def new_npe_estimator(n_theta: int, n_x: int, *, density_estimator: str = "maf", hidden_features: int = 50,
                      num_transforms: int = 5, embedding_dim: int | None = None) -> nn.Module:
    """An untrained estimator of the very architecture `train_npe` builds for these sizes, to receive
    a trained one's state dict (its z-scoring statistics are buffers there, so they are restored too).
    Built on stand-in data (fixed seed, global torch RNG untouched)."""
    check_sbi_version()
    from sbi.neural_nets import posterior_nn
    from sbi.neural_nets.embedding_nets import FCEmbedding

    n_theta, n_x = check_positive_int(n_theta, "n_theta"), check_positive_int(n_x, "n_x")
    with torch.random.fork_rng(devices=[]), _quiet():
        torch.manual_seed(0)
        embedding = nn.Identity() if embedding_dim is None else FCEmbedding(n_x, embedding_dim)
        builder = posterior_nn(model=density_estimator, hidden_features=hidden_features,
                               num_transforms=num_transforms, embedding_net=embedding,
                               z_score_theta="independent", z_score_x="independent")
        net = builder(torch.randn(8, n_theta), torch.randn(8, n_x))
    return net.to("cpu").eval()


# ----------------------------------------------------------------------------------- diagnostics


def c2st(a: torch.Tensor, b: torch.Tensor, *, seed: int, n_folds: int = 5, classifier: str = "rf") -> float:
    """Classifier two-sample test accuracy, ``sbi.utils.metrics.c2st`` (0.5: indistinguishable)."""
    check_sbi_version()
    from sbi.utils.metrics import c2st as sbi_c2st

    acc = sbi_c2st(torch.as_tensor(a, dtype=torch.float32), torch.as_tensor(b, dtype=torch.float32),
                   seed=int(seed), n_folds=n_folds, classifier=classifier)
    return float(acc)


def _on_posterior(fn, thetas, xs, posterior, num_posterior_samples: int, seed: int):
    with torch.random.fork_rng(devices=[]), _quiet():
        torch.manual_seed(seed)
        return fn(torch.as_tensor(thetas, dtype=torch.float32), torch.as_tensor(xs, dtype=torch.float32),
                  posterior, num_posterior_samples=num_posterior_samples, show_progress_bar=False)


def run_sbc(thetas: torch.Tensor, xs: torch.Tensor, posterior, *, num_posterior_samples: int, seed: int):
    """``sbi.diagnostics.run_sbc`` (marginal ranks) -> (ranks (N, d), data-averaged posterior draws (N, d)).

    ``posterior``: any object with sbi's ``sample_batched(sample_shape, x, show_progress_bars)``
    returning (num_samples, N, d).
    """
    check_sbi_version()
    from sbi.diagnostics import run_sbc as sbi_run_sbc

    return _on_posterior(sbi_run_sbc, thetas, xs, posterior, num_posterior_samples, seed)


def check_sbc(ranks, prior_samples, dap_samples, *, num_posterior_samples: int, seed: int) -> dict:
    """``sbi.diagnostics.check_sbc``: {"ks_pvals" (d,), "c2st_ranks" (d,), "c2st_dap" (1,)} as lists."""
    check_sbi_version()
    from sbi.diagnostics import check_sbc as sbi_check_sbc

    with torch.random.fork_rng(devices=[]), _quiet():
        torch.manual_seed(seed)
        out = sbi_check_sbc(ranks, torch.as_tensor(prior_samples, dtype=torch.float32),
                            torch.as_tensor(dap_samples, dtype=torch.float32),
                            num_posterior_samples=num_posterior_samples)
    return {k: torch.as_tensor(v).reshape(-1).tolist() for k, v in out.items()}


def run_tarp(thetas: torch.Tensor, xs: torch.Tensor, posterior, *, num_posterior_samples: int, seed: int):
    """``sbi.diagnostics.run_tarp`` -> (expected coverage probability, credibility levels alpha)."""
    check_sbi_version()
    from sbi.diagnostics import run_tarp as sbi_run_tarp

    return _on_posterior(sbi_run_tarp, thetas, xs, posterior, num_posterior_samples, seed)


def check_tarp(ecp, alpha) -> tuple[float, float]:
    """``sbi.diagnostics.check_tarp`` -> (ATC: > 0 too wide, < 0 too narrow; KS p-value)."""
    check_sbi_version()
    from sbi.diagnostics import check_tarp as sbi_check_tarp

    atc, p = sbi_check_tarp(ecp, alpha)
    return float(atc), float(p)
