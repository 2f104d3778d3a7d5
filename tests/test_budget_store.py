"""Budget enforcement (CountingSimulator, run_method), the method registry, and the ResultStore."""

import os
import re
from dataclasses import dataclass

import numpy as np
import pandas as pd
import pytest
import torch

from camo_sbi.budget import BudgetExceededError, CountingSimulator
from camo_sbi.experiments.store import ResultStore, cell_key
from camo_sbi.inference import registry
from camo_sbi.inference.registry import (
    Capabilities,
    Implementation,
    MethodSpec,
    get_method,
    make_config,
    run_method,
    run_method_sequence,
)
from camo_sbi.inference.result import PosteriorResult
from camo_sbi.scenarios.reaching import make_reaching_task
from tests.toy_sim import ToySimulator

TRUE = torch.tensor([-0.3, 0.4, -0.5, 0.6], dtype=torch.float64)


class SpySimulator(ToySimulator):
    """The toy simulator, recording how many trajectories it was asked for."""

    def __init__(self, **kw):
        super().__init__(**kw)
        self.calls = []

    def simulate(self, theta, goal, start=None):
        self.calls.append(1 if theta.dim() == 1 else int(theta.shape[0]))
        return super().simulate(theta, goal, start)


def _thetas(b, seed=0):
    from camo_sbi.priors import BoxPrior

    sim = ToySimulator()
    return BoxPrior(sim.bounds, sim.start).sample(b, seed=seed)


GOAL = torch.tensor([0.5, 0.5, 0.0], dtype=torch.float64)


# ---------------------------------------------------------------- CountingSimulator


def test_counter_counts_batch_size_per_call():
    spy = SpySimulator()
    c = CountingSimulator(spy, max_simulations=None)
    assert c.n_simulations == 0 and c.remaining is None
    c.simulate(_thetas(5), GOAL)
    c.simulate(_thetas(1)[0], GOAL)  # a single (2n,) theta costs one
    c.simulate(_thetas(12), GOAL)
    assert c.n_simulations == 18
    assert spy.calls == [5, 1, 12]


def test_counter_returns_the_wrapped_result_unchanged():
    spy = ToySimulator()
    c = CountingSimulator(spy, max_simulations=100)
    th = _thetas(4)
    a, b = c.simulate(th, GOAL), spy.simulate(th, GOAL)
    for f in ("q", "ee", "length", "reached"):
        assert torch.equal(getattr(a, f), getattr(b, f))


def test_counter_delegates_attributes():
    spy = SpySimulator(n=3, max_steps=12)
    c = CountingSimulator(spy, max_simulations=10)
    assert c.wrapped is spy
    assert c.n_joints == 3 and c.joint_names == ["x0", "x1", "x2"] and c.max_steps == 12
    assert torch.equal(c.bounds, spy.bounds) and torch.equal(c.start, spy.start)
    q = torch.tensor([[0.1, 0.2, 0.3]], dtype=torch.float64)
    torch.testing.assert_close(c.forward_kinematics(q), spy.forward_kinematics(q))
    with pytest.raises(AttributeError):
        c.no_such_attribute  # noqa: B018
    # delegation never counts
    assert c.n_simulations == 0 and spy.calls == []


def test_counter_raises_before_simulating_and_leaves_state_unchanged():
    spy = SpySimulator()
    c = CountingSimulator(spy, max_simulations=10)
    c.simulate(_thetas(6), GOAL)
    assert c.remaining == 4
    with pytest.raises(BudgetExceededError, match="budget"):
        c.simulate(_thetas(5), GOAL)
    assert c.n_simulations == 6 and c.remaining == 4
    assert spy.calls == [6]  # the over-budget call never reached the simulator
    # exactly using up the remainder is allowed, one more is not
    c.simulate(_thetas(4), GOAL)
    assert c.n_simulations == 10 and c.remaining == 0
    with pytest.raises(BudgetExceededError):
        c.simulate(_thetas(1)[0], GOAL)
    assert c.n_simulations == 10 and spy.calls == [6, 4]


def test_budget_exceeded_is_a_runtime_error_with_the_numbers():
    c = CountingSimulator(ToySimulator(), max_simulations=3)
    with pytest.raises(RuntimeError, match=r"0 simulations used, 7 more requested, budget is 3"):
        c.simulate(_thetas(7), GOAL)


@pytest.mark.parametrize("cap, exc", [(0, ValueError), (-5, ValueError), (2.5, TypeError), (True, TypeError)])
def test_counter_rejects_bad_cap(cap, exc):
    with pytest.raises(exc, match="^max_simulations"):
        CountingSimulator(ToySimulator(), max_simulations=cap)


def test_counter_counts_trajectories_produced_by_broadcasting(panda_sim):
    """One theta against M goals yields M simulated trajectories: that must cost M, not 1.

    The Panda simulator broadcasts a batch of one against the goals (documented in
    `KinematicSimulator.simulate`), so a method can otherwise get M trajectories for one unit.
    """
    theta = torch.cat([panda_sim.bounds[:, 0:1], panda_sim.bounds[:, 1:2]], dim=1).reshape(-1)
    goals = panda_sim.forward_kinematics(panda_sim.start).expand(5, 3).clone() + 0.01
    c = CountingSimulator(panda_sim, max_simulations=3)
    try:
        traj = c.simulate(theta, goals)
    except BudgetExceededError:
        return  # refusing 5 trajectories on a budget of 3 is correct
    assert c.n_simulations == traj.batch_size, (
        f"counted {c.n_simulations} simulation(s) for {traj.batch_size} trajectories"
    )


# ---------------------------------------------------------------- run_method with a fake method


@dataclass(frozen=True)
class FakeConfig:
    per_call: int = 5
    calls: int = 1
    swallow: bool = False  # catch BudgetExceededError and carry on
    reported: int = 999_999  # what the method (wrongly) self-reports


FAKE_LOG: list = []


def _fake_run(task, observations, *, budget, seed, config):
    sim = task.simulator
    FAKE_LOG.append({"simulator": sim, "budget": budget, "seed": seed, "cap": getattr(sim, "max_simulations", None),
                     "n_obs": len(observations)})
    rng = np.random.default_rng(seed)
    done = 0
    for _ in range(config.calls):
        th = task.prior.sample(config.per_call, rng)
        try:
            sim.simulate(th, observations[0].goal, observations[0].start)
            done += config.per_call
        except BudgetExceededError:
            if not config.swallow:
                raise
    FAKE_LOG[-1]["done"] = done
    n = task.prior.dim
    return PosteriorResult(method="whatever", samples=np.zeros((3, n)), weights=None, estimate=np.zeros(n),
                           n_simulations=config.reported, wall_time=-1.0, n_tasks=-1)


def _fake_run_sequence(task, observations, *, budget, seed, config):
    out = []
    for k in range(len(observations)):
        r = _fake_run(task, observations[: k + 1], budget=budget, seed=seed + k, config=config)
        out.append(r)
    return out


@pytest.fixture
def fake_method(monkeypatch):
    plain = Implementation(_fake_run, FakeConfig)
    continual = Implementation(_fake_run, FakeConfig, _fake_run_sequence)
    monkeypatch.setitem(registry._REGISTRY, "fake", MethodSpec("fake", "test", lambda: plain, Capabilities()))
    monkeypatch.setitem(registry._REGISTRY, "fake-seq", MethodSpec("fake-seq", "test", lambda: continual,
                                                                   Capabilities(continual=True)))
    FAKE_LOG.clear()
    yield "fake"
    FAKE_LOG.clear()


@pytest.fixture(scope="module")
def toy_task():
    return make_reaching_task(ToySimulator(), TRUE, n_train=3, n_test=2, seed=0)


def test_run_method_caps_at_budget_times_observations(fake_method, toy_task):
    res = run_method("fake", toy_task, budget=4, seed=1, config={"per_call": 4, "calls": 3})
    log = FAKE_LOG[-1]
    assert isinstance(log["simulator"], CountingSimulator)
    assert log["cap"] == 12 and log["budget"] == 4 and log["seed"] == 1
    assert res.n_simulations == 12 and log["done"] == 12
    # a subset of the observations lowers the cap
    res2 = run_method("fake", toy_task, toy_task.observations[:2], budget=4, seed=1,
                      config={"per_call": 2, "calls": 4})
    assert FAKE_LOG[-1]["cap"] == 8 and res2.n_simulations == 8 and res2.n_tasks == 2


def test_run_method_stops_an_overspending_method(fake_method, toy_task):
    with pytest.raises(BudgetExceededError, match="budget is 12"):
        run_method("fake", toy_task, budget=4, seed=1, config={"per_call": 5, "calls": 3})
    # 2 calls of 5 fitted; the third was refused before simulating
    counter = FAKE_LOG[-1]["simulator"]
    assert counter.n_simulations == 10 and counter.max_simulations == 12
    assert type(toy_task.simulator) is ToySimulator  # the caller's task is not rewired


def test_run_method_method_that_ignores_the_error_cannot_exceed_cap(fake_method, toy_task):
    res = run_method("fake", toy_task, budget=4, seed=1, config={"per_call": 5, "calls": 10, "swallow": True})
    assert res.n_simulations == 10 <= 12
    assert FAKE_LOG[-1]["done"] == 10


def test_run_method_overrides_self_reported_fields(fake_method, toy_task):
    res = run_method("fake", toy_task, budget=10, seed=3, config={"per_call": 7, "reported": 123_456})
    assert res.n_simulations == 7  # from the wrapper, not the method's 123456
    assert res.method == "fake"
    assert res.n_tasks == 3
    assert res.wall_time >= 0.0  # the method said -1


def test_run_method_fresh_counter_per_call(fake_method, toy_task):
    run_method("fake", toy_task, budget=4, seed=0, config={"per_call": 12})
    res = run_method("fake", toy_task, budget=4, seed=0, config={"per_call": 12})
    assert res.n_simulations == 12  # the second run was not charged for the first
    assert FAKE_LOG[0]["simulator"] is not FAKE_LOG[1]["simulator"]


def test_run_method_bad_arguments(fake_method, toy_task):
    with pytest.raises(ValueError, match="observations"):
        run_method("fake", toy_task, [], budget=4, seed=0)
    with pytest.raises(ValueError, match="budget"):
        run_method("fake", toy_task, budget=0, seed=0)
    with pytest.raises(TypeError, match="budget"):
        run_method("fake", toy_task, budget=2.5, seed=0)
    with pytest.raises(ValueError, match="method"):
        run_method("no-such-method", toy_task, budget=4, seed=0)
    with pytest.raises(ValueError, match="per_cal"):
        run_method("fake", toy_task, budget=4, seed=0, config={"per_cal": 3})
    assert FAKE_LOG == []  # nothing ran


def test_run_method_sequence_reruns_non_continual_with_growing_caps(fake_method, toy_task):
    res = run_method_sequence("fake", toy_task, budget=4, seed=0, config={"per_call": 4, "calls": 10,
                                                                         "swallow": True})
    assert [r.n_tasks for r in res] == [1, 2, 3]
    assert [log["cap"] for log in FAKE_LOG] == [4, 8, 12]
    assert [r.n_simulations for r in res] == [4, 8, 12]


def test_run_method_sequence_continual_shares_one_capped_counter(fake_method, toy_task):
    res = run_method_sequence("fake-seq", toy_task, budget=4, seed=0,
                              config={"per_call": 3, "calls": 1, "reported": 777})
    sims = {id(log["simulator"]) for log in FAKE_LOG}
    assert len(sims) == 1 and FAKE_LOG[0]["cap"] == 12
    assert [r.n_tasks for r in res] == [1, 2, 3] and all(r.method == "fake-seq" for r in res)
    # the counter saw 3 + 3 + 3 simulations; the final count must come from it, not the method's 777
    assert res[-1].n_simulations == 9


# ---------------------------------------------------------------- registry


def test_get_method_known_and_unknown():
    from camo_sbi.inference import camo

    impl = get_method("camo").load()
    assert impl.run is camo.run and impl.config is camo.CamoConfig and impl.run_sequence is camo.run_sequence
    assert get_method("naive").name == "naive"
    with pytest.raises(ValueError, match=r"^method: unknown method 'camoo'.*camo, camo-js, camo-cs, camo-hull, camo-seq, camo-seq-cs, naive"):
        get_method("camoo")
    with pytest.raises(ValueError, match="method"):
        get_method(None)
    with pytest.raises(ValueError, match="method"):
        get_method(["camo"])


def test_make_config_defaults_dicts_overrides_and_unknown_fields():
    from camo_sbi.inference.camo import CamoConfig

    assert make_config("camo") == CamoConfig()
    c = make_config("camo", {"keep_best": 7})
    assert isinstance(c, CamoConfig) and c.keep_best == 7
    c2 = make_config("camo", c, space="cartesian")
    assert c2.keep_best == 7 and c2.space == "cartesian" and c.space == "joint"
    assert make_config("camo", {"keep_best": 7}, keep_best=9).keep_best == 9
    with pytest.raises(ValueError, match=r"unknown field.*'kep_best'"):
        make_config("camo", {"kep_best": 3})
    with pytest.raises(ValueError, match=r"unknown field.*'foo'"):
        make_config("camo", foo=1)
    with pytest.raises(TypeError, match="config"):
        make_config("camo", object())
    with pytest.raises(ValueError, match="method"):
        make_config("nope")


def test_variants_always_apply_their_defaults():
    """camo-hull given a plain CamoConfig is still camo-hull (it was plain CAMO under that label)."""
    from camo_sbi.inference.camo import CamoConfig

    for cfg in (None, CamoConfig(), CamoConfig(contain_observed=False, keep_best=9), {"keep_best": 9}):
        c = make_config("camo-hull", cfg)
        assert c.contain_observed is True and c.space == "joint"
    assert make_config("camo-hull", CamoConfig(keep_best=9)).keep_best == 9  # other fields kept
    assert make_config("camo-cs", CamoConfig(space="joint")).space == "cartesian"
    # a dict that contradicts the variant is refused, naming the field
    with pytest.raises(ValueError, match=r"^config: method 'camo-hull' is defined by contain_observed=True"):
        make_config("camo-hull", {"contain_observed": False})
    with pytest.raises(ValueError, match=r"^config: method 'camo-cs' is defined by space='cartesian'"):
        make_config("camo-cs", space="joint")


def test_capabilities_drive_the_method_lists():
    baselines = registry.names(baseline=True)
    assert baselines == ["naive", "nominal", "oracle"]
    assert "npe" in registry.names(baseline=False) and "naive" not in registry.names(baseline=False)
    assert registry.names(space="cartesian", baseline=True) == ["nominal", "oracle"]  # naive needs joints
    assert "camo-cs" not in registry.names(space="joint")
    # what simulates nothing per person: the baselines and the amortized methods (trained once beforehand)
    assert set(registry.names(simulates=False)) == set(baselines) | set(registry.names(amortized=True))
    assert "npe-amortized" in registry.names(amortized=True)
    assert registry.capabilities("oracle").needs_truth and not registry.capabilities("nominal").needs_truth
    for name in registry.names():
        spec = get_method(name)
        impl = spec.load()  # every loader imports and returns a real implementation
        assert callable(impl.run) and isinstance(impl.config, type)
        assert spec.capabilities.continual == (impl.run_sequence is not None), name
        if spec.base is not None:
            assert get_method(spec.base).load() == impl, name
    with pytest.raises(ValueError, match="^spec: a method named 'camo' is already registered"):
        registry.register(get_method("camo"))


# ---------------------------------------------------------------- ResultStore


def _rows(tag, n=3):
    return [{"cell": tag, "i": i, "value": float(i) / 3} for i in range(n)]


def test_store_put_done_table(tmp_path):
    st = ResultStore(tmp_path / "run")
    assert (tmp_path / "run" / "cells").is_dir()
    assert st.table().empty and st.finished_keys() == set()
    assert not st.done("b")
    st.put("b", _rows("b"))
    st.put("a", _rows("a", 2))
    assert st.done("a") and st.done("b") and not st.done("c")
    assert st.finished_keys() == {"a", "b"}
    df = st.table()
    assert list(df.columns) == ["cell", "i", "value"]
    assert df.cell.tolist() == ["a", "a", "b", "b", "b"]  # key order
    np.testing.assert_allclose(df.value.to_numpy(), [0, 1 / 3, 0, 1 / 3, 2 / 3], rtol=0, atol=1e-15)
    # a second store on the same directory sees the same cells (resumability)
    pd.testing.assert_frame_equal(ResultStore(tmp_path / "run").table(), df)
    out = st.write_table()
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "run" / "results.csv"), df)
    pd.testing.assert_frame_equal(out, df)


def test_store_reput_replaces_not_duplicates(tmp_path):
    st = ResultStore(tmp_path)
    st.put("k", _rows("old", 4))
    st.put("k", _rows("new", 2))
    df = st.table()
    assert len(df) == 2 and set(df.cell) == {"new"}
    assert len(list((tmp_path / "cells").iterdir())) == 1


def _no_temp_files(d):
    return [p.name for p in d.iterdir() if p.suffix == ".tmp" or p.name.startswith(".")]


def test_store_crash_mid_write_leaves_no_cell_and_no_temp(tmp_path, monkeypatch):
    st = ResultStore(tmp_path)
    st.put("keep", _rows("keep"))

    def boom(src, dst):
        assert os.path.exists(src)  # the temp file was fully written before the (failing) rename
        raise OSError("simulated crash during rename")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError, match="simulated crash"):
        st.put("new", _rows("new"))
    with pytest.raises(OSError, match="simulated crash"):
        st.put("keep", _rows("overwrite", 1))  # an existing cell must survive a failed re-put
    monkeypatch.undo()
    assert not st.done("new")
    assert st.finished_keys() == {"keep"}
    assert _no_temp_files(tmp_path / "cells") == []
    df = st.table()
    assert df.cell.tolist() == ["keep"] * 3


def test_store_crash_during_write_itself(tmp_path, monkeypatch):
    """A failure while writing the temp file (disk full) also leaves nothing behind."""
    st = ResultStore(tmp_path)

    def full(fd):
        raise OSError("No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(OSError, match="No space"):
        st.put("x", _rows("x"))
    monkeypatch.undo()
    assert not st.done("x") and _no_temp_files(tmp_path / "cells") == []


def test_store_cell_with_no_rows_does_not_break_table(tmp_path):
    st = ResultStore(tmp_path)
    st.put("a", _rows("a"))
    st.put("empty", [])
    assert st.done("empty")
    df = st.table()
    assert df.cell.tolist() == ["a"] * 3


def test_cell_key_order_independent_and_distinct():
    a = cell_key({"method": "camo", "seed": 1, "budget": 100})
    b = cell_key({"budget": 100, "seed": 1, "method": "camo"})
    assert a == b
    assert cell_key({"method": "camo", "seed": 2, "budget": 100}) != a
    assert cell_key({"method": "camo", "seed": 1}) != a
    # values that slug to the same text still differ by the digest
    assert cell_key({"a": "x/y"}) != cell_key({"a": "x-y"})
    assert cell_key({"a": "x y"}) != cell_key({"a": "x-y"})


@pytest.mark.parametrize(
    "params",
    [
        {"path": "../../etc/passwd", "x": 1},
        {"name": "a b\tc\nd", "unicode": "Δθ→π", "slash": "a\\b/c"},
        {"nul": "a\x00b", "colon": "C:\\x", "star": "*?<>|\"'"},
        {"long": "x" * 1000, "more": list(range(50))},
        {},
    ],
)
def test_cell_key_is_filesystem_safe(params, tmp_path):
    key = cell_key(params)
    assert re.fullmatch(r"[A-Za-z0-9=._-]+", key), key
    assert "/" not in key and "\\" not in key and key not in (".", "..")
    assert len(key) + len(".csv") <= 255
    # usable as a cell file name, round-trips through the store
    st = ResultStore(tmp_path)
    st.put(key, [{"v": 1}])
    assert st.done(key) and st.finished_keys() == {key}
    assert [p.parent for p in (tmp_path / "cells").iterdir()] == [tmp_path / "cells"]


def test_the_cap_s_old_name_is_refused_naming_the_new_one():
    """issue 26's vocabulary: ``budget`` is per task; the counter's total cap is ``max_simulations``."""
    with pytest.raises(TypeError, match=r"^budget: renamed 'max_simulations'"):
        CountingSimulator(ToySimulator(), budget=3)
    with pytest.raises(ValueError, match="^max_simulations:"):
        CountingSimulator(ToySimulator(), max_simulations=0)
