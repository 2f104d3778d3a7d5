"""`camo_sbi.experiments.grid`: cell keys as before, skipping, worker-count independence, failures."""

from __future__ import annotations

import argparse
import pickle

import pandas as pd
import pytest

from camo_sbi.experiments import calibrate, compare, reproduce_hrc, reproduce_panda, robustness
from camo_sbi.experiments.grid import Cell, run_grid
from camo_sbi.experiments.models import ModelSpec
from camo_sbi.experiments.store import ResultStore

# (command, argv, the keys of its cells) computed with main's code at fca0fe6, before grid.py
# existed (compare.cell_specs, calibrate.cell_specs, the loop of robustness.main): every run
# folder made since then resumes only if these stay byte-identical
GOLDEN = [
    ('compare', ['--model', 'panda', '--methods', 'camo,naive,abc-smc', '--budgets', '150,300', '--seeds', '2', '--tasks', '2', '--test-goals', '3'],
     ['base_seed=0__budget=150__method=camo__seed=0__space=joint__subject=shoulder_restricted__task=panda__tasks=2__test_goals=3__f0955fec', 'base_seed=0__budget=150__method=camo__seed=1__space=joint__subject=shoulder_restricted__task=panda__tasks=2__test_goals=3__1fe7a765', 'base_seed=0__budget=300__method=camo__seed=0__space=joint__subject=shoulder_restricted__task=panda__tasks=2__test_goals=3__2b4d3241', 'base_seed=0__budget=300__method=camo__seed=1__space=joint__subject=shoulder_restricted__task=panda__tasks=2__test_goals=3__34a4141a', 'base_seed=0__budget=150__method=naive__seed=0__space=joint__subject=shoulder_restricted__task=panda__tasks=2__test_goals=3__832e2686', 'base_seed=0__budget=150__method=naive__seed=1__space=joint__subject=shoulder_restricted__task=panda__tasks=2__test_goals=3__9b981510', 'base_seed=0__budget=300__method=naive__seed=0__space=joint__subject=shoulder_restricted__task=panda__tasks=2__test_goals=3__2bf6f4de', 'base_seed=0__budget=300__method=naive__seed=1__space=joint__subject=shoulder_restricted__task=panda__tasks=2__test_goals=3__42b73c4c', 'base_seed=0__budget=150__method=abc-smc__seed=0__space=joint__subject=shoulder_restricted__task=panda__tasks=2__test_goals=3__afc44270', 'base_seed=0__budget=150__method=abc-smc__seed=1__space=joint__subject=shoulder_restricted__task=panda__tasks=2__test_goals=3__ac9afa70', 'base_seed=0__budget=300__method=abc-smc__seed=0__space=joint__subject=shoulder_restricted__task=panda__tasks=2__test_goals=3__999e6e35', 'base_seed=0__budget=300__method=abc-smc__seed=1__space=joint__subject=shoulder_restricted__task=panda__tasks=2__test_goals=3__874b9f65', 'base_seed=0__budget=150__method=nominal__seed=0__space=joint__subject=shoulder_restricted__task=panda__tasks=2__test_goals=3__88eb43aa', 'base_seed=0__budget=150__method=nominal__seed=1__space=joint__subject=shoulder_restricted__task=panda__tasks=2__test_goals=3__ffced179', 'base_seed=0__budget=300__method=nominal__seed=0__space=joint__subject=shoulder_restricted__task=panda__tasks=2__test_goals=3__d634018a', 'base_seed=0__budget=300__method=nominal__seed=1__space=joint__subject=shoulder_restricted__task=panda__tasks=2__test_goals=3__b5b61f50', 'base_seed=0__budget=150__method=oracle__seed=0__space=joint__subject=shoulder_restricted__task=panda__tasks=2__test_goals=3__b71143a4', 'base_seed=0__budget=150__method=oracle__seed=1__space=joint__subject=shoulder_restricted__task=panda__tasks=2__test_goals=3__d511c362', 'base_seed=0__budget=300__method=oracle__seed=0__space=joint__subject=shoulder_restricted__task=panda__tasks=2__test_goals=3__40f5713e', 'base_seed=0__budget=300__method=oracle__seed=1__space=joint__subject=shoulder_restricted__task=panda__tasks=2__test_goals=3__459cf314']),
    ('compare', ['--model', 'panda', '--methods', 'camo,npe', '--budgets', '100', '--seeds', '1', '--config', 'camo={"keep_best": 50}', '--space', 'cartesian'],
     ['base_seed=0__budget=100__config=-keep_best-50-__method=camo__seed=0__space=cartesian__subject=shoulder_restricted__task=panda__tasks=3__test_goals=10__382ae055', 'base_seed=0__budget=100__method=npe__seed=0__space=cartesian__subject=shoulder_restricted__task=panda__tasks=3__test_goals=10__b08fa5c1', 'base_seed=0__budget=100__method=naive__seed=0__space=cartesian__subject=shoulder_restricted__task=panda__tasks=3__test_goals=10__e79005b1', 'base_seed=0__budget=100__method=nominal__seed=0__space=cartesian__subject=shoulder_restricted__task=panda__tasks=3__test_goals=10__50789b0d', 'base_seed=0__budget=100__method=oracle__seed=0__space=cartesian__subject=shoulder_restricted__task=panda__tasks=3__test_goals=10__5d24fa4e']),
    ('compare', ['--model', 'human', '--height', '1.8', '--methods', 'camo', '--budgets', '50', '--seeds', '1', '--seed', '3'],
     ['base_seed=3__budget=50__method=camo__model=-height_m-1.8-kind-human-__seed=0__space=joint__subject=frozen_shoulder__task=human__tasks=3__test_goals=10__1edc3695', 'base_seed=3__budget=50__method=naive__model=-height_m-1.8-kind-human-__seed=0__space=joint__subject=frozen_shoulder__task=human__tasks=3__test_goals=1__6b16933f', 'base_seed=3__budget=50__method=nominal__model=-height_m-1.8-kind-human-__seed=0__space=joint__subject=frozen_shoulder__task=human__tasks=3__test_goals__9b8f3e2d', 'base_seed=3__budget=50__method=oracle__model=-height_m-1.8-kind-human-__seed=0__space=joint__subject=frozen_shoulder__task=human__tasks=3__test_goals=__23e5847d']),
    ('compare', ['--model', 'panda', '--methods', 'npe-amortized,camo', '--budgets', '80', '--seeds', '1', '--amortized', '/tmp/est.pt'],
     ['base_seed=0__budget=80__estimator=-tmp-est.pt__method=npe-amortized__seed=0__space=joint__subject=shoulder_restricted__task=panda__tasks=3__test_goals__74130df1', 'base_seed=0__budget=80__method=camo__seed=0__space=joint__subject=shoulder_restricted__task=panda__tasks=3__test_goals=10__e7307ed1', 'base_seed=0__budget=80__method=naive__seed=0__space=joint__subject=shoulder_restricted__task=panda__tasks=3__test_goals=10__8369c19d', 'base_seed=0__budget=80__method=nominal__seed=0__space=joint__subject=shoulder_restricted__task=panda__tasks=3__test_goals=10__2225b52d', 'base_seed=0__budget=80__method=oracle__seed=0__space=joint__subject=shoulder_restricted__task=panda__tasks=3__test_goals=10__7663a52b']),
    ('calibrate', ['--model', 'panda', '--methods', 'camo,naive', '--subjects', '3', '--tasks', '1', '--budget', '60'],
     ['budget=60__config=-__method=camo__model=panda__sbc_draws=100__seed=0__subject=0__tasks=1__version=calibrate-1__a25ea909', 'budget=60__config=-__method=naive__model=panda__sbc_draws=100__seed=0__subject=0__tasks=1__version=calibrate-1__b508a052', 'budget=60__config=-__method=camo__model=panda__sbc_draws=100__seed=0__subject=1__tasks=1__version=calibrate-1__e8022e14', 'budget=60__config=-__method=naive__model=panda__sbc_draws=100__seed=0__subject=1__tasks=1__version=calibrate-1__c0e97efb', 'budget=60__config=-__method=camo__model=panda__sbc_draws=100__seed=0__subject=2__tasks=1__version=calibrate-1__627d0dbd', 'budget=60__config=-__method=naive__model=panda__sbc_draws=100__seed=0__subject=2__tasks=1__version=calibrate-1__f8dec1e3']),
    ('calibrate', ['--model', 'panda', '--methods', 'camo,abc-smc', '--subjects', '2', '--budget', '500', '--config', 'camo={"keep_best": 50}', '--seed', '4'],
     ['budget=500__config=-keep_best-50-__method=camo__model=panda__sbc_draws=100__seed=4__subject=0__tasks=3__version=calibrate-1__7fdbb741', 'budget=500__config=-population_size-100-__method=abc-smc__model=panda__sbc_draws=100__seed=4__subject=0__tasks=3__version=calibrate-1__48263623', 'budget=500__config=-keep_best-50-__method=camo__model=panda__sbc_draws=100__seed=4__subject=1__tasks=3__version=calibrate-1__a6facb3f', 'budget=500__config=-population_size-100-__method=abc-smc__model=panda__sbc_draws=100__seed=4__subject=1__tasks=3__version=calibrate-1__b3103ba6']),
    ('calibrate', ['--model', 'human', '--height', '1.8', '--methods', 'naive,npe', '--subjects', '2', '--sbc-draws', '20'],
     ['budget=500__config=-__method=naive__model=human__model_settings=-height_m-1.8-kind-human-__sbc_draws=20__seed=0__subject=0__tasks=3__version=calibrate__7f536424', 'budget=500__config=-__method=npe__model=human__model_settings=-height_m-1.8-kind-human-__sbc_draws=20__seed=0__subject=0__tasks=3__version=calibrate-1__652b87d4', 'budget=500__config=-__method=naive__model=human__model_settings=-height_m-1.8-kind-human-__sbc_draws=20__seed=0__subject=1__tasks=3__version=calibrate__cfb44d08', 'budget=500__config=-__method=npe__model=human__model_settings=-height_m-1.8-kind-human-__sbc_draws=20__seed=0__subject=1__tasks=3__version=calibrate-1__c76a201b']),
    ('calibrate', ['--model', 'panda', '--methods', 'npe-amortized,naive', '--subjects', '1', '--amortized', '/tmp/est.pt'],
     ['budget=500__config=-estimator_path-tmp-est.pt-__method=npe-amortized__model=panda__sbc_draws=100__seed=0__subject=0__tasks=3__version=calibrate-1__b1e12f45', 'budget=500__config=-__method=naive__model=panda__sbc_draws=100__seed=0__subject=0__tasks=3__version=calibrate-1__a11326c3']),
    ('robustness', ['--methods', 'camo,naive', '--seeds', '1', '--tasks', '2', '--test-goals', '3', '--budget', '100', '--conditions', 'clean,rate x3'],
     ['base_seed=0__budget=100__condition=clean__methods=camo-naive__model=-kind-panda-__seed=0__subject=shoulder_restricted__task=panda__tasks=2__test_goals__89a6bc34', 'base_seed=0__budget=100__condition=rate-x3__methods=camo-naive__model=-kind-panda-__seed=0__subject=shoulder_restricted__task=panda__tasks=2__test_goa__fa9f0af4']),
    ('robustness', ['--model', 'panda', '--methods', 'camo-js,oracle', '--seeds', '2', '--conditions', 'clean,taller 5%', '--body-scale', 'free'],
     ['base_seed=0__body_scale=free__budget=1000__condition=clean__methods=camo-js-oracle__model=-kind-panda-__seed=0__subject=shoulder_restricted__task=pand__af9f3739', 'base_seed=0__body_scale=free__budget=1000__condition=taller-5-__methods=camo-js-oracle__model=-kind-panda-__seed=0__subject=shoulder_restricted__task=__25f083a9', 'base_seed=0__body_scale=free__budget=1000__condition=clean__methods=camo-js-oracle__model=-kind-panda-__seed=1__subject=shoulder_restricted__task=pand__76881afd', 'base_seed=0__body_scale=free__budget=1000__condition=taller-5-__methods=camo-js-oracle__model=-kind-panda-__seed=1__subject=shoulder_restricted__task=__e897ad63']),
    ('robustness', ['--model', 'human', '--height', '1.8', '--methods', 'naive', '--seeds', '1'],
     ['base_seed=0__budget=1000__condition=clean__methods=naive__model=-kind-human-height_m-1.8-__seed=0__subject=frozen_shoulder__task=human__tasks=5__test___4b1fdcb3', 'base_seed=0__budget=1000__condition=noise-1deg-5mm__methods=naive__model=-kind-human-height_m-1.8-__seed=0__subject=frozen_shoulder__task=human__tasks__ff4da55b', 'base_seed=0__budget=1000__condition=noise-3deg-15mm__methods=naive__model=-kind-human-height_m-1.8-__seed=0__subject=frozen_shoulder__task=human__task__d91d1c83', 'base_seed=0__budget=1000__condition=rate-x3__methods=naive__model=-kind-human-height_m-1.8-__seed=0__subject=frozen_shoulder__task=human__tasks=5__tes__2d0c408d', 'base_seed=0__budget=1000__condition=taller-5-__methods=naive__model=-kind-human-height_m-1.8-__seed=0__subject=frozen_shoulder__task=human__tasks=5__t__0c09abb7', 'base_seed=0__budget=1000__condition=shorter-5-__methods=naive__model=-kind-human-height_m-1.8-__seed=0__subject=frozen_shoulder__task=human__tasks=5____808c9811']),
    # reproduce panda and reproduce hrc (issue 37: onto the grid runner): the keys main's loops
    # computed at e6dcb27 (the cell file names of those runs), so their run folders resume
    ('reproduce panda', ['--runs', '3', '--tasks', '2', '--test-goals', '3', '--samples', '100'],
     ['bandwidth=None__bandwidth_mode=None__epsilon=None__horizon=None__keep_best=None__methods=-camo-js-camo-cs-camo-hull-camo-seq-naive-nominal-oracle-__mo__3be2aa2c', 'bandwidth=None__bandwidth_mode=None__epsilon=None__horizon=None__keep_best=None__methods=-camo-js-camo-cs-camo-hull-camo-seq-naive-nominal-oracle-__mo__da113f39', 'bandwidth=None__bandwidth_mode=None__epsilon=None__horizon=None__keep_best=None__methods=-camo-js-camo-cs-camo-hull-camo-seq-naive-nominal-oracle-__mo__1dd8a0ad']),
    ('reproduce panda', ['--setting', 'paper', '--runs', '2', '--tasks', '2', '--test-goals', '3', '--samples', '100'],
     ['bandwidth=None__bandwidth_mode=None__epsilon=None__horizon=21__keep_best=None__methods=-camo-seq-camo-seq-cs-camo-js-camo-cs-camo-hull-naive-nominal-o__6bc935ae', 'bandwidth=None__bandwidth_mode=None__epsilon=None__horizon=21__keep_best=None__methods=-camo-seq-camo-seq-cs-camo-js-camo-cs-camo-hull-naive-nominal-o__b8a84c73']),
    ('reproduce panda', ['--setting', 'informative', '--design', 'active', '--runs', '2', '--tasks', '3', '--test-goals', '4', '--samples', '100', '--methods', 'camo-seq'],
     ['bandwidth=None__bandwidth_mode=None__design=active__design_method=camo-seq__epsilon=None__horizon=None__keep_best=None__methods=-camo-seq-naive-nomina__e290101f', 'bandwidth=None__bandwidth_mode=None__design=active__design_method=camo-seq__epsilon=None__horizon=None__keep_best=None__methods=-camo-seq-naive-nomina__d9744b80']),
    ('reproduce hrc', ['--runs', '2', '--tasks', '2', '--test-trials', '2', '--samples', '200', '--keep-best', '50'],
     ['bandwidth=0.2__epsilon=None__fix_torso=False__keep_best=50__no_hull=False__observe=reach__priors=-strong-weak-__run=0__samples=200__seed=0__space=join__2bf447ad', 'bandwidth=0.2__epsilon=None__fix_torso=False__keep_best=50__no_hull=False__observe=reach__priors=-strong-weak-__run=1__samples=200__seed=0__space=join__123a70eb']),
]


def _parse(mod, argv):
    p = argparse.ArgumentParser()
    mod.add_arguments(p)
    return p.parse_args(argv)


def _keys(command, argv):
    if command == "reproduce panda":
        args = _parse(reproduce_panda, argv)
        reproduce_panda._check(args)
        return [c.key for c in reproduce_panda.grid_cells(args, *reproduce_panda.model_and_subjects(args))]
    if command == "reproduce hrc":
        args = _parse(reproduce_hrc, argv)
        args.priors = reproduce_hrc._parse_priors(args.priors)
        return [c.key for c in reproduce_hrc.grid_cells(args)]
    if command == "compare":
        return [c.key for c in compare.grid_cells(_parse(compare, argv), build=False)]
    if command == "calibrate":
        return [c.key for c in calibrate.grid_cells(_parse(calibrate, argv))]
    args = _parse(robustness, argv)
    return [c.key for c in robustness.grid_cells(args, args.methods.split(","), args.conditions.split(","))]


@pytest.mark.parametrize(("command", "argv", "keys"), GOLDEN, ids=lambda v: v if isinstance(v, str) else None)
def test_cell_keys_are_those_of_the_commands_before_grid(command, argv, keys):
    assert _keys(command, argv) == keys


# ------------------------------------------------------------------------------ a toy grid

PANDA = ModelSpec(kind="panda")


def _cells(n=6):
    return [Cell(model=PANDA, subject="s", seed=i, budget=10 + i, tasks=1, method=m, extras={"k": i % 2},
                 model_key=(("task", "toy"),)) for i in range(n) for m in ("a", "b")]


def toy_cell(cell, out):
    """Rows that depend on the cell only (module-level: worker processes import it)."""
    import numpy as np

    rng = np.random.default_rng([cell.seed, cell.budget, ord(cell.method)])
    return [{"method": cell.method, "seed": cell.seed, "metric": f"m{j}", "value": float(v), "status": "ok"}
            for j, v in enumerate(rng.normal(size=3))]


def raising_cell(cell, out):
    """``toy_cell``, except that the cells of seed 2 raise."""
    if cell.seed == 2:
        raise RuntimeError("boom")
    return toy_cell(cell, out)


def failed_run_cell(cell, out):
    """``toy_cell``, with method "b" of seed 3 ending as a failed run (rows with its status)."""
    rows = toy_cell(cell, out)
    return [{**r, "status": "failed: toy"} for r in rows] if (cell.seed, cell.method) == (3, "b") else rows


def test_cell_is_frozen_checked_and_pickles_with_its_key():
    cell = _cells(1)[0]
    with pytest.raises(AttributeError):
        cell.seed = 3
    with pytest.raises(TypeError):
        cell.extras["k"] = 2
    back = pickle.loads(pickle.dumps(cell))
    assert back == cell and back.key == cell.key and dict(back.extras) == {"k": 0}
    assert cell.key == "budget=10__k=0__method=a__seed=0__subject=s__task=toy__tasks=1__" + cell.key[-8:]
    renamed = Cell(model=PANDA, subject="s", seed=0, budget=10, tasks=1, extras={"k": 0}, budget_key="samples")
    assert renamed.key_fields() == {"subject": "s", "seed": 0, "samples": 10, "tasks": 1, "k": 0}
    for kw, name in [({"model": "panda"}, "model"), ({"seed": -1}, "seed"), ({"budget": 0}, "budget"),
                     ({"tasks": True}, "tasks"), ({"method": 3}, "method"), ({"extras": [1]}, "extras"),
                     ({"extras": {"seed": 1}}, "extras"), ({"budget_key": ""}, "budget_key"),
                     ({"extras": {"samples": 1}, "budget_key": "samples"}, "extras")]:
        with pytest.raises((TypeError, ValueError), match=f"^{name}: "):
            Cell(**{**dict(model=PANDA, subject="s", seed=0, budget=1, tasks=1), **kw})


def test_run_grid_skips_stored_cells(tmp_path):
    store = ResultStore(tmp_path)
    cells = _cells()
    assert sorted(run_grid(toy_cell, cells[:5], store, progress=False)) == sorted(c.key for c in cells[:5])
    before = {c.key: (store.cells / f"{c.key}.csv").stat().st_mtime_ns for c in cells[:5]}
    ran = run_grid(toy_cell, cells, store, progress=False)
    assert sorted(ran) == sorted(c.key for c in cells[5:])
    assert before == {k: (store.cells / f"{k}.csv").stat().st_mtime_ns for k in before}  # not rewritten
    assert store.finished_keys() == {c.key for c in cells}
    assert run_grid(toy_cell, cells, store, progress=False) == []


@pytest.mark.slow  # in the slow tier for the default tier's 4-minute budget (issue 28)
def test_same_table_for_any_number_of_workers(tmp_path):
    tables = []
    for workers in (1, 2):
        store = ResultStore(tmp_path / f"w{workers}")
        run_grid(toy_cell, _cells(), store, workers, progress=False)
        tables.append(store.write_table(keys=[c.key for c in _cells()]))
    pd.testing.assert_frame_equal(tables[0], tables[1])
    assert (tmp_path / "w1" / "results.csv").read_bytes() == (tmp_path / "w2" / "results.csv").read_bytes()


def test_a_failed_run_is_stored_with_its_status_and_the_grid_goes_on(tmp_path):
    """As compare always did: a method that ends badly is a row set with its status."""
    store = ResultStore(tmp_path)
    cells = _cells()
    assert len(run_grid(failed_run_cell, cells, store, progress=False)) == len(cells)
    failed = store.read(next(c.key for c in cells if (c.seed, c.method) == (3, "b")))
    assert (failed.status == "failed: toy").all()


@pytest.mark.slow  # in the slow tier for the default tier's 4-minute budget (issue 28)
@pytest.mark.parametrize("workers", [1, 2])
def test_a_raising_cell_stops_the_grid_and_the_next_run_resumes(workers, tmp_path):
    """As compare always did: a cell function that raises stops the grid with its exception (a
    note names the cell); the finished cells stay, the next run computes only the others."""
    store = ResultStore(tmp_path)
    cells = _cells()
    with pytest.raises(RuntimeError, match="boom") as exc:
        run_grid(raising_cell, cells, store, workers, progress=False)
    assert any(c.key in note for c in cells if c.seed == 2 for note in getattr(exc.value, "__notes__", []))
    done = store.finished_keys()
    assert not done & {c.key for c in cells if c.seed == 2}
    if workers == 1:  # in order: everything before the first raising cell is stored
        assert done == {c.key for c in cells[:4]}
    ran = run_grid(toy_cell, cells, store, workers, progress=False)
    assert sorted(ran) == sorted(c.key for c in cells if c.key not in done)
    assert store.finished_keys() == {c.key for c in cells}


def test_run_grid_refuses_bad_arguments(tmp_path):
    store = ResultStore(tmp_path)
    with pytest.raises(TypeError, match="^fn: "):
        run_grid(None, _cells(), store)
    with pytest.raises(TypeError, match="^cells: "):
        run_grid(toy_cell, [{"key": "x"}], store)
    with pytest.raises(ValueError, match="^workers: "):
        run_grid(toy_cell, _cells(), store, 0)
    with pytest.raises(ValueError, match="^scheduler: "):
        run_grid(toy_cell, _cells(), store, scheduler="nowhere")
