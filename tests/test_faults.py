"""Fault injection (issue #14): every fault is injected on purpose and the outcome measured.

* URDF numbers that are not finite are refused when parsed, naming the joint and attribute.
"""

from __future__ import annotations

import pytest

from tests.conftest import TINY_URDF

# ------------------------------------------------------------------------------ URDF numbers


@pytest.mark.parametrize(
    "old, new, message",
    [
        ('xyz="0.05 0 0.2"', 'xyz="0.05 nan 0.2"', "joint 'j2' origin xyz contains nan"),
        ('rpy="0.3 -0.2 0.1"', 'rpy="0.3 -inf 0.1"', "joint 'j2' origin rpy contains inf"),
        ('<axis xyz="0 0.6 0.8"/>', '<axis xyz="0 NaN 0.8"/>', "joint 'j3' axis contains nan"),
        ('lower="-2.0"', 'lower="nan"', "joint 'j3' limit lower contains nan"),
        ('upper="0.3"', 'upper="inf"', "joint 'j2' limit upper contains inf"),
        ('rpy="0 0.5 0"', 'rpy="0 nan 0"', "joint 'tool' origin rpy contains nan"),  # a fixed joint, folded in
    ],
)
def test_urdf_non_finite_number_is_refused_before_any_kernel(old, new, message, monkeypatch):
    from camo_sbi.simulators import from_urdf, kernel

    assert old in TINY_URDF
    monkeypatch.setattr(kernel, "load_kernel", lambda *a, **k: pytest.fail("kernel code ran"))
    with pytest.raises(ValueError, match=f"^urdf: {message}$"):
        from_urdf(TINY_URDF.replace(old, new, 1), "tip", start=[0.2, 0.1, -0.3])
