"""The machinery of the `camo_sbi.inference.distances` package rather than its numbers.

`ChunkRunner`'s lifetime (a runner in use is never shut down under its caller), concurrent
callers of `dtw_distances` with different thread counts (bit for bit the sequential results),
and the guard that keeps numba's on-disk cache in step with the kernel modules.
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import numpy as np
import pytest
from numba.core.dispatcher import Dispatcher

from camo_sbi import _threads as sched
from camo_sbi.inference import distances
from camo_sbi.inference.distances import ChunkRunner, chunks, dtw_distances, numba_cache


def _mark(c, n_chunks, out):
    out[c] = c + 1


def _blocking(started, release):
    """A chunk kernel whose chunk 1 signals ``started`` and waits for ``release``."""

    def fn(c, n_chunks, out):
        if c == 1:
            started.set()
            release.wait(10)
        out[c] = c + 1

    return fn


def _in_thread(fn, *args):
    """Start fn(*args) in a thread; returns (thread, list of the exceptions it raised)."""
    errors = []

    def target():
        try:
            fn(*args)
        except BaseException as exc:  # pragma: no cover - reported by the test
            errors.append(exc)

    t = threading.Thread(target=target)
    t.start()
    return t, errors


def _walks(seed, B=400, T=40, D=7):
    rng = np.random.default_rng(seed)
    sim = rng.normal(size=(B, T, D)).cumsum(axis=1) * 0.3
    return sim[0, :35].copy(), sim, rng.integers(10, T + 1, size=B)


@pytest.fixture
def fresh_default(monkeypatch):
    """The shared default runner starts from none; the runners made meanwhile are closed."""
    made = []
    real = sched.ChunkRunner

    def tracked(threads):
        made.append(real(threads))
        return made[-1]

    monkeypatch.setattr(sched, "_default", None)
    monkeypatch.setattr(sched, "ChunkRunner", tracked)
    yield made
    for r in made:
        r.close()


# ----------------------------------------------------------------------------------------------
# ChunkRunner
# ----------------------------------------------------------------------------------------------


def test_runner_runs_every_chunk_and_closes_as_a_context_manager():
    with ChunkRunner(2) as r:
        out = np.zeros(3)
        r.run(_mark, 3, out)
        np.testing.assert_array_equal(out, [1, 2, 3])
        r.run(_mark, 1, out)  # fewer chunks than threads is fine
        assert not r.closed
    assert r.closed
    with pytest.raises(RuntimeError, match="^ChunkRunner: closed"):
        r.run(_mark, 2, out)
    r.close()  # idempotent


def test_runner_argument_errors_name_the_argument():
    with pytest.raises(ValueError, match="^threads:"):
        ChunkRunner(0)
    with pytest.raises(TypeError, match="^threads:"):
        ChunkRunner(1.5)
    with ChunkRunner(1) as r:
        with pytest.raises(ValueError, match="^n_chunks:"):
            r.run(_mark, 3, np.zeros(3))


def test_runner_reraises_a_chunk_error_after_every_chunk_ended():
    ended = []

    def fn(c, n_chunks):
        if c == 1:
            raise KeyError("chunk 1")
        threading.Event().wait(0.05)
        ended.append(c)

    with ChunkRunner(2) as r:
        with pytest.raises(KeyError, match="chunk 1"):
            r.run(fn, 3)
        assert sorted(ended) == [0, 2]


def test_closing_a_runner_in_use_lets_its_run_finish():
    started, release = threading.Event(), threading.Event()
    out = np.zeros(2)
    r = ChunkRunner(1)
    t, errors = _in_thread(r.run, _blocking(started, release), 2, out)
    assert started.wait(10)
    r.close()  # while chunk 1 runs on the pool
    with pytest.raises(RuntimeError, match="^ChunkRunner: closed"):
        r.run(_mark, 1, np.zeros(1))
    release.set()
    t.join(10)
    assert not errors and not t.is_alive()
    np.testing.assert_array_equal(out, [1, 2])


def test_growing_the_default_runner_never_shuts_down_one_in_use(fresh_default):
    started, release = threading.Event(), threading.Event()
    out_a, out_b = np.zeros(2), np.zeros(4)
    # takes a default runner of 1 thread and holds it
    t, errors = _in_thread(sched.run_chunks, _blocking(started, release), 2, out_a)
    assert started.wait(10)
    small = sched._default
    sched.run_chunks(_mark, 4, out_b)  # needs 3 threads: a new default replaces it
    assert sched._default is not small and sched._default.threads == 3
    assert small.closed  # closed, but its run goes on
    release.set()
    t.join(10)
    assert not errors and not t.is_alive()
    np.testing.assert_array_equal(out_a, [1, 2])
    np.testing.assert_array_equal(out_b, [1, 2, 3, 4])
    assert [r.threads for r in fresh_default] == [1, 3]


# ----------------------------------------------------------------------------------------------
# concurrent callers of dtw_distances
# ----------------------------------------------------------------------------------------------


def test_concurrent_calls_with_different_thread_counts_match_sequential_bit_for_bit(
    fresh_default,
):
    obs, sim, lens = _walks(40)
    eps = float(np.quantile(dtw_distances(obs, sim, lens).numpy(), 0.2))
    jobs = [(w, kw) for w in (4, 1, 3, 2) for kw in ({}, {"keep_best": 25}, {"epsilon": eps})]
    want = [dtw_distances(obs, sim, lens, workers=1, **kw).numpy() for _, kw in jobs]
    for _ in range(4):
        sched._default = None  # each round grows the shared runner while others use it
        barrier = threading.Barrier(len(jobs))
        got, errors = {}, []

        def call(i, w, kw, barrier=barrier, got=got, errors=errors):
            try:
                barrier.wait(30)
                for _ in range(3):
                    got.setdefault(i, []).append(
                        dtw_distances(obs, sim, lens, workers=w, **kw).numpy()
                    )
            except BaseException as exc:
                errors.append(exc)

        threads = [threading.Thread(target=call, args=(i, *job)) for i, job in enumerate(jobs)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(60)
        assert not errors, errors
        for i, want_i in enumerate(want):
            assert np.isfinite(want_i).any()
            for d in got[i]:
                assert np.array_equal(d.view(np.uint64), want_i.view(np.uint64)), jobs[i]
    assert max(r.threads for r in fresh_default) == 3


# ----------------------------------------------------------------------------------------------
# import paths and numba's cache
# ----------------------------------------------------------------------------------------------


def test_public_names_and_import_paths():
    assert set(distances.__all__) == {"ChunkRunner", "dtw_distances", "l2_distance"}
    from camo_sbi.inference.distances import _candidate_bounds, l2_distance  # noqa: F401


def test_the_cache_guard_sees_every_kernel_and_its_digest_is_current():
    mods = distances.KERNEL_MODULES
    assert chunks in mods and len(mods) == 5
    caches = numba_cache._caches(mods)
    # every kernel of the package is under the guard (numba still exposes its cache)
    kernels = [
        v
        for m in mods
        for v in vars(m).values()
        if isinstance(v, Dispatcher) and v.py_func.__module__ == m.__name__
    ]
    assert len(caches) == len(kernels) >= 16
    digest = numba_cache.sources_digest(mods)
    for path in {c.cache_path for c in caches}:
        assert (Path(path) / numba_cache.STAMP_NAME).read_text() == digest
    assert not numba_cache.flush_if_changed(mods)  # nothing changed since the import


_CALLEE = """
from numba import njit

@njit(cache=True)
def f():
    return {value}
"""
_CALLER = """
from numba import njit
from pkg.a import f

@njit(cache=True)
def g():
    return f()
"""
_MAIN = """
import importlib.util, sys
sys.path.insert(0, {root!r})
spec = importlib.util.spec_from_file_location("numba_cache", {guard!r})
guard = importlib.util.module_from_spec(spec)
spec.loader.exec_module(guard)
import pkg.a, pkg.b
flushed = guard.flush_if_changed((pkg.a, pkg.b))
print(pkg.b.g(), flushed)
"""


def test_the_cache_guard_drops_a_cached_caller_when_its_callee_module_changes(tmp_path):
    """numba alone would return the old callee's value from g's cache (numba issue #1833)."""
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "b.py").write_text(_CALLER)
    guard = importlib.util.find_spec("camo_sbi.inference.distances.numba_cache").origin
    main = tmp_path / "main.py"
    main.write_text(_MAIN.format(root=str(tmp_path), guard=guard))

    def run(value):
        (pkg / "a.py").write_text(textwrap.dedent(_CALLEE.format(value=value)))
        res = subprocess.run([sys.executable, str(main)], capture_output=True, text=True)
        assert res.returncode == 0, res.stderr
        return res.stdout.split()

    assert run(1) == ["1", "True"]  # first run: no digest yet
    assert run(1) == ["1", "False"]  # unchanged: the caches are used as they are
    assert run(22) == ["22", "True"]  # only a.py changed: g's cache is dropped
