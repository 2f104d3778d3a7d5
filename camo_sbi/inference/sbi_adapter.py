"""The only module importing sbi: every use of sbi's public API goes through these functions.

    build_flow(kind, n_inputs, n_conditions, ...)          a conditional flow q(input | condition)
    train_npe(theta, x, ...)                               sbi's NPE trainer (per-task NPE)
    fit_density_estimator(estimator, inputs, conditions)   our seeded loop over ``estimator.loss``
    train_nle / train_nre / train_vector_field / train_tsnpe  sbi's NLE_A, NRE_C, FMPE / NPSE, NPE_C truncated
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
    "import_sbi",
    "SBI_SUPPORTED",
    "VECTOR_FIELDS",
    "VectorFieldDensity",
    "build_flow",
    "c2st",
    "mmd",
    "check_sbc",
    "check_sbi_version",
    "check_tarp",
    "fit_density_estimator",
    "logistic_prior",
    "mmd_misspecification_p",
    "nle_log_likelihood",
    "nre_log_ratio",
    "run_sbc",
    "run_tarp",
    "sbi_version",
    "train_nle",
    "train_npe",
    "train_nre",
    "train_tsnpe",
    "train_vector_field",
]

SBI_SUPPORTED = ((0, 25), (0, 28))
"""Supported sbi versions: [0.25, 0.28), the range pyproject.toml pins."""

FLOW_KINDS = ("maf", "nsf")
LR_SCHEDULES = ("constant", "cosine")


def sbi_version() -> tuple[int, ...]:
    import sbi

    return tuple(int(p) for p in sbi.__version__.split("+")[0].split(".")[:3] if p.isdigit())


def import_sbi() -> None:
    """Import the sbi modules `train_npe` uses (and scikit-learn, which sbi imports): about 4-5 s
    of CPU in a fresh process, which the registry times as a run's ``import_time`` instead of
    charging it to the run's ``wall_time`` (`Implementation.setup`)."""
    import sbi.inference  # noqa: F401
    import sbi.neural_nets  # noqa: F401
    import sbi.neural_nets.embedding_nets  # noqa: F401

    # torch imports torch._dynamo lazily when the first optimiser is built (seconds of CPU): here,
    # not inside the first training
    torch.optim.Adam([torch.zeros(1, requires_grad=True)])


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
                          desc: str = "training", balance: float = 0.0, prior_log_prob=None,
                          lr_schedule: str = "constant") -> dict:
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
    bar over epochs. ``lr_schedule``: "constant" (Adam at ``learning_rate`` throughout) or
    "cosine" (the rate falls per step from ``learning_rate`` to 0 along a half cosine over
    ``max_epochs`` epochs; an early stop cuts it short).

    Returns {"epochs", "best_validation_loss", "training_loss", "validation_loss" (per epoch),
    "epoch_seconds" and "epoch_cpu_seconds" (wall and process CPU seconds from the start to the
    end of each epoch), "stopped" ("converged",
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
    check_choice(lr_schedule, LR_SCHEDULES, "lr_schedule")
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
        total_steps = max_epochs * math.ceil(train.shape[0] / batch_size)
        step = 0
        best, best_state, since, stopped = math.inf, None, 0, "max_epochs"
        history, val_history, clock, cpu_clock = [], [], [], []
        c0 = time.process_time()
        bar = tqdm(range(max_epochs), desc=desc, unit="epoch", disable=not progress, leave=False)
        for _ in bar:
            estimator.train()
            order = train[torch.randperm(train.shape[0], generator=gen)]
            total = 0.0
            for s in range(0, order.shape[0], batch_size):
                idx = order[s : s + batch_size]
                if lr_schedule == "cosine":
                    for group in opt.param_groups:
                        group["lr"] = 0.5 * learning_rate * (1.0 + math.cos(math.pi * step / total_steps))
                step += 1
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
            val_history.append(vl)
            clock.append(time.perf_counter() - t0)
            cpu_clock.append(time.process_time() - c0)
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
    return {"epochs": len(history), "best_validation_loss": best, "training_loss": history,
            "validation_loss": val_history, "epoch_seconds": clock,
            "epoch_cpu_seconds": cpu_clock, "stopped": stopped,
            "time_train": time.perf_counter() - t0, "n_train": int(train.shape[0]), "n_validation": n_val}


def _warm_start(net: nn.Module, trained: nn.Module) -> None:
    """Copy ``trained``'s weights into the freshly built ``net`` of the same architecture.

    Copied: every parameter and every integer buffer (the flow's permutations, which the weights
    are tied to; the masks' degrees). Kept from ``net``: its floating-point buffers, i.e. the
    z-scoring statistics sbi computed from the NEW training data (and the masks, which the
    architecture fixes). ValueError if the two do not match name for name and shape for shape.
    """
    new = dict(net.named_parameters()) | dict(net.named_buffers())
    old = dict(trained.named_parameters()) | dict(trained.named_buffers())
    if new.keys() != old.keys() or any(new[k].shape != old[k].shape for k in new):
        raise ValueError("init_from: its architecture differs from the estimator being trained "
                         "(sizes or settings differ)")
    params = dict(net.named_parameters())
    with torch.no_grad():
        for name, t in new.items():
            if name in params or not t.is_floating_point():
                t.copy_(old[name].to(t.device))


def train_npe(theta: torch.Tensor, x: torch.Tensor, *, seed: int, density_estimator: str = "maf",
              hidden_features: int = 50, num_transforms: int = 5, embedding_dim: int | None = None,
              training_batch_size: int = 100, learning_rate: float = 1e-3,
              validation_fraction: float = 0.1, stop_after_epochs: int = 20, max_epochs: int = 200,
              device: str = "cpu", init_from: nn.Module | None = None) -> tuple[nn.Module, dict]:
    """Single-round sbi NPE (maximum likelihood) of q(theta | x), z-scored inside the flow.

    ``embedding_dim``: None (x fed as is) or the output size of an sbi ``FCEmbedding`` trained
    jointly. ``init_from``: None (fresh weights from ``seed``) or an estimator `train_npe`
    returned for the same sizes and settings: training starts from its weights and
    permutations (a warm start), with the z-scoring statistics of THIS ``theta`` and ``x``
    (ValueError if the architectures differ). Returns (estimator on the CPU in eval mode,
    {"epochs", "best_validation_loss", "time_train"}) read from the trainer's public
    ``summary``. Global torch RNG untouched.
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
        if init_from is not None:
            fresh = builder

            def builder(batch_theta, batch_x):  # sbi's public builder contract: (theta, x) -> estimator
                net = fresh(batch_theta, batch_x)
                _warm_start(net, init_from)
                return net

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


def mmd(a: torch.Tensor, b: torch.Tensor) -> float:
    """Unbiased squared maximum-mean discrepancy, ``sbi.utils.metrics.unbiased_mmd_squared`` (Gaussian
    kernel, median-heuristic length scale; 0: the same distribution). Needs at least 2 rows each."""
    check_sbi_version()
    from sbi.utils.metrics import unbiased_mmd_squared

    if a.shape[0] < 2 or b.shape[0] < 2:
        raise ValueError(f"a: the unbiased MMD needs at least 2 samples per set, got {a.shape[0]} and {b.shape[0]}")
    return float(unbiased_mmd_squared(torch.as_tensor(a, dtype=torch.float64), torch.as_tensor(b, dtype=torch.float64)))


def mmd_misspecification_p(x_obs: torch.Tensor, x: torch.Tensor, *, seed: int, n_shuffle: int = 1000) -> float:
    """p-value of ``sbi.diagnostics.misspecification.calc_misspecification_mmd`` in x-space (RBF
    MMD, median-heuristic bandwidth, a permutation baseline of ``n_shuffle`` draws): is
    ``x_obs`` (n_obs, d) out of the distribution of ``x`` (N, d)? Seeded (fork_rng)."""
    check_sbi_version()
    from sbi.diagnostics.misspecification import calc_misspecification_mmd

    with torch.random.fork_rng(devices=[]), _quiet():
        torch.manual_seed(int(seed))
        p, _ = calc_misspecification_mmd(torch.as_tensor(x_obs, dtype=torch.float32),
                                         torch.as_tensor(x, dtype=torch.float32), mode="x_space",
                                         n_shuffle=int(n_shuffle), max_samples=x.shape[0])
    return float(p)


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


# ----------------------------------------------------------------------------------- a trained NSF without sbi


class _Linear(nn.Module):
    """The parameters of an ``nn.Linear`` (same state-dict keys), applied with ``F.linear``."""

    def __init__(self, n_in: int, n_out: int):
        super().__init__()
        self.weight = nn.Parameter(torch.empty(n_out, n_in))
        self.bias = nn.Parameter(torch.empty(n_out))

    def forward(self, x):
        return nn.functional.linear(x, self.weight, self.bias)


class _ResidualBlock(nn.Module):
    def __init__(self, hidden: int, n_context: int):
        super().__init__()
        self.context_layer = _Linear(n_context, hidden)
        self.linear_layers = nn.ModuleList([_Linear(hidden, hidden), _Linear(hidden, hidden)])

    def forward(self, x, context):
        t = self.linear_layers[1](torch.relu(self.linear_layers[0](torch.relu(x))))
        return x + nn.functional.glu(torch.cat((t, self.context_layer(context)), dim=1), dim=1)


class _ResidualNet(nn.Module):
    def __init__(self, n_in: int, n_out: int, hidden: int, n_context: int, num_blocks: int = 2):
        super().__init__()
        self.hidden_features = hidden
        self.initial_layer = _Linear(n_in + n_context, hidden)
        self.blocks = nn.ModuleList([_ResidualBlock(hidden, n_context) for _ in range(num_blocks)])
        self.final_layer = _Linear(hidden, n_out)

    def forward(self, x, context):
        t = self.initial_layer(torch.cat((x, context), dim=1))
        for block in self.blocks:
            t = block(t, context)
        return self.final_layer(t)


_MIN_BIN, _MIN_DERIVATIVE = 1e-3, 1e-3  # nflows' defaults for widths, heights and derivatives


def _rq_spline(x, uw, uh, ud, inverse: bool, bound: float):
    """nflows' ``unconstrained_rational_quadratic_spline`` with linear tails (same operations)."""
    inside = (x >= -bound) & (x <= bound)
    ud = nn.functional.pad(ud, pad=(1, 1))
    constant = math.log(math.exp(1 - _MIN_DERIVATIVE) - 1)
    ud[..., 0] = constant
    ud[..., -1] = constant
    if not torch.any(inside):
        return x.clone(), torch.zeros_like(x)
    every = bool(inside.all())  # the usual case: no masking copies (same values either way)
    if not every:
        out, lad = x.clone(), torch.zeros_like(x)
        x, uw, uh, ud = x[inside], uw[inside, :], uh[inside, :], ud[inside, :]
    nb = uw.shape[-1]

    def knots(u):
        s = _MIN_BIN + (1 - _MIN_BIN * nb) * torch.softmax(u, dim=-1)
        c = nn.functional.pad(torch.cumsum(s, dim=-1), pad=(1, 0), mode="constant", value=0.0)
        c = 2 * bound * c - bound
        c[..., 0] = -bound
        c[..., -1] = bound
        return c, c[..., 1:] - c[..., :-1]

    cw, widths = knots(uw)
    derivatives = _MIN_DERIVATIVE + nn.functional.softplus(ud)
    ch, heights = knots(uh)
    locations = ch if inverse else cw
    locations[..., -1] += 1e-6
    idx = (torch.sum(x[..., None] >= locations, dim=-1) - 1)[..., None]
    in_cw = cw.gather(-1, idx)[..., 0]
    in_w = widths.gather(-1, idx)[..., 0]
    in_ch = ch.gather(-1, idx)[..., 0]
    delta = heights / widths
    in_delta = delta.gather(-1, idx)[..., 0]
    in_d = derivatives.gather(-1, idx)[..., 0]
    in_d1 = derivatives[..., 1:].gather(-1, idx)[..., 0]
    in_h = heights.gather(-1, idx)[..., 0]
    if inverse:
        a = (x - in_ch) * (in_d + in_d1 - 2 * in_delta) + in_h * (in_delta - in_d)
        b = in_h * in_d - (x - in_ch) * (in_d + in_d1 - 2 * in_delta)
        c = -in_delta * (x - in_ch)
        discriminant = b.pow(2) - 4 * a * c
        root = (2 * c) / (-b - torch.sqrt(discriminant))
        y = root * in_w + in_cw
        t1 = root * (1 - root)
        denominator = in_delta + ((in_d + in_d1 - 2 * in_delta) * t1)
        numerator = in_delta.pow(2) * (in_d1 * root.pow(2) + 2 * in_delta * t1 + in_d * (1 - root).pow(2))
        ld = -(torch.log(numerator) - 2 * torch.log(denominator))
    else:
        theta = (x - in_cw) / in_w
        t1 = theta * (1 - theta)
        numerator = in_h * (in_delta * theta.pow(2) + in_d * t1)
        denominator = in_delta + ((in_d + in_d1 - 2 * in_delta) * t1)
        y = in_ch + numerator / denominator
        dnum = in_delta.pow(2) * (in_d1 * theta.pow(2) + 2 * in_delta * t1 + in_d * (1 - theta).pow(2))
        ld = torch.log(dnum) - 2 * torch.log(denominator)
    if every:
        return y, ld
    out[inside], lad[inside] = y, ld
    return out, lad


class _Coupling(nn.Module):
    """nflows' ``PiecewiseRationalQuadraticCouplingTransform`` (linear tails), sbi's NSF settings."""

    def __init__(self, n: int, hidden: int, n_context: int, even: bool, num_bins: int, bound: float):
        super().__init__()
        mask = torch.arange(n) % 2 == (0 if even else 1)  # sbi's create_alternating_binary_mask
        self.register_buffer("identity_features", torch.nonzero(~mask).reshape(-1))
        self.register_buffer("transform_features", torch.nonzero(mask).reshape(-1))
        self.num_bins, self.bound = num_bins, bound
        self.transform_net = _ResidualNet(int((~mask).sum()), int(mask.sum()) * (3 * num_bins - 1), hidden, n_context)

    def run(self, x, context, inverse: bool):
        ident, trans = x[:, self.identity_features], x[:, self.transform_features]
        p = self.transform_net(ident, context).reshape(x.shape[0], trans.shape[1], -1)
        nb, scale = self.num_bins, math.sqrt(self.transform_net.hidden_features)
        y, lad = _rq_spline(trans, p[..., :nb] / scale, p[..., nb : 2 * nb] / scale, p[..., 2 * nb :], inverse,
                            self.bound)
        out = torch.empty_like(x)
        out[:, self.identity_features] = ident
        out[:, self.transform_features] = y
        return out, lad.reshape(x.shape[0], -1).sum(dim=1)


class _LULinear(nn.Module):
    """nflows' ``LULinear`` (eps 1e-3): x -> L U x + bias with unit-diagonal L."""

    def __init__(self, n: int):
        super().__init__()
        self.n = n
        self.bias = nn.Parameter(torch.zeros(n))
        self.lower_entries = nn.Parameter(torch.zeros(n * (n - 1) // 2))
        self.upper_entries = nn.Parameter(torch.zeros(n * (n - 1) // 2))
        self.unconstrained_upper_diag = nn.Parameter(torch.zeros(n))

    def _lower_upper(self):
        n = self.n
        lo_i, up_i, dg = torch.tril_indices(n, n, -1), torch.triu_indices(n, n, 1), torch.arange(n)
        lower = self.lower_entries.new_zeros(n, n)
        lower[lo_i[0], lo_i[1]] = self.lower_entries
        lower[dg, dg] = 1.0
        diag = nn.functional.softplus(self.unconstrained_upper_diag) + 1e-3
        upper = self.upper_entries.new_zeros(n, n)
        upper[up_i[0], up_i[1]] = self.upper_entries
        upper[dg, dg] = diag
        return lower, upper, torch.sum(torch.log(diag))

    def run(self, x, context, inverse: bool):
        lower, upper, logdet = self._lower_upper()
        if inverse:  # nflows' (deprecated) triangular_solve: solve_triangular differs in the last bit
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                y, _ = torch.triangular_solve((x - self.bias).t(), lower, upper=False, unitriangular=True)
                y, _ = torch.triangular_solve(y, upper, upper=True, unitriangular=False)
            return y.t(), -logdet * x.new_ones(x.shape[0])
        y = nn.functional.linear(nn.functional.linear(x, upper), lower, self.bias)
        return y, logdet * x.new_ones(x.shape[0])


class NsfReader(nn.Module):
    """A trained sbi NSF (`build_flow("nsf", ...)`, no embedding net) evaluated without importing sbi.

    It holds the same parameters under the same state-dict keys as sbi's ``NFlowsFlow`` (so
    ``load_state_dict(strict=True)`` reads a saved flow's weights) and performs the same
    operations in the same order as nflows (Gaussian base, alternating rational-quadratic
    coupling layers with linear tails and LU linear layers): the same seed gives the same
    draws (``tests/test_amortized.py`` compares it with the sbi flow). For inference only:
    ``sample``, ``sample_and_log_prob`` and ``log_prob`` with sbi's shapes; no training.
    Importing sbi (and nflows, which imports matplotlib) costs seconds per process; not
    importing it is what makes a cold estimator load fast (docs/studies/design_measurements.md).
    """

    def __init__(self, n_inputs: int, n_conditions: int, *, hidden_features: int, num_transforms: int,
                 num_bins: int = 10, tail_bound: float = 3.0):
        super().__init__()
        layers = []
        for i in range(num_transforms):
            layers += [_Coupling(n_inputs, hidden_features, n_conditions, i % 2 == 0, num_bins, tail_bound),
                       _LULinear(n_inputs)]
        self.net = nn.Module()
        self.net._transform = nn.Module()
        self.net._transform._transforms = nn.ModuleList(layers)
        self.n_inputs = n_inputs
        self._log_z = 0.5 * n_inputs * math.log(2 * math.pi)

    def _cascade(self, x, context, inverse: bool):
        total = x.new_zeros(x.shape[0])
        layers = self.net._transform._transforms
        for layer in (reversed(layers) if inverse else layers):
            x, lad = layer.run(x, context, inverse)
            total = total + lad
        return x, total

    def _base_log_prob(self, noise):
        return -0.5 * (noise**2).reshape(noise.shape[0], -1).sum(dim=1) - torch.tensor(self._log_z,
                                                                                       dtype=torch.float64)

    @torch.no_grad()
    def sample_and_log_prob(self, sample_shape, condition):
        b, n = condition.shape[0], int(torch.Size(sample_shape).numel())
        noise = torch.randn(b * n, self.n_inputs)
        log_prob = self._base_log_prob(noise)
        x, lad = self._cascade(noise, condition.repeat_interleave(n, dim=0), inverse=True)
        return x.reshape((*sample_shape, b, -1)), (log_prob - lad).reshape((*sample_shape, -1))

    @torch.no_grad()
    def sample(self, sample_shape, condition):
        b, n = condition.shape[0], int(torch.Size(sample_shape).numel())
        x, _ = self._cascade(torch.randn(b * n, self.n_inputs), condition.repeat_interleave(n, dim=0), inverse=True)
        return x.reshape(b, n, -1).transpose(0, 1).reshape((*sample_shape, b, self.n_inputs))

    @torch.no_grad()
    def log_prob(self, input, condition):  # noqa: A002 - sbi's argument name
        x = input if input.dim() == 3 else input.unsqueeze(0)
        s, b = x.shape[0], max(x.shape[1], condition.shape[0])
        x = x.expand(s, b, x.shape[-1]).reshape(s * b, -1)
        c = condition.expand(b, condition.shape[-1]).unsqueeze(0).expand(s, b, -1).reshape(s * b, -1)
        noise, lad = self._cascade(x, c, inverse=False)
        return (self._base_log_prob(noise) + lad).reshape(s, b)


# ----------------------------------------------------------------------------------- sbi's other families
# NLE, NRE-C, FMPE, NPSE and truncated sequential NPE (TSNPE), each trained through its sbi trainer
# (``sbi.inference.NLE_A / NRE_C / FMPE / NPSE / NPE_C``: ``append_simulations``, ``train``,
# ``build_posterior``), on conditions already in the prior box's logit coordinates z.

VECTOR_FIELDS = ("fmpe", "npse")
_U_EPS = 1e-6  # as flow_space: logit coordinates of (eps, 1 - eps)


def logistic_prior(n: int):
    """The uniform prior of the box in its logit coordinates z: n independent standard logistics,
    as the torch ``Distribution`` sbi's trainers and posteriors take (``sample``/``log_prob``)."""
    from torch.distributions import Independent, SigmoidTransform, TransformedDistribution, Uniform

    n = check_positive_int(n, "n")
    base = Uniform(torch.full((n,), _U_EPS), torch.full((n,), 1.0 - _U_EPS), validate_args=False)
    return Independent(TransformedDistribution(base, [SigmoidTransform().inv], validate_args=False), 1,
                       validate_args=False)


def _train(make_trainer, theta: torch.Tensor, x: torch.Tensor, seed: int, **train_kwargs):
    """Build an sbi trainer (seeded, inside ``fork_rng``), append (theta, x), train; (trainer,
    estimator, info with ``epochs``, ``best_validation_loss``, ``time_train``)."""
    check_sbi_version()
    t0 = time.perf_counter()
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        with _quiet():
            trainer = make_trainer()
            trainer.append_simulations(torch.as_tensor(theta).float(), torch.as_tensor(x).float())
            estimator = trainer.train(show_train_summary=False, **train_kwargs)
    summary = trainer.summary
    info = {"epochs": int(summary["epochs_trained"][-1]),
            "best_validation_loss": float(summary["best_validation_loss"][-1]),
            "time_train": time.perf_counter() - t0}
    return trainer, estimator, info


def _training(training_batch_size, learning_rate, validation_fraction, stop_after_epochs, max_epochs) -> dict:
    return {"training_batch_size": training_batch_size, "learning_rate": learning_rate,
            "validation_fraction": validation_fraction, "stop_after_epochs": stop_after_epochs,
            "max_num_epochs": max_epochs}


def train_nle(theta: torch.Tensor, x: torch.Tensor, *, seed: int, density_estimator: str = "maf",
              hidden_features: int = 50, num_transforms: int = 5, training_batch_size: int = 100,
              learning_rate: float = 1e-3, validation_fraction: float = 0.1, stop_after_epochs: int = 20,
              max_epochs: int = 200, device: str = "cpu") -> tuple[nn.Module, dict]:
    """sbi NLE (``NLE_A``): a conditional flow q(x | theta), z-scored inside. Returns (estimator on
    the CPU in eval mode, info); evaluate it with `nle_log_likelihood`. Global torch RNG untouched."""
    check_choice(density_estimator, FLOW_KINDS, "density_estimator")
    from sbi.inference import NLE_A
    from sbi.neural_nets import likelihood_nn

    def make():
        net = likelihood_nn(model=density_estimator, hidden_features=hidden_features, num_transforms=num_transforms)
        return NLE_A(prior=None, density_estimator=net, device=device, show_progress_bars=False,
                     tracker=_NullTracker())

    _, est, info = _train(make, theta, x, seed, **_training(training_batch_size, learning_rate, validation_fraction,
                                                            stop_after_epochs, max_epochs))
    return est.to("cpu").eval(), info


def new_nle_estimator(n_theta: int, n_x: int, *, density_estimator: str = "maf", hidden_features: int = 50,
                      num_transforms: int = 5) -> nn.Module:
    """An untrained estimator of the very architecture `train_nle` builds for these sizes, to receive
    a trained one's state dict (z-scoring statistics included: they are buffers). Built on stand-in
    data (fixed seed, global torch RNG untouched)."""
    check_sbi_version()
    check_choice(density_estimator, FLOW_KINDS, "density_estimator")
    from sbi.neural_nets import likelihood_nn

    n_theta, n_x = check_positive_int(n_theta, "n_theta"), check_positive_int(n_x, "n_x")
    with torch.random.fork_rng(devices=[]), _quiet():
        torch.manual_seed(0)
        builder = likelihood_nn(model=density_estimator, hidden_features=hidden_features,
                                num_transforms=num_transforms)
        net = builder(torch.randn(8, n_theta), torch.randn(8, n_x))
    return net.to("cpu").eval()


@torch.no_grad()
def nle_log_likelihood(estimator: nn.Module, x_obs: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """(N,) float64 log q(x_obs | theta_j) of a `train_nle` estimator for theta (N, d), x_obs (F,)."""
    theta = torch.as_tensor(theta, dtype=torch.float32)
    x = torch.as_tensor(x_obs, dtype=torch.float32).reshape(1, 1, -1).expand(1, theta.shape[0], -1)
    return estimator.log_prob(x, condition=theta).reshape(-1).double()


def train_nre(theta: torch.Tensor, x: torch.Tensor, *, seed: int, classifier: str = "resnet",
              hidden_features: int = 50, num_classes: int = 5, gamma: float = 1.0,
              training_batch_size: int = 200, learning_rate: float = 5e-4, validation_fraction: float = 0.1,
              stop_after_epochs: int = 20, max_epochs: int = 200, device: str = "cpu") -> tuple[nn.Module, dict]:
    """sbi NRE-C (``NRE_C``, Miller et al. 2022): a classifier whose logit estimates
    log p(x | theta) / p(x) up to a constant, z-scored inside, ``num_classes`` contrastive classes,
    ``gamma`` the odds of the joint class. Returns (estimator, info); evaluate with `nre_log_ratio`."""
    check_choice(classifier, ("linear", "mlp", "resnet"), "classifier")
    check_positive_int(num_classes, "num_classes")
    check_positive_float(gamma, "gamma")
    from sbi.inference import NRE_C
    from sbi.neural_nets import classifier_nn

    def make():
        return NRE_C(prior=None, classifier=classifier_nn(model=classifier, hidden_features=hidden_features),
                     device=device, show_progress_bars=False, tracker=_NullTracker())

    _, est, info = _train(make, theta, x, seed, num_classes=num_classes, gamma=gamma,
                          **_training(training_batch_size, learning_rate, validation_fraction, stop_after_epochs,
                                      max_epochs))
    return est.to("cpu").eval(), info


@torch.no_grad()
def nre_log_ratio(estimator: nn.Module, x_obs: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """(N,) float64 unnormalised log ratio of a `train_nre` estimator for theta (N, d), x_obs (F,)."""
    theta = torch.as_tensor(theta, dtype=torch.float32)
    x = torch.as_tensor(x_obs, dtype=torch.float32).reshape(1, -1).expand(theta.shape[0], -1)
    return estimator.unnormalized_log_ratio(theta, x).reshape(-1).double()


class VectorFieldDensity:
    """A trained FMPE or NPSE posterior q(theta | x) (sbi's ``VectorFieldPosterior``) seen as a flow:
    ``log_prob(input, condition)`` (probability-flow ODE, sbi's ``posterior.log_prob``) and
    ``sample(sample_shape, condition)`` (ODE sampling: the draws come from the very density that
    ``log_prob`` evaluates, so importance weights built on both are consistent). ``ode_kwargs``:
    the ODE solver's ``atol``, ``rtol`` and ``exact`` (trace), passed to sbi."""

    def __init__(self, posterior, dim: int, ode_kwargs: dict):
        self.posterior, self.dim, self.ode_kwargs = posterior, int(dim), dict(ode_kwargs)

    def eval(self):
        return self

    def log_prob(self, input: torch.Tensor, condition: torch.Tensor) -> torch.Tensor:  # noqa: A002 - sbi's name
        theta = torch.as_tensor(input, dtype=torch.float32).reshape(-1, self.dim)
        with _quiet():
            return self.posterior.log_prob(theta, x=torch.as_tensor(condition, dtype=torch.float32).reshape(1, -1),
                                           ode_kwargs=self.ode_kwargs).reshape(-1)

    @torch.no_grad()
    def sample(self, sample_shape, condition: torch.Tensor) -> torch.Tensor:
        with _quiet():
            return self.posterior.sample(sample_shape, x=torch.as_tensor(condition, dtype=torch.float32).reshape(1, -1),
                                         show_progress_bars=False)


def train_vector_field(kind: str, theta: torch.Tensor, x: torch.Tensor, *, seed: int, hidden_features: int = 64,
                       num_layers: int = 3, sde_type: str = "ve", training_batch_size: int = 200,
                       learning_rate: float = 5e-4, validation_fraction: float = 0.1, stop_after_epochs: int = 20,
                       max_epochs: int = 200, atol: float = 1e-4, rtol: float = 1e-3, exact: bool = True,
                       device: str = "cpu") -> tuple[VectorFieldDensity, dict]:
    """sbi FMPE (flow matching) or NPSE (score matching, ``sde_type`` "ve", "vp" or "subvp") of
    q(theta | x) with an MLP vector field, under the logistic prior of ``theta``'s logit
    coordinates (`logistic_prior`). Returns (`VectorFieldDensity`, info)."""
    check_choice(kind, VECTOR_FIELDS, "kind")
    check_choice(sde_type, ("ve", "vp", "subvp"), "sde_type")
    from sbi.inference import FMPE, NPSE
    from sbi.neural_nets import posterior_flow_nn, posterior_score_nn

    prior = logistic_prior(int(theta.shape[1]))

    def make():
        common = {"model": "mlp", "hidden_features": hidden_features, "num_layers": num_layers}
        if kind == "fmpe":
            return FMPE(prior=prior, vf_estimator=posterior_flow_nn(**common), device=device,
                        show_progress_bars=False, tracker=_NullTracker())
        return NPSE(prior=prior, vf_estimator=posterior_score_nn(sde_type=sde_type, **common), sde_type=sde_type,
                    device=device, show_progress_bars=False, tracker=_NullTracker())

    trainer, est, info = _train(make, theta, x, seed, **_training(training_batch_size, learning_rate,
                                                                  validation_fraction, stop_after_epochs, max_epochs))
    with _quiet():
        posterior = trainer.build_posterior(est.to("cpu").eval(), prior=prior, sample_with="ode")
    return VectorFieldDensity(posterior, theta.shape[1], {"atol": atol, "rtol": rtol, "exact": exact}), info


def train_tsnpe(theta: torch.Tensor, x: torch.Tensor, x_obs: torch.Tensor, simulate, *, rounds: int,
                round_size: int, seed: int, quantile: float = 1e-4, support_samples: int = 10000,
                min_acceptance: float = 1e-3, density_estimator: str = "maf", hidden_features: int = 50,
                num_transforms: int = 5, training_batch_size: int = 100, learning_rate: float = 1e-3,
                validation_fraction: float = 0.1, stop_after_epochs: int = 20, max_epochs: int = 200,
                device: str = "cpu") -> tuple[nn.Module, dict]:
    """Truncated sequential NPE (Deistler et al. 2022) with sbi's ``NPE_C``, ``get_density_thresholder``
    and ``RestrictedPrior``, in the logit coordinates (logistic prior, `logistic_prior`).

    Round 0 trains on the caller's prior draws (``theta``, ``x``). Each of the ``rounds`` - 1 later
    rounds truncates the prior to the current posterior's highest-density region holding all but
    ``quantile`` of its mass (threshold estimated from ``support_samples`` posterior draws), draws
    ``round_size`` parameters from it, gets their summaries from ``simulate(theta (m, d)) -> x (m, F)``
    (the caller simulates and counts) and retrains on everything so far (``force_first_round_loss``:
    proposals that are the prior truncated need no correction). Drawing from the truncated prior is by
    rejection from the prior while its acceptance (measured on ``support_samples`` prior draws) is at
    least ``min_acceptance``; below that by sampling-importance-resampling from the posterior (bounded
    time, never a hang). Returns (the last round's estimator q(theta | x), info: per-round ``epochs``,
    ``acceptance``, ``truncation``)."""
    rounds = check_positive_int(rounds, "rounds")
    round_size = check_positive_int(round_size, "round_size", minimum=2)
    check_positive_float(quantile, "quantile")
    support_samples = check_positive_int(support_samples, "support_samples", minimum=100)
    if not callable(simulate):
        raise TypeError(f"simulate: expected a callable, got {type(simulate).__name__}")
    check_sbi_version()
    from sbi.inference import NPE_C
    from sbi.neural_nets import posterior_nn
    from sbi.utils import RestrictedPrior, get_density_thresholder

    t0 = time.perf_counter()
    prior = logistic_prior(int(theta.shape[1]))
    x_obs = torch.as_tensor(x_obs, dtype=torch.float32).reshape(1, -1)
    train_kwargs = _training(training_batch_size, learning_rate, validation_fraction, stop_after_epochs, max_epochs)
    rounds_info = []
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        with _quiet():
            net = posterior_nn(model=density_estimator, hidden_features=hidden_features, num_transforms=num_transforms,
                               z_score_theta="independent", z_score_x="independent")
            trainer = NPE_C(prior=prior, density_estimator=net, device=device, show_progress_bars=False,
                            tracker=_NullTracker())
            trainer.append_simulations(torch.as_tensor(theta).float(), torch.as_tensor(x).float())
            estimator = trainer.train(show_train_summary=False, **train_kwargs)
        rounds_info.append({"round": 0, "n": int(theta.shape[0]), "truncation": "prior"})
        for r in range(1, rounds):
            with _quiet(), contextlib.redirect_stderr(io.StringIO()):  # sbi's sampling progress bars
                posterior = trainer.build_posterior(estimator, prior=prior).set_default_x(x_obs)
                inside = get_density_thresholder(posterior, quantile=quantile,
                                                 num_samples_to_estimate_support=support_samples)
                acceptance = float(inside(prior.sample((support_samples,))).float().mean())
                how = "rejection" if acceptance >= min_acceptance else "sir"
                restricted = RestrictedPrior(prior, inside, posterior=posterior, sample_with=how)
                draws = restricted.sample((round_size,), show_progress_bars=False, print_rejected_frac=False,
                                          oversampling_factor=32)
            x_new = torch.as_tensor(simulate(draws.double()))
            with _quiet():
                trainer.append_simulations(draws.float(), x_new.float())
                estimator = trainer.train(show_train_summary=False, force_first_round_loss=True, **train_kwargs)
            rounds_info.append({"round": r, "n": int(draws.shape[0]), "truncation": how,
                                "prior_acceptance": acceptance})
    summary = trainer.summary
    info = {"epochs": [int(e) for e in summary["epochs_trained"]],
            "best_validation_loss": float(summary["best_validation_loss"][-1]),
            "rounds": rounds_info, "time_train": time.perf_counter() - t0}
    return estimator.to("cpu").eval(), info
