"""Compile once (issue 38): the compile notice, the path-independent kernel cache, `camo-sbi warmup`."""

from __future__ import annotations

import importlib.util
import logging
import os
import subprocess
import sys
import types

import pytest

from camo_sbi import _compiling
from camo_sbi.experiments.cli import main as cli_main

_MODULE = """
from numba import njit

@njit
def f(x):
    return x + 1

@njit
def g(x):
    return x * 2

@njit
def dtw_chunk(x):
    return f(x) + g(x)
"""


def _module(name: str) -> types.ModuleType:
    mod = types.ModuleType(name)
    exec(compile(_MODULE, f"<{name}>", "exec"), mod.__dict__)  # noqa: S102 - the test's own source
    return mod


def test_the_notice_is_one_line_per_kind_and_only_for_camo_sbi_kernels(monkeypatch, caplog):
    monkeypatch.setitem(_compiling._state, "said", set())
    _compiling.announce_compiling()
    _compiling.announce_compiling()  # installed once: a second call adds no second listener
    caplog.set_level(logging.WARNING, logger="camo_sbi")
    other = _module("someone_elses_module")
    assert other.f(1) == 2
    assert not [r for r in caplog.records if "compiling" in r.getMessage()]  # not ours: silent
    # a cascade entry point: its callees f and g compile inside its event and say nothing
    cascade = _module("camo_sbi.inference.distances.test_notice_kernels")
    assert cascade.dtw_chunk(1) == 4
    lines = [r.getMessage() for r in caplog.records if "compiling" in r.getMessage()]
    assert len(lines) == 1 and lines[0].startswith("compiling camo_sbi's pruned DTW kernels"), lines
    ours = _module("camo_sbi.inference.test_notice_kernels")
    assert ours.f(1) == 2 and ours.g(2) == 4 and ours.f(1.5) == 2.5  # three compilations
    chain = _module("camo_sbi_kernel_test_notice")
    assert chain.f(3) == 4 and chain.g(3) == 6
    lines = [r.getMessage() for r in caplog.records if "compiling" in r.getMessage()]
    assert len(lines) == 3, lines
    for line, kind in zip(lines, ("cascade", "package", "chain"), strict=True):
        assert line.startswith(f"compiling {_compiling._WHAT[kind]} (once, about "
                               f"{_compiling.COMPILE_SECONDS[kind]} s"), line
    assert all("camo-sbi warmup" in ln for ln in lines)


_KERNELS = """
from numba import njit

@njit(cache=True)
def f(x):
    return x + 41
"""
_MAIN = """
import importlib.util, sys
from numba.core import event
sys.path.insert(0, {root!r})
spec = importlib.util.spec_from_file_location("numba_cache_under_test", {guard!r})  # without torch
guard = sys.modules[spec.name] = importlib.util.module_from_spec(spec)
spec.loader.exec_module(guard)
compiled = []
class L(event.Listener):
    def on_start(self, ev):
        compiled.append(ev.data["dispatcher"].py_func.__name__)
    def on_end(self, ev):
        pass
event.register("numba:compile", L())
import pkg.kernels as k
print(guard.use_private_cache((k,)), k.f(1), len(compiled))
"""


def test_a_second_clone_of_the_same_sources_loads_the_kernels_the_first_compiled(tmp_path):
    """numba's own locator files a cache under a digest of the source's absolute path, so a fresh
    clone compiled everything again; `PackageLocator` files it under the package's name."""
    guard = importlib.util.find_spec("camo_sbi.inference.distances.numba_cache").origin
    cache = tmp_path / "cache"

    def run(clone: str, body: str = _KERNELS) -> list[str]:
        root = tmp_path / clone
        (root / "pkg").mkdir(parents=True, exist_ok=True)
        (root / "pkg" / "__init__.py").write_text("")
        (root / "pkg" / "kernels.py").write_text(body)
        main = root / "main.py"
        main.write_text(_MAIN.format(root=str(root), guard=guard))
        env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
        res = subprocess.run([sys.executable, str(main)], capture_output=True, text=True, env=env, timeout=120)
        assert res.returncode == 0, res.stderr
        return res.stdout.split()

    assert run("a") == [str(cache), "42", "1"]  # first clone: compiled once
    assert run("b") == [str(cache), "42", "0"]  # another directory, same sources: loaded
    ours = lambda: sorted(d.name for d in cache.glob("pkg-*"))  # noqa: E731  (numba's decorator makes empty pkg_<sha1>)
    first = ours()
    assert len(first) == 1 and list((cache / first[0]).glob("kernels.f-*.nbi"))
    changed = _KERNELS.replace("x + 41", "x + 99")
    assert run("c", changed) == [str(cache), "100", "1"]  # other sources: compiled, in their own directory
    assert run("a") == [str(cache), "42", "0"]  # ... which left the first sources' cache alone
    assert len(ours()) == 2 and first[0] in ours()


def test_warmup_refuses_an_unknown_model_in_one_line(capsys):
    with pytest.raises(SystemExit) as exc:
        cli_main(["warmup", "--models", "panda,octopus"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("camo-sbi: error: --models: unknown model 'octopus'"), err


@pytest.mark.slow  # compiles every kernel from empty caches (about a minute on 2 cores)
def test_after_warmup_a_first_comparison_compiles_nothing(tmp_path):
    """`camo-sbi warmup` in empty caches says it compiles (both kinds); a comparison run next, in a
    fresh process on the same caches, compiles nothing of camo_sbi's (no notice: numba fires its
    compile event only when it compiles, not when it loads from the cache)."""
    cli = [sys.executable, "-m", "camo_sbi"]
    env = {**{k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "CAMO_SBI_KERNEL_CACHE")},
           "XDG_CACHE_HOME": str(tmp_path / "cache"), "MPLCONFIGDIR": str(tmp_path / "mpl")}
    warm = subprocess.run([*cli, "warmup"], env=env, capture_output=True, text=True, timeout=1800)
    assert warm.returncode == 0, warm.stderr
    assert warm.stdout.startswith("warmup panda: ")
    notices = [ln for ln in warm.stderr.splitlines() if "compiling" in ln]
    assert len(notices) == 3 and any("DTW and KDE" in ln for ln in notices), notices
    assert any("pruned DTW" in ln for ln in notices), notices
    grid = ["compare", "--model", "panda", "--methods", "camo,abc-smc", "--budgets", "150", "--seeds", "1",
            "--tasks", "2", "--test-goals", "2", "--no-report", "--out", str(tmp_path / "after")]
    after = subprocess.run([*cli, *grid], env=env, capture_output=True, text=True, timeout=1800)
    assert after.returncode == 0, after.stderr
    assert not [ln for ln in after.stderr.splitlines() if "compiling" in ln], after.stderr
    # a large batch (the pruned cascade) in a fresh process: loaded, not compiled
    big = subprocess.run([sys.executable, "-c", _LARGE_CALL], env=env, capture_output=True, text=True, timeout=1800)
    assert big.returncode == 0, big.stderr
    assert big.stdout.split() == ["compiled", "0"], (big.stdout, big.stderr)


_LARGE_CALL = """
import numpy as np
from numba.core import event
compiled = []
class L(event.Listener):
    def on_start(self, ev):
        compiled.append(ev.data["dispatcher"].py_func.__module__)
    def on_end(self, ev):
        pass
event.register("numba:compile", L())
from camo_sbi.inference.distances import dtw_distances
from camo_sbi.inference.distances.api import SMALL_CALL_CELLS
B = SMALL_CALL_CELLS // (80 * 90) + 1
rng = np.random.default_rng(1)
sim = rng.normal(size=(B, 90, 7)).cumsum(axis=1).astype(np.float32)
obs = rng.normal(size=(80, 7)).cumsum(axis=0)
for kw in ({}, {"keep_best": 5}, {"epsilon": 50.0}):
    dtw_distances(obs, sim, **kw)
print("compiled", len([m for m in compiled if m.startswith("camo_sbi")]))
"""
