"""Trial (issue 23 item 4, not a registered method): camo-seq with the touched bounds CONDITIONED on
(fixed in the prior before inference) against camo-touched (fixed after) and naive, binding-bound
error after 10 reaches on the first RUNS runs of `reproduce panda --setting informative`.

    PYTHONPATH=. python docs/studies/touched_conditioned.py panda 10

A study only: `BoxPrior` has no per-bound "known" API (``fixed`` is per joint), so this sets the
touched coordinates' low = high on a fresh prior's tensors directly.
"""
import argparse
import dataclasses
import sys

import numpy as np
import torch

from camo_sbi._validation import derive_seed
from camo_sbi.evaluation.metrics import binding_bounds
from camo_sbi.experiments.models import ModelSpec, subject_limits
from camo_sbi.experiments.reproduce_panda import SETTINGS, method_config
from camo_sbi.inference.registry import run_method
from camo_sbi.inference.touched import touched_bounds
from camo_sbi.priors import BoxPrior
from camo_sbi.scenarios.reaching import make_reaching_task

model = ModelSpec(kind=sys.argv[1])
sim = model.build()
st = SETTINGS["informative"]
args = argparse.Namespace(setting="informative", keep_best=None, bandwidth=None, bandwidth_mode=None, sampling=None, epsilon=None, scheduler=None)
res = {k: [] for k in ("naive", "camo-touched", "conditioned")}
for run in range(int(sys.argv[2])):
    subject = st.subjects[run % 2]
    truth = subject_limits(model, sim, subject)
    task = make_reaching_task(sim, truth, n_train=10, n_test=20, seed=derive_seed(0, run), workspace="nominal", min_binding_test=0.5)
    b = binding_bounds(sim, truth, task.test_starts, task.test_goals, task.prior)
    touched, ext = touched_bounds([o.q for o in task.observations])
    p = BoxPrior(sim.bounds, sim.start)
    idx = torch.as_tensor(np.flatnonzero(touched))
    p.low[idx] = torch.as_tensor(ext[touched])
    p.high[idx] = torch.as_tensor(ext[touched])
    p.free_mask = p.high > p.low
    ctask = dataclasses.replace(task, prior=p)
    for name, t, m in (("naive", task, "naive"), ("camo-touched", task, "camo-touched"), ("conditioned", ctask, "camo-seq")):
        r = run_method(m, t, budget=2000, seed=derive_seed(0, run, 1), config=method_config(m, args))
        e = np.degrees(np.abs(r.estimate - truth.numpy()))
        res[name].append(e[b].mean())
    print(run, {k: round(v[-1], 2) for k, v in res.items()}, flush=True)
for k, v in res.items():
    print(k, f"limit_error_binding_deg mean {np.mean(v):.2f}")
