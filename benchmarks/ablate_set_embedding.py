"""Which set embedding lets the set-form flow learn: validation loss of four embeddings, same data, same flow.

    python benchmarks/ablate_set_embedding.py [--model panda] [--sets 3000] [--epochs 30] [--flow maf]

Simulates ``--sets`` sets of 10 reaches (the training design of `amortized.simulate_training_set`),
then trains the same flow behind each embedding, every set always complete (no subset redraw),
and prints the best validation loss in nats (lower is better; the prior's in these logit
coordinates is 2 nats per free limit, 28.0 for the Panda):

- ``mlp-mean``: the first design, a DeepSet: mean over reaches of a per-reach MLP, then an MLP;
- ``linear-mean``: a linear layer on the mean of the standardised reach features;
- ``pooled``: a linear layer on their mean, max and min;
- ``pooled+mlp``: pooled plus the MLP's mean (`amortized_flows.SetFlow`, the shipped embedding).

Measured (Panda, 3000 sets, 30 epochs, MAF, 2 loaded cores): mlp-mean 27.93, linear-mean 21.16,
pooled 20.32, pooled+mlp 20.26.
"""

from __future__ import annotations

import argparse
import types

import torch
from torch import nn


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--model", default="panda")
    p.add_argument("--sets", type=int, default=3000)
    p.add_argument("--epochs", type=int, default=30)
    p.add_argument("--flow", default="maf")
    args = p.parse_args()

    from camo_sbi.experiments.subjects import build_model
    from camo_sbi.inference import amortized as A
    from camo_sbi.inference import amortized_flows as F
    from camo_sbi.inference import flow_space, sbi_adapter
    from camo_sbi.priors import BoxPrior

    torch.set_num_threads(1)
    sim = build_model(args.model)
    prior = BoxPrior(sim.bounds, sim.start)
    cfg = A.TrainConfig(simulations=10 * args.sets, form="set", density_estimator=args.flow)
    data = A.simulate_training_set(sim, prior, cfg, 0)
    lo, w = prior.low[prior.free_mask], (prior.high - prior.low)[prior.free_mask]
    z = flow_space.to_unconstrained(data["theta"][:, prior.free_mask], lo, w, "logit").float()
    x = data["x"]["joint"]
    reaches = x.reshape(-1, x.shape[-1])
    keep = reaches.std(0) > 1e-8 * (1 + reaches.abs().amax(0))
    n_f = int(keep.sum())
    cond = F.SetFlow.pack(x[..., keep], torch.ones(x.shape[:2], dtype=torch.bool))

    def standardised(self, condition):
        sets, _ = self._unpack(condition)
        return (sets - self.x_mean) / self.x_std

    variants = {
        "mlp-mean": (nn.Sequential(nn.Linear(64 + 1, 128), nn.ReLU(), nn.Linear(128, 64)),
                     lambda self, xs: [self.phi(xs).mean(1), torch.ones(xs.shape[0], 1)]),
        "linear-mean": (nn.Linear(n_f, 64), lambda self, xs: [xs.mean(1)]),
        "pooled": (nn.Linear(3 * n_f, 64), lambda self, xs: [xs.mean(1), xs.amax(1), xs.amin(1)]),
        "pooled+mlp": (None, None),  # the shipped SetFlow.embed
    }
    print(f"{args.model}: {args.sets} sets x 10 reaches, {n_f} features per reach, {args.flow}, {args.epochs} epochs")
    for name, (rho, parts) in variants.items():
        flow = F.new_flow(cfg, z.shape[1], n_f, 1)
        flow.set_statistics(z, reaches[:, keep].float())
        flow.train = types.MethodType(lambda self, mode=True: nn.Module.train(self, False), flow)  # complete sets
        if rho is not None:
            flow.rho = rho

            def embed(self, condition, parts=parts):
                return self.rho(torch.cat(parts(self, standardised(self, condition)), -1))

            flow.embed = types.MethodType(embed, flow)
        info = sbi_adapter.fit_density_estimator(flow, z, cond, seed=1, batch_size=51, max_epochs=args.epochs,
                                                 stop_after_epochs=args.epochs, validation_fraction=0.05)
        print(f"{name:12s} best validation loss {info['best_validation_loss']:.2f} nats ({info['epochs']} epochs)")


if __name__ == "__main__":
    main()
