"""Achieved per-bound binding share on the test goals of `reproduce panda --setting informative --runs 30` (seed 0).

    PYTHONPATH=. python docs/studies/binding_per_bound.py panda|human

For each run's subject: the least, over its restricted bounds, share of the 20 held-out reaches
that relaxing that bound alone moves by > 1 mm (`binding_test_bound_min_fraction`).
"""

import sys

import numpy as np

from camo_sbi._validation import derive_seed
from camo_sbi.experiments.models import ModelSpec, subject_limits
from camo_sbi.experiments.reproduce_panda import SETTINGS
from camo_sbi.scenarios.reaching import make_reaching_task, task_binding_metrics

model = ModelSpec(kind=sys.argv[1])
sim = model.build()
subjects = list(SETTINGS["informative"].subjects)
vals = {s: [] for s in subjects}
for run in range(30):
    s = subjects[run % len(subjects)]
    th = subject_limits(model, sim, s)
    task = make_reaching_task(sim, th, n_train=10, n_test=20, seed=derive_seed(0, run), workspace="nominal",
                              min_binding_test=0.5)
    vals[s].append(task_binding_metrics(task)["binding_test_bound_min_fraction"])
for s, v in vals.items():
    print(f"{sys.argv[1]} {s}: least per-bound binding fraction over restricted bounds: mean {np.mean(v):.2f}, "
          f"min {np.min(v):.2f}, runs with >= 0.5: {sum(x >= 0.5 for x in v)}/{len(v)}")
