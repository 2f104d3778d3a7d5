"""Simulator contract: FK vs PyBullet, kernel vs torch reference, batching, limits, reach, validation.

Most tests are parametrised over `conftest.SIMULATOR_FACTORIES` (Panda, a tiny URDF with
a prismatic joint, the human model).
"""

from __future__ import annotations

import dataclasses
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from camo_sbi.simulators import (
    ControllerConfig,
    KinematicSimulator,
    Simulator,
    Trajectories,
    from_urdf,
    panda,
    sample_goals,
)
from camo_sbi.simulators.kernel import generate_source, kernel_fk
from camo_sbi.simulators.panda import PANDA_READY, panda_urdf_path
from tests.conftest import TINY_URDF, assert_fk_matches_pybullet, tiny

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """The torch reference runs small batches here: one thread is faster and immune to a busy machine."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def random_problem(sim, B: int, seed: int, dtype=torch.float64):
    """Random limits bracketing the start posture (as the box prior does) and goals sampled
    uniformly inside those limits. Returns theta (B, 2n), goals (B, 3)."""
    g = torch.Generator().manual_seed(seed)
    b, s, n = sim.bounds, sim.start, sim.n_joints
    u = torch.rand(B, n, 2, generator=g, dtype=torch.float64)
    lo = b[:, 0] + (s - b[:, 0]) * u[..., 0]
    hi = s + (b[:, 1] - s) * u[..., 1]
    q = lo + (hi - lo) * torch.rand(B, n, generator=g, dtype=torch.float64)
    theta = torch.stack([lo, hi], dim=-1).reshape(B, 2 * n)
    return theta.to(dtype), sim.forward_kinematics(q).to(dtype)


# ----------------------------------------------------------------------------- kinematics
def test_fk_matches_pybullet(any_sim):
    err = assert_fk_matches_pybullet(any_sim, n=100, seed=0)
    print(f"\n{any_sim.end_effector}: max FK error vs pybullet {err:.2e} m")


def test_spec_kernel_and_pk_fk_agree(any_sim):
    rng = np.random.default_rng(1)
    lim = any_sim.bounds.numpy()
    q = lim[:, 0] + (lim[:, 1] - lim[:, 0]) * rng.random((64, any_sim.n_joints))
    ref = any_sim.forward_kinematics(torch.from_numpy(q)).numpy()
    np.testing.assert_allclose(any_sim.spec.fk_numpy(q), ref, atol=1e-12)
    np.testing.assert_allclose(kernel_fk(any_sim.spec, q), ref, atol=1e-12)
    # batch shapes of forward_kinematics
    qt = torch.from_numpy(q)
    assert any_sim.forward_kinematics(qt[0]).shape == (3,)
    assert any_sim.forward_kinematics(qt.reshape(8, 8, -1)).shape == (8, 8, 3)


def test_panda_model(panda_sim):
    assert isinstance(panda_sim, Simulator)
    assert panda_sim.joint_names == [f"panda_joint{i}" for i in range(1, 8)]
    assert panda_sim.n_joints == 7 and panda_sim.end_effector == "panda_grasptarget"
    assert panda_sim.bounds.dtype == torch.float64 and panda_sim.bounds.shape == (7, 2)
    assert torch.allclose(panda_sim.start, torch.tensor(PANDA_READY, dtype=torch.float64))
    assert "<robot" in panda_sim.urdf
    assert float(panda_sim.bounds[3, 1]) == 0.0  # joint 4 upper limit from the URDF


# ----------------------------------------------------------------------------- controller
def test_kernel_matches_torch_reference(any_sim):
    theta, goals = random_problem(any_sim, 48, seed=2)
    a = any_sim.with_config(backend="numba").simulate(theta, goals)
    b = any_sim.with_config(backend="torch").simulate(theta, goals)
    assert torch.equal(a.length, b.length) and torch.equal(a.reached, b.reached)
    assert (a.q - b.q).abs().max() < 1e-9
    assert (a.ee - b.ee).abs().max() < 1e-9


PAPER_CONTROLLER = ControllerConfig(max_steps=21, early_stop=False, null_gain=0.0, gain=0.1, derivative_gain=0.5,
                                    damping=1e-7, max_cartesian_step=1e3, max_joint_step=1e3)


def test_fixed_horizon_pd_controller_kernel_matches_torch_reference(any_sim):
    theta, goals = random_problem(any_sim, 24, seed=5)
    sims = [any_sim.with_config(PAPER_CONTROLLER, backend=b) for b in ("numba", "torch")]
    a, b = (s.simulate(theta, goals) for s in sims)
    assert (a.length == 21).all() and torch.equal(a.length, b.length) and torch.equal(a.reached, b.reached)
    assert (a.q - b.q).abs().max() < 1e-9 and (a.ee - b.ee).abs().max() < 1e-9
    # the reached flag is judged at the last point of the fixed horizon
    assert torch.equal(a.reached, (goals - a.ee[:, -1]).norm(dim=-1) < PAPER_CONTROLLER.tol)


def test_fixed_horizon_pd_controller_is_the_authors_law(panda_sim):
    """The authors' step (Simulator_rtb.controller, no limit penalties inside the limits):
    dq = dt pinv(J) (P e - D (x_t - x_{t-1}) / dt), dt = 0.02, P = 5, D = 0.5, then a clip.
    Re-implemented here with numpy's pinv on pytorch-kinematics' Jacobian."""
    sim = panda_sim.with_config(PAPER_CONTROLLER)
    lo, hi = sim.bounds[:, 0].clone(), sim.bounds[:, 1].clone()
    lo[0], hi[0] = sim.start[0] - 0.5, sim.start[0] + 0.5  # one restricted joint, as the authors' truth
    theta = torch.stack([lo, hi], dim=1).reshape(-1)
    g = torch.Generator().manual_seed(1)
    q_goal = sim.bounds[:, 0] + (sim.bounds[:, 1] - sim.bounds[:, 0]) * torch.rand(3, 7, generator=g, dtype=torch.float64)
    goals = sim.forward_kinematics(q_goal)
    traj = sim.simulate(theta.expand(3, -1), goals)
    dt, P, D = 0.02, 5.0, 0.5
    for b in range(3):
        q = sim.start.numpy().copy()
        x_prev = None
        for t in range(21):
            J6, pose = sim.chain.reference_jacobian(torch.from_numpy(q)[None])
            x = pose[0, :3, 3].numpy()
            np.testing.assert_allclose(traj.q[b, t].numpy(), q, atol=1e-6, rtol=0)
            vel = np.zeros(3) if x_prev is None else (x - x_prev) / dt
            x_prev = x
            dq = dt * np.linalg.pinv(J6[0, :3].numpy()) @ (P * (goals[b].numpy() - x) - D * vel)
            q = np.clip(q + dq, lo.numpy(), hi.numpy())
    assert float((traj.q[:, -1] - traj.q[:, -2]).abs().max()) > 1e-4  # not converged after 20 steps


def test_output_layout_dtype_and_padding(panda_sim):
    theta, goals = random_problem(panda_sim, 32, seed=3, dtype=torch.float32)
    for backend in ("numba", "torch"):
        tr = panda_sim.with_config(backend=backend).simulate(theta, goals)
        T = panda_sim.config.max_steps
        assert isinstance(tr, Trajectories)
        assert tr.q.shape == (32, T, 7) and tr.ee.shape == (32, T, 3)
        assert tr.q.dtype == tr.ee.dtype == torch.float32
        assert tr.length.dtype == torch.int64 and tr.reached.dtype == torch.bool
        assert bool(((tr.length >= 1) & (tr.length <= T)).all())
        start = panda_sim.start.to(torch.float32)
        assert torch.equal(tr.q[:, 0], start.expand(32, -1))
        for i in range(32):
            L = int(tr.length[i])
            assert torch.equal(tr.q[i, L:], tr.q[i, L - 1].expand(T - L, -1))
            assert torch.equal(tr.ee[i, L:], tr.ee[i, L - 1].expand(T - L, -1))
            err = (goals[i] - tr.ee[i, L - 1]).norm()
            assert bool(tr.reached[i]) == bool(err < panda_sim.config.tol)
            if L < T:
                assert tr.reached[i]


def test_float32_tracks_float64(panda_sim):
    theta, goals = random_problem(panda_sim, 64, seed=4)
    a = panda_sim.simulate(theta, goals)
    b = panda_sim.simulate(theta.float(), goals.float())
    # same outcome for nearly all reaches, final positions within a few mm
    assert (a.reached == b.reached).float().mean() >= 0.95
    both = a.reached & b.reached
    assert (a.ee[both, -1] - b.ee[both, -1].double()).norm(dim=-1).max() < 0.02


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_batched_equals_per_sample(panda_sim, backend):
    sim = panda_sim.with_config(backend=backend)
    theta, goals = random_problem(sim, 6, seed=5)
    starts = sim.start + 0.0 * theta[:, 0::2]
    batch = sim.simulate(theta, goals, starts)
    for i in range(6):
        one = sim.simulate(theta[i], goals[i], starts[i])
        assert int(one.length[0]) == int(batch.length[i]) and bool(one.reached[0]) == bool(batch.reached[i])
        assert (one.q[0] - batch.q[i]).abs().max() <= 1e-12
        assert (one.ee[0] - batch.ee[i]).abs().max() <= 1e-12


def test_broadcasting(panda_sim, input_checks):
    theta, goals = random_problem(panda_sim, 4, seed=6)
    full = panda_sim.simulate(theta[:1].expand(4, -1), goals, panda_sim.start.expand(4, -1))
    bc = panda_sim.simulate(theta[0], goals)  # one theta, many goals, default start
    assert torch.equal(full.q, bc.q)
    # a non-contiguous theta (every other row of a larger batch) gives the rows' own results
    wide = torch.cat([theta, theta]).reshape(2, 4, -1).transpose(0, 1).reshape(8, -1)[::2]
    assert not wide.is_contiguous()
    assert torch.equal(panda_sim.simulate(wide, goals).q, panda_sim.simulate(theta, goals).q)
    one_goal = panda_sim.simulate(theta, goals[0])
    assert one_goal.q.shape[0] == 4


def test_deterministic(panda_sim):
    theta, goals = random_problem(panda_sim, 16, seed=7)
    a, b = panda_sim.simulate(theta, goals), panda_sim.simulate(theta, goals)
    assert torch.equal(a.q, b.q) and torch.equal(a.ee, b.ee) and torch.equal(a.length, b.length)


def test_thread_count_does_not_change_results(panda_sim, tmp_path):
    theta, goals = random_problem(panda_sim, 200, seed=8, dtype=torch.float32)
    here = panda_sim.simulate(theta, goals)
    out = tmp_path / "one_thread.pt"
    code = (
        "import torch, sys\n"
        "from camo_sbi.simulators import panda\n"
        "from tests.test_simulators import random_problem\n"
        "sim = panda()\n"
        "theta, goals = random_problem(sim, 200, seed=8, dtype=torch.float32)\n"
        "tr = sim.simulate(theta, goals)\n"
        f"torch.save((tr.q, tr.ee, tr.length), {str(out)!r})\n"
    )
    env = dict(os.environ, NUMBA_NUM_THREADS="1", PYTHONPATH=str(ROOT))
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT, env=env, timeout=300)
    q, ee, length = torch.load(out)
    assert torch.equal(q, here.q) and torch.equal(ee, here.ee) and torch.equal(length, here.length)


def test_trajectories_stay_inside_theta(any_sim):
    g = torch.Generator().manual_seed(9)
    B, n = 64, any_sim.n_joints
    # narrow limits around the start, goals anywhere in the full range: clamping is exercised
    width = 0.3 * (any_sim.bounds[:, 1] - any_sim.bounds[:, 0])
    lo = torch.maximum(any_sim.start - width * torch.rand(B, n, generator=g, dtype=torch.float64), any_sim.bounds[:, 0])
    hi = torch.minimum(any_sim.start + width * torch.rand(B, n, generator=g, dtype=torch.float64), any_sim.bounds[:, 1])
    theta = torch.stack([lo, hi], -1).reshape(B, -1)
    goals = sample_goals(any_sim, any_sim.bounds, B, g)
    for backend in ("numba", "torch"):
        tr = any_sim.with_config(backend=backend).simulate(theta, goals)
        assert bool((tr.q >= lo[:, None, :]).all()) and bool((tr.q <= hi[:, None, :]).all())


def test_reach_rate_panda(panda_sim):
    g = torch.Generator().manual_seed(10)
    goals = sample_goals(panda_sim, panda_sim.bounds, 1000, g)
    tr = panda_sim.simulate(panda_sim.bounds.reshape(-1), goals)
    full = tr.reached.double().mean().item()
    theta, goals2 = random_problem(panda_sim, 1000, seed=11)
    sub = panda_sim.simulate(theta, goals2).reached.double().mean().item()
    print(f"\nPanda reach rate: full limits {full:.3f} (mean length {tr.length.double().mean():.1f}), "
          f"random sub-limits {sub:.3f}")
    assert full >= 0.97
    assert sub >= 0.85


def test_goal_at_start_and_edge_cases(panda_sim):
    x0 = panda_sim.forward_kinematics(panda_sim.start)
    theta = panda_sim.bounds.reshape(-1)
    for backend in ("numba", "torch"):
        sim = panda_sim.with_config(backend=backend)
        tr = sim.simulate(theta, x0)
        assert int(tr.length[0]) == 1 and bool(tr.reached[0])
        assert torch.equal(tr.q[0], panda_sim.start.expand(sim.config.max_steps, -1))
        one = sim.with_config(max_steps=1).simulate(theta, x0 + 0.5)
        assert one.q.shape == (1, 1, 7) and int(one.length[0]) == 1 and not bool(one.reached[0])
        empty = sim.simulate(theta.expand(0, -1), x0)
        assert empty.q.shape == (0, sim.config.max_steps, 7)


# ----------------------------------------------------------------------------- URDF handling
def test_tiny_urdf_with_prismatic_joint(tmp_path):
    sim = tiny()
    assert sim.spec.joint_types == ("revolute", "prismatic", "revolute")
    assert sim.joint_names == ["j1", "j2", "j3"]
    assert torch.allclose(sim.bounds, torch.tensor([[-2.5, 2.5], [-0.1, 0.3], [-2.0, 2.0]], dtype=torch.float64))
    path = tmp_path / "tiny.urdf"
    path.write_text(TINY_URDF)
    from_path = from_urdf(path, "tip", start=[0.2, 0.1, -0.3])
    assert from_path.spec.digest == sim.spec.digest
    theta, goals = random_problem(sim, 200, seed=12)
    tr = sim.simulate(theta, goals)
    print(f"\ntiny URDF reach rate {tr.reached.double().mean():.3f}")
    assert tr.reached.double().mean() >= 0.8


def test_joint_subset_locks_the_rest_at_zero():
    sim6 = panda(joints=[f"panda_joint{i}" for i in range(1, 7)], start=PANDA_READY[:6])
    full = panda()
    q6 = torch.rand(10, 6, dtype=torch.float64)
    q7 = torch.cat([q6, torch.zeros(10, 1, dtype=torch.float64)], dim=1)
    assert torch.allclose(sim6.forward_kinematics(q6), full.forward_kinematics(q7), atol=1e-12)
    np.testing.assert_allclose(kernel_fk(sim6.spec, q6.numpy()), full.forward_kinematics(q7).numpy(), atol=1e-12)


def test_generated_source_is_dtype_pure(panda_sim):
    src = generate_source(panda_sim.spec, np.float32)
    body = src.split('"""', 2)[2]
    assert "F = np.float32" in body and "linalg" not in body
    # float64 only for the damped 3x3 solve (D) when lambda^2 is below float32 resolution: casts in,
    # the solve, one cast back out; the float32 solve otherwise
    assert body.count("float64") == 1 and "D = np.float64" in body and "if lam2 < F(1e-06):" in body
    d_lines = [ln.strip() for ln in body.splitlines() if re.search(r"(?<![\w.])D\(", ln)]
    assert d_lines and all(re.match(r"(j\d+_\d_d|n\d+_d|v\d_d|lam2_d|idet_d) = D\(", ln) for ln in d_lines), d_lines
    assert all(f"d{k} = F(dd{k}_d)" in body for k in range(panda_sim.n_joints))
    assert "D(" not in generate_source(panda_sim.spec, np.float64)  # float64 kernels: one plain solve
    stripped = re.sub(r"[FD]\([^()]*\)", "F()", body)
    assert not re.search(r"(?<![\w.])\d+\.\d*|(?<![\w.])\.\d+", stripped), "bare float literal in kernel"
    # serial row-chunk kernels run on the shared thread runner (no numba prange)
    assert "prange" not in body and "nogil=True" in body and "def simulate(c, n_chunks," in body


# ----------------------------------------------------------------------------- validation
BAD_SIMULATE = [
    ("theta", lambda s: dict(theta=torch.zeros(13, dtype=torch.float64))),
    ("theta", lambda s: dict(theta=torch.zeros(2, 16, dtype=torch.float64))),
    ("theta", lambda s: dict(theta=s.bounds.flip(1).reshape(-1))),
    ("theta", lambda s: dict(theta=s.bounds.reshape(-1).clone().index_fill_(0, torch.tensor([3]), float("nan")))),
    ("theta", lambda s: dict(theta=s.bounds.reshape(-1).clone().index_fill_(0, torch.tensor([1]), float("inf")))),
    ("goal", lambda s: dict(goal=torch.zeros(4, dtype=torch.float64))),
    ("goal", lambda s: dict(goal=torch.zeros(2, 2, 3, dtype=torch.float64))),
    ("goal", lambda s: dict(goal=torch.tensor([0.3, float("nan"), 0.5], dtype=torch.float64))),
    ("goal", lambda s: dict(theta=s.bounds.reshape(1, -1).expand(3, -1), goal=torch.zeros(2, 3, dtype=torch.float64))),
    ("start", lambda s: dict(start=torch.zeros(6, dtype=torch.float64))),
    ("start", lambda s: dict(start=s.start.clone().index_fill_(0, torch.tensor([2]), float("nan")))),
    ("start", lambda s: dict(start=s.bounds[:, 1] + 0.01)),
    ("start", lambda s: dict(theta=torch.stack([s.start + 0.1, s.start + 0.2], -1).reshape(-1))),
]


@pytest.fixture(params=["numpy", "torch"])
def input_checks(request, monkeypatch):
    """The input checks on CPU tensors run in numpy; "torch" forces the path a GPU tensor takes."""
    if request.param == "torch":
        import camo_sbi._validation as validation
        import camo_sbi.simulators.simulator as simulator

        monkeypatch.setattr(validation, "cpu_array", lambda t: None)
        monkeypatch.setattr(simulator, "cpu_array", lambda t: None)
    return request.param


@pytest.mark.parametrize("backend", ["numba", "torch"])
@pytest.mark.parametrize("name,make", BAD_SIMULATE)
def test_simulate_rejects_bad_inputs(panda_sim, backend, name, make, input_checks):
    sim = panda_sim.with_config(backend=backend)
    kw = dict(theta=sim.bounds.reshape(-1), goal=torch.tensor([0.4, 0.1, 0.4], dtype=torch.float64), start=None)
    kw.update(make(sim))
    with pytest.raises(ValueError, match=f"^{name}"):
        sim.simulate(kw["theta"], kw["goal"], kw["start"])


def test_simulate_rejects_bad_types(panda_sim):
    with pytest.raises(TypeError, match="^theta"):
        panda_sim.simulate("abc", [0.4, 0.1, 0.4])
    with pytest.raises(TypeError, match="^theta"):
        panda_sim.simulate(panda_sim.bounds.reshape(-1).half(), [0.4, 0.1, 0.4])
    # start just inside the slack is accepted
    panda_sim.simulate(torch.stack([panda_sim.start + 5e-7, panda_sim.start + 0.1], -1).reshape(-1),
                       [0.4, 0.1, 0.4])


@pytest.mark.parametrize("field,value,exc", [
    ("tol", float("nan"), ValueError), ("gain", float("inf"), ValueError), ("damping", -0.1, ValueError),
    ("max_cartesian_step", 0.0, ValueError), ("max_joint_step", float("nan"), ValueError),
    ("null_gain", -1.0, ValueError), ("null_gain", float("inf"), ValueError),
    ("max_steps", 0, ValueError), ("max_steps", 1.5, TypeError),
    ("derivative_gain", -0.5, ValueError), ("early_stop", 1, TypeError),
])
def test_config_validation(field, value, exc):
    with pytest.raises(exc, match=f"^{field}"):
        ControllerConfig(**{field: value})


def test_config_is_frozen_and_strict():
    cfg = ControllerConfig()
    assert cfg.max_steps == 100
    with pytest.raises(TypeError):
        ControllerConfig(gains=1.0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.tol = 0.1
    assert ControllerConfig(null_gain=0.0).null_gain == 0.0


def test_construction_validation(panda_sim, tmp_path):
    path = panda_urdf_path()
    with pytest.raises(ValueError, match="^end_effector"):
        from_urdf(path, "no_such_link")
    with pytest.raises(ValueError, match="^joints"):
        from_urdf(path, "panda_hand", joints=["panda_joint1", "nope"])
    with pytest.raises(ValueError, match="^joints"):
        from_urdf(path, "panda_hand", joints=["panda_joint2", "panda_joint1"])
    with pytest.raises(ValueError, match="^backend"):
        from_urdf(path, "panda_hand", backend="cuda")
    with pytest.raises(TypeError, match="^controller"):
        from_urdf(path, "panda_hand", controller={"tol": 0.01})
    with pytest.raises(ValueError, match="^start"):
        from_urdf(path, "panda_hand", start=[0.0, 0.0, 0.0, 0.5, 0.0, 1.0, 0.0])
    with pytest.raises(ValueError, match="^urdf"):
        from_urdf(tmp_path / "missing.urdf", "tip")
    with pytest.raises(ValueError, match="^urdf"):
        from_urdf("<robot name='x'><link name='a'/><joint name='j' type='revolute'></robot>", "a")
    with pytest.raises(ValueError, match="^q"):
        panda_sim.forward_kinematics(torch.zeros(3, 6))
    with pytest.raises(ValueError, match="^limits"):
        sample_goals(panda_sim, torch.zeros(6, 2), 5, torch.Generator())
    with pytest.raises(ValueError, match="^n"):
        sample_goals(panda_sim, panda_sim.bounds, 0, torch.Generator())


def test_sample_goals_reachable_and_seeded(panda_sim):
    lim = panda_sim.bounds.clone()
    lim[:, 1] = (lim[:, 0] + lim[:, 1]) / 2
    a = sample_goals(panda_sim, lim, 50, torch.Generator().manual_seed(0))
    b = sample_goals(panda_sim, lim, 50, torch.Generator().manual_seed(0))
    assert a.shape == (50, 3) and a.dtype == torch.float64 and torch.equal(a, b)
    assert isinstance(panda_sim, KinematicSimulator)
