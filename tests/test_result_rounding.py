"""An estimate whose lower bound exceeds its upper bound by rounding is ordered; nothing else moves."""

from __future__ import annotations

import numpy as np
import pytest

from camo_sbi.inference.result import ROUNDING_TOL, PosteriorResult, order_rounded_bounds


def test_rounding_violations_become_the_midpoint_and_nothing_else_moves():
    e = np.array([0.785398 + 2e-16, 0.785398, -1.0, 1.0, 0.3, 0.3, 0.5 + 0.5 * ROUNDING_TOL, 0.5])
    out = order_rounded_bounds(e)
    assert out[0] == out[1] and out[0] <= 0.785398 + 2e-16 and out[1] >= 0.785398
    assert out[6] == out[7] == pytest.approx(0.5 + 0.25 * ROUNDING_TOL, abs=1e-15)
    assert np.array_equal(out[2:6], e[2:6])  # ordered pairs, and lo == hi, bit for bit
    assert e[0] > e[1]  # the input is not modified


def test_a_real_violation_is_left_for_the_checks_downstream():
    e = np.array([0.4, 0.3])  # 0.1 rad: not rounding
    assert np.array_equal(order_rounded_bounds(e), e)


def test_posterior_result_orders_its_estimate():
    s = np.array([[0.785398, 0.785398, -1.0, 1.0]])
    r = PosteriorResult(method="m", samples=s, weights=None, estimate=[0.785398 + 2e-16, 0.785398, -1.0, 1.0],
                        n_simulations=0, wall_time=0.0, n_tasks=1)
    assert 0.785398 + 2e-16 > 0.785398 and r.estimate[0] <= r.estimate[1] and np.array_equal(r.estimate[2:], [-1.0, 1.0])
