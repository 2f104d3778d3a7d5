"""Named seed streams: one table of what each stream seeds, and the same numbers as before."""

from __future__ import annotations

import numpy as np
import pytest

from camo_sbi._validation import SEED_STREAMS, derive_seed


def test_a_named_stream_is_its_integer_so_every_number_stays_the_same():
    # the formula the commands used with integers: SeedSequence(parts).generate_state(2)[0] >> 1
    for name, k in SEED_STREAMS.items():
        expected = int(np.random.SeedSequence([3, 1, k]).generate_state(2, np.uint64)[0] >> 1)
        assert derive_seed(3, 1, name) == derive_seed(3, 1, k) == expected
    assert len(set(SEED_STREAMS.values())) == len(SEED_STREAMS)  # distinct streams, distinct integers
    assert derive_seed(3, 1, "method") != derive_seed(3, 1, "posterior-file")


def test_an_unknown_stream_is_refused_naming_the_argument():
    with pytest.raises(ValueError, match=r"^parts: unknown seed stream 'methdo'"):
        derive_seed(0, "methdo")
