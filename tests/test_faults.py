"""Fault injection (issue #14): every fault is injected on purpose and the outcome measured.

* URDF numbers that are not finite are refused when parsed, naming the joint and attribute.
* The kernel cache: a directory that is a symlink, foreign-owned or group/other-writable is
  never read (a planted pickle does not run); kernels are then compiled in memory with the
  same numbers. A corrupt numba index/data file or generated module is deleted and rebuilt.
"""

from __future__ import annotations

import os
import pickle
import shutil
import stat
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

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


# ------------------------------------------------------------------------------ kernel cache

# one revolute joint: the whole generator / numba path at the smallest compile time
ONE_JOINT_URDF = """<?xml version="1.0"?>
<robot name="one">
  <link name="base"/><link name="l1"/><link name="tip"/>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/>
    <origin xyz="0 0 0.1" rpy="0 0 0"/><axis xyz="0 0 1"/><limit lower="-2" upper="2" effort="1" velocity="1"/>
  </joint>
  <joint name="tool" type="fixed"><parent link="l1"/><child link="tip"/><origin xyz="0.3 0 0" rpy="0 0 0"/></joint>
</robot>
"""


def _one_joint():
    from camo_sbi.simulators import from_urdf

    return from_urdf(ONE_JOINT_URDF, "tip", start=[0.1])


def _reach(sim):
    """Simulated trajectories (numpy) for 12 goals: what the cache must not change."""
    rng = np.random.default_rng(0)
    ang = rng.uniform(-1.5, 1.5, 12)
    goals = torch.as_tensor(np.stack([0.3 * np.cos(ang), 0.3 * np.sin(ang), np.full(12, 0.1)], 1))
    theta = torch.tensor([-1.8, 1.9], dtype=torch.float64).expand(12, -1)
    t = sim.simulate(theta, goals)
    return [x.numpy().copy() for x in (t.q, t.ee, t.length, t.reached)]


def _assert_same(a, b):
    for x, y in zip(a, b, strict=True):
        assert x.dtype == y.dtype and np.array_equal(x, y)  # bit for bit


@pytest.fixture
def kernel_env(monkeypatch):
    """A fresh in-process kernel state; returns a function pointing the cache at a directory."""
    from camo_sbi.simulators import kernel

    monkeypatch.setattr(kernel, "_loaded", {})
    monkeypatch.setattr(kernel, "_warned", set())

    def use(path):
        monkeypatch.setenv("CAMO_SBI_KERNEL_CACHE", str(path))
        kernel._loaded.clear()
        return Path(path)

    return use


@pytest.fixture(scope="module")
def primed(tmp_path_factory):
    """A private cache directory holding the one-joint kernel, and that kernel's numbers."""
    from camo_sbi.simulators import kernel

    d = tmp_path_factory.mktemp("kernels") / "primed"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(kernel, "_loaded", {})
        mp.setenv("CAMO_SBI_KERNEL_CACHE", str(d))
        with warnings.catch_warnings():
            warnings.simplefilter("error", kernel.KernelCacheWarning)
            ref = _reach(_one_joint())
    assert stat.S_IMODE(d.stat().st_mode) == 0o700  # created private
    files = sorted(p.name for p in (d / "__pycache__").iterdir())
    assert any(f.endswith(".nbi") for f in files) and any(f.endswith(".nbc") for f in files), files
    return d, ref


def _copy(primed_dir: Path, dest: Path) -> Path:
    shutil.copytree(primed_dir, dest)  # copy2 keeps the mtimes numba's index is stamped with
    return dest


def _kernel_warnings(record):
    from camo_sbi.simulators.kernel import KernelCacheWarning

    return [str(w.message) for w in record if issubclass(w.category, KernelCacheWarning)]


def test_kernel_cache_directory_checks(tmp_path, monkeypatch):
    from camo_sbi.simulators import kernel

    private = tmp_path / "private"
    private.mkdir(mode=0o700)
    assert kernel.check_cache_dir(private) is None
    os.chmod(private, 0o755)  # readable by others, writable only by the owner: allowed
    assert kernel.check_cache_dir(private) is None
    for mode in (0o777, 0o720, 0o702):
        os.chmod(private, mode)
        assert kernel.check_cache_dir(private) == f"is writable by group or others (mode {mode:o})"
    os.chmod(private, 0o700)
    (private / "__pycache__").mkdir(mode=0o777)
    os.chmod(private / "__pycache__", 0o777)
    assert "(its __pycache__)" in kernel.check_cache_dir(private)
    os.chmod(private / "__pycache__", 0o700)
    link = tmp_path / "link"
    link.symlink_to(private)
    assert kernel.check_cache_dir(link) == "is a symbolic link"
    afile = tmp_path / "file"
    afile.write_text("")
    assert kernel.check_cache_dir(afile) == "is not a directory"
    monkeypatch.setattr(kernel, "_current_uid", lambda: os.getuid() + 1)  # we run as the owner: pretend not
    assert kernel.check_cache_dir(private) == (f"is owned by uid {os.getuid()}, not by this user "
                                               f"(uid {os.getuid() + 1})")


def test_default_cache_directory_is_created_private(tmp_path, monkeypatch):
    from camo_sbi.simulators import kernel

    monkeypatch.delenv("CAMO_SBI_KERNEL_CACHE", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    old = os.umask(0)  # even a permissive umask gives a private directory
    try:
        d, reason = kernel._private_cache_dir()
    finally:
        os.umask(old)
    assert d == tmp_path / "xdg" / "camo_sbi" / "kernels" and reason is None
    assert stat.S_IMODE(d.stat().st_mode) == 0o700
    monkeypatch.setenv("CAMO_SBI_KERNEL_CACHE", str(tmp_path / "file" / "kernels"))
    (tmp_path / "file").write_text("")
    d, reason = kernel._private_cache_dir()
    assert reason.startswith("cannot be created")


@pytest.mark.parametrize("fault", ["world-writable", "foreign-owned", "symlink"])
def test_unsafe_cache_is_never_read_and_kernels_compile_in_memory(fault, primed, kernel_env, tmp_path,
                                                                   monkeypatch, recwarn):
    """A pickle planted in an unsafe cache never runs; the kernel is compiled in memory instead."""
    from camo_sbi.simulators import kernel

    d = _copy(primed[0], tmp_path / "planted")
    marker = tmp_path / "pickle-ran"
    for p in (d / "__pycache__").glob("*.nbi"):
        p.write_bytes(pickle.dumps(_Planted(marker)))
    if fault == "world-writable":
        os.chmod(d, 0o777)
        cache, reason = d, "is writable by group or others (mode 777)"
    elif fault == "foreign-owned":
        monkeypatch.setattr(kernel, "_current_uid", lambda: os.getuid() + 1)
        cache, reason = d, f"is owned by uid {os.getuid()}, not by this user"
    else:
        cache, reason = tmp_path / "link", "is a symbolic link"
        cache.symlink_to(d)
    kernel_env(cache)
    before = {p.name: p.read_bytes() for p in d.rglob("*") if p.is_file()}
    mod = kernel.load_kernel(_one_joint().spec, np.float64)
    assert mod.__file__.startswith("<camo_sbi kernel")  # compiled in memory
    assert not marker.exists(), "a planted pickle ran"
    msgs = _kernel_warnings(recwarn)
    assert len(msgs) == 1 and str(cache) in msgs[0] and reason in msgs[0], msgs
    assert {p.name: p.read_bytes() for p in d.rglob("*") if p.is_file()} == before  # nothing written
    kernel.load_kernel(_one_joint().spec, np.float32)
    assert len(_kernel_warnings(recwarn)) == 1  # warned once


def test_planted_pickle_would_run_if_the_cache_were_read(primed, kernel_env, tmp_path):
    """Control for the test above: numba does unpickle the index it finds (so the check matters)."""
    from camo_sbi.simulators import kernel

    d = _copy(primed[0], tmp_path / "own")
    marker = tmp_path / "pickle-ran"
    for p in (d / "__pycache__").glob("*.nbi"):
        p.write_bytes(pickle.dumps(_Planted(marker)))
    kernel_env(d)
    with warnings.catch_warnings():
        warnings.simplefilter("error", kernel.KernelCacheWarning)
        kernel.load_kernel(_one_joint().spec, np.float64)  # a private directory: trusted, read
    assert marker.exists()


class _Planted:
    """Unpickling this touches ``marker``: stands in for arbitrary code in a planted cache file."""

    def __init__(self, marker):
        self.marker = Path(marker)

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def test_in_memory_kernel_gives_the_same_numbers(primed, kernel_env, tmp_path, recwarn):
    d = tmp_path / "open"
    d.mkdir()
    os.chmod(d, 0o777)
    kernel_env(d)
    _assert_same(_reach(_one_joint()), primed[1])
    assert len(_kernel_warnings(recwarn)) == 1
    assert not any(d.iterdir())


def _garbage(p: Path) -> None:
    p.write_bytes(b"\x80\x04garbage\xff" * 7)


def _truncate(p: Path) -> None:
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])


def _empty(p: Path) -> None:
    p.write_bytes(b"")


@pytest.mark.parametrize(
    "pattern, damage",
    [
        ("__pycache__/*simulate*.nbi", _garbage),
        ("__pycache__/*simulate*.nbc", _truncate),
        ("__pycache__/*fk*.nbc", _empty),
        ("*.py", _garbage),
    ],
    ids=["nbi-garbage", "nbc-truncated", "nbc-empty", "py-garbage"],
)
def test_corrupt_cache_file_is_rebuilt(pattern, damage, primed, kernel_env, tmp_path, monkeypatch, recwarn):
    from pickle import UnpicklingError

    from camo_sbi.simulators import kernel

    d = _copy(primed[0], tmp_path / "cache")
    (target,) = d.glob(pattern)
    damage(target)
    kernel_env(d)
    if target.suffix == ".nbi":  # what the fault did before: numba raises on every load
        with pytest.raises(UnpicklingError):
            kernel._import_file(target.name.split(".")[0], d / f"{target.name.split('.')[0]}.py", np.float64)
        kernel._loaded.clear()
    _assert_same(_reach(_one_joint()), primed[1])
    assert _kernel_warnings(recwarn) == []  # rebuilt on disk, not a fallback
    assert target.exists() and target.read_bytes() != b"" and b"garbage" not in target.read_bytes()
    # the rebuilt cache is valid: a new process (fresh state) loads it without another rebuild
    monkeypatch.setattr(kernel, "_remove_cached", lambda *a: pytest.fail("rebuilt twice"))
    kernel._loaded.clear()
    _assert_same(_reach(_one_joint()), primed[1])


def test_cache_failing_twice_falls_back_to_memory(primed, kernel_env, tmp_path, monkeypatch, recwarn):
    from camo_sbi.simulators import kernel

    d = _copy(primed[0], tmp_path / "cache")
    kernel_env(d)

    def broken(*args):
        raise EOFError("Ran out of input")

    monkeypatch.setattr(kernel, "_import_file", broken)
    mod = kernel.load_kernel(_one_joint().spec, np.float64)
    assert mod.__file__.startswith("<camo_sbi kernel")
    (msg,) = _kernel_warnings(recwarn)
    assert str(d) in msg and "could not be loaded or rebuilt (EOFError: Ran out of input)" in msg
