"""Issue 33: does a human-like reach model predict a REAL recording better than the controller?

Runs ``camo-sbi infer`` twice on the same real recording, once with ``--reach-model controller``
(the paper's differential-kinematics controller) and once with ``--reach-model minimum-jerk``
(`camo_sbi.scenarios.generators.reach_model`), same methods, budget and seed, and compares the
posterior-predictive Cartesian error of each method (``model_check.csv``, column
``predictive_error_mm``: per reach, the mean over 399 posterior draws of the mean distance per
step between the observed hand path and the draw's simulated one). Prints per method and reach
both errors, their ratio (minimum-jerk / controller; the issue's target: at most 0.5) and the
model check's verdicts; the controller arm is the reference timed in the same run. Also the
``shape_error_mm`` column: the same error with every path resampled over its own duration (the
path without its timing; the reach model's duration is normalised, not the person's).

    python benchmarks/bench_reach_model_real.py --out /tmp/reach_model_real -- \\
        --observations tests/data/pyomeca_shoulder.c3d --model human --markers isb \\
        --marker-map tests/data/pyomeca_shoulder_map.json --reaches auto --side right \\
        --noise-joint-deg 1 --methods naive,camo-seq,camo-touched

Everything after ``--`` is passed to ``camo-sbi infer`` (without ``--out``/``--reach-model``).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd

CLI = str(Path(sys.executable).with_name("camo-sbi"))


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if "--" not in argv:
        raise SystemExit("usage: bench_reach_model_real.py --out DIR -- INFER_ARGS ...")
    k = argv.index("--")
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv[:k])
    infer_args = argv[k + 1:]
    tables, walls = {}, {}
    for law in ("controller", "minimum-jerk"):
        out = args.out / law
        t0 = time.perf_counter()
        run = subprocess.run([CLI, "infer", *infer_args, "--reach-model", law, "--out", str(out), "--force"],
                             capture_output=True, text=True)
        walls[law] = time.perf_counter() - t0
        if run.returncode != 0:
            raise SystemExit(f"infer --reach-model {law} failed:\n{run.stderr[-3000:]}")
        t = pd.read_csv(out / "model_check.csv")
        tables[law] = t[t["reach"].notna()].set_index(["method", "reach"])
    cols = ["predictive_error_mm", "shape_error_mm", "verdict", "onset_model"]
    both = (tables["controller"][["onset_observed", *cols]].add_suffix("_controller")
            .join(tables["minimum-jerk"][cols].add_suffix("_minimum_jerk"), how="inner"))
    for e in ("predictive_error_mm", "shape_error_mm"):
        both[f"{e}_ratio"] = both[f"{e}_minimum_jerk"] / both[f"{e}_controller"]
    print(both.to_string())
    errors = [f"{e}_{law}" for e in ("predictive_error_mm", "shape_error_mm") for law in ("controller", "minimum_jerk")]
    per_method = both.groupby(level="method")[errors].mean()
    for e in ("predictive_error_mm", "shape_error_mm"):
        per_method[f"{e}_ratio"] = per_method[f"{e}_minimum_jerk"] / per_method[f"{e}_controller"]
    print("\nmean over reaches (mm): predictive_error = time-aligned (held at the end), shape_error = each "
          "path over its own duration:")
    print(per_method.round(3).T.to_string())
    print(f"\nwall: controller {walls['controller']:.1f} s (reference), minimum-jerk {walls['minimum-jerk']:.1f} s "
          f"({walls['minimum-jerk'] / walls['controller']:.2f}x)")
    both.to_csv(args.out / "reach_model_real.csv")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
