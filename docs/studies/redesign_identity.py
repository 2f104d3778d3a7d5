"""Before/after the redesign: the same task, methods and seeds under the old code (commit
c375cd7, before the Task contract, the registry and the distances package) and the new one.

    git worktree add /tmp/old c375cd7
    PYTHONPATH=/tmp/old .venv/bin/python docs/studies/redesign_identity.py /tmp/id_old.json
    .venv/bin/python docs/studies/redesign_identity.py /tmp/id_new.json
    # then compare the two JSON files (estimates per method and seed)

Measured 2026-12-01: every estimate (camo-cs, camo-js, camo-hull, naive, abc-smc, npe; two
seeds; 3 tasks, budget 300) is bit-identical between the two.
"""
import sys, json, warnings, numpy as np, torch
warnings.simplefilter("ignore")
from camo_sbi.simulators import panda
from camo_sbi.scenarios.reaching import make_reaching_task
try:
    from camo_sbi.inference.registry import run_method
    new = True
except ImportError:
    from camo_sbi.inference.methods import run_method
    new = False
try:
    from camo_sbi.experiments.subjects import subject_theta
except ImportError:
    from camo_sbi.experiments.subjects import subject_theta
sim = panda()
theta = subject_theta(sim, "panda", "shoulder_restricted")
out = {}
for seed in (0, 1):
    task = make_reaching_task(sim, theta, n_train=3, n_test=5, seed=seed)
    for label, name, cfg in (("camo-cs", "camo", {"space": "cartesian"}), ("camo-js", "camo", {"space": "joint"}),
                             ("camo-hull", "camo", {"contain_observed": True}), ("naive", "naive", None),
                             ("abc-smc", "abc-smc", None), ("npe", "npe", {"max_epochs": 30})):
        r = run_method(name, task, budget=300, seed=seed, config=cfg)
        out[f"{label}/{seed}"] = [float(v) for v in r.estimate]
json.dump(out, open(sys.argv[1], "w"))
print("new" if new else "old", "done")
