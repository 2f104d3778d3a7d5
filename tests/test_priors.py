"""BoxPrior: support, LHS stratification, moments, fixed joints, free/expand, log_prob, seeding, bad input."""

import math

import numpy as np
import pytest
import torch

from camo_sbi.priors import BoxPrior

# a 3-joint box with an asymmetric start (s_i != midpoint) so lo/hi widths differ
BOUNDS = torch.tensor([[-2.0, 1.0], [-0.5, 3.0], [-1.0, 1.0]], dtype=torch.float64)
START = torch.tensor([0.4, -0.2, 0.9], dtype=torch.float64)


def _prior(**kw):
    return BoxPrior(BOUNDS, START, **kw)


def _expected_low_high(bounds=BOUNDS, start=START):
    n = bounds.shape[0]
    low, high = np.empty(2 * n), np.empty(2 * n)
    low[0::2], high[0::2] = bounds[:, 0].numpy(), start.numpy()
    low[1::2], high[1::2] = start.numpy(), bounds[:, 1].numpy()
    return low, high


@pytest.mark.parametrize("sampling", ["uniform", "lhs"])
def test_samples_inside_box_and_bracket_start(sampling):
    prior = _prior(sampling=sampling)
    theta = prior.sample(2000, seed=0)
    assert theta.shape == (2000, 6) and theta.dtype == torch.float64
    low, high = _expected_low_high()
    x = theta.numpy()
    assert np.all(x >= low) and np.all(x <= high)
    lo, hi = x[:, 0::2], x[:, 1::2]
    s = START.numpy()
    # every draw is a valid limit vector that contains the observed start posture
    assert np.all(lo <= s) and np.all(s <= hi) and np.all(lo <= hi)
    assert bool(prior.contains(theta).all())
    # ... and the draws actually fill the box (not collapsed onto one corner)
    span = x.max(0) - x.min(0)
    assert np.all(span > 0.95 * (high - low))


def test_default_start_is_midpoint():
    prior = BoxPrior(BOUNDS)
    torch.testing.assert_close(prior.start, BOUNDS.mean(dim=1))
    x = prior.sample(500, seed=1).numpy()
    mid = BOUNDS.mean(dim=1).numpy()
    assert np.all(x[:, 0::2] <= mid) and np.all(x[:, 1::2] >= mid)


@pytest.mark.parametrize("n", [7, 50, 333])
def test_lhs_one_draw_per_stratum(n):
    prior = _prior(sampling="lhs", fixed={1: (-0.3, 2.0)})
    theta = prior.sample(n, seed=11).numpy()
    low, high = _expected_low_high()
    free = prior.free_mask.numpy()
    assert free.sum() == 4
    for c in np.flatnonzero(free):
        u = (theta[:, c] - low[c]) / (high[c] - low[c])
        bins = np.floor(u * n).astype(int)
        # each of the n equal bins holds exactly one draw
        np.testing.assert_array_equal(np.sort(bins), np.arange(n))


def test_uniform_draws_are_not_stratified():
    """Control for the LHS test: i.i.d. draws almost never hit every bin exactly once."""
    n = 50
    theta = _prior(sampling="uniform").sample(n, seed=11).numpy()
    low, high = _expected_low_high()
    bins = np.floor((theta[:, 0] - low[0]) / (high[0] - low[0]) * n).astype(int)
    assert len(np.unique(bins)) < n


def test_uniform_moments():
    """Mean and variance of N i.i.d. draws match U[a, b] within 5 standard errors per coordinate.

    SE(mean) = w / sqrt(12 N); SE(var) = w^2 sqrt(1/80 - 1/144) / sqrt(N).
    """
    N = 40_000
    x = _prior().sample(N, seed=123).numpy()
    low, high = _expected_low_high()
    w = high - low
    mean_true, var_true = (low + high) / 2, w**2 / 12
    se_mean = w / math.sqrt(12 * N)
    se_var = w**2 * math.sqrt(1 / 80 - 1 / 144) / math.sqrt(N)
    assert np.all(np.abs(x.mean(0) - mean_true) < 5 * se_mean)
    assert np.all(np.abs(x.var(0) - var_true) < 5 * se_var)


def test_lhs_mean_within_half_a_bin():
    """With one draw per bin, the sample mean is within w / (2N) of the centre (deterministic bound)."""
    N = 400
    x = _prior(sampling="lhs").sample(N, seed=5).numpy()
    low, high = _expected_low_high()
    w = high - low
    assert np.all(np.abs(x.mean(0) - (low + high) / 2) <= w / (2 * N) + 1e-12)
    # variance also close to w^2 / 12
    np.testing.assert_allclose(x.var(0), w**2 / 12, rtol=0.02)


@pytest.mark.parametrize("sampling", ["uniform", "lhs"])
def test_fixed_joints_constant_and_excluded(sampling):
    prior = _prior(fixed={0: (-1.0, 0.5), 2: (0.9, 0.95)}, sampling=sampling)
    assert prior.n_free == 2 and prior.dim == 6 and prior.n_joints == 3
    np.testing.assert_array_equal(prior.free_mask.numpy(), [False, False, True, True, False, False])
    theta = prior.sample(300, seed=2)
    np.testing.assert_array_equal(theta[:, 0].numpy(), -1.0)
    np.testing.assert_array_equal(theta[:, 1].numpy(), 0.5)
    np.testing.assert_array_equal(theta[:, 4].numpy(), 0.9)
    np.testing.assert_array_equal(theta[:, 5].numpy(), 0.95)
    # the free coordinates still vary over their full intervals
    low, high = _expected_low_high()
    sd = theta[:, 2:4].std(dim=0).numpy()
    np.testing.assert_allclose(sd, (high - low)[2:4] / math.sqrt(12), rtol=0.15)
    assert prior.free(theta).shape == (300, 2)
    np.testing.assert_array_equal(prior.free(theta).numpy(), theta[:, 2:4].numpy())


def test_fixed_integer_keys_of_numpy_type_and_start_on_fixed_limit():
    prior = _prior(fixed={np.int64(1): (-0.2, -0.2)})  # lo == start == hi is allowed
    assert prior.n_free == 4
    theta = prior.sample(10, seed=0)
    assert torch.all(theta[:, 2:4] == -0.2)


def test_all_joints_fixed():
    fixed = {0: (-1.0, 0.5), 1: (-0.3, 0.0), 2: (0.5, 1.0)}
    prior = _prior(fixed=fixed)
    assert prior.n_free == 0
    theta = prior.sample(4, seed=0)
    np.testing.assert_array_equal(theta.numpy(), np.tile([-1.0, 0.5, -0.3, 0.0, 0.5, 1.0], (4, 1)))
    assert torch.all(prior.log_prob(theta) == 0.0)


def test_free_expand_round_trip():
    prior = _prior(fixed={1: (-0.3, 2.0)})
    theta = prior.sample(64, seed=4)
    f = prior.free(theta)
    assert f.shape == (64, prior.n_free)
    np.testing.assert_array_equal(prior.expand(f).numpy(), theta.numpy())
    # the other way round: arbitrary free coordinates survive expand -> free
    g = torch.randn(9, prior.n_free, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    np.testing.assert_array_equal(prior.free(prior.expand(g)).numpy(), g.numpy())
    # expand fills the fixed coordinates with their values
    e = prior.expand(g).numpy()
    np.testing.assert_array_equal(e[:, 2], -0.3)
    np.testing.assert_array_equal(e[:, 3], 2.0)
    # a single (n_free,) vector becomes a batch of one
    assert prior.expand(g[0]).shape == (1, 6)


def test_log_prob_inside_and_outside():
    prior = _prior(fixed={2: (0.5, 1.0)})
    theta = prior.sample(100, seed=8)
    lp = prior.log_prob(theta)
    low, high = _expected_low_high()
    widths = (high - low)[:4]  # joint 2 fixed: density over the four free coordinates
    expected = -np.log(widths).sum()
    assert torch.isfinite(lp).all()
    np.testing.assert_allclose(lp.numpy(), expected, rtol=1e-12)
    # moving any single free coordinate beyond its interval gives -inf
    for c, delta in [(0, -0.01 - (theta[0, 0] - low[0])), (1, 0.01 + (high[1] - theta[0, 1])),
                     (3, 0.01 + (high[3] - theta[0, 3]))]:
        bad = theta[:1].clone()
        bad[0, c] += float(delta)
        assert prior.log_prob(bad).item() == -math.inf
        assert not bool(prior.contains(bad)[0])
    # a fixed coordinate off its value is outside too
    bad = theta[:1].clone()
    bad[0, 4] += 1e-3
    assert prior.log_prob(bad).item() == -math.inf
    # lo above the start (hi below) is outside: the start must be bracketed
    bad = theta[:1].clone()
    bad[0, 0] = START[0] + 0.05
    assert prior.log_prob(bad).item() == -math.inf


def test_log_prob_integrates_to_one_monte_carlo():
    """exp(log_prob) * box volume == 1 on draws (density is exactly uniform over free coords)."""
    prior = _prior()
    low, high = _expected_low_high()
    vol = np.prod(high - low)
    lp = prior.log_prob(prior.sample(10, seed=0)).numpy()
    np.testing.assert_allclose(np.exp(lp) * vol, 1.0, rtol=1e-12)


@pytest.mark.parametrize("sampling", ["uniform", "lhs"])
def test_seeding(sampling):
    prior = _prior(sampling=sampling)
    a, b = prior.sample(200, seed=42), prior.sample(200, seed=42)
    np.testing.assert_array_equal(a.numpy(), b.numpy())
    c = prior.sample(200, seed=43)
    assert not np.allclose(a.numpy(), c.numpy())
    # a numpy Generator seeded identically gives the same draws as the int seed
    d = prior.sample(200, seed=np.random.default_rng(42))
    np.testing.assert_array_equal(a.numpy(), d.numpy())
    # consecutive draws from one Generator differ (state advances)
    g = np.random.default_rng(7)
    assert not np.allclose(prior.sample(20, g).numpy(), prior.sample(20, g).numpy())


def test_sampling_does_not_touch_global_rng_state():
    np.random.seed(0)
    torch.manual_seed(0)
    before_np, before_t = np.random.get_state()[1].copy(), torch.get_rng_state().clone()
    _prior(sampling="lhs").sample(10, seed=1)
    _prior().sample(10, seed=1)
    np.testing.assert_array_equal(np.random.get_state()[1], before_np)
    assert torch.equal(torch.get_rng_state(), before_t)


def test_with_sampling_keeps_box():
    p = _prior(fixed={0: (-1.0, 0.5)})
    q = p.with_sampling("lhs")
    assert q.sampling == "lhs" and p.sampling == "uniform"
    assert torch.equal(p.low, q.low) and torch.equal(p.high, q.high) and q.fixed == p.fixed


@pytest.mark.parametrize(
    "kwargs, exc, match",
    [
        ({"bounds": [-1.0, 1.0]}, ValueError, "bounds"),
        ({"bounds": [[-1.0, 1.0, 2.0]]}, ValueError, "bounds"),
        ({"bounds": [[1.0, -1.0]]}, ValueError, "bounds"),
        ({"bounds": [[1.0, 1.0]]}, ValueError, "bounds"),
        ({"bounds": [[-1.0, float("nan")]]}, ValueError, "bounds"),
        ({"bounds": "abc"}, TypeError, "bounds"),
        ({"bounds": [[-1.0, 1.0]], "start": [2.0]}, ValueError, "start"),
        ({"bounds": [[-1.0, 1.0]], "start": [-1.5]}, ValueError, "start"),
        ({"bounds": [[-1.0, 1.0]], "start": [0.0, 0.0]}, ValueError, "start"),
        ({"bounds": [[-1.0, 1.0]], "start": [float("inf")]}, ValueError, "start"),
        ({"fixed": {3: (-1.0, 0.5)}}, ValueError, "fixed"),
        ({"fixed": {-1: (-1.0, 0.5)}}, ValueError, "fixed"),
        ({"fixed": {True: (-1.0, 0.5)}}, ValueError, "fixed"),
        ({"fixed": {0.0: (-1.0, 0.5)}}, ValueError, "fixed"),
        ({"fixed": {0: (0.5, 0.8)}}, ValueError, "fixed"),  # lo above the start 0.4
        ({"fixed": {0: (-1.0, 0.3)}}, ValueError, "fixed"),  # hi below the start
        ({"fixed": {0: (-2.5, 0.5)}}, ValueError, "fixed"),  # beyond the bounds
        ({"fixed": {0: (-1.0, 1.5)}}, ValueError, "fixed"),
        ({"fixed": {0: (0.5, -1.0)}}, ValueError, "fixed"),  # swapped
        ({"fixed": {0: (float("nan"), 0.5)}}, ValueError, "fixed"),
        ({"sampling": "sobol"}, ValueError, "sampling"),
        ({"sampling": "LHS"}, ValueError, "sampling"),
    ],
)
def test_bad_construction(kwargs, exc, match):
    kw = {"bounds": BOUNDS, "start": START, **kwargs}
    if "bounds" in kwargs and "start" not in kwargs:
        kw["start"] = None
    with pytest.raises(exc, match=match):
        BoxPrior(kw.pop("bounds"), kw.pop("start"), **kw)


@pytest.mark.parametrize(
    "fixed",
    [
        {0: (-1.0, 0.0, 0.5)},  # three values
        {0: 0.5},  # not a pair
        {0: ("a", "b")},  # not numbers
        [(0, (-1.0, 0.5))],  # not a mapping
    ],
    ids=["triple", "scalar", "strings", "list"],
)
def test_malformed_fixed_entries_name_fixed(fixed):
    with pytest.raises((ValueError, TypeError), match="fixed"):
        _prior(fixed=fixed)


def test_bad_sample_and_evaluation_inputs():
    prior = _prior()
    with pytest.raises(ValueError, match="n"):
        prior.sample(0, seed=0)
    with pytest.raises(TypeError, match="n"):
        prior.sample(2.0, seed=0)
    with pytest.raises(TypeError, match="seed"):
        prior.sample(3, seed=1.5)
    with pytest.raises(TypeError, match="seed"):
        prior.sample(3, seed=None)
    with pytest.raises(ValueError, match="theta"):
        prior.log_prob(torch.zeros(3, 5))
    with pytest.raises(ValueError, match="theta"):
        prior.contains(torch.zeros(7))
    with pytest.raises(ValueError, match="free_theta"):
        prior.expand(torch.zeros(2, 5))


def test_free_rejects_wrong_width_with_named_error():
    with pytest.raises(ValueError, match="theta"):
        _prior().free(torch.zeros(3, 5))


# --- conditioning on observed postures (BoxPrior.containing) ------------------------------


@pytest.mark.parametrize("sampling", ["uniform", "lhs"])
def test_containing_draws_contain_every_observed_posture(sampling):
    prior = _prior(sampling=sampling)
    q = torch.tensor([[0.1, -0.4, 0.9], [0.7, 0.5, 0.2], [0.4, -0.2, 0.95]], dtype=torch.float64)
    post = prior.containing(q)
    a = torch.minimum(q.min(0).values, START)
    b = torch.maximum(q.max(0).values, START)
    torch.testing.assert_close(post.inner, torch.stack([a, b], dim=1))
    torch.testing.assert_close(post.low[0::2], BOUNDS[:, 0])
    torch.testing.assert_close(post.high[0::2], a)
    torch.testing.assert_close(post.low[1::2], b)
    torch.testing.assert_close(post.high[1::2], BOUNDS[:, 1])
    draws = post.sample(500, 1)
    assert bool((draws[:, 0::2] <= a).all()) and bool((draws[:, 1::2] >= b).all())
    assert bool(post.contains(draws).all()) and bool(prior.contains(draws).all())
    # conditioning twice on the same evidence changes nothing; on more, it narrows further
    torch.testing.assert_close(post.containing(q).inner, post.inner)
    more = post.containing(torch.tensor([[-1.5, 2.0, -0.9]], dtype=torch.float64))
    assert float(more.high[0]) == -1.5 and float(more.low[3]) == 2.0
    # the original is untouched and sampling / fixed are carried over
    torch.testing.assert_close(prior.inner, torch.stack([START, START], dim=1))
    assert post.sampling == sampling and post.with_sampling("uniform").inner.equal(post.inner)


def test_containing_respects_fixed_joints_and_rejects_impossible_postures():
    prior = _prior(fixed={1: (-0.3, 0.5)})
    inside = prior.containing(torch.tensor([[0.0, 0.5 + 1e-7, 0.0]], dtype=torch.float64))
    assert float(inside.low[2]) == float(inside.high[2]) == -0.3  # fixed joint stays fixed
    assert float(inside.low[3]) == float(inside.high[3]) == 0.5  # float32 rounding clipped onto it
    with pytest.raises(ValueError, match="postures: joint 1"):
        prior.containing(torch.tensor([[0.0, 0.8, 0.0]], dtype=torch.float64))
    with pytest.raises(ValueError, match="postures: joint 0"):
        prior.containing(torch.tensor([[-2.5, 0.0, 0.0]], dtype=torch.float64))
    with pytest.raises(ValueError, match="postures"):
        prior.containing(torch.zeros(4, 2))
    with pytest.raises(ValueError, match="postures"):
        prior.containing(torch.tensor([[0.0, float("nan"), 0.0]]))
    with pytest.raises(ValueError, match="inner"):
        BoxPrior(BOUNDS, START, inner=torch.tensor([[0.5, 0.6], [-1.0, 1.0], [0.0, 1.0]]))


def test_grid_sampling_draws_the_documented_levels():
    """sampling='grid': each free bound takes one of the 5 equally spaced values of its joint's
    range on its side of the split (lower: <= split, upper: > split), as the authors' code."""
    from camo_sbi.priors import GRID_LEVELS

    bounds = torch.tensor([[0.0, math.pi], [-1.0, 3.0]], dtype=torch.float64)
    start = torch.tensor([math.pi / 2, 0.0], dtype=torch.float64)
    prior = BoxPrior(bounds, start, sampling="grid")
    draws = prior.sample(4000, 0)
    grid0 = np.linspace(0.0, math.pi, GRID_LEVELS)
    grid1 = np.linspace(-1.0, 3.0, GRID_LEVELS)
    expected = [grid0[grid0 <= math.pi / 2], grid0[grid0 > math.pi / 2], grid1[grid1 <= 0.0], grid1[grid1 > 0.0]]
    for c, values in enumerate(expected):
        got = np.unique(draws[:, c].numpy())
        np.testing.assert_allclose(got, values, rtol=0, atol=1e-12)  # every level is drawn, nothing else
    assert bool(prior.contains(draws).all())
    assert torch.equal(draws, BoxPrior(bounds, start, sampling="grid").sample(4000, 0))  # seeded
    # the nominal bounds are drawable exactly
    assert (draws[:, 0] == 0.0).any() and (draws[:, 1] == math.pi).any()
