"""npe-amortized: training once, files, refusals, zero simulations at inference, a known posterior."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from camo_sbi.budget import CountingSimulator
from camo_sbi.inference import (
    amortized,
    amortized_data,
    amortized_estimator,
    amortized_flows,
    flow_space,
    sbi_adapter,
)
from camo_sbi.inference.amortized import AmortizedConfig, TrainConfig, load_estimator, train
from camo_sbi.inference.npe_posterior import NpePosterior
from camo_sbi.inference.registry import capabilities, run_method
from camo_sbi.priors import BoxPrior
from camo_sbi.scenarios.reaching import make_reaching_task, observe
from camo_sbi.task import NoiseModel, Observation, Task
from tests.toy_sim import ToySimulator

TRUE = torch.tensor([-0.3, 0.4, -0.5, 0.6], dtype=torch.float64)
TINY = TrainConfig(simulations=600, spaces=("joint", "cartesian"), max_epochs=3, hidden_features=8,
                   num_transforms=1, training_batch_size=50)
RUN = {"n_posterior_samples": 300, "is_rounds": 1, "min_ess": 0.0}


@pytest.fixture(scope="module")
def paths(tmp_path_factory):
    """One tiny toy estimator per form (the default form is "set")."""
    d = tmp_path_factory.mktemp("amortized")
    out = {}
    for form in amortized.FORMS:
        out[form] = d / f"toy-{form}.pt"
        train(ToySimulator(), model="toy", config=dataclasses.replace(TINY, form=form), seed=0).save(out[form])
    return out


@pytest.fixture(scope="module")
def est_path(paths):
    return paths["per-reach"]


@pytest.fixture(scope="module")
def task():
    return make_reaching_task(ToySimulator(), TRUE, n_train=3, n_test=2, seed=0, name="toy", subject="toy")


def _run(task, path, **cfg):
    return run_method("npe-amortized", task, budget=1, seed=5, config={**RUN, "estimator_path": str(path), **cfg})


def test_registered_as_amortized_and_simulation_free():
    cap = capabilities("npe-amortized")
    assert cap.amortized and not cap.simulates and cap.posterior
    assert set(cap.spaces) == {"joint", "cartesian"}


def test_training_is_deterministic_and_leaves_the_global_rng_alone():
    cfg = dataclasses.replace(TINY, simulations=200, max_epochs=1, spaces=("joint",))
    torch.manual_seed(123)
    before = torch.random.get_rng_state()
    a = train(ToySimulator(), model="toy", config=cfg, seed=3)
    assert torch.equal(torch.random.get_rng_state(), before)
    b = train(ToySimulator(), model="toy", config=cfg, seed=3)
    for (ka, va), (kb, vb) in zip(a.flows["joint"].state_dict().items(), b.flows["joint"].state_dict().items(),
                                  strict=True):
        assert ka == kb and torch.equal(va, vb), ka
    c = train(ToySimulator(), model="toy", config=cfg, seed=4)
    assert not torch.equal(next(iter(a.flows["joint"].parameters())), next(iter(c.flows["joint"].parameters())))


@pytest.mark.parametrize("form", amortized.FORMS)
def test_save_load_round_trip_gives_identical_samples(form, paths, task, tmp_path):
    est_path = paths[form]
    est = load_estimator(est_path)
    assert est.form == form
    assert est.training_simulations == TINY.simulations and est.training_time > 0
    assert est.spaces == ("joint", "cartesian")
    # the file is a state dict + JSON metadata: it loads with weights_only=True
    blob = torch.load(est_path, weights_only=True)
    assert set(blob) == {"format", "metadata", "state_dict"} and isinstance(blob["metadata"], str)
    copy = tmp_path / "copy.pt"
    copy.write_bytes(est.to_bytes())
    again = amortized_estimator.from_bytes(copy.read_bytes())
    for space in est.spaces:
        for (k, v), (k2, v2) in zip(est.flows[space].state_dict().items(),
                                    again.flows[space].state_dict().items(), strict=True):
            assert k == k2 and torch.equal(v, v2)
    for space in ("joint", "cartesian"):
        a = _run(task, est_path, space=space)
        b = _run(task, copy, space=space)
        np.testing.assert_array_equal(a.samples, b.samples)
        torch.testing.assert_close(a.weights, b.weights, rtol=0, atol=0)
        np.testing.assert_array_equal(a.estimate, b.estimate)
    assert not np.array_equal(_run(task, est_path).samples,
                              run_method("npe-amortized", task, budget=1, seed=6,
                                         config={**RUN, "estimator_path": str(est_path)}).samples)


class _NoSimulation:
    """A simulator that fails the test if anything simulates (attributes delegated)."""

    def __init__(self, sim):
        self._sim = sim

    def simulate(self, *args, **kwargs):
        raise AssertionError("npe-amortized simulated at inference")

    def __getattr__(self, name):
        return getattr(self._sim, name)


@pytest.mark.parametrize("form", amortized.FORMS)
def test_inference_simulates_nothing(form, paths, task):
    est_path = paths[form]
    res = _run(task, est_path)
    assert res.n_simulations == 0  # counted by the registry's budget wrapper
    assert res.status == "ok" and res.n_tasks == 3
    assert res.extras["training_simulations"] == TINY.simulations and res.extras["form"] == form
    guarded = task.with_simulator(CountingSimulator(_NoSimulation(task.simulator), 1))
    res2 = _run(guarded, est_path)
    np.testing.assert_array_equal(res.samples, res2.samples)
    assert bool(task.prior.contains(torch.from_numpy(res.samples)).all())


def test_refuses_what_it_was_not_trained_for(est_path, task, tmp_path):
    with pytest.raises(ValueError, match="^estimator_path: npe-amortized needs"):
        run_method("npe-amortized", task, budget=1, seed=0, config=RUN)
    with pytest.raises(ValueError, match="^estimator: no such file"):
        _run(task, tmp_path / "missing.pt")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match="^estimator: .*not a camo_sbi amortized estimator"):
        _run(task, bad)
    other = tmp_path / "other.pt"
    torch.save({"format": "something/else", "metadata": "{}", "state_dict": {}}, other)
    with pytest.raises(ValueError, match="^estimator: .*format"):
        _run(task, other)
    # another body model (3 joints), another horizon
    three = make_reaching_task(ToySimulator(n=3), torch.tensor([-0.3, 0.4, -0.5, 0.6, -0.2, 0.2]), n_train=1,
                               n_test=1, seed=0)
    with pytest.raises(ValueError, match="^estimator: .*differs in .*joint_names"):
        _run(three, est_path)
    slow = make_reaching_task(ToySimulator(max_steps=25), TRUE, n_train=1, n_test=1, seed=0)
    with pytest.raises(ValueError, match="^estimator: .*differs in"):
        _run(slow, est_path)
    # a strong prior (a fixed joint), another start, other noise, a space without a flow
    strong = dataclasses.replace(task, prior=BoxPrior(task.prior.bounds, task.prior.start, fixed={0: (-0.3, 0.4)}))
    with pytest.raises(ValueError, match="^task.prior:"):
        _run(strong, est_path)
    start = torch.tensor([0.05, -0.05], dtype=torch.float64)
    moved = task.with_observations(observe(task.simulator, TRUE, torch.tensor([[0.3, 0.2, 0.0]]), start))
    with pytest.raises(ValueError, match="^observations: reach 0 starts at"):
        _run(moved, est_path)
    noisy = dataclasses.replace(task, noise=NoiseModel(joint_deg=1.0))
    with pytest.raises(ValueError, match="^task.noise:"):
        _run(noisy, est_path)
    joint_only = tmp_path / "joint.pt"
    train(ToySimulator(), model="toy", config=dataclasses.replace(TINY, spaces=("joint",), simulations=200,
                                                                  max_epochs=1), seed=0).save(joint_only)
    with pytest.raises(ValueError, match="^space: .*not 'cartesian'"):
        _run(task, joint_only, space="cartesian")


def test_a_set_file_of_another_set_embedding_is_refused(paths, tmp_path):
    """The set embedding changed once (the first DeepSet learned nothing); a file of another
    embedding is refused by name, never loaded into the wrong architecture."""
    import io
    import json

    blob = torch.load(paths["set"], weights_only=True)
    meta = json.loads(blob["metadata"])
    assert meta["set_embedding"] == amortized_flows.SET_EMBEDDING
    for value in (None, "deepset-mean/0"):
        m = {k: v for k, v in meta.items() if k != "set_embedding"} | ({} if value is None else {"set_embedding": value})
        m["sha256"] = amortized.payload_sha256(m, blob["state_dict"])  # a consistent file of that embedding
        buf = io.BytesIO()
        torch.save(blob | {"metadata": json.dumps(m)}, buf)
        with pytest.raises(ValueError, match="^estimator: .*set embedding .*retrain"):
            amortized_estimator.from_bytes(buf.getvalue())


def test_a_loaded_nsf_is_the_sbi_flow_draw_for_draw_without_importing_sbi(paths):
    """Loading builds `sbi_adapter.NsfReader` from the metadata and loads the weights: the same
    seed gives bit-identical draws, log densities and sampling to sbi's own flow with those
    weights (both forms); and a fresh process loads and samples without importing sbi or nflows."""
    import json
    import subprocess
    import sys

    for form, path in paths.items():
        est = load_estimator(path)
        blob = torch.load(path, weights_only=True)
        meta = json.loads(blob["metadata"])
        for k, space in enumerate(est.spaces):
            fast = est.flows[space]
            assert isinstance(fast.net, sbi_adapter.NsfReader)
            ref = amortized_flows.new_flow(est.settings, int(est.free_mask.sum()), meta["features"][space]["n_kept"], 0)
            ref.load_state_dict({key[len(space) + 1:]: v for key, v in blob["state_dict"].items()
                                 if key.startswith(space + ".")})
            ref.eval()
            assert not isinstance(ref.net, sbi_adapter.NsfReader)
            width = fast.max_set * (fast.n_features + 1) if form == "set" else meta["features"][space]["n_kept"]
            cond = torch.randn(3, width, generator=torch.Generator().manual_seed(k))
            if form == "set":
                cond = cond.abs().round()  # validity flags 0/1
            got = []
            for flow in (fast, ref):
                with torch.no_grad(), torch.random.fork_rng(devices=[]):
                    torch.manual_seed(7)
                    z = flow.sample((200,), cond)
                    lp = flow.log_prob(z[:, 1], cond[1:2].expand(200, -1))
                    out = [z, lp]
                    if form == "set":
                        torch.manual_seed(8)
                        out += list(flow.sample_and_log_prob((300,), cond[:1]))
                got.append(out)
            for a, b in zip(*got, strict=True):
                assert a.shape == b.shape and torch.equal(a, b), (form, space)
    code = ("import sys, torch; from camo_sbi.inference.amortized import load_estimator; "
            f"e = load_estimator({str(paths['set'])!r}); "
            "e.flows['joint'].sample_and_log_prob((10,), torch.zeros(1, e.flows['joint'].max_set * "
            "(e.flows['joint'].n_features + 1))); "
            "print(sorted(m for m in ('sbi', 'nflows', 'zuko') if m in sys.modules))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "[]"


def test_a_file_of_an_unknown_weight_layout_names_the_sbi_versions(paths):
    """An NSF file whose weights do not fit the layout `NsfReader` (and this sbi) reads, here a
    consistent file (valid checksum) whose layer names an imagined sbi 0.99 renamed, is a
    ValueError naming the sbi that wrote it and the versions this camo_sbi reads."""
    import io
    import json
    from importlib import metadata as dist

    blob = torch.load(paths["set"], weights_only=True)
    meta = json.loads(blob["metadata"])
    state = {k.replace("._transforms.", "._layers."): v for k, v in blob["state_dict"].items()}
    meta["versions"] = {**meta["versions"], "sbi": "0.99.0"}
    meta["sha256"] = amortized.payload_sha256(meta, state)
    buf = io.BytesIO()
    torch.save(blob | {"metadata": json.dumps(meta), "state_dict": state}, buf)
    with pytest.raises(ValueError, match=r"^estimator: .*joint weights do not fit .*written with sbi 0\.99\.0; "
                                         r"this camo_sbi reads the flow layout of sbi >= 0\.25, < 0\.28 "
                                         rf"\(installed: sbi {dist.version('sbi')}\); retrain"):
        amortized_estimator.from_bytes(buf.getvalue())


def _flip(data: bytes, n: int = 200) -> bytes:
    mid = len(data) // 2
    return data[:mid] + bytes(b ^ 0xFF for b in data[mid : mid + n]) + data[mid + n :]


def test_a_damaged_or_incomplete_estimator_file_is_refused_by_name(paths, tmp_path):
    """Every file carries the sha256 of its payload (metadata and weights), verified before use:
    200 flipped bytes mid-file, an edited weight or metadata entry, a missing entry and a file of
    the format before checksums are each one ValueError naming the file; nothing runs."""
    import io
    import json

    good = paths["set"].read_bytes()
    blob = torch.load(io.BytesIO(good), weights_only=True)
    meta = json.loads(blob["metadata"])
    assert meta["sha256"] == amortized.payload_sha256(meta, blob["state_dict"])
    flipped = tmp_path / "flipped.pt"
    flipped.write_bytes(_flip(good))
    with pytest.raises(ValueError, match=f"^estimator: '{flipped}' (fails its sha256 check|is not a camo_sbi)"):
        load_estimator(flipped)

    def save(name, b):
        buf = io.BytesIO()
        torch.save(b, buf)
        (tmp_path / name).write_bytes(buf.getvalue())
        return tmp_path / name

    key = next(k for k, v in blob["state_dict"].items() if v.is_floating_point())
    weights = {**blob["state_dict"], key: blob["state_dict"][key] + 1e-3}
    with pytest.raises(ValueError, match="^estimator: .*weights.pt' fails its sha256 check"):
        load_estimator(save("weights.pt", {**blob, "state_dict": weights}))
    edited = json.dumps({**meta, "seed": meta["seed"] + 1})
    with pytest.raises(ValueError, match="^estimator: .*meta.pt' fails its sha256 check"):
        load_estimator(save("meta.pt", {**blob, "metadata": edited}))
    for entry in ("metadata", "state_dict"):
        with pytest.raises(ValueError, match=f"^estimator: .*no-{entry}.pt' has no valid {entry} entry"):
            load_estimator(save(f"no-{entry}.pt", {k: v for k, v in blob.items() if k != entry}))
    old = {**blob, "format": "camo_sbi.amortized/1"}
    with pytest.raises(ValueError, match="^estimator: .*old.pt' has format 'camo_sbi.amortized/1', written before "
                                         ".*retrain"):
        load_estimator(save("old.pt", old))


def _compare_refuses(estimator, tmp_path, capsys) -> str:
    """compare with this estimator file exits 2 with one line naming it, running no cell."""
    from camo_sbi.experiments.cli import main

    out = tmp_path / "run"
    with pytest.raises(SystemExit) as exc:
        main(["compare", "--model", "panda", "--methods", "npe-amortized", "--amortized", str(estimator),
              "--budgets", "20", "--seeds", "1", "--tasks", "2", "--no-report", "--out", str(out)])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("camo-sbi: error: --amortized: estimator: ") and str(estimator) in err[0]
    assert not (out / "cells").exists()
    return err[0]


def test_infer_with_a_byte_flipped_estimator_exits_2_naming_the_file(paths, tmp_path, capsys):
    flipped = tmp_path / "flipped.pt"
    flipped.write_bytes(_flip(paths["set"].read_bytes()))
    _compare_refuses(flipped, tmp_path, capsys)


def _resigned(blob: dict, edit) -> bytes:
    """The file with its metadata edited by ``edit(meta)`` and correctly re-signed (a consistent
    sha256): only the metadata checks stand between it and the loader."""
    import copy
    import io
    import json

    meta = copy.deepcopy(json.loads(blob["metadata"]))
    edit(meta)
    meta["sha256"] = amortized.payload_sha256(meta, blob["state_dict"])
    buf = io.BytesIO()
    torch.save({**blob, "metadata": json.dumps(meta)}, buf)
    return buf.getvalue()


def _set(path: str, value):
    def edit(meta):
        *parents, last = path.split(".")
        node = meta
        for p in parents:
            node = node[p]
        if value is _DELETE:
            del node[last]
        else:
            node[last] = value
    return edit


_DELETE = object()
# issue 36: each ended in a traceback, n_kept = 1e7 after taking 5.2 GB
RESIGNED = [
    ("settings", _DELETE, r"settings: missing"),
    ("prior", _DELETE, r"prior: missing"),
    ("seed", "abc", r"seed: expected an integer"),
    ("settings.hidden_features", 1e6, r"settings: hidden_features: expected an integer"),
    ("settings.hidden_features", 10**6, r"settings.hidden_features: 1000000 is larger than the \d+ weights"),
    ("features.joint.n_kept", 1e7, r"features.joint.n_kept: 10000000.0 is not the \d+ features"),
    ("features.joint.n_kept", 10**7, r"features.joint.n_kept: 10000000 is not"),
    ("settings.max_set", 10**9, r"settings: simulations: the set form needs at least 10000000000"),
    ("settings", lambda m: m["settings"].update(max_set=10**9, simulations=10**12),
     r"settings.max_set: 1000000000 reaches in a set, at most 10000"),
    ("settings.num_transforms", 10**9, r"settings.num_transforms: 1000000000 is larger"),
    ("settings.noise", _DELETE, r"settings: missing 'noise'"),
    ("settings.spaces", ["joint", "joint"], r"settings: spaces: expected one or more distinct"),
    ("prior.low", [0.0] * 3, r"prior.low: expected a non-empty list of an even number"),
    ("prior.high", [float("nan")] * 4, r"prior.high: expected .* finite numbers"),
    ("fingerprint.start", ["x"], r"fingerprint.start: expected 2 finite numbers"),
    ("training.joint", {}, r"training.joint: expected a table of epochs"),
    ("model", 7, r"model: expected a string, got int"),
]


@pytest.mark.parametrize("key, value, message", RESIGNED, ids=[f"{k}={'...' if callable(v) else 'deleted' if v is _DELETE else repr(v)}"[:40]
                              for k, v, _ in RESIGNED])
def test_a_resigned_estimator_with_edited_metadata_is_refused_naming_the_key(paths, key, value, message):
    blob = torch.load(paths["set"], weights_only=True)
    data = _resigned(blob, value if callable(value) else _set(key, value))
    with pytest.raises(ValueError, match=f"^estimator: 'edited.pt''s metadata: {message}"):
        amortized_estimator.from_bytes(data, "'edited.pt'")
    amortized_estimator.from_bytes(_resigned(blob, lambda m: None), "'same.pt'")  # re-signing alone is fine


def test_compare_with_a_resigned_estimator_exits_2_in_one_line(paths, tmp_path, capsys):
    blob = torch.load(paths["set"], weights_only=True)
    edited = tmp_path / "edited.pt"
    edited.write_bytes(_resigned(blob, _set("features.joint.n_kept", 10**7)))
    assert "features.joint.n_kept" in _compare_refuses(edited, tmp_path, capsys)


def test_set_form_refuses_more_reaches_than_it_was_trained_on(paths):
    est_path = paths["set"]
    sim = ToySimulator()
    many = make_reaching_task(sim, TRUE, n_train=TINY.max_set + 1, n_test=1, seed=0)
    with pytest.raises(ValueError, match="^observations: .*at most max_set"):
        _run(many, est_path)
    ok = run_method("npe-amortized", many, many.observations[: TINY.max_set], budget=1, seed=0,
                    config={**RUN, "estimator_path": str(est_path)})
    assert ok.n_tasks == TINY.max_set and ok.weights is None


def test_set_training_data_are_sets_of_one_limit_vector():
    sim = ToySimulator()
    prior = BoxPrior(sim.bounds, sim.start)
    cfg = dataclasses.replace(TINY, spaces=("joint",), max_set=4, form="set")
    data = amortized.simulate_training_set(sim, prior, cfg, 0, n=400)
    assert data["theta"].shape == (100, 4) and data["x"]["joint"].shape[:2] == (100, 4)
    # the 4 reaches of a set share their limits but not their goals
    goals = data["x"]["joint"][:, :, :2]
    assert bool((goals[:, 0] != goals[:, 1]).any(dim=-1).all())
    ref = sim.simulate(data["theta"][:1].expand(4, -1), torch.cat([goals[0], torch.zeros(4, 1, dtype=goals.dtype)], 1))
    from camo_sbi.inference.flow_space import trajectory_summary

    np.testing.assert_allclose(data["x"]["joint"][0, :, 3:].numpy(),
                               trajectory_summary(ref.q, ref.length, n_points=cfg.n_points).numpy(), atol=1e-5)


def test_config_and_train_arguments_are_checked():
    with pytest.raises(TypeError, match="^estimator_path:"):
        AmortizedConfig(estimator_path=3)
    with pytest.raises(TypeError, match="^estimator: renamed 'estimator_path'"):
        AmortizedConfig(estimator="panda.pt")
    with pytest.raises(ValueError, match="^point_estimate:"):
        AmortizedConfig(point_estimate="argmin")
    with pytest.raises(ValueError, match="^point_estimate: 'map' is now called 'mode'"):
        AmortizedConfig(point_estimate="map")
    with pytest.raises(TypeError, match="^simulation_batch_size: renamed 'chunk_size'"):
        TrainConfig(simulation_batch_size=64)
    with pytest.raises(ValueError, match="^spaces:"):
        TrainConfig(spaces=("joint", "joint"))
    with pytest.raises(ValueError, match="^spaces:"):
        TrainConfig(spaces=("elbow",))
    with pytest.raises(ValueError, match="^simulations:"):
        TrainConfig(simulations=1)
    with pytest.raises(ValueError, match="^simulations: the set form"):
        TrainConfig(simulations=50, form="set")
    with pytest.raises(ValueError, match="^form:"):
        TrainConfig(form="pairs")
    with pytest.raises(TypeError, match="^noise:"):
        TrainConfig(noise=0.1)
    with pytest.raises(ValueError, match="^model:"):
        train(ToySimulator(), model="", config=TINY, seed=0)
    with pytest.raises(TypeError, match="^config:"):
        train(ToySimulator(), model="toy", config={"simulations": 10}, seed=0)


def test_degenerate_importance_weights_set_a_fallback_status(paths, task):
    """combine="is": a too-small ESS is a fallback, warned; the weights are returned."""
    with pytest.warns(RuntimeWarning, match="fallback: combining 3 reaches: low effective sample size"):
        res = _run(task, paths["per-reach"], combine="is", min_ess=1e9)
    assert res.status.startswith("fallback: combining 3 reaches: low effective sample size")
    assert res.weights is not None and res.extras["sampler"] == "is" and res.extras["ess"] > 0


def test_smc_on_request_and_an_unfinished_tempering_is_a_fallback(paths, task):
    res = _run(task, paths["per-reach"], combine="smc")
    assert res.extras["sampler"] == "smc" and res.status == "ok" and res.extras["stages"] >= 1
    assert res.weights is not None and res.weights.shape == (AmortizedConfig().smc_particles,)
    assert res.extras["ess"] >= AmortizedConfig().smc_target_ess * AmortizedConfig().smc_particles
    with pytest.warns(RuntimeWarning, match="fallback: combining 3 reaches: SMC did not reach the target"):
        cut = _run(task, paths["per-reach"], combine="smc", smc_max_stages=1, smc_target_ess=0.99)
    assert cut.status.startswith("fallback: combining 3 reaches: SMC") and cut.extras["stages"] == 1


def test_mcmc_is_the_default_and_a_stuck_sampler_is_a_fallback(paths, task):
    res = _run(task, paths["per-reach"])
    assert res.weights is None and res.extras["sampler"] == "mcmc" and res.status == "ok"
    assert 0.01 <= res.extras["acceptance"] <= 1 and res.extras["steps"] == AmortizedConfig().mcmc_steps
    with pytest.warns(RuntimeWarning, match="fallback: combining 3 reaches: MCMC barely moved"):
        stuck = _run(task, paths["per-reach"], combine="mcmc", min_acceptance=1.0)
    assert stuck.status.startswith("fallback: combining 3 reaches: MCMC")


def test_combine_is_checked(paths, task):
    with pytest.raises(ValueError, match="^combine:"):
        AmortizedConfig(combine="gibbs")
    # a set-form estimator combines nothing: asking it for a sampler is refused, not ignored
    with pytest.raises(ValueError, match="^combine: 'smc' applies to per-reach estimators"):
        _run(task, paths["set"], combine="smc")
    assert _run(task, paths["set"]).extras["sampler"] == "flow"
    assert _run(task, paths["per-reach"]).extras["sampler"] == "mcmc"  # None: the per-reach default
    with pytest.raises(ValueError, match="^mcmc_burn_in:"):
        AmortizedConfig(mcmc_steps=10, mcmc_burn_in=10)
    with pytest.raises(ValueError, match="^mcmc_de_fraction:"):
        AmortizedConfig(mcmc_de_fraction=1.5)
    for field, bad in [("smc_particles", 4), ("smc_moves", 0), ("smc_target_ess", 1.0), ("smc_base", "prior"),
                       ("smc_independent_fraction", 1.5), ("smc_max_stages", 0), ("smc_inflate", 0.0)]:
        with pytest.raises(ValueError, match=f"^{field}:"):
            AmortizedConfig(**{field: bad})


class _GaussianFlow(torch.nn.Module):
    """A fake per-reach "flow": q(z | x) = N(z; x, diag(sd^2)) (the condition IS the mean)."""

    def __init__(self, sd):
        super().__init__()
        self.sd = torch.as_tensor(sd, dtype=torch.float64)

    def _dist(self, condition):
        return torch.distributions.Normal(condition.to(torch.float64), self.sd)

    def log_prob(self, input, condition):  # noqa: A002 - (S, B, d) input, (B, d) condition
        return self._dist(condition).log_prob(input.to(torch.float64)).sum(-1).float()

    def sample(self, sample_shape, condition):
        return self._dist(condition).sample(torch.Size(sample_shape)).float()


def _gaussian_product(seed_means: int = 0, transform: str = "logit"):
    """Three reaches, d = 3: the target prod_i N(z; m_i, S) / p_z(z)^2 (p_z: the prior in z,
    standard logistic for "logit"; for "none" uniform on the box [-1, 1]^3, whose edges cut the product)."""
    sd = torch.tensor([0.3, 0.5, 0.2], dtype=torch.float64)
    means = torch.tensor([[0.2, -0.4, 1.0], [0.4, -0.1, 0.9], [0.0, -0.3, 1.2]], dtype=torch.float64)
    flow = _GaussianFlow(sd)
    post = NpePosterior([flow] * 3, list(means), torch.full((3,), -1.0), torch.full((3,), 1.0),
                            theta_transform=transform)
    return post, means, sd


def _prior_z(grid, transform):
    if transform == "none":
        return torch.where(grid.abs() <= 1, 0.0, -math.inf)
    return torch.nn.functional.logsigmoid(grid) + torch.nn.functional.logsigmoid(-grid)


@pytest.mark.parametrize("sampler, transform", [("mcmc", "logit"), ("smc", "logit"), ("smc", "none")])
def test_samplers_recover_a_known_product_posterior(sampler, transform):
    """The exact target on a fine 1-D grid per coordinate (it factorises), against each sampler:
    MCMC with 128 chains x 300 kept sweeps; SMC with 4096 weighted particles (ESS >= 2048)."""
    post, means, sd = _gaussian_product(transform=transform)
    if sampler == "mcmc":
        draws = post.sample_mcmc(20000, 3, chains=128, steps=400, burn_in=100)
        assert draws.weights.shape == (draws.samples.shape[0],) and 0.1 < draws.diagnostics["acceptance"] < 0.9
    else:
        draws = post.sample_smc(3, particles=4096)
        assert draws.diagnostics["reached"] and draws.ess >= 0.5 * 4096 and len(draws.diagnostics["betas"]) > 2  # it had to temper
    z = post.to_unconstrained(draws.samples)
    w_draws = draws.weights
    grid = torch.linspace(-6, 6, 24001, dtype=torch.float64)[:, None]
    for j in range(3):
        lq = sum(torch.distributions.Normal(means[i, j], sd[j]).log_prob(grid[:, 0]) for i in range(3))
        lp = _prior_z(grid[:, 0], transform)  # -inf outside the box for "none": the target is 0 there
        w = torch.softmax(torch.where(torch.isfinite(lp), lq - 2 * lp, -math.inf), 0)
        mu = float(w @ grid[:, 0])
        s = float((w @ (grid[:, 0] - mu) ** 2).sqrt())
        m_hat = float(w_draws @ z[:, j])
        s_hat = float((w_draws @ (z[:, j] - m_hat) ** 2).sqrt())
        # Monte Carlo error: effective sample ~1 000+ (MCMC) / >= 2048 (SMC): sd / 30; tolerance 0.1 sd
        assert abs(m_hat - mu) < 0.1 * s, (j, m_hat, mu, s)
        assert abs(s_hat / s - 1) < 0.1, (j, s_hat, s)


def test_smc_is_deterministic_and_checks_its_arguments():
    post, _, _ = _gaussian_product()
    torch.manual_seed(0)
    before = torch.random.get_rng_state()
    a = post.sample_smc(1, particles=64)
    assert torch.equal(torch.random.get_rng_state(), before)
    b = post.sample_smc(1, particles=64)
    torch.testing.assert_close(a.samples, b.samples, rtol=0, atol=0)
    torch.testing.assert_close(a.weights, b.weights, rtol=0, atol=0)
    assert not torch.equal(a.samples, post.sample_smc(2, particles=64).samples)
    assert a.samples.shape == (64, 3) and abs(float(a.weights.sum()) - 1) < 1e-9
    for kwargs, needle in [({"particles": 4}, "particles"), ({"target_ess": 1.0}, "target_ess"),
                           ({"base": "prior"}, "base"), ({"independent_fraction": 2.0}, "independent_fraction")]:
        with pytest.raises(ValueError, match=f"^{needle}:"):
            post.sample_smc(1, **kwargs)


def test_logit_coordinates_round_trip_with_the_jacobian_of_the_prior():
    """z = logit(u): the uniform box prior is a standard logistic in z, and the Jacobian is exact."""
    lo, w = torch.tensor([-1.0, 0.5]), torch.tensor([2.0, 1.5])
    theta = lo + w * torch.rand(1000, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    z = flow_space.to_unconstrained(theta, lo, w, "logit")
    back, logdet = flow_space.from_unconstrained(z, lo, w, "logit")
    torch.testing.assert_close(back, theta.double(), rtol=0, atol=1e-9)
    prior_z = (torch.nn.functional.logsigmoid(z) + torch.nn.functional.logsigmoid(-z)).sum(-1)
    # uniform density 1/prod(w) in theta = logistic(z) / |d theta / d z|
    torch.testing.assert_close(prior_z - logdet, torch.full((1000,), -float(torch.log(w).sum()), dtype=torch.float64))


def test_mcmc_is_deterministic_given_its_seed_and_leaves_the_global_rng_alone():
    post, _, _ = _gaussian_product()
    torch.manual_seed(0)
    before = torch.random.get_rng_state()
    a = post.sample_mcmc(500, 1, chains=16, steps=20, burn_in=10)
    assert torch.equal(torch.random.get_rng_state(), before)
    b = post.sample_mcmc(500, 1, chains=16, steps=20, burn_in=10)
    c = post.sample_mcmc(500, 2, chains=16, steps=20, burn_in=10)
    torch.testing.assert_close(a.samples, b.samples, rtol=0, atol=0)
    assert not torch.equal(a.samples, c.samples)
    assert a.samples.shape == (16 * 10, 3)


def test_goal_design_is_independent_of_the_training_limits():
    sim = ToySimulator()
    prior = BoxPrior(sim.bounds, sim.start)
    data = amortized.simulate_training_set(sim, prior, dataclasses.replace(TINY, spaces=("joint",), form="per-reach"),
                                           0, n=4000)
    theta, goal = data["theta"], data["x"]["joint"][:, :2]
    # the goals are the design's (FK of configurations inside independent prior draws) ...
    np.testing.assert_array_equal(goal.numpy(), amortized_data.design_goals(sim, prior, 4000, 0)[:, :2].numpy())
    # ... uncorrelated with the limits they are simulated with (|r| ~ 1/sqrt(4000) ~ 0.016)
    r = np.corrcoef(np.c_[theta.numpy(), goal.numpy()].T)[:4, 4:]
    assert np.abs(r).max() < 0.06
    # and the training starts are the model's default start (inside every drawn limit vector)
    assert bool(((theta[:, 0::2] <= sim.start) & (sim.start <= theta[:, 1::2])).all())


# ---------------------------------------------------------------------------------------------
# a toy with a known posterior
# ---------------------------------------------------------------------------------------------
# A 1-joint point robot (ToySimulator n=1) moving 0.04 per step from 0 toward goals beyond 0.8:
# 21 points, never arriving, so the summary (20 points after the start + the length) IS the
# trajectory, and with Gaussian noise sigma on every point the per-reach likelihood is exactly
# prod_t N(x_t | min(0.04 t, hi), sigma^2) (goals > 0; lo for goals < 0). The exact combined
# posterior is a 1-D grid computation per limit, with the simulator itself on the grid.

SIGMA = 0.05
TOY_TRUE = torch.tensor([-0.6, 0.5], dtype=torch.float64)
TOY_GOALS = torch.tensor([[0.9, 0.0, 0.0], [0.95, 0.0, 0.0], [-0.95, 0.0, 0.0]], dtype=torch.float64)


def _toy_problem():
    sim = ToySimulator(n=1, max_steps=21, step=0.04)
    noise = NoiseModel(joint_deg=math.degrees(SIGMA))
    gen = torch.Generator().manual_seed(1)
    obs = tuple(Observation(o.start, o.goal, noise.perturb(o.q, "joint", gen)) for o in observe(sim, TOY_TRUE, TOY_GOALS))
    assert all(o.length == 21 for o in obs)
    return Task("toy1", "toy1", sim, BoxPrior(sim.bounds, sim.start), obs, noise=noise), sim, noise


def _reference(task, sim) -> dict:
    """Exact posterior mean and sd of each limit (uniform prior, the grid through the simulator)."""
    out = {}
    for idx, side in ((0, "lo"), (1, "hi")):
        grid = torch.linspace(-1, 0, 4001) if side == "lo" else torch.linspace(0, 1, 4001)
        theta = torch.tensor([[-1.0, 1.0]], dtype=torch.float64).repeat(grid.shape[0], 1)
        theta[:, idx] = grid.double()
        ll = torch.zeros(grid.shape[0], dtype=torch.float64)
        for o in task.observations:
            if (float(o.goal[0]) > 0) == (side == "hi"):
                q = sim.simulate(theta, o.goal).q[:, 1:21, 0]
                ll += (-((o.q[1:21, 0] - q) ** 2) / (2 * SIGMA**2)).sum(1)
        w = torch.softmax(ll, 0)
        mu = float((w * grid.double()).sum())
        out[side] = (mu, float((w * (grid.double() - mu) ** 2).sum().sqrt()))
    return out


def _check_toy(sims: int, epochs: int, tmp_path, mean_tol_sd: float, sd_ratio: tuple[float, float],
               form: str = "per-reach", flow: str = "maf", patience: int = 5):
    task, sim, noise = _toy_problem()
    cfg = TrainConfig(simulations=sims, form=form, noise=noise, max_epochs=epochs, hidden_features=32, num_transforms=3,
                      training_batch_size=256, stop_after_epochs=patience, density_estimator=flow)
    path = train(sim, model="toy1", config=cfg, seed=0).save(tmp_path / "toy1.pt")
    res = run_method("npe-amortized", task, budget=1, seed=0, config={"estimator_path": str(path)})
    assert res.status == "ok" and res.n_simulations == 0
    w = res.normalized_weights()
    mean = w @ res.samples
    sd = np.sqrt(w @ (res.samples - mean) ** 2)
    ref = _reference(task, sim)
    for i, side in enumerate(("lo", "hi")):
        mu, s = ref[side]
        assert abs(mean[i] - mu) <= mean_tol_sd * s, (side, mean[i], mu, s)
        assert sd_ratio[0] * s <= sd[i] <= sd_ratio[1] * s, (side, sd[i], s)


def test_toy_posterior_recovered_roughly(tmp_path):
    """Fast variant (~20 s): 5 000 simulations; the mean within 5 sd of the exact one."""
    _check_toy(5000, 15, tmp_path, mean_tol_sd=5.0, sd_ratio=(0.5, 20.0))


@pytest.mark.slow
def test_toy_posterior_recovered(tmp_path):
    """40 000 simulations: the mean within 1.5 exact sd, the sd within a factor 0.5-3."""
    _check_toy(40000, 80, tmp_path, mean_tol_sd=1.5, sd_ratio=(0.5, 3.0))


def test_maf_transforms_leave_their_first_coordinate_unconditioned():
    """Why NSF is the default flow: in sbi's MAF (nflows' MADE) the affine parameters of the first
    coordinate of each transform have no hidden input, so that coordinate ignores the condition.
    Structural, so untrained flows show it: the same base noise under two conditions gives one
    identical coordinate for a one-transform MAF, none for a two-transform NSF (coupling layers
    that alternate which coordinate they transform, each given the condition)."""
    def same_columns(kind, transforms):
        flow = sbi_adapter.build_flow(kind, 2, 4, hidden_features=16, num_transforms=transforms, seed=0).eval()
        draws = []
        for c in (torch.zeros(1, 4), torch.full((1, 4), 3.0)):
            with torch.random.fork_rng(devices=[]), torch.no_grad():
                torch.manual_seed(0)
                draws.append(flow.sample(torch.Size([50]), c).reshape(50, 2))
        return [bool(torch.equal(draws[0][:, i], draws[1][:, i])) for i in range(2)]

    assert sum(same_columns("maf", 1)) == 1
    assert sum(same_columns("nsf", 2)) == 0


@pytest.mark.slow
@pytest.mark.xfail(strict=False, raises=AssertionError, reason=(
    "CPU-dependent: on CI's CPU the upper limit's mean is 0.575 against the exact 0.521 +- 0.012 "
    "(4.5 sd) at 20 000 simulations; on an AMD EPYC machine (2026-12-07) the same seed gives lo "
    "-0.587 (0.9 sd) and hi 0.516 (0.4 sd), sd 2.9x and 3.9x, and the test passes (it XPASSed "
    "there under the old strict mark, failing .ci/run). Not strict, so neither CPU fails; any "
    "error other than the assertion still fails. Recovery is asserted by the 50 000-simulation "
    "test (test_set_form_toy_posterior_recovered), which passes on both."))
def test_set_form_toy_posterior_recovered_roughly(tmp_path):
    """The set form (neural spline flow, the default) on the same toy (~60 s quiet, 214-705 s at
    load 20-27): 20 000 simulations = 2 000 sets of 10 reaches; the mean within 3 exact sd of each
    limit, the sd within a factor 0.5-6 (an earlier round measured lo -0.587 vs -0.606 +- 0.020, hi
    0.518 vs 0.521 +- 0.012; CI's CPU gives hi 0.575: the xfail mark above). Slow tier: in the default tier
    the set form's training, file and sampling path is covered by the tiny-estimator tests
    (`test_save_load_round_trip_gives_identical_samples`, `test_inference_simulates_nothing`,
    `test_a_loaded_nsf_is_the_sbi_flow_draw_for_draw_without_importing_sbi`)."""
    _check_toy(20000, 30, tmp_path, mean_tol_sd=3.0, sd_ratio=(0.5, 6.0), form="set", flow="nsf")


@pytest.mark.slow
def test_set_form_toy_posterior_recovered(tmp_path):
    """The set form, 50 000 simulations (5 000 sets), early-stopping patience 10: the mean within
    1.5 exact sd, the sd within 0.5-5x (measured: lo -0.613 vs -0.606 +- 0.020, hi 0.534 vs
    0.521 +- 0.012; sd 2.5x and 4x: conservative). With patience 5 at 100 000 simulations the
    training stopped at epoch 18 and lo came out 4.4 sd low (-0.696): the set form's validation
    loss is noisy, because training redraws the subsets every epoch."""
    _check_toy(50000, 60, tmp_path, mean_tol_sd=1.5, sd_ratio=(0.5, 5.0), form="set", flow="nsf", patience=10)


# ---------------------------------------------------------------------------------------------
# the command line: amortize, compare --amortized, compare training once
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("extra, needle", [
    (["--simulations", "0"], "--simulations"),
    (["--space", "elbow"], "--space"),
    (["--noise-ee-mm", "-1"], "--noise-ee-mm"),
    (["--seed", "-1"], "--seed"),
    (["--form", "pairs"], "--form"),
    (["--flow", "glow"], "--flow"),
    (["--threads", "0"], "--threads"),
    (["--fast", "--form", "per-reach"], "--fast"),
    (["--batch-size", "1"], "--batch-size"),
])
def test_amortize_bad_options_exit_2(extra, needle, tmp_path, capsys):
    from camo_sbi.experiments.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["amortize", "--out", str(tmp_path / "x.pt"), *extra])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0], err


def test_amortize_fast_and_threads_reach_the_training_config():
    """--fast is FAST_SET_TRAINING's optimiser, --threads the training's torch threads; --max-epochs still wins."""
    from camo_sbi.experiments.amortize import train_config
    from camo_sbi.inference.amortized import FAST_SET_TRAINING

    default = train_config(simulations=1000, spaces=("joint",))
    cfg = train_config(simulations=1000, spaces=("joint",), fast=True, threads=2)
    assert {k: getattr(cfg, k) for k in FAST_SET_TRAINING} == FAST_SET_TRAINING != {
        k: getattr(default, k) for k in FAST_SET_TRAINING}
    assert cfg.n_threads == 2 and default.n_threads == 1
    assert train_config(simulations=1000, spaces=("joint",), fast=True, max_epochs=5).max_epochs == 5


def test_amortize_batch_size_changes_the_batch_only():
    """--batch-size sets the reaches per batch and nothing else of the optimiser; it wins over --fast's."""
    from camo_sbi.experiments.amortize import train_config
    from camo_sbi.experiments.cli import build_parser

    default = train_config(simulations=1000, spaces=("joint",))
    cfg = train_config(simulations=1000, spaces=("joint",), batch_size=2048)
    assert cfg.training_batch_size == 2048 != default.training_batch_size
    assert cfg == dataclasses.replace(default, training_batch_size=2048)
    assert train_config(simulations=1000, spaces=("joint",), fast=True, batch_size=1024).training_batch_size == 1024
    args = build_parser().parse_args(["amortize", "--out", "x.pt", "--batch-size", "2048"])
    assert args.batch_size == 2048


@pytest.mark.slow  # in the slow tier for the default tier's 4-minute budget (issue 28)
def test_amortize_then_compare_with_the_file(tmp_path):
    import pandas as pd

    from camo_sbi.experiments.cli import main

    path = tmp_path / "panda.pt"
    assert main(["amortize", "--model", "panda", "--simulations", "300", "--max-epochs", "2", "--out",
                 str(path), "--space", "joint,cartesian", "--noise-joint-deg", "0.5"]) == 0
    est = load_estimator(path)
    assert est.spaces == ("joint", "cartesian") and est.noise == NoiseModel(joint_deg=0.5)
    with pytest.raises(SystemExit) as exc:  # no silent overwrite
        main(["amortize", "--model", "panda", "--simulations", "300", "--out", str(path)])
    assert exc.value.code == 2
    # compare's tasks are noise-free: the noisy estimator is refused, naming task.noise
    with pytest.raises(SystemExit) as exc:
        main(["compare", "--methods", "npe-amortized", "--budgets", "20", "--seeds", "1", "--tasks", "1",
              "--test-goals", "2", "--amortized", str(path), "--no-report", "--out", str(tmp_path / "c0")])
    assert exc.value.code == 2
    clean = tmp_path / "clean.pt"
    assert main(["amortize", "--model", "panda", "--simulations", "300", "--max-epochs", "2", "--form",
                 "per-reach", "--flow", "maf", "--out", str(clean)]) == 0
    out = tmp_path / "c1"
    assert main(["compare", "--methods", "npe-amortized,camo", "--budgets", "20", "--seeds", "1", "--tasks", "2",
                 "--test-goals", "2", "--amortized", str(clean), "--no-report", "--out", str(out)]) == 0
    df = pd.read_csv(out / "results.csv")
    am = df[df["method"] == "npe-amortized"]
    assert set(am.loc[am["metric"] == "n_simulations", "value"]) == {0}
    assert set(am.loc[am["metric"] == "training_simulations", "value"]) == {300}
    cost = pd.read_csv(out / "amortized_cost.csv")
    camo = cost[cost["method"] == "camo"].iloc[0]
    assert camo["simulations_per_person"] == 40 and camo["training_simulations"] == 300
    assert camo["break_even_persons_simulations"] == math.ceil(300 / 40)
    # --config reaches the method: the SMC sampler gives other estimates than the default MCMC
    smc = tmp_path / "c2"
    args = ["compare", "--methods", "npe-amortized", "--budgets", "20", "--seeds", "1", "--tasks", "2",
            "--test-goals", "2", "--amortized", str(clean), "--no-report"]
    assert main([*args, "--config", 'npe-amortized={"combine": "smc"}', "--out", str(smc)]) == 0
    ds = pd.read_csv(smc / "results.csv")
    err = "cartesian_error_mm"
    a = am[am["metric"] == err].sort_values("n_tasks")["value"].to_numpy()
    b = ds[(ds["method"] == "npe-amortized") & (ds["metric"] == err)].sort_values("n_tasks")["value"].to_numpy()
    assert a.shape == b.shape == (2,) and not np.allclose(a, b)
    # a folder never mixes settings: the same folder without the override is refused
    with pytest.raises(SystemExit) as exc:
        main([*args, "--out", str(smc)])
    assert exc.value.code == 2
    with pytest.raises(SystemExit) as exc:
        main([*args, "--config", 'npe-amortized={"combine": "gibbs"}', "--out", str(tmp_path / "c3")])
    assert exc.value.code == 2


def test_compare_trains_the_estimator_once_and_reuses_it(tmp_path, capsys):
    from camo_sbi.experiments.cli import main

    argv = ["compare", "--methods", "npe-amortized", "--budgets", "20", "--seeds", "2", "--tasks", "1",
            "--test-goals", "2", "--amortize-simulations", "200", "--no-report", "--out", str(tmp_path / "c")]
    assert main(argv) == 0
    first = capsys.readouterr().out
    files = list((tmp_path / "c" / "work" / "amortized").glob("*.pt"))
    assert len(files) == 1 and first.count("trained ") == 1
    mtime = files[0].stat().st_mtime_ns
    assert main([*argv[:-2], "--workers", "2", "--out", str(tmp_path / "c")]) == 0
    assert "reused " in capsys.readouterr().out and files[0].stat().st_mtime_ns == mtime


def test_more_tasks_than_a_set_estimator_takes_is_refused_before_any_cell(paths, tmp_path, capsys):
    from camo_sbi.experiments.cli import main

    common = ["--methods", "npe-amortized,naive", "--tasks", str(TINY.max_set + 1)]
    for cmd, extra in (("compare", ["--budgets", "20", "--seeds", "1", "--no-report"]),
                       ("calibrate", ["--subjects", "2"])):
        for where in (["--amortized", str(paths["set"])], ["--amortize-simulations", "200"]):
            out = tmp_path / f"{cmd}{len(where[1])}"
            with pytest.raises(SystemExit) as exc:
                main([cmd, *common, *extra, *where, "--out", str(out)])
            assert exc.value.code == 2
            line = capsys.readouterr().err.strip().splitlines()[-1]
            assert line.startswith(f"camo-sbi: error: --tasks: {TINY.max_set + 1} reaches, but the set-form"), line
            assert not (out / "cells").exists() and not list(out.glob("work/amortized/*.pt"))


def test_a_file_from_before_a_controller_setting_existed_counts_it_at_its_default():
    """Estimators written before ``derivative_gain``/``early_stop`` existed name neither; the
    controller then behaved as those defaults do, so the file still matches a default model
    and is refused for a model that uses the new setting."""
    from camo_sbi.inference.amortized_data import fingerprint_differences, model_fingerprint
    from camo_sbi.simulators import panda

    sim = panda()
    now = model_fingerprint(sim)
    old = {**now, "controller": {k: v for k, v in now["controller"].items()
                                 if k not in ("derivative_gain", "early_stop")}}
    assert fingerprint_differences(old, now) == []
    other = model_fingerprint(sim.with_config(derivative_gain=0.5))
    assert fingerprint_differences(old, other) == ["controller"]
    other = model_fingerprint(sim.with_config(early_stop=False))
    assert fingerprint_differences(old, other) == ["controller"]


def _balance_gap(flow, z, x, prior):
    with torch.no_grad():
        d_joint = -flow.loss(z, condition=x) - prior(z)
        shuffled = z[torch.randperm(z.shape[0], generator=torch.Generator().manual_seed(1))]
        d_marg = -flow.loss(shuffled, condition=x) - prior(shuffled)
        return float(torch.sigmoid(d_joint).mean() + torch.sigmoid(d_marg).mean() - 1.0)


def test_balanced_training_shrinks_the_balance_gap():
    """Balanced NPE's penalty drives E_joint[s(d)] + E_marg[s(d)] toward 1 on held-out pairs.

    Toy: z ~ N(0, I_2) (prior), x = z + N(0, 0.3^2) (informative). Plain maximum likelihood on
    few pairs leaves a gap away from 0; with the penalty (weight 100) the gap must be at least
    halved in magnitude. Both runs use the same seed and pairs."""
    from camo_sbi.inference import sbi_adapter

    gen = torch.Generator().manual_seed(0)
    z = torch.randn(600, 2, generator=gen)
    x = z + 0.3 * torch.randn(600, 2, generator=gen)
    zt = torch.randn(4000, 2, generator=gen)
    xt = zt + 0.3 * torch.randn(4000, 2, generator=gen)
    prior = lambda v: torch.distributions.Normal(0.0, 1.0).log_prob(v).sum(-1)  # noqa: E731
    gaps = {}
    for lam in (0.0, 100.0):
        flow = sbi_adapter.build_flow("maf", 2, 2, hidden_features=32, num_transforms=2, seed=3)
        # one torch thread, as train() does: small batches on two threads timed out (900 s) at load 25
        with flow_space.torch_threads(1):
            sbi_adapter.fit_density_estimator(flow, z, x, seed=4, batch_size=64, max_epochs=25,
                                              stop_after_epochs=25, balance=lam, prior_log_prob=prior)
            gaps[lam] = _balance_gap(flow, zt, xt, prior)
    # measured: plain -0.042, balanced -0.009
    assert abs(gaps[100.0]) < 0.5 * abs(gaps[0.0]), gaps
    with pytest.raises(TypeError, match="^prior_log_prob:"):
        sbi_adapter.fit_density_estimator(flow, z, x, seed=4, balance=1.0)
    with pytest.raises(ValueError, match="^balance:"):
        TrainConfig(balance=-1.0)


class _NanFlow(_GaussianFlow):
    def log_prob(self, input, condition):  # noqa: A002
        return torch.full(input.shape[:-1], float("nan"))


def test_smc_with_no_finite_density_reports_it_instead_of_nan_weights():
    """A flow with NaN density everywhere: no NaN leaves the sampler; it says it did not reach the posterior."""
    flow = _NanFlow(torch.tensor([0.3, 0.5, 0.2]))
    post = NpePosterior([flow] * 2, [torch.zeros(3), torch.ones(3)], torch.full((3,), -1.0),
                            torch.full((3,), 1.0))
    draws = post.sample_smc(0, particles=32, max_stages=3)
    assert not draws.diagnostics["reached"] and draws.ess == 0.0
    assert torch.isfinite(draws.weights).all() and abs(float(draws.weights.sum()) - 1) < 1e-12
    assert torch.isfinite(draws.samples).all()


def test_settings_of_an_estimator_file_written_before_the_vocabulary_still_load():
    """An estimator file's metadata from before chunk_size (``simulation_batch_size``) loads as chunk_size."""
    d = TrainConfig(simulations=200, chunk_size=32).to_json()
    assert d["chunk_size"] == 32 and "simulation_batch_size" not in d
    d["simulation_batch_size"] = d.pop("chunk_size")
    assert TrainConfig.from_json(d) == TrainConfig(simulations=200, chunk_size=32)
