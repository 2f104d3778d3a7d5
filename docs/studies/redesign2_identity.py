"""Before/after "samplers apart from estimators" (issue 26, item 1): the same Panda task, methods,
samplers and seeds under the base commit (d128a24, samplers inside `npe.NpePosterior`) and under
the branch (samplers in `camo_sbi.inference.samplers`). Every estimate and a sha256 of every
sample, weight and log-density array are dumped to JSON; the two files must be equal.

    git -C /work/main worktree add /tmp/i26a_base d128a24
    cd /tmp/i26a_base && OMP_NUM_THREADS=1 PYTHONPATH=/tmp/i26a_base \
        /work/main/.venv/bin/python /work/wt/i26a/docs/studies/redesign2_identity.py /tmp/id2_base.json
    cd /work/wt/i26a && OMP_NUM_THREADS=1 PYTHONPATH=/work/wt/i26a \
        /work/main/.venv/bin/python docs/studies/redesign2_identity.py /tmp/id2_branch.json
    cmp /tmp/id2_base.json /tmp/id2_branch.json && echo identical

Covered: every registered method cheap enough here (camo, camo-js, camo-cs, camo-hull, camo-seq,
camo-seq-cs, camo-touched, naive, nominal, oracle, abc-smc, npe with its importance sampler as
`run` uses it, and the fitted posterior sampled by importance sampling, population MCMC and
tempered SMC), and npe-amortized with a tiny per-reach estimator (combine = mcmc, is, smc) and
a tiny set-form one, trained in the script on the Panda. Task: Panda, subject
shoulder_restricted, 3 train / 5 test reaches, budget 300, seeds 0 and 1.

Measured 2026-12-05 (2-core machine, branch i26a at the samplers commit): the two JSON files
are byte-identical (``cmp``: identical; 40 entries): every estimate, status and sha256 of
samples + weights (+ log densities for the posterior samplers) agrees bit for bit, for both
seeds. A second run of the base gave the same file, so the comparison is not luck of the
moment. (The flows are tiny and briefly trained: the point is identity, not accuracy.)

Measured again 2026-12-05 on main after the whole of issue 26's second step (samplers, the
body-model registry, the metric catalog, named seed streams, declared budget rules, the
unified vocabulary: ``point_estimate``/"mode", ``chunk_size``, ``estimator_path``,
``max_simulations``, ``trajectory_summary``; then again after the grid runner, the jinja2
report and scipy's bootstrap), the script run from main's tree against d128a24:

    cd /tmp/i26a_base && OMP_NUM_THREADS=1 PYTHONPATH=/tmp/i26a_base \
        /work/main/.venv/bin/python /work/main/docs/studies/redesign2_identity.py /tmp/id2_base_now.json
    cd /work/main && OMP_NUM_THREADS=1 PYTHONPATH=/work/main \
        .venv/bin/python docs/studies/redesign2_identity.py /tmp/id2_main_now.json
    cmp /tmp/id2_base_now.json /tmp/id2_main_now.json   # identical, 40 entries
"""
import hashlib
import json
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

warnings.simplefilter("ignore")
from camo_sbi.experiments.subjects import subject_theta  # noqa: E402
from camo_sbi.inference import amortized, npe  # noqa: E402
from camo_sbi.inference.registry import run_method  # noqa: E402
from camo_sbi.scenarios.reaching import make_reaching_task  # noqa: E402
from camo_sbi.simulators import panda  # noqa: E402

# the config field naming the estimator file: "estimator" before the unified vocabulary, then "estimator_path"
EST = "estimator_path" if "estimator_path" in amortized.AmortizedConfig.__dataclass_fields__ else "estimator"


def digest(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        if a is None:
            h.update(b"None")
            continue
        a = np.ascontiguousarray(np.asarray(a))
        h.update(f"{a.dtype}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def result_entry(r) -> dict:
    return {"estimate": [float(v) for v in r.estimate], "status": r.status,
            "samples": digest(r.samples, r.weights)}


def draws_entry(d) -> dict:
    """Base: ImportanceSample / McmcSample / SmcSample (numpy theta, log_prob); branch:
    samplers.WeightedDraws (torch samples, log_density)."""
    if hasattr(d, "theta"):
        theta, w, lp = d.theta, d.weights, d.log_prob
    else:
        theta, w, lp = d.samples.numpy(), d.weights.numpy(), d.log_density.numpy()
    return {"mean": [float(v) for v in np.asarray(w) @ np.asarray(theta)], "draws": digest(theta, w, lp)}


sim = panda()
theta = subject_theta(sim, "panda", "shoulder_restricted")
out = {}
tmp = Path(tempfile.mkdtemp())
TINY = dict(simulations=600, max_epochs=3, hidden_features=8, num_transforms=1, training_batch_size=50)
est_paths = {}
for form in ("per-reach", "set"):
    est_paths[form] = tmp / f"panda-{form}.pt"
    amortized.train(sim, model="panda", config=amortized.TrainConfig(form=form, **TINY), seed=0).save(est_paths[form])
for seed in (0, 1):
    task = make_reaching_task(sim, theta, n_train=3, n_test=5, seed=seed)
    for label, name, cfg in (
        ("camo", "camo", None), ("camo-cs", "camo-cs", None), ("camo-js", "camo-js", None),
        ("camo-hull", "camo-hull", None), ("camo-seq", "camo-seq", None), ("camo-seq-cs", "camo-seq-cs", None),
        ("camo-touched", "camo-touched", None), ("naive", "naive", None), ("nominal", "nominal", None),
        ("oracle", "oracle", None), ("abc-smc", "abc-smc", None), ("npe", "npe", {"max_epochs": 30}),
    ):
        out[f"{label}/{seed}"] = result_entry(run_method(name, task, budget=300, seed=seed, config=cfg))
        print(label, seed, flush=True)
    post, _ = npe.fit(task, task.observations, budget=300, seed=seed, config=npe.NpeConfig(max_epochs=30))
    out[f"npe-posterior-is/{seed}"] = draws_entry(post.sample_is(2000, seed, is_rounds=2))
    out[f"npe-posterior-mcmc/{seed}"] = draws_entry(post.sample_mcmc(2000, seed, chains=64, steps=60, burn_in=30))
    for base in ("mixture", "gaussian"):
        out[f"npe-posterior-smc-{base}/{seed}"] = draws_entry(post.sample_smc(seed, particles=256, base=base))
    for combine in ("mcmc", "is", "smc"):
        cfg = {EST: str(est_paths["per-reach"]), "combine": combine, "n_posterior_samples": 2000,
               "mcmc_steps": 60, "mcmc_burn_in": 30, "smc_particles": 256}
        out[f"npe-amortized-{combine}/{seed}"] = result_entry(run_method("npe-amortized", task, budget=1, seed=seed,
                                                                          config=cfg))
    out[f"npe-amortized-set/{seed}"] = result_entry(run_method(
        "npe-amortized", task, budget=1, seed=seed, config={EST: str(est_paths["set"]),
                                                             "n_posterior_samples": 2000}))
    print("posterior + amortized", seed, flush=True)
Path(sys.argv[1]).write_text(json.dumps(out, indent=1, sort_keys=True))
print("done", len(out), "entries")
