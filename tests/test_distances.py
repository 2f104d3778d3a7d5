"""Exact DTW (`dtw_distances`) against independent references, with and without pruning.

References: `dtw_reference` (tests/_dtw_reference.py, a plain numpy O(n m) table) and, when
installed, the ``dtw-python`` package (``dtw.dtw(..., dist_method="euclidean",
step_pattern="symmetric1")``, the same recursion). Pruned results must be bit-identical to the
unpruned ones on every candidate they report; the lower bounds must never exceed the true DTW.
The golden values (tests/data/dtw_golden.npz) freeze the outputs of the code before it became
a package; they are compared to a stated tolerance (GOLDEN_RTOL), since numba's code, and so the
last bits, depend on the CPU (docs/guide/reproducibility.md).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

import camo_sbi.inference.distances.api as dtw_api
from camo_sbi.inference.distances import _candidate_bounds, dtw_distances, l2_distance
from tests._dtw_reference import dtw_reference


@pytest.fixture(autouse=True, params=["small-calls", "cascade"])
def dtw_path(request, monkeypatch):
    """Every test runs on both paths: every call as a small call (the plain recursion one
    candidate at a time, `chunks.scalar_chunk`), and every call through the pruned cascade of
    lane blocks (``SMALL_CALL_CELLS = 0``)."""
    monkeypatch.setattr(dtw_api, "SMALL_CALL_CELLS", 10**15 if request.param == "small-calls" else 0)
    return request.param

# ----------------------------------------------------------------------------------------------
# data
# ----------------------------------------------------------------------------------------------


def _reaches(rng, B, T, D, *, min_len=1, noise=0.05):
    """Smooth reaching-like curves: minimum-jerk moves from a common start towards nearby
    goals, with a wiggle, valid lengths in [min_len, T], padding repeating the last point."""
    start = rng.normal(size=D)
    goal = start + rng.normal(size=D)
    lens = rng.integers(min_len, T + 1, size=B)
    out = np.empty((B, T, D))
    for b in range(B):
        m = lens[b]
        s = np.clip(np.arange(T) / max(m - 1, 1), 0.0, 1.0)
        prof = 10 * s**3 - 15 * s**4 + 6 * s**5
        g = goal + 0.3 * rng.normal(size=D)
        wiggle = noise * rng.normal(size=D) * np.sin(np.pi * s)[:, None]
        out[b] = start + prof[:, None] * (g - start) + wiggle
    return out, lens


def _walks(rng, B, T, D):
    sim = rng.normal(size=(B, T, D)).cumsum(axis=1) * 0.3
    return sim, rng.integers(1, T + 1, size=B)


def _references(obs, sim, lens):
    return np.array([dtw_reference(obs, sim[b, : lens[b]]) for b in range(len(sim))])


def _expected_pruned(full, *, epsilon=None, keep_best=None):
    """What the pruned call must return, derived from the full values."""
    d = full.copy()
    if epsilon is not None:
        d[d >= epsilon] = np.inf
    if keep_best is not None and keep_best < len(d):
        best = np.argsort(d, kind="stable")[:keep_best]
        kept = np.full(len(d), np.inf)
        kept[best] = d[best]
        d = kept
    return d


# ----------------------------------------------------------------------------------------------
# exactness
# ----------------------------------------------------------------------------------------------


def test_reference_on_a_hand_computed_case():
    a = np.array([[0.0], [1.0], [2.0]])
    b = np.array([[0.0], [2.0]])
    # costs |a_i - b_j|: [[0, 2], [1, 1], [2, 0]]; best path (0,0) (1,0) (2,1) = 0 + 1 + 0
    assert dtw_reference(a, b) == pytest.approx(1.0)
    assert float(dtw_distances(a, b[None])[0]) == pytest.approx(1.0)
    # a single point against a trajectory: the sum of its distances to every point
    y = np.array([[3.0, 4.0], [0.0, 0.0], [6.0, 8.0]])
    assert float(dtw_distances(np.zeros((1, 2)), y[None])[0]) == pytest.approx(15.0)


def test_reference_matches_dtw_python():
    dtw = pytest.importorskip("dtw")
    rng = np.random.default_rng(0)
    for n, m, D in [(7, 5, 1), (20, 33, 3), (31, 12, 7), (1, 9, 3), (9, 1, 2)]:
        a, b = rng.normal(size=(n, D)), rng.normal(size=(m, D))
        ref = dtw.dtw(a, b, dist_method="euclidean", step_pattern="symmetric1", distance_only=True)
        assert dtw_reference(a, b) == pytest.approx(ref.distance, rel=1e-10, abs=1e-10)
        assert float(dtw_distances(a, b[None])[0]) == pytest.approx(ref.distance, rel=1e-10)


@pytest.mark.parametrize("D", [1, 3, 7, 9])
@pytest.mark.parametrize("kind", ["reaches", "walks"])
def test_full_dtw_matches_reference(D, kind):
    rng = np.random.default_rng(D)
    gen = _reaches if kind == "reaches" else _walks
    sim, lens = gen(rng, 45, 28, D)
    obs_all, _ = gen(rng, 1, 31, D)
    obs, n_obs = obs_all[0], 23  # observed padded beyond its own length
    ref = _references(obs[:n_obs], sim, lens)
    d = dtw_distances(obs, sim, lens, observed_length=n_obs)
    assert d.dtype == torch.float64 and d.device.type == "cpu" and d.shape == (45,)
    np.testing.assert_allclose(d.numpy(), ref, rtol=1e-9, atol=1e-9)


def test_full_dtw_matches_dtw_python_on_a_batch():
    dtw = pytest.importorskip("dtw")
    rng = np.random.default_rng(3)
    sim, lens = _reaches(rng, 20, 40, 3)
    obs = _reaches(rng, 1, 35, 3)[0][0]
    d = dtw_distances(obs, sim, lens).numpy()
    for b in range(20):
        ref = dtw.dtw(
            obs,
            sim[b, : lens[b]],
            dist_method="euclidean",
            step_pattern="symmetric1",
            distance_only=True,
        )
        assert d[b] == pytest.approx(ref.distance, rel=1e-9, abs=1e-6)


def test_full_and_pruned_dtw_match_dtaidistance():
    dtw_ndim = pytest.importorskip("dtaidistance.dtw_ndim")
    rng = np.random.default_rng(6)
    for D in (3, 7):
        sim, lens = _reaches(rng, 300, 60, D, min_len=15)
        obs = _reaches(rng, 1, 55, D)[0][0]
        ref = np.array(
            [
                dtw_ndim.distance_fast(obs, sim[b, : lens[b]], inner_dist="euclidean")
                for b in range(300)
            ]
        )
        full = dtw_distances(obs, sim, lens).numpy()
        np.testing.assert_allclose(full, ref, rtol=1e-9, atol=1e-9)
        kept = dtw_distances(obs, sim, lens, keep_best=20).numpy()
        best = np.argsort(ref, kind="stable")[:20]
        assert set(np.flatnonzero(np.isfinite(kept))) == set(best)
        np.testing.assert_allclose(kept[best], ref[best], rtol=1e-9)


def test_input_types_and_padding_are_ignored():
    rng = np.random.default_rng(4)
    sim, lens = _reaches(rng, 30, 25, 3)
    obs = sim[0, : lens[0]].copy()
    ref = dtw_distances(obs, sim, lens).numpy()
    assert ref[0] == 0.0
    # torch tensors (float32 is computed in float64 from the float32 values)
    d_t = dtw_distances(torch.from_numpy(obs), torch.from_numpy(sim), torch.from_numpy(lens))
    np.testing.assert_array_equal(d_t.numpy(), ref)
    sim32 = torch.from_numpy(sim).float()
    d32 = dtw_distances(torch.from_numpy(obs), sim32, lens).numpy()
    ref32 = _references(obs, sim32.double().numpy(), lens)
    np.testing.assert_allclose(d32, ref32, rtol=1e-9)
    # whatever sits in the padding (even NaN) is never read
    garbage = sim.copy()
    for b in range(len(sim)):
        garbage[b, lens[b] :] = np.nan if b % 2 else 1e6
    np.testing.assert_array_equal(dtw_distances(obs, garbage, lens).numpy(), ref)
    np.testing.assert_array_equal(
        dtw_distances(obs, garbage, lens, keep_best=5).numpy(), _expected_pruned(ref, keep_best=5)
    )


def test_equal_lengths_dtw_is_at_most_the_diagonal_path():
    rng = np.random.default_rng(5)
    sim, _ = _reaches(rng, 25, 30, 7)
    obs = sim[3] + 0.01
    d = dtw_distances(obs, sim).numpy()
    diagonal = np.linalg.norm(sim - obs[None], axis=-1).sum(axis=1)
    assert np.all(d <= diagonal * (1 + 1e-12))
    # Eq. 2 is the L2 norm of the stacked differences
    l2 = l2_distance(obs, sim).numpy()
    np.testing.assert_allclose(l2, np.sqrt(((sim - obs[None]) ** 2).sum(axis=(1, 2))))
    assert l2_distance(obs, torch.from_numpy(sim[3])).shape == (1,)


# ----------------------------------------------------------------------------------------------
# pruning: identical to the full computation on every candidate it reports
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("D", [3, 7])
def test_pruning_is_exact_on_realistic_batches(D):
    rng = np.random.default_rng(10 + D)
    sim, lens = _reaches(rng, 700, 50, D, min_len=20)
    obs = _reaches(rng, 1, 50, D)[0][0][:44]
    full = dtw_distances(obs, sim, lens).numpy()
    np.testing.assert_allclose(full[:25], _references(obs, sim[:25], lens[:25]), rtol=1e-9)
    for k in (1, 7, 60, 699, 700, 5000):
        got = dtw_distances(obs, sim, lens, keep_best=k).numpy()
        np.testing.assert_array_equal(got, _expected_pruned(full, keep_best=k))
        # the k best indices, in order, are those of the full computation
        n_keep = min(k, len(full))
        assert np.array_equal(
            np.argsort(got, kind="stable")[:n_keep], np.argsort(full, kind="stable")[:n_keep]
        )
    for q in (0.01, 0.2, 0.9):
        eps = float(np.quantile(full, q))
        got = dtw_distances(obs, sim, lens, epsilon=eps).numpy()
        np.testing.assert_array_equal(got, _expected_pruned(full, epsilon=eps))
        got = dtw_distances(obs, sim, lens, epsilon=eps, keep_best=40).numpy()
        np.testing.assert_array_equal(got, _expected_pruned(full, epsilon=eps, keep_best=40))
    # epsilon equal to an attained value: that candidate is out (DTW >= epsilon)
    eps = float(np.sort(full)[50])
    got = dtw_distances(obs, sim, lens, epsilon=eps).numpy()
    assert np.isinf(got[np.argsort(full)[50]]) and np.isfinite(got).sum() == 50


def test_pruning_is_exact_randomised():
    rng = np.random.default_rng(11)
    for trial in range(25):
        B = int(rng.integers(1, 80))
        T = int(rng.integers(1, 30))
        D = int(rng.choice([1, 2, 3, 7]))
        gen = _walks if trial % 2 else _reaches
        sim, lens = gen(rng, B, T, D)
        obs = gen(rng, 1, int(rng.integers(1, 30)), D)[0][0]
        full = dtw_distances(obs, sim, lens).numpy()
        np.testing.assert_allclose(full, _references(obs, sim, lens), rtol=1e-9, atol=1e-12)
        k = int(rng.integers(1, B + 2))
        eps = float(np.quantile(full, rng.uniform())) + 1e-12
        for kw in ({"keep_best": k}, {"epsilon": eps}, {"keep_best": k, "epsilon": eps}):
            got = dtw_distances(obs, sim, lens, **kw).numpy()
            np.testing.assert_array_equal(got, _expected_pruned(full, **kw), err_msg=str(kw))


def test_ties_are_broken_by_index():
    rng = np.random.default_rng(12)
    base, lens = _reaches(rng, 10, 30, 3)
    sim = np.concatenate([base, base, base])  # every value three times
    lens = np.concatenate([lens, lens, lens])
    obs = _reaches(rng, 1, 30, 3)[0][0]
    full = dtw_distances(obs, sim, lens).numpy()
    for k in (1, 2, 4, 5, 29):
        got = dtw_distances(obs, sim, lens, keep_best=k).numpy()
        np.testing.assert_array_equal(got, _expected_pruned(full, keep_best=k))
    # a candidate identical to the observation: distance exactly 0
    sim[7, : lens[7]] = obs[: lens[7]]
    d = dtw_distances(obs[: lens[7]], sim, lens, keep_best=1).numpy()
    assert d[7] == 0.0 and np.isinf(np.delete(d, 7)).all()


def test_small_calls_and_the_cascade_give_the_same_bits(monkeypatch):
    rng = np.random.default_rng(14)
    for D, dtype in ((3, np.float32), (7, np.float64), (1, np.float32)):
        sim, lens = _reaches(rng, 300, 60, D, min_len=5)
        sim = sim.astype(dtype)
        obs = _reaches(rng, 1, 55, D)[0][0]
        eps = float(np.median(dtw_distances(obs, sim, lens).numpy()))
        for kw in ({}, {"keep_best": 17}, {"epsilon": eps}, {"keep_best": 5, "epsilon": eps}):
            got = {}
            for path, cells in (("small", 10**15), ("cascade", 0)):
                monkeypatch.setattr(dtw_api, "SMALL_CALL_CELLS", cells)
                got[path] = dtw_distances(obs, sim, lens, **kw).numpy()
            np.testing.assert_array_equal(got["small"], got["cascade"], err_msg=str((D, kw)))
            assert 0 < np.isfinite(got["small"]).sum() <= (150 if "epsilon" in kw else 300)
    # the default sends a call by its table size: 55 x (sum of lengths) cells
    monkeypatch.undo()
    assert 55 * int(lens.sum()) <= dtw_api.SMALL_CALL_CELLS < 55 * 10**6


def test_results_do_not_depend_on_threads_or_calls():
    rng = np.random.default_rng(13)
    sim, lens = _reaches(rng, 500, 40, 7, min_len=10)
    obs = _reaches(rng, 1, 40, 7)[0][0]
    for kw in ({}, {"keep_best": 30}, {"epsilon": 1.5}):
        runs = [dtw_distances(obs, sim, lens, workers=w, **kw).numpy() for w in (1, 2, 3, 2)]
        for r in runs[1:]:
            np.testing.assert_array_equal(r, runs[0])


# ----------------------------------------------------------------------------------------------
# bounds
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("D", [1, 3, 7])
def test_bounds_bracket_the_true_dtw(D):
    rng = np.random.default_rng(20 + D)
    for trial in range(6):
        gen = _walks if trial % 2 else _reaches
        B, T = 40, int(rng.integers(2, 30))
        sim, lens = gen(rng, B, T, D)
        obs = gen(rng, 1, int(rng.integers(1, 30)), D)[0][0]
        n = len(obs)
        true = _references(obs, sim, lens)
        for seg in (1, 3, 10, 1000):
            bd = _candidate_bounds(obs, sim, lens, seg=seg)
            assert np.all(bd["lb"] <= true), (trial, seg)
            assert np.all(bd["coarse_lb"] <= bd["lb"] * (1 + 1e-12) + 1e-300)
            assert np.all(bd["ub"] >= true)
        # every row / column bound is below every cell of its row / column, and the suffix
        # bounds added to the DP's row (column) minima never exceed the DTW
        for b in range(B):
            y = sim[b, : lens[b]]
            m = len(y)
            cost = np.sqrt(((obs[:, None] - y[None]) ** 2).sum(-1))
            rs = bd["row_suffix"][b]
            cs = bd["col_suffix"][b]
            assert np.all(rs[:-1] - rs[1:] <= cost.min(axis=1) * (1 + 1e-9) + 1e-12)
            assert np.all(cs[:m] - cs[1 : m + 1] <= cost.min(axis=0) * (1 + 1e-9) + 1e-12)
            acc = np.full((n + 1, m + 1), np.inf)
            acc[0, 0] = 0.0
            for i in range(n):
                for j in range(m):
                    acc[i + 1, j + 1] = cost[i, j] + min(acc[i, j], acc[i, j + 1], acc[i + 1, j])
            Dm = acc[1:, 1:]
            assert np.all(Dm.min(axis=1)[:-1] + rs[1:n] <= true[b] * (1 + 1e-12))
            assert np.all(Dm.min(axis=0)[:-1] + cs[1:m] <= true[b] * (1 + 1e-12))


# ----------------------------------------------------------------------------------------------
# golden values: outputs of the code as it was before distances.py became a package
# (tests/data/make_dtw_golden.py says how they were made; never re-freeze them to pass)
# ----------------------------------------------------------------------------------------------

_GOLDEN = Path(__file__).parent / "data" / "dtw_golden.npz"
with np.load(_GOLDEN) as _z:
    _GOLDEN_CASES = sorted({key.split("/")[0] for key in _z.files})


@pytest.fixture(scope="module")
def golden():
    with np.load(_GOLDEN) as z:
        return {key: z[key] for key in z.files}


# A golden value is a fact about the maths, not about one machine's rounding: numba compiles the
# kernels for the CPU it runs on (FMA contraction, vector width), so another x86-64 CPU may differ
# in the last bits (one Xeon got 6.062639332032146 for 6.0626393320321466, 1 ulp). Every value is
# a sum of at most ~100 correctly rounded terms, so its rounding error is below 1e-13 relative;
# GOLDEN_RTOL = 1e-12 allows that with margin and still catches any change in the recursion (a
# wrong step or a dropped cell moves a value by far more: see
# test_golden_comparison_tolerates_rounding_but_not_a_change). Bit-identity between two calls in
# the SAME run (workers, pruning, batching) is tested exactly elsewhere in this file.
GOLDEN_RTOL = 1e-12


def _assert_golden_close(got, want, what):
    """``got`` equals the golden ``want`` to GOLDEN_RTOL (relative to the case's largest finite
    golden value for entries near zero); infinities and NaNs in the same places."""
    got, want = np.asarray(got), np.asarray(want)
    assert got.dtype == want.dtype and got.shape == want.shape, what
    finite = want[np.isfinite(want)]
    scale = float(np.abs(finite).max()) if finite.size else 1.0
    np.testing.assert_allclose(got, want, rtol=GOLDEN_RTOL, atol=GOLDEN_RTOL * max(scale, 1.0),
                               equal_nan=True, err_msg=what)


def _assert_pruned_close(got, want, full, kw, what):
    """A pruned call (``epsilon`` and/or ``keep_best``) against its golden output. Where both are
    finite they agree to GOLDEN_RTOL. Which candidates are kept may differ only at a near-tie,
    a candidate whose golden full DTW lies within GOLDEN_RTOL of the cut (``epsilon`` is an
    attained value in the ``eps_min`` calls, and some cases have equal DTWs at the keep_best
    boundary): there a last-bit difference legitimately decides in or out."""
    got, want, full = np.asarray(got), np.asarray(want), np.asarray(full)
    both = np.isfinite(got) & np.isfinite(want)
    np.testing.assert_allclose(got[both], want[both], rtol=GOLDEN_RTOL, err_msg=what)
    differs = np.flatnonzero(np.isfinite(got) != np.isfinite(want))
    if differs.size == 0:
        return
    cuts = []
    eps = kw.get("epsilon")
    if eps is not None:
        cuts.append(float(eps))
    k = kw.get("keep_best")
    if k is not None:
        under = np.sort(full[full < eps]) if eps is not None else np.sort(full)
        cuts += [float(v) for v in under[max(k - 1, 0) : k + 1]]
    cuts = np.asarray(cuts)
    near = np.abs(full[differs][:, None] - cuts[None]) <= GOLDEN_RTOL * np.abs(cuts[None])
    assert near.any(axis=1).all(), f"{what}: kept set differs at {differs[~near.any(axis=1)].tolist()}"


def _check_golden_case(golden, case, check=_assert_golden_close, check_pruned=_assert_pruned_close):
    obs, sim, lens = golden[f"{case}/obs"], golden[f"{case}/sim"], golden[f"{case}/lens"]
    n = int(golden[f"{case}/n"])
    calls = sorted(key for key in golden if key.startswith(f"{case}/dtw/"))
    assert len(calls) == 8
    full = golden[f"{case}/dtw/full_w1"]
    for key in calls:
        opt = key.split("/")[2]
        prefix = f"{case}/kw/{opt}/"
        kw = {k[len(prefix) :]: golden[k].item() for k in golden if k.startswith(prefix)}
        got = dtw_distances(obs, sim, lens, observed_length=n, **kw).numpy()
        if "epsilon" in kw or "keep_best" in kw:
            assert got.dtype == golden[key].dtype, key
            check_pruned(got, golden[key], full, kw, key)
        else:
            check(got, golden[key], key)
    x = np.asarray(obs[:n], dtype=np.float64)
    s64 = np.where(np.isnan(sim), 0.0, sim).astype(np.float64)
    for seg in (20, 3, 1000):
        bounds = _candidate_bounds(x, s64, lens, seg=seg)
        for name, v in bounds.items():
            key = f"{case}/bounds/{seg}/{name}"
            if key in golden:
                check(v, golden[key], key)
    eq = sim[:, :n] if not np.isnan(sim[:, :n]).any() else np.nan_to_num(sim[:, :n])
    check(l2_distance(obs[:n], eq).numpy(), golden[f"{case}/l2"], f"{case}/l2")


@pytest.mark.parametrize("case", _GOLDEN_CASES)
def test_golden_values_are_unchanged(golden, case):
    _check_golden_case(golden, case)


def test_golden_comparison_tolerates_rounding_but_not_a_change(golden):
    """The tolerance is not a blank cheque: a last-bit difference anywhere passes (as another
    CPU's rounding would), a relative change of 1e-9 in one value fails, and a candidate moved
    across a cut that it was not near fails."""
    case = "lanes_d7"
    shifted = dict(golden)  # goldens one ulp up, as another CPU's rounding could give: passes
    for key, v in golden.items():
        if key.startswith((f"{case}/dtw/", f"{case}/bounds/")) or key == f"{case}/l2":
            shifted[key] = np.nextafter(v, np.inf)
    _check_golden_case(shifted, case)
    full_key = f"{case}/dtw/full_w1"
    moved = dict(golden)
    moved[full_key] = golden[full_key] * np.where(np.arange(len(golden[full_key])) == 5, 1 + 1e-9, 1.0)
    with pytest.raises(AssertionError, match="full_w1"):
        _check_golden_case(moved, case)
    full = golden[full_key]
    kw = {"keep_best": 7}
    kept = _expected_pruned(full, **kw)
    far = int(np.argsort(full)[-1])  # the largest DTW, far from the 7th-best cut
    wrong = kept.copy()
    wrong[far] = full[far]
    with pytest.raises(AssertionError, match="kept set differs"):
        _assert_pruned_close(wrong, kept, full, kw, "keep7")
    order = np.argsort(full, kind="stable")
    tied = full.copy()
    tied[order[7]] = tied[order[6]]  # the 7th and 8th best tied: either may be kept
    swapped = _expected_pruned(tied, **kw)
    swapped[order[6]], swapped[order[7]] = np.inf, tied[order[6]]
    _assert_pruned_close(swapped, _expected_pruned(tied, **kw), tied, kw, "keep7 tie")


# ----------------------------------------------------------------------------------------------
# validation
# ----------------------------------------------------------------------------------------------


def _ok():
    rng = np.random.default_rng(30)
    sim, lens = _reaches(rng, 4, 10, 3)
    return sim[0], sim, lens


@pytest.mark.parametrize(
    "change, exc, prefix",
    [
        (dict(observed=np.zeros((5, 2))), ValueError, "simulated"),
        (dict(observed=np.zeros(5)), ValueError, "observed"),
        (dict(observed=np.zeros((0, 3))), ValueError, "observed"),
        (dict(observed="abc"), TypeError, "observed"),
        (dict(simulated=np.zeros((10, 3))), ValueError, "simulated"),
        (dict(simulated=np.zeros((0, 10, 3))), ValueError, "simulated"),
        (dict(lengths=np.array([1, 2, 3])), ValueError, "lengths"),
        (dict(lengths=np.array([1, 2, 3, 0])), ValueError, "lengths"),
        (dict(lengths=np.array([1, 2, 3, 11])), ValueError, "lengths"),
        (dict(lengths=np.array([1.0, 2.0, 3.0, 4.0])), TypeError, "lengths"),
        (dict(lengths=torch.ones(4)), TypeError, "lengths"),
        (dict(observed_length=0), ValueError, "observed_length"),
        (dict(observed_length=11), ValueError, "observed_length"),
        (dict(observed_length=2.5), TypeError, "observed_length"),
        (dict(epsilon=0.0), ValueError, "epsilon"),
        (dict(epsilon=-1.0), ValueError, "epsilon"),
        (dict(epsilon=float("nan")), ValueError, "epsilon"),
        (dict(epsilon="1"), TypeError, "epsilon"),
        (dict(keep_best=0), ValueError, "keep_best"),
        (dict(keep_best=2.0), TypeError, "keep_best"),
        (dict(keep_best=True), TypeError, "keep_best"),
        (dict(workers=0), ValueError, "workers"),
    ],
)
def test_invalid_arguments_name_the_argument(change, exc, prefix):
    obs, sim, lens = _ok()
    kw = dict(observed=obs, simulated=sim, lengths=lens)
    kw.update(change)
    with pytest.raises(exc, match=f"^{prefix}"):
        dtw_distances(kw.pop("observed"), kw.pop("simulated"), kw.pop("lengths"), **kw)


@pytest.mark.parametrize("pruning", [{}, {"keep_best": 2}, {"epsilon": 1.0}])
def test_nan_and_inf_in_valid_steps_are_rejected(pruning):
    obs, sim, lens = _ok()
    bad = sim.copy()
    bad[2, lens[2] - 1, 1] = np.inf
    with pytest.raises(ValueError, match=r"^simulated: .*sample 2, step"):
        dtw_distances(obs, bad, lens, **pruning)
    bad_obs = obs.copy()
    bad_obs[1, 0] = np.nan
    with pytest.raises(ValueError, match="^observed"):
        dtw_distances(bad_obs, sim, lens, **pruning)
    # beyond observed_length the observation is never read
    bad_obs = obs.copy()
    bad_obs[-1] = np.nan
    d = dtw_distances(bad_obs, sim, lens, observed_length=len(obs) - 1, **pruning)
    assert not torch.isnan(d).any()


def test_l2_distance_validation():
    obs, sim, _ = _ok()
    with pytest.raises(ValueError, match="^simulated"):
        l2_distance(obs[:5], sim)
    with pytest.raises(ValueError, match="^simulated"):
        l2_distance(obs, sim[..., :2])
    with pytest.raises(ValueError, match="^observed"):
        l2_distance(np.full_like(obs, np.nan), sim)
    with pytest.raises(ValueError, match="^a"):
        dtw_reference(np.zeros(3), np.zeros((3, 1)))
