"""The networks of the amortized estimator (`amortized`): sbi flows on standardised coordinates.

`Flow`: a per-reach flow q(z | x), inputs and conditions standardised with stored training
statistics. `SetFlow`: q(z | {x_1..x_k}) behind a permutation-invariant set embedding, trained
jointly. `new_flow` builds either, untrained (through sbi) or as `sbi_adapter.NsfReader` for
loading (no sbi import). Apart from `amortized` because the file format (`amortized_estimator`)
and training both build them.
"""

from __future__ import annotations

import torch
from torch import nn

from camo_sbi.inference import sbi_adapter

__all__ = ["SET_EMBEDDING", "Flow", "SetFlow", "new_flow", "uses_reader"]


class Flow(nn.Module):
    """An sbi flow q(z' | x') on standardised coordinates, exposed on raw ones.

    z' = (z - z_mean) / z_std, x' = (x - x_mean) / x_std (statistics of the training set,
    stored as buffers); ``log_prob`` includes the Jacobian of the z standardisation. Same
    interface as an sbi density estimator: ``log_prob(input, condition)``, ``sample(shape,
    condition)``, ``loss(input, condition)``.
    """

    def __init__(self, net: nn.Module, n_inputs: int, n_conditions: int):
        super().__init__()
        self.net = net
        self.register_buffer("z_mean", torch.zeros(n_inputs))
        self.register_buffer("z_std", torch.ones(n_inputs))
        self.register_buffer("x_mean", torch.zeros(n_conditions))
        self.register_buffer("x_std", torch.ones(n_conditions))

    def set_statistics(self, z: torch.Tensor, x: torch.Tensor) -> None:
        self.z_mean.copy_(z.mean(0))
        self.z_std.copy_(z.std(0).clamp_min(1e-6))
        self.x_mean.copy_(x.mean(0))
        self.x_std.copy_(x.std(0).clamp_min(1e-6))

    def _x(self, condition):
        return (condition.to(torch.float32) - self.x_mean) / self.x_std

    def log_prob(self, input, condition):  # noqa: A002 - sbi's argument name
        zs = (input.to(torch.float32) - self.z_mean) / self.z_std
        return self.net.log_prob(zs, self._x(condition)) - torch.log(self.z_std).sum()

    def loss(self, input, condition):  # noqa: A002
        return -self.log_prob(input, condition)

    def sample(self, sample_shape, condition):
        return self.net.sample(torch.Size(sample_shape), self._x(condition)) * self.z_std + self.z_mean


class SetFlow(nn.Module):
    """q(z | {x_1..x_k}): a permutation-invariant set embedding feeding an sbi flow; trained jointly.

    The embedding of a set of k reaches (features standardised with stored statistics, x'):
    Linear([mean x', max x', min x', mean phi(x'), k / K]), with phi a per-reach MLP. The
    raw pooled features come first because a limit shows in the extreme postures over the
    reaches; a DeepSet of the MLP features alone (mean-pooled, the first design) learned
    far less (``benchmarks/ablate_set_embedding.py``; docs/studies/amortized_measurements.md).

    Conditions are packed as (B, K * (F + 1)): K = max_set reaches of F raw features, each
    followed by a validity flag (1: a reach of the set, 0: padding). In training mode ``loss``
    redraws every example's subset (size uniform on 1..K among its valid reaches) from the global
    torch RNG, which `sbi_adapter.fit_density_estimator` seeds inside ``fork_rng``: each epoch sees
    new sets. In eval mode (validation, inference) the stored flags are used.
    """

    def __init__(self, net: nn.Module, n_inputs: int, n_features: int, max_set: int, hidden: int = 128,
                 embed: int = 64):
        super().__init__()
        self.net, self.n_features, self.max_set = net, n_features, max_set
        self.phi = nn.Sequential(nn.Linear(n_features, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                                 nn.Linear(hidden, embed))
        self.rho = nn.Linear(3 * n_features + embed + 1, embed)
        self.register_buffer("z_mean", torch.zeros(n_inputs))
        self.register_buffer("z_std", torch.ones(n_inputs))
        self.register_buffer("x_mean", torch.zeros(n_features))
        self.register_buffer("x_std", torch.ones(n_features))

    set_statistics = Flow.set_statistics

    @staticmethod
    def pack(sets: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """(B, K, F) reaches and (B, K) bool validity -> (B, K * (F + 1)) float32 conditions."""
        return torch.cat([sets.to(torch.float32), valid.to(torch.float32).unsqueeze(-1)], -1).flatten(1)

    def _unpack(self, condition):
        c = condition.to(torch.float32).reshape(condition.shape[0], self.max_set, self.n_features + 1)
        return c[..., :-1], c[..., -1] > 0.5

    def embed(self, condition) -> torch.Tensor:
        sets, valid = self._unpack(condition)
        if self.training:  # a new random subset of each example's valid reaches
            k = torch.randint(1, self.max_set + 1, (sets.shape[0], 1))
            k = torch.minimum(k, valid.sum(1, keepdim=True))
            rank = torch.argsort(torch.argsort(torch.rand(valid.shape) + (~valid).float(), dim=1), dim=1)
            valid = rank < k
        xs = (sets - self.x_mean) / self.x_std
        v = valid.unsqueeze(-1)
        w = v.to(torch.float32)
        n = w.sum(1).clamp_min(1.0)
        pooled = [(xs * w).sum(1) / n, torch.where(v, xs, -1e4).amax(1), torch.where(v, xs, 1e4).amin(1),
                  (self.phi(xs) * w).sum(1) / n, w.sum(1) / self.max_set]
        return self.rho(torch.cat(pooled, -1))

    def log_prob(self, input, condition):  # noqa: A002
        zs = (input.to(torch.float32) - self.z_mean) / self.z_std
        return self.net.log_prob(zs, self.embed(condition)) - torch.log(self.z_std).sum()

    def loss(self, input, condition):  # noqa: A002
        return -self.log_prob(input, condition)

    def sample(self, sample_shape, condition):
        return self.net.sample(torch.Size(sample_shape), self.embed(condition)) * self.z_std + self.z_mean

    def sample_and_log_prob(self, sample_shape, condition):
        """Draws (raw z) and their log densities in one pass of the flow (sbi's
        ``sample_and_log_prob``; a MAF's inverse yields its log-determinant, so no second pass)."""
        zs, lp = self.net.sample_and_log_prob(torch.Size(sample_shape), self.embed(condition))
        return zs * self.z_std + self.z_mean, lp - torch.log(self.z_std).sum()


SET_EMBED = 64
# the set embedding's architecture, written to a set-form file's metadata; files of an
# earlier (or later) embedding are refused with a message, never half-loaded
SET_EMBEDDING = "pooled-mean-max-min-phi/1"


def new_flow(settings, n_inputs: int, n_conditions: int, seed: int, *,
              reader: bool = False) -> nn.Module:
    """The untrained flow of ``settings.form``; ``n_conditions``: features per reach.

    ``reader``: the NSF built as `sbi_adapter.NsfReader` (inference only, no sbi import; the
    weights must then be loaded), else sbi's trainable flow."""
    is_set = settings.form == "set"
    if reader:
        net = sbi_adapter.NsfReader(n_inputs, SET_EMBED if is_set else n_conditions,
                                    hidden_features=settings.hidden_features,
                                    num_transforms=settings.num_transforms)
    else:
        net = sbi_adapter.build_flow(settings.density_estimator, n_inputs, SET_EMBED if is_set else n_conditions,
                                     hidden_features=settings.hidden_features,
                                     num_transforms=settings.num_transforms,
                                     embedding_dim=None if is_set else settings.embedding_dim,
                                     embedding_hidden=settings.embedding_hidden, seed=seed)
    if not is_set:
        return Flow(net, n_inputs, n_conditions)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed + 1)
        return SetFlow(net, n_inputs, n_conditions, settings.max_set, settings.embedding_hidden, SET_EMBED)


def uses_reader(settings, n_inputs: int) -> bool:
    """Whether a loaded flow is evaluated by `sbi_adapter.NsfReader`: an NSF of 2+ inputs (sbi builds
    a one-input NSF differently) without an sbi embedding net."""
    return (settings.density_estimator == "nsf" and n_inputs > 1
            and (settings.form == "set" or settings.embedding_dim is None))
