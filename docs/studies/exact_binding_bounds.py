"""The exact posterior on the binding bounds, touched and untouched apart (issue 35 item 4).

    PYTHONPATH=. python docs/studies/exact_binding_bounds.py panda 5 7 --out docs/studies/exact_binding_panda_s7.csv
    PYTHONPATH=. python docs/studies/exact_binding_bounds.py panda 4 7 --methods abc-smc,npe,nle --out OTHER.csv
    (add --resume to keep the runs OTHER.csv already holds after a kill)

``--methods`` (default: exact-likelihood, naive, camo-seq) runs other registered methods on the
very same runs (same subjects, reaches, noise and method seed), so their rows can be written to
a file of their own and read beside the first.

Informative setting (`reproduce panda --setting informative`'s design: the model's informative
subjects cycled over runs, 10 training reaches from the nominal workspace, 20 held-out goals of
which at least half bind), with observation noise 1 deg / 5 mm on every recorded value (the
exact likelihood needs a noise model; every reach's start is exact). Per run (task seed
``derive_seed(SEED, run)``, noise ``derive_seed(SEED, run, "observation-noise")``): the binding
bounds of the held-out reaches (`binding_bounds`), each split into TOUCHED (the noise-free
training reaches reach it: their observed extreme equals the true limit) and UNTOUCHED; the
error of each method's estimate on them (exact-likelihood: the posterior median; naive: the
observed min/max after its noise filter; camo-seq: its argmax) and whether its 90 % central
interval (`weighted_quantile` 0.05 / 0.95; a point estimate has none) covers the truth.
Writes one row per (run, method, binding bound) and prints the summary.
"""

import argparse
import os
import sys
import time

import numpy as np
import pandas as pd

from camo_sbi._validation import derive_seed
from camo_sbi.evaluation.metrics import binding_bounds
from camo_sbi.experiments.models import ModelSpec, subject_limits
from camo_sbi.experiments.reference import reference_task
from camo_sbi.experiments.reproduce_panda import SETTINGS, method_config
from camo_sbi.inference.registry import get_method, run_method
from camo_sbi.inference.result import weighted_quantile
from camo_sbi.scenarios.reaching import make_reaching_task
from camo_sbi.simulators.registry import get_model
from camo_sbi.task import NoiseModel

METHODS = ("exact-likelihood", "naive", "camo-seq")
NOISE = NoiseModel(joint_deg=1.0, ee_mm=5.0)


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("model")
    p.add_argument("runs", type=int)
    p.add_argument("seed", type=int)
    p.add_argument("--particles", type=int, default=1000)
    p.add_argument("--moves", type=int, default=10)
    p.add_argument("--mcmc-steps", type=int, default=40)
    p.add_argument("--methods", default=",".join(METHODS), help="comma-separated registered methods")
    p.add_argument("--budget", type=int, default=2000, help="simulations per reach")
    p.add_argument("--out", required=True)
    p.add_argument("--resume", action="store_true",
                   help="keep the runs --out already holds for every method (same model and seed) and skip them")
    a = p.parse_args()
    methods = [m for m in a.methods.split(",") if m]
    for m in methods:
        get_method(m)  # an unknown name fails here, before any run
    model = ModelSpec(kind=a.model)
    sim = model.build()
    subjects = list(get_model(a.model).informative)
    st = SETTINGS["informative"]
    cfg_args = argparse.Namespace(setting="informative", keep_best=None, bandwidth=None, bandwidth_mode=None,
                                  sampling=None, epsilon=None, scheduler=None)
    rows, done = [], set()
    if a.resume and os.path.exists(a.out):
        old = pd.read_csv(a.out)
        if not old.empty and (set(old.model) != {a.model} or set(old.seed) != {a.seed}):
            raise ValueError(f"--resume: {a.out} holds another model or seed")
        done = {int(r) for r, g in old.groupby("run") if set(methods) <= set(g.method)}
        rows = old[old.run.isin(done) & old.method.isin(methods)].to_dict("records")
        print(f"resuming: runs {sorted(done)} kept from {a.out}", flush=True)
    for run in range(a.runs):
        if run in done:
            continue
        subject = subjects[run % len(subjects)]
        truth = subject_limits(model, sim, subject).numpy()
        clean = make_reaching_task(sim, subject_limits(model, sim, subject), n_train=10, n_test=20,
                                   seed=derive_seed(a.seed, run), workspace=st.workspace,
                                   min_binding_test=st.min_binding_test)
        task = reference_task(sim, model, subject, run, setting="informative", tasks=10, test_goals=20, noise=NOISE,
                              base_seed=a.seed)
        binding = binding_bounds(sim, clean.true_theta, clean.test_starts, clean.test_goals, clean.prior)
        allq = np.concatenate([o.q.numpy() for o in clean.observations])
        ext = np.stack([allq.min(0), allq.max(0)], 1).reshape(-1)
        touched = np.abs(ext - truth) < 1e-9
        for m in methods:
            cfg = {"particles": a.particles, "moves": a.moves, "mcmc_steps": a.mcmc_steps} \
                if get_method(m).capabilities.exact else method_config(m, cfg_args)
            t0 = time.perf_counter()
            r = run_method(m, task, budget=a.budget, seed=derive_seed(a.seed, run, 1), config=cfg)
            lo90, hi90 = (weighted_quantile(r.samples, r.weights, q) for q in (0.05, 0.95))
            for b in np.flatnonzero(binding):
                rows.append({"model": a.model, "seed": a.seed, "run": run, "subject": subject, "method": m,
                             "bound": int(b), "touched": bool(touched[b]),
                             "error_deg": float(np.degrees(abs(r.estimate[b] - truth[b]))),
                             "covered90": bool(lo90[b] <= truth[b] <= hi90[b]) if r.samples.shape[0] > 1 else None,
                             "interval90_deg": float(np.degrees(hi90[b] - lo90[b])),
                             "status": r.status, "n_simulations": r.n_simulations,
                             "seconds": time.perf_counter() - t0})
        print(f"run {run} {subject}: {int(binding.sum())} binding bounds, {int((binding & touched).sum())} touched",
              flush=True)
        pd.DataFrame(rows).to_csv(a.out + ".tmp", index=False)
        os.replace(a.out + ".tmp", a.out)
    df = pd.DataFrame(rows)
    for (m, t), g in df.groupby(["method", "touched"]):
        cov = g.covered90.dropna()
        print(f"{m:17s} {'touched  ' if t else 'untouched'} n={len(g):3d} mean |error| {g.error_deg.mean():6.2f} deg "
              f"median {g.error_deg.median():6.2f}; 90% coverage "
              f"{'-' if cov.empty else f'{cov.astype(float).mean():.2f}'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
