"""Cold start on a new URDF: time from a fresh process to the first `infer` result.

A user's new chain (tests/data/arm7.urdf, 7 revolute joints, not the Panda or the human)
reaches 5 recorded goals (written by `simulate_recordings` beforehand); the first result is
`limits.csv` of camo + naive + nominal at budget 200 per reach (the report is timed apart).
Each scenario runs in a fresh Python process and prints its breakdown:

    import        import camo_sbi (the CLI's modules, the registry, torch, numpy)
    urdf parse    from_urdf: URDF text -> ChainSpec + pytorch-kinematics chain
    kernel f32    the chain's float32 kernel (CAMO's candidates): code generation + numba compile
                  (or load from the cache)
    load          load_recordings (checks + resampling; FK for the rate estimate)
    camo, naive, nominal   run_method, each (CAMO's first run compiles / loads its DTW and KDE kernels)
    write         limits.csv
    first result  import .. write
    report        report.html (matplotlib, 50 posterior-predictive draws per method and reach, float32)
    kernel f64    the float64 kernel, compiled only with --predict-goals (task.predict is float64)

Scenarios (each a fresh process):

    cold chain    CAMO_SBI_KERNEL_CACHE -> an empty temp dir: the new chain's kernel is generated
                  and compiled; the package's own numba caches (DTW, KDE) as installed
    cold all      also NUMBA_CACHE_DIR -> an empty temp dir: every numba kernel compiles (a first
                  run after installing)
    warm          the same caches again (the plain reference: everything cached)

Wall and process CPU time per phase are printed (on a shared machine the CPU time is the
better guide to an idle one: every phase but the kernel's prange loop is single-threaded);
the ratio cold / warm is printed for the first result. Target: <= 10 s cold on 2 cores.

    python benchmarks/bench_cold_start.py
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
URDF = ROOT / "tests" / "data" / "arm7.urdf"
LIMITS = ROOT / "tests" / "data" / "arm7_limits.json"
START = "0,0.4,0,-1.1,0,0.7,0"
METHODS = ("camo", "naive", "nominal")
BUDGET = 200


def child(recording: str, out: str) -> None:
    """One fresh process: the infer pipeline step by step; prints {phase: [wall s, cpu s]}."""
    t = {}
    marks = [time.perf_counter(), time.process_time()]

    def lap(name):
        w, c = time.perf_counter(), time.process_time()
        t[name] = [w - marks[0], c - marks[1]]
        marks[:] = [w, c]

    from camo_sbi.experiments import (  # what `camo-sbi infer` imports
        infer,
        infer_limits,
        infer_report,
    )
    from camo_sbi.experiments.models import ModelSpec
    from camo_sbi.inference.registry import run_method
    from camo_sbi.io.recordings import load_recordings
    from camo_sbi.simulators import from_urdf
    from camo_sbi.simulators.kernel import load_kernel
    from camo_sbi.task import NoiseModel

    lap("import")
    start = [float(v) for v in START.split(",")]
    sim = from_urdf(URDF.read_text(), "tool", start=start)
    lap("urdf parse")
    import numpy as np
    import torch

    def kernel(np_dt, torch_dt):
        load_kernel(sim.spec, np_dt)  # generate + import the module
        # first call: numba compiles (or loads its cache)
        sim.simulate(sim.bounds.reshape(-1).to(torch_dt), torch.tensor([0.3, 0.1, 0.6], dtype=torch_dt))

    kernel(np.float32, torch.float32)  # CAMO's candidates (CamoConfig.sim_dtype) and the report
    lap("kernel f32")
    obs = load_recordings(recording, sim)
    task = infer._recorded_task(ModelSpec(kind="urdf", urdf=str(URDF), ee="tool"), sim, obs, NoiseModel())
    lap("load")
    results = {}
    for m in METHODS:
        results[m] = run_method(m, task, budget=BUDGET, seed=0, config={})
        lap(m)
    table = infer_limits.limits_table(results, sim)
    Path(out).mkdir(parents=True, exist_ok=True)
    (Path(out) / "limits.csv").write_text(table.to_csv(index=False))
    lap("write")
    t["first result"] = [sum(v[i] for v in t.values()) for i in (0, 1)]
    t["scipy.stats loaded"] = [float("scipy.stats" in sys.modules)] * 2
    marks[:] = [time.perf_counter(), time.process_time()]
    infer_report.write_infer_report(Path(out), task, results, [], table, {"observations": recording}, 0)
    lap("report")
    kernel(np.float64, torch.float64)  # only with --predict-goals: task.predict simulates in float64
    lap("kernel f64")
    print(json.dumps(t))


def run(recording: Path, env: dict, out: Path) -> dict:
    s = time.perf_counter()
    p = subprocess.run([sys.executable, __file__, "--child", str(recording), str(out)], env=env,
                       capture_output=True, text=True, check=True)
    t = json.loads(p.stdout.strip().splitlines()[-1])
    t["process wall"] = time.perf_counter() - s
    return t


def main() -> None:
    tmp = Path(tempfile.mkdtemp(prefix="camo_cold_"))
    recording = tmp / "reaches.csv"
    env = {**os.environ, "CAMO_SBI_KERNEL_CACHE": str(tmp / "kernels"), "NUMBA_NUM_THREADS": "2"}
    subprocess.run([sys.executable, "-m", "camo_sbi.experiments.cli", "simulate-observations", "--urdf", str(URDF),
                    "--ee", "tool", "--start", START, "--limits", str(LIMITS), "--reaches", "5", "--seed", "0",
                    "--out", str(recording)], env={**env, "CAMO_SBI_KERNEL_CACHE": str(tmp / "prep")},
                   check=True, capture_output=True)
    rows = {
        "cold chain": run(recording, env, tmp / "a"),
        "cold all": run(recording, {**env, "CAMO_SBI_KERNEL_CACHE": str(tmp / "kernels2"),
                                    "NUMBA_CACHE_DIR": str(tmp / "numba")}, tmp / "b"),
        "warm": run(recording, env, tmp / "c"),
    }
    keys = list(rows["warm"])
    print(f"load average {os.getloadavg()[0]:.2f} (2 cores, shared); seconds, wall / process CPU")
    print(f"{'':20s}" + "".join(f"{k:>18s}" for k in rows))
    for k in keys:
        if k == "process wall":
            print(f"{k:20s}" + "".join(f"{rows[r][k]:18.2f}" for r in rows))
        else:
            print(f"{k:20s}" + "".join(f"{rows[r][k][0]:10.2f} /{rows[r][k][1]:6.2f}" for r in rows))
    w = rows["warm"]["first result"][0]
    for r in ("cold chain", "cold all"):
        print(f"{r} / warm, first result (wall): {rows[r]['first result'][0] / w:.1f}x")


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        child(sys.argv[2], sys.argv[3])
    else:
        main()
