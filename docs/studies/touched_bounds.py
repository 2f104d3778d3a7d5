"""Why the observed min/max (naive) wins on the binding bounds (issue 23 item 4).

    PYTHONPATH=. python docs/studies/touched_bounds.py panda 10

The informative setting's first RUNS runs (seed 0, the tasks of `reproduce panda --setting
informative`): per binding bound, whether the training reaches observe it exactly (the observed
extreme equals the true limit), each method's error on those and on the others after 10
reaches, and how often `touched_bounds` flags a bound that is not exactly the true limit.
"""

import argparse
import sys

import numpy as np

from camo_sbi._validation import derive_seed
from camo_sbi.evaluation.metrics import binding_bounds
from camo_sbi.experiments.models import ModelSpec, subject_limits
from camo_sbi.experiments.reproduce_panda import SETTINGS, method_config
from camo_sbi.inference.registry import run_method
from camo_sbi.inference.touched import touched_bounds
from camo_sbi.scenarios.reaching import make_reaching_task

METHODS = ("naive", "camo-js", "camo-seq", "camo-hull", "camo-touched")


def main(argv=None) -> int:
    model = ModelSpec(kind=sys.argv[1] if argv is None else argv[0])
    runs = int(sys.argv[2] if argv is None else argv[1])
    sim = model.build()
    st = SETTINGS["informative"]
    args = argparse.Namespace(setting="informative", keep_best=None, bandwidth=None, bandwidth_mode=None,
                              sampling=None, epsilon=None, scheduler=None)
    err = {m: {"exact": [], "other": []} for m in METHODS}
    flagged = wrong = 0
    for run in range(runs):
        subject = st.subjects[run % len(st.subjects)]
        truth = subject_limits(model, sim, subject)
        task = make_reaching_task(sim, truth, n_train=10, n_test=20, seed=derive_seed(0, run),
                                  workspace=st.workspace, min_binding_test=st.min_binding_test)
        binding = binding_bounds(sim, truth, task.test_starts, task.test_goals, task.prior)
        touched, ext = touched_bounds([o.q for o in task.observations])
        exact = np.abs(ext - truth.numpy()) < 1e-9
        flagged += int(touched.sum())
        wrong += int((touched & ~exact).sum())
        for m in METHODS:
            r = run_method(m, task, budget=2000, seed=derive_seed(0, run, 1), config=method_config(m, args))
            e = np.degrees(np.abs(r.estimate - truth.numpy()))
            err[m]["exact"] += list(e[binding & exact])
            err[m]["other"] += list(e[binding & ~exact])
        print(f"run {run} {subject}: {int(binding.sum())} binding bounds, {int((binding & exact).sum())} observed "
              f"exactly; touched_bounds flags {int(touched.sum())}", flush=True)
    for m in METHODS:
        print(f"{m:13s} binding bounds observed exactly: n={len(err[m]['exact'])} mean error "
              f"{np.mean(err[m]['exact']):.2f} deg; the others: n={len(err[m]['other'])} "
              f"{np.mean(err[m]['other']):.2f} deg")
    print(f"touched_bounds flagged {flagged} bounds, {wrong} of them not exactly the true limit")
    return 0


if __name__ == "__main__":
    sys.exit(main())
