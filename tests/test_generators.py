"""Human-like reach generators (issue 33) against hand computations: the minimum-jerk profile,
the via-point, the limits, the determinism of the per-reach nuisances."""

import math

import numpy as np
import pytest
import torch

from camo_sbi.scenarios.generators import (
    GeneratorConfig,
    HumanLikeReaches,
    make_generator,
    minimum_jerk,
    minimum_jerk_speed,
)
from camo_sbi.simulators import sample_goals
from camo_sbi.simulators.base import theta_to_limits


@pytest.fixture(scope="module")
def sim():
    from tests.conftest import build_simulator

    return build_simulator("panda")


@pytest.fixture(scope="module")
def free(sim):
    return sim.bounds.reshape(-1).clone()  # the full range: no limit in the way


def _inner_goals(sim, n, seed):
    """Goals well inside the workspace: FK of postures in the middle half of every range."""
    b = sim.bounds
    mid, half = b.mean(dim=1), (b[:, 1] - b[:, 0]) / 4
    lim = torch.stack([torch.maximum(mid - half, b[:, 0]), torch.minimum(mid + half, b[:, 1])], dim=1)
    return sample_goals(sim, lim, n, seed)


def test_profile_closed_form():
    tau = np.linspace(0, 1, 1001)
    s = minimum_jerk(tau)
    assert s[0] == 0 and abs(s[-1] - 1) < 1e-12
    # the speed profile is the derivative of the position profile (central differences)
    np.testing.assert_allclose(np.gradient(s, tau)[1:-1], minimum_jerk_speed(tau)[1:-1], atol=1e-4)
    assert abs(tau[np.argmax(minimum_jerk_speed(tau))] - 0.5) < 1e-9
    assert abs(minimum_jerk_speed(0.5) - 1.875) < 1e-12


def test_minimum_jerk_speed_is_bell_shaped_and_peaks_at_mid_time(sim, free):
    k = 3.0
    gen = HumanLikeReaches(sim, GeneratorConfig("minimum-jerk", seed=4, slowness=(k, k)))
    goals = _inner_goals(sim, 4, 11)
    tr = gen.simulate(free.expand(4, -1), goals)
    x0 = sim.forward_kinematics(sim.start).double()
    cap = sim.config.max_cartesian_step
    for b in range(4):
        L = float((goals[b] - x0).norm())
        D = math.ceil(k * L / cap)  # the documented duration, by hand
        assert D >= 8
        ee = tr.ee[b].double()
        speed = (ee[1:D + 1] - ee[:D]).norm(dim=-1).numpy()
        # the closed form: displacement per step L (s((t+1)/D) - s(t/D)); tracking within 2 mm per step
        t = np.arange(D)
        expected = L * (minimum_jerk((t + 1) / D) - minimum_jerk(t / D))
        np.testing.assert_allclose(speed, expected, atol=2e-3)
        assert abs((np.argmax(speed) + 0.5) - D / 2) <= 1.0  # the peak at mid-time (step t covers t..t+1)
        # the path is the straight minimum-jerk line: positions within 3 mm of x_d(t)
        xd = x0 + (goals[b] - x0) * torch.as_tensor(minimum_jerk(np.arange(D + 1) / D)).unsqueeze(-1)
        assert float((ee[:D + 1] - xd).norm(dim=-1).max()) < 3e-3
        assert bool(tr.reached[b])


def test_via_point_path_passes_its_via_point(sim, free):
    k, h = 3.0, 0.15
    gen = HumanLikeReaches(sim, GeneratorConfig("via-point", seed=2, slowness=(k, k), via_height=(h, h)))
    goals = _inner_goals(sim, 4, 5)
    tr = gen.simulate(free.expand(4, -1), goals)
    x0 = sim.forward_kinematics(sim.start).double()
    for b in range(4):
        via = 0.5 * (x0 + goals[b]) + torch.tensor([0.0, 0.0, h], dtype=torch.float64)
        L = int(tr.length[b])
        gap = float((tr.ee[b, :L].double() - via).norm(dim=-1).min())
        assert gap < 5e-3, f"reach {b}: nearest point {gap * 1e3:.1f} mm from the via point"
        # the hand rises h above the start-goal midpoint on the way: lift, then place
        assert float(tr.ee[b, :L, 2].max()) > float(0.5 * (x0[2] + goals[b, 2])) + h - 5e-3
        assert bool(tr.reached[b])


def test_limits_respected_and_a_goal_beyond_them_ends_where_they_stop_the_hand(sim):
    from camo_sbi.experiments.subjects import subject_theta

    theta = subject_theta(sim, "panda", "mixed_restricted")
    lim = theta_to_limits(theta)
    goals = sample_goals(sim, sim.bounds, 12, 3)  # nominal workspace: some beyond the subject
    for name in ("minimum-jerk", "via-point"):
        gen = make_generator(sim, name, seed=1, tremor_mm=2.0)
        tr = gen.simulate(theta.expand(12, -1), goals)
        assert bool(((tr.q >= lim[:, 0] - 1e-12) & (tr.q <= lim[:, 1] + 1e-12)).all())
        final = tr.ee[torch.arange(12), tr.length - 1]
        torch.testing.assert_close(final, tr.ee[:, -1])  # held after the end
        # the final hand is FK of the final posture (joint angles and positions consistent)
        torch.testing.assert_close(sim.forward_kinematics(tr.q[:, -1]), tr.ee[:, -1], atol=1e-9, rtol=0)
        far = (final - goals).norm(dim=-1) >= sim.config.tol
        assert torch.equal(far, ~tr.reached)
        # an unreached goal: the hand stopped (moved < 0.5 mm in its last step) before the horizon
        L = tr.length
        for b in torch.nonzero(far).flatten().tolist():
            if int(L[b]) < tr.ee.shape[1]:
                assert float((tr.ee[b, L[b] - 1] - tr.ee[b, L[b] - 2]).norm()) < 5e-4


def test_nuisances_are_keyed_on_the_reach_not_the_batch(sim, free):
    gen = make_generator(sim, "minimum-jerk", seed=7, tremor_mm=3.0)
    goals = _inner_goals(sim, 3, 1)
    a = gen.simulate(free.expand(3, -1), goals)
    b = gen.simulate(free.expand(3, -1), goals.flip(0))
    torch.testing.assert_close(a.ee, b.ee.flip(0), rtol=0, atol=1e-12)
    # another seed: other durations / tremor
    c = make_generator(sim, "minimum-jerk", seed=8, tremor_mm=3.0).simulate(free.expand(3, -1), goals)
    assert not torch.equal(a.length, c.length) or float((a.ee - c.ee).abs().max()) > 1e-4
    # the controller is the simulator itself
    assert make_generator(sim, "controller") is sim


def test_bad_input_names_the_argument(sim):
    with pytest.raises(ValueError, match="generator"):
        make_generator(sim, "spline")
    with pytest.raises(ValueError, match="kind"):
        GeneratorConfig("spline")
    with pytest.raises(ValueError, match="slowness"):
        GeneratorConfig(slowness=(3.0, 2.0))
    with pytest.raises(ValueError, match="tremor_mm"):
        make_generator(sim, "controller", tremor_mm=2.0)
    with pytest.raises(ValueError, match="tremor_mm"):
        GeneratorConfig(tremor_mm=-1.0)
    with pytest.raises(ValueError, match="theta"):
        make_generator(sim, "via-point").simulate(torch.zeros(3), torch.zeros(3))


DATA = __import__("pathlib").Path(__file__).parent / "data"
ARM7 = ["--urdf", str(DATA / "arm7.urdf"), "--ee", "tool", "--start", "0,0.4,0,-1.1,0,0.7,0"]


def test_simulate_observations_generator_flag(tmp_path, capsys):
    """``--generator via-point`` writes slower reaches (bell-shaped speed, lift then place: more
    samples for the same goals) than the controller; bad combinations exit 2 naming the flag."""
    from camo_sbi.experiments.cli import main
    from camo_sbi.experiments.models import ModelSpec
    from camo_sbi.io.recordings import load_recordings

    sim = ModelSpec(kind="urdf", urdf=str(DATA / "arm7.urdf"), ee="tool",
                    start=(0, 0.4, 0, -1.1, 0, 0.7, 0)).build()
    obs = {}
    for g in ("controller", "via-point"):
        out = tmp_path / f"{g}.csv"
        assert main(["simulate-observations", *ARM7, "--limits", str(DATA / "arm7_limits.json"), "--reaches", "3",
                     "--generator", g, "--out", str(out)]) == 0
        assert f"({g})" in capsys.readouterr().out
        obs[g] = load_recordings(out, sim, resample=None)
    for a, b in zip(obs["controller"], obs["via-point"], strict=True):
        torch.testing.assert_close(a.goal, b.goal)  # the same goals, another way of moving
    assert sum(o.length for o in obs["via-point"]) > 1.3 * sum(o.length for o in obs["controller"])
    with pytest.raises(SystemExit) as exc:
        main(["simulate-observations", *ARM7, "--limits", str(DATA / "arm7_limits.json"), "--tremor-mm", "2",
              "--out", str(tmp_path / "x.csv")])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--tremor-mm" in err[0]


@pytest.mark.slow
@pytest.mark.parametrize("generator", ["minimum-jerk", "via-point"])
def test_reproduce_misspecified_runs_with_the_usual_metrics(tmp_path, generator):
    import pandas as pd

    from camo_sbi.experiments.cli import main

    out = tmp_path / generator
    assert main(["reproduce", "panda", "--model", "panda", "--setting", "misspecified", "--generator", generator,
                 "--tremor-mm", "2", "--runs", "1", "--tasks", "2", "--test-goals", "4", "--methods", "naive",
                 "--out", str(out)]) == 0
    df = pd.read_csv(out / "results.csv")
    metrics = set(df.metric)
    for m in ("cartesian_error_mm", "reachability_f1", "binding_test_fraction", "binding_train_fraction"):
        assert m in metrics
    # the oracle (true limits, the controller) no longer scores 0: the model's own error
    oracle = df[(df.method == "oracle") & (df.metric == "cartesian_error_mm")].value
    assert float(oracle.min()) > 1.0
