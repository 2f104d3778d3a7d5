"""The authors' setting (issue 24): their 7-DOF DH arm, their controller's limit terms, their
variants, no NaN from the paper controller, and non-finite candidates as method failures."""

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from camo_sbi.inference.camo import Camo, CamoConfig
from camo_sbi.inference.registry import run_method_sequence
from camo_sbi.priors import BoxPrior
from camo_sbi.scenarios.reaching import make_reaching_task, observe
from camo_sbi.simulators.controller import ControllerConfig
from camo_sbi.simulators.simulator import from_urdf
from tests.toy_sim import ToySimulator

DATA = Path(__file__).parent / "data"
URDF, LIMITS = DATA / "authors_dh7.urdf", DATA / "authors_dh7_limits.json"
PI = math.pi
START = np.array([PI / 2, PI / 6, PI / 6, 0.0, PI / 2, PI / 2, 0.0])  # their rest_position
# their DH table (Simulator_rtb.World), lengths in metres: (a, d, alpha)
DH = [(0, 0, PI / 2), (0, 0, -PI / 2), (0, 0.40, PI / 2), (0.41, 0, 0), (0, 0, -PI / 2), (0, 0, -PI / 2),
      (0, 0.10, PI / 2)]
PAPER = ControllerConfig(max_steps=21, early_stop=False, null_gain=0.0, gain=0.1, derivative_gain=0.5,
                         damping=1e-6, max_cartesian_step=1e3, max_joint_step=1e3, limit_gain=0.2)


def _dh_frames(q):
    """Standard DH: T_i = T_{i-1} Rz(q_i) Tz(d_i) Tx(a_i) Rx(alpha_i) (roboticstoolbox's DHRobot)."""
    T, out = np.eye(4), [np.eye(4)]
    for (a, d, al), qi in zip(DH, q, strict=True):
        ct, st, ca, sa = np.cos(qi), np.sin(qi), np.cos(al), np.sin(al)
        T = T @ np.array([[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0, sa, ca, d],
                          [0, 0, 0, 1]])
        out.append(T)
    return out


def _dh_fk(q):
    return _dh_frames(q)[-1][:3, 3]


def _dh_jacobian(q):
    F = _dh_frames(q)
    pe = F[-1][:3, 3]
    return np.stack([np.cross(F[i][:3, 2], pe - F[i][:3, 3]) for i in range(7)], axis=1)


def _their_reach(theta, start, goal, steps=20, KN=10.0, dt=0.02, buf=0.01):
    """Simulator_rtb.Simulator.simulate_p2p / controller, by hand: returns (q (steps+1, 7), number
    of steps at which the lower-buffer push acted)."""
    lo, hi = theta[0::2], theta[1::2]
    q, vel = start.astype(float).copy(), np.zeros(3)
    x = _dh_fk(q)
    qs, pushes = [q.copy()], 0
    for _ in range(steps):
        J = _dh_jacobian(q)
        Jp = np.linalg.pinv(J)
        N = np.eye(7) - Jp @ J
        e, e_dot = goal - x, -vel
        pl, pu = 2 * KN * np.clip(buf + lo - q, 0, 0.2), 2 * KN * np.clip(q - hi - buf, 0, 0.2)
        hl, hu = KN * np.clip(lo - q, 0, None), KN * np.clip(q - hi, 0, None)
        pushes += int((pl > 0).any())
        q_new = q + dt * (Jp @ (5 * e) + Jp @ (0.5 * e_dot)) + dt * (N @ pl + N @ pu) + dt * (hl + hu)
        q_new = np.clip(q_new, lo, hi)
        x_new = _dh_fk(q_new)
        vel = (x_new - x) / dt
        q, x = q_new, x_new
        qs.append(q.copy())
    return np.array(qs), pushes


def _truth():
    lim = json.loads(LIMITS.read_text())
    return np.array([v for pair in lim.values() for v in pair])


@pytest.fixture(scope="module")
def arm():
    return from_urdf(str(URDF), "tool", start=torch.tensor(START))


def test_urdf_is_the_authors_dh_arm(arm):
    """FK at their start posture (and at random postures) equals their DH product."""
    assert arm.n_joints == 7
    np.testing.assert_allclose(arm.forward_kinematics(torch.tensor(START)[None])[0].numpy(), _dh_fk(START),
                               atol=1e-12, rtol=0)
    q = np.random.default_rng(0).uniform(-3, 3, size=(20, 7))
    np.testing.assert_allclose(arm.forward_kinematics(torch.tensor(q)).numpy(),
                               np.array([_dh_fk(r) for r in q]), atol=1e-12, rtol=0)
    # the generator script writes these very files
    import importlib.util

    spec = importlib.util.spec_from_file_location("make_authors_dh7", DATA / "make_authors_dh7.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.urdf() == URDF.read_text() and json.loads(LIMITS.read_text()) == mod.limits()


def test_limit_terms_are_the_authors_formula_step_by_step(arm):
    """One trajectory where a lower limit is approached, compared at every step with their
    controller computed by hand (numpy pinv, their penalties); numba == torch reference; and
    without the limit terms the path differs (so the comparison can fail)."""
    theta = _truth()
    q_goal = theta[0::2] + (theta[1::2] - theta[0::2]) * np.random.default_rng(0).random((40, 7))[39]
    goal = _dh_fk(q_goal)
    want, pushes = _their_reach(theta, START, goal)
    assert pushes >= 5 and want[:, 0].min() == theta[0]  # the buffer push acts; the shoulder roll hits its limit
    got = {}
    for backend in ("numba", "torch"):
        sim = arm.with_config(PAPER, backend=backend)
        tr = sim.simulate(torch.tensor(theta)[None], torch.tensor(goal)[None])
        got[backend] = tr.q[0].numpy()
        np.testing.assert_allclose(got[backend], want, atol=1e-5, rtol=0)
    np.testing.assert_allclose(got["numba"], got["torch"], atol=1e-9, rtol=0)
    off = arm.with_config(PAPER.replace(limit_gain=0.0)).simulate(torch.tensor(theta)[None], torch.tensor(goal)[None])
    assert np.abs(off.q[0].numpy() - want).max() > 0.1


def test_paper_controller_is_finite_in_float32(arm):
    """damping 1e-6 (lambda^2 = 1e-12, below float32 resolution) at their straight-elbow start:
    the grid prior's candidates stay finite in float32 and track float64."""
    sim = arm.with_config(PAPER)
    prior = BoxPrior(sim.bounds, sim.start, sampling="grid")
    theta = prior.sample(2000, np.random.default_rng(0))
    goal = torch.tensor(_dh_fk(_truth()[0::2] + 0.3), dtype=torch.float64)
    t32 = sim.simulate(theta.float(), goal.float())
    t64 = sim.simulate(theta, goal)
    assert bool(torch.isfinite(t32.q).all()) and bool(torch.isfinite(t32.ee).all())
    assert float((t32.ee.double() - t64.ee).abs().max()) < 1e-2


def test_nonfinite_candidates_are_a_method_failure_not_an_input_error():
    """A controller gain that overflows float32 (inf) makes every float32 candidate NaN, while
    the float64 observations stay finite: CAMO reports failed (first task) / fallback, never raises."""
    sim = ToySimulator()
    true = torch.tensor([-0.6, 0.5, -0.4, 0.7], dtype=torch.float64)
    obs = observe(sim, true, torch.tensor([[0.9, -0.9, 0.0], [-0.9, 0.9, 0.0]], dtype=torch.float64))

    class Broken(ToySimulator):  # float32 simulations are NaN, float64 ones finite
        def simulate(self, theta, goal, start=None):
            tr = super().simulate(theta, goal, start)
            if theta.dtype == torch.float32:
                tr.q[: theta.shape[0] // 2] = float("nan")
            return tr

    prior = BoxPrior(sim.bounds, sim.start)
    camo = Camo(Broken(), prior, CamoConfig(keep_best=20), n_samples=200, seed=0)
    with pytest.warns(RuntimeWarning, match="not finite"):
        camo.observe_all(obs)
    res = camo.result()
    assert res.status.startswith("fallback: ") and "non-finite" in res.status
    assert res.extras["nonfinite_candidates"] == [100, 100] and np.isfinite(res.estimate).all()
    assert bool(torch.isfinite(camo.kept).all()) and camo.kept.shape[0] == 40

    class AllBroken(ToySimulator):
        def simulate(self, theta, goal, start=None):
            tr = super().simulate(theta, goal, start)
            tr.q[:] = float("nan")
            return tr

    camo = Camo(AllBroken(), prior, CamoConfig(keep_best=20), n_samples=200, seed=0)
    with pytest.warns(RuntimeWarning, match="not finite"):
        res = camo.observe_all(obs).result()
    assert res.status.startswith("failed: ") and res.samples.shape[0] == 1 and np.isfinite(res.estimate).all()


def test_overflowing_controller_gain_in_a_reproduce_run_exits_0(tmp_path, monkeypatch, capsys):
    """The CLI: a controller setting that forces non-finite float32 candidates (gain 1e39 is inf in
    float32; the subject, simulated in float64, stays finite) gives exit 0 and non-ok statuses."""
    from camo_sbi.experiments import reproduce_panda
    from camo_sbi.experiments.cli import main

    paper = reproduce_panda.SETTINGS["paper"]
    monkeypatch.setitem(reproduce_panda.SETTINGS, "paper", reproduce_panda.Setting(
        **{**paper.__dict__, "controller": {**paper.controller, "gain": 1e39, "max_cartesian_step": 0.05}}))
    out = tmp_path / "run"
    rc = main(["reproduce", "panda", "--setting", "paper", "--runs", "1", "--tasks", "2", "--test-goals", "2",
               "--samples", "50", "--methods", "camo-seq", "--out", str(out)])
    assert rc == 0 and "not finite" in capsys.readouterr().err
    df = pd.read_csv(out / "results.csv")
    seq = df[df.method == "camo-seq"]
    assert len(seq) and seq.status.str.startswith(("fallback: ", "failed: ")).all()
    assert seq.status.str.contains("non-finite").all()


def test_camo_seq_cs_draws_from_the_js_bank():
    """camo-seq-cs (the authors' CS): from task 2 on, its candidates come from the JS chain's
    acceptances clipped to the observed joint hull, so every kept vector contains every joint
    posture seen so far, although it scores Cartesian observations; task 1 is prior draws."""
    sim = ToySimulator()
    true = torch.tensor([-0.6, 0.5, -0.4, 0.7], dtype=torch.float64)
    task = make_reaching_task(sim, true, n_train=3, n_test=2, seed=4, name="toy", require_reached=False)
    results = run_method_sequence("camo-seq-cs", task, budget=300, seed=1,
                                  config={"keep_best": 20, "bandwidth": 0.01})
    assert [r.n_tasks for r in results] == [1, 2, 3] and all(r.status == "ok" for r in results)
    camo = Camo(sim, task.prior, CamoConfig(space="cartesian", proposal="sequential-js", keep_best=20,
                                            bandwidth=0.01), n_samples=300, seed=1)
    seen = []
    for i, o in enumerate(task.observations):
        camo.observe(o.start, o.goal, o.ee, o.q)
        seen += [o.start[None], o.q]
        if i >= 1:
            q = torch.cat(seen)
            kept = camo.records[-1].kept
            assert bool((kept[:, 0::2] <= q.min(0).values + 1e-12).all())
            assert bool((kept[:, 1::2] >= q.max(0).values - 1e-12).all())
    np.testing.assert_array_equal(camo.result().estimate, results[-1].estimate)
    plain = Camo(sim, task.prior, CamoConfig(space="cartesian", keep_best=20, bandwidth=0.01), n_samples=300, seed=1)
    plain.observe(task.observations[0].start, task.observations[0].goal, task.observations[0].ee)
    torch.testing.assert_close(plain.records[0].kept, camo.records[0].kept)
    with pytest.raises(ValueError, match="^joint_trajectory:"):
        Camo(sim, task.prior, CamoConfig(space="cartesian", proposal="sequential-js"), n_samples=10,
             seed=0).observe(task.observations[0].start, task.observations[0].goal, task.observations[0].ee)
    with pytest.raises(ValueError, match="^proposal:"):
        CamoConfig(space="joint", proposal="sequential-js")


@pytest.mark.slow
def test_reproduce_paper_on_the_authors_arm(tmp_path):
    """The authors' arm through the CLI, 2 runs: exit 0, results/claims with camo-seq and
    camo-seq-cs, figures."""
    from camo_sbi.experiments.cli import main

    out = tmp_path / "dh7"
    start = ",".join(repr(float(q)) for q in START)
    rc = main(["reproduce", "panda", "--setting", "paper", "--urdf", str(URDF), "--ee", "tool", "--start", start,
               "--limits", str(LIMITS), "--runs", "2", "--tasks", "4", "--test-goals", "4", "--samples", "500",
               "--out", str(out)])
    assert rc == 0
    df = pd.read_csv(out / "results.csv")
    assert {"camo-seq", "camo-seq-cs", "camo-js", "camo-cs", "naive", "nominal", "oracle"} <= set(df.method)
    claims = pd.read_csv(out / "claims.csv")
    assert {"camo-seq", "camo-seq-cs"} <= set(claims.method)
    assert set(claims[claims.method == "camo-seq"].variant) == {"the authors' JS, as their code runs it"}
    assert (out / "fig2_cartesian_error_vs_tasks.png").is_file() and (out / "fig3_final_error.png").is_file()
