"""Issue 36 (reliability, round four): counts bounded up front, a study's combined table keeps its
entries apart, estimator metadata checked before use, a full disk, planted symlinks and an
unreachable scheduler end in one clear line (exit 2), never a hang, a traceback or a segfault."""

from __future__ import annotations

import pytest

from camo_sbi import _memory as budget
from camo_sbi.experiments.cli import main
from tests.test_cli_conventions import STUDY
from tests.test_infer_cli import recording  # noqa: F401 - the fixture: 4 simulated reaches of arm7

GB = 2**30


def _exit_2(argv, capsys) -> str:
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err  # one line, no traceback
    return err[0]


# ----------------------------------------------------------------------------- counts (severe 3)

def test_grid_memory_bound_names_the_count_that_does_not_fit():
    kw = {"cells_per_seed": 3, "tasks": 3, "test_goals": 10, "n_joints": 7, "max_steps": 100}
    small = budget.check_grid_fits(seeds=2, **kw, memory_bytes=GB)
    # the lower bound: 6 cells of 1 KB + 3 rows of 100 B each, and one cell's 13 reaches in flight
    assert small == 6 * (1000 + 3 * 100) + 13 * 100 * 10 * 8
    assert budget.check_grid_fits(seeds=4, **kw, memory_bytes=GB) > small
    with pytest.raises(ValueError, match=r"^--seeds: 1000000000000000000 is too large: .* make --seeds smaller$"):
        budget.check_grid_fits(seeds=10**18, **kw, names={"seeds": "--seeds"}, memory_bytes=23 * GB)
    with pytest.raises(ValueError, match=r"^tasks: 100000000 is too large: .*needs at least .* this machine has 23 GB"):
        budget.check_grid_fits(seeds=2, **{**kw, "tasks": 10**8}, memory_bytes=23 * GB)
    with pytest.raises(ValueError, match=r"^test_goals: "):
        budget.check_grid_fits(seeds=2, **{**kw, "test_goals": 10**9}, memory_bytes=23 * GB)
    with pytest.raises(ValueError, match=r"^workers: 1000 is too large"):
        budget.check_grid_fits(seeds=1000, **kw, workers=1000, memory_bytes=23 * GB)
    with pytest.raises(ValueError, match=r"^seeds: must be >= 1"):
        budget.check_grid_fits(seeds=0, **kw)


@pytest.mark.parametrize("key, value", [("seeds", 10**18), ("tasks", 10**8), ("test-goals", 10**9)])
def test_study_with_absurd_counts_is_refused_up_front(key, value, tmp_path, capsys, monkeypatch):
    """The reporter's cases (23 GB machine): refused before the first entry runs, naming the
    file, the entry and the key; nothing is written."""
    monkeypatch.setattr(budget, "physical_memory", lambda: 23 * GB)
    line = f"{key} = 1\n" if key != "test-goals" else "test-goals = 2\n"
    assert line in STUDY
    study = tmp_path / "study.toml"
    study.write_text(STUDY.replace(line, f"{key} = {value}\n"))
    msg = _exit_2(["run", str(study), "--out", str(tmp_path / "out")], capsys)
    assert msg.startswith(f"camo-sbi: error: {study}: [[model]] 1 (panda): {key}: {value} is too large"), msg
    assert not (tmp_path / "out").exists()


def test_compare_refuses_counts_with_the_models_real_size(tmp_path, capsys, monkeypatch):
    """compare's own check knows the model (7 joints, 100 points a reach): 1e7 tasks need 80 GB."""
    monkeypatch.setattr(budget, "physical_memory", lambda: 23 * GB)
    msg = _exit_2(["compare", "--model", "panda", "--methods", "naive", "--tasks", "10000000",
                   "--out", str(tmp_path / "o")], capsys)
    assert msg.startswith("camo-sbi: error: --tasks: 10000000 is too large") and "80.1 GB" in msg, msg
    msg = _exit_2(["compare", "--model", "panda", "--methods", "naive", "--seeds", "1000", "--workers", "1000",
                   "--out", str(tmp_path / "o")], capsys)
    assert msg.startswith("camo-sbi: error: --workers: 1000 is too large"), msg
    assert not (tmp_path / "o").exists()


# ----------------------------------------------------------------------------- study table (severe 4)

# STUDY's settings (naive, budget 20, 2 test goals, no report) with 2 tasks, on two entries that
# differ only by their name and seed
TWO_ON_ONE = STUDY.split("[[model]]")[0].replace("tasks = 1", "tasks = 2") + """\
[[model]]
name = "a"
model = "panda"

[[model]]
name = "b"
model = "panda"
seed = 1
"""


def test_study_table_keeps_two_entries_on_one_model_apart(tmp_path, capsys):
    import pandas as pd

    study = tmp_path / "study.toml"
    study.write_text(TWO_ON_ONE)
    out = tmp_path / "out"
    assert main(["run", str(study), "--out", str(out)]) == 0
    table = pd.read_csv(out / "results.csv")
    assert table.columns[0] == "entry" and set(table.entry) == {"a", "b"}
    key = ["entry", "task", "subject", "method", "budget", "seed", "n_tasks", "metric"]
    assert set(key) <= set(table.columns)
    assert not table.duplicated(key).any()
    # without the entry the two grids collide on every row: the column is what keeps them apart
    assert table.drop(columns="entry").duplicated(key[1:]).sum() == len(table) // 2
    for name in ("a", "b"):  # every entry's rows are its own grid's, unchanged
        own = pd.read_csv(out / name / "results.csv")
        mine = table[table.entry == name].drop(columns="entry").reset_index(drop=True)
        pd.testing.assert_frame_equal(mine, own)
    capsys.readouterr()
    assert main(["run", str(study), "--out", str(out)]) == 0  # a re-run resumes: every cell finished
    rerun = capsys.readouterr().out
    assert rerun.count("cells, ") == 2 and all(
        line.split()[0] == line.split()[2] for line in rerun.splitlines() if " already finished" in line), rerun
    pd.testing.assert_frame_equal(pd.read_csv(out / "results.csv"), table)


@pytest.mark.parametrize("second", ['name = "a"', 'name = "A"'])
def test_study_refuses_duplicate_entry_names(second, tmp_path, capsys):
    study = tmp_path / "study.toml"
    study.write_text(TWO_ON_ONE.replace('name = "b"', second))
    msg = _exit_2(["run", str(study), "--out", str(tmp_path / "out")], capsys)
    assert msg.startswith(f"camo-sbi: error: {study}: [[model]] 2") and "must be unique" in msg, msg


# ----------------------------------------------------------------------------- a full disk

_LIMITED = """\
import resource, signal, sys
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails (EFBIG), as on a full disk
resource.setrlimit(resource.RLIMIT_FSIZE, ({limit}, {limit}))
from camo_sbi.experiments.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _run_limited(argv, limit_bytes: int):
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-c", _LIMITED.format(limit=limit_bytes), *argv],
                          capture_output=True, text=True, timeout=600)


def _assert_one_clean_line(proc, needle: str):
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-2000:])  # not 139 (a segfault), not 1
    assert "Traceback" not in proc.stderr and "Exception ignored" not in proc.stderr, proc.stderr[-2000:]
    assert lines[-1].startswith("camo-sbi: error: ") and needle in lines[-1], lines[-1]
    assert not any(line.startswith("camo-sbi: error") for line in lines[:-1]), proc.stderr


def test_a_netcdf_that_cannot_be_written_is_one_oserror_naming_the_file(tmp_path):
    """In this process, the file size limited below the file (the kernel refuses the write, as a
    full disk does): one OSError naming the file, no half-written file, no HDF5 object left open
    (before, HDF5 wrote on disk itself and crashed the interpreter at exit)."""
    import errno
    import resource
    import signal

    import arviz as az
    import numpy as np

    from camo_sbi.diagnostics.arviz_io import load_netcdf, save_netcdf

    idata = az.from_dict(posterior={"limits": np.random.default_rng(0).normal(size=(1, 2000, 4))})
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    old = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (8192, hard))
    try:
        with pytest.raises(OSError) as exc:
            save_netcdf(idata, tmp_path / "p.nc")
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, old)
    assert exc.value.errno == errno.EFBIG and exc.value.filename == str(tmp_path / "p.nc")
    assert list(tmp_path.iterdir()) == []
    save_netcdf(idata, tmp_path / "p.nc")  # with room, the same call writes a file arviz reads back
    np.testing.assert_array_equal(load_netcdf(tmp_path / "p.nc").posterior["limits"].values,
                                  idata.posterior["limits"].values)


@pytest.mark.slow
def test_infer_on_a_full_disk_exits_2_in_one_line(recording, tmp_path):  # noqa: F811 - the imported fixture
    """Every file size limited to 8 KB (RLIMIT_FSIZE: the kernel refuses the write in C, where
    HDF5 writes, as a full disk does; no root needed): the first netCDF (a few tens of KB) cannot
    be written. Before, HDF5's half-written file printed "Exception ignored" tracebacks and the
    interpreter crashed at exit (139); now one line names the file, exit 2."""
    from tests.test_infer_cli import MODEL, NOISE

    out = tmp_path / "infer"
    proc = _run_limited(["infer", "--observations", str(recording), *MODEL, *NOISE, "--methods", "naive",
                         "--out", str(out)], 8192)
    _assert_one_clean_line(proc, f"{out}/estimates/naive.nc: File too large (EFBIG)")
    assert not list((out / "estimates").glob(".*.tmp"))  # no half-written file left behind


@pytest.mark.slow
def test_compare_on_a_full_disk_exits_2_in_one_line(tmp_path):
    """As above for compare (its cells write their netCDF through the same writer)."""
    out = tmp_path / "compare"
    proc = _run_limited(["compare", "--model", "panda", "--methods", "naive", "--budgets", "20", "--seeds", "1",
                         "--tasks", "1", "--test-goals", "2", "--no-report", "--out", str(out)], 8192)
    _assert_one_clean_line(proc, "File too large (EFBIG)")
    assert f"{out}/estimates/" in proc.stderr.strip().splitlines()[-1]


@pytest.mark.slow
def test_infer_on_a_real_full_filesystem_exits_2_naming_the_file(recording, tmp_path):  # noqa: F811 - the imported fixture
    """The reporter's case itself, ENOSPC from a 300 KB tmpfs (needs root to mount, as on CI)."""
    import os
    import subprocess
    import sys

    from tests.test_infer_cli import MODEL, NOISE

    full = tmp_path / "full"
    full.mkdir()
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root (CI runs as root); the RLIMIT_FSIZE test covers the path")
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(full)], capture_output=True)
    if mounted.returncode != 0:
        pytest.skip(f"mount -t tmpfs refused here: {mounted.stderr.decode().strip()}")
    try:
        proc = subprocess.run([sys.executable, "-m", "camo_sbi", "infer", "--observations", str(recording), *MODEL,
                               *NOISE, "--methods", "naive", "--out", str(full / "o")],
                              capture_output=True, text=True, timeout=600)
        _assert_one_clean_line(proc, "No space left on device (ENOSPC)")
    finally:
        subprocess.run(["umount", str(full)], check=True)


# ----------------------------------------------------------------------------- planted links

@pytest.mark.parametrize("planted", ["cells", "posteriors/camo.nc", "run.lock", "manifest.json"])
def test_a_run_folder_with_a_planted_link_is_refused_before_anything_is_written(planted, tmp_path):
    from camo_sbi.experiments.rundir import RunDirectory

    out, elsewhere = tmp_path / "out", tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "precious").write_text("keep me")
    link = out / planted
    link.parent.mkdir(parents=True)
    link.symlink_to(elsewhere if planted == "cells" else elsewhere / "precious")
    with pytest.raises(ValueError, match=rf"^--out {out}: {link} is a symbolic link \(to '{elsewhere}.*'\); "
                                         "a run folder holds its own files only"):
        RunDirectory(out, "compare", {"a": 1}).open()
    assert [p.name for p in elsewhere.iterdir()] == ["precious"] and (elsewhere / "precious").read_text() == "keep me"
    assert not (out / "run.lock").exists() or (out / "run.lock").is_symlink()


def test_compare_with_a_planted_cells_link_exits_2_and_writes_nothing_outside(tmp_path, capsys):
    out, elsewhere = tmp_path / "out", tmp_path / "elsewhere"
    elsewhere.mkdir()
    out.mkdir()
    (out / "cells").symlink_to(elsewhere)
    msg = _exit_2(["compare", "--model", "panda", "--methods", "naive", "--budgets", "20", "--seeds", "1",
                   "--tasks", "1", "--test-goals", "2", "--no-report", "--out", str(out)], capsys)
    assert msg.startswith(f"camo-sbi: error: --out {out}: {out / 'cells'} is a symbolic link"), msg
    assert list(elsewhere.iterdir()) == []


def test_out_itself_may_be_a_link(tmp_path):
    """The user's own choice of --out (a link to a data disk) is followed; only links inside it are refused."""
    from camo_sbi.experiments.rundir import RunDirectory

    real = tmp_path / "real"
    real.mkdir()
    (tmp_path / "out").symlink_to(real)
    with RunDirectory(tmp_path / "out", "compare", {"a": 1}) as run:
        assert run.created
    assert (real / "manifest.json").is_file()


# ----------------------------------------------------------------------------- scheduler addresses
# loopback only: nothing here (nor any manual try) connects to another address

def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]  # closed again: nothing listens there


@pytest.fixture()
def wrong_peers():
    """Two loopback listeners that are not Dask schedulers: one silent, one answering like an HTTP
    proxy (the reporter's tcp://10.255.255.1:8786 reached one: dask read "HTTP/1.1" as a frame
    length, 3.07 EiB). Returns {name: address}."""
    import socket
    import threading

    servers, stop = [], threading.Event()

    def serve(sock, reply):
        sock.settimeout(0.2)
        held = []
        while not stop.is_set():
            try:
                conn, _ = sock.accept()
            except TimeoutError:
                continue
            held.append(conn)
            if reply:
                conn.sendall(reply)
        for conn in held:
            conn.close()

    peers = {}
    for name, reply in (("silent", b""), ("http", b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n")):
        sock = socket.socket()
        sock.bind(("127.0.0.1", 0))
        sock.listen(4)
        t = threading.Thread(target=serve, args=(sock, reply), daemon=True)
        t.start()
        servers.append((sock, t))
        peers[name] = f"tcp://127.0.0.1:{sock.getsockname()[1]}"
    yield peers
    stop.set()
    for sock, t in servers:
        t.join()
        sock.close()


def test_a_wrong_scheduler_address_is_one_valueerror_in_bounded_time(wrong_peers, monkeypatch):
    pytest.importorskip("distributed")
    from camo_sbi import distributed as dist

    monkeypatch.setattr(dist, "CONNECT_TIMEOUT", 1.0)
    cases = {"refused": (f"tcp://127.0.0.1:{_free_port()}", "ConnectionRefusedError"),
             "silent": (wrong_peers["silent"], "TimeoutError: no Dask handshake"),
             "http": (wrong_peers["http"], "not a Dask handshake")}
    for name, (address, why) in cases.items():
        with pytest.raises(ValueError) as exc:
            dist.get_client(address)
        msg = str(exc.value)
        assert msg.startswith(f"scheduler: cannot connect to a Dask scheduler at '{address}' within 1 s ("), msg
        assert why in msg and "\n" not in msg, (name, msg)
        assert address not in dist._CLIENTS


def test_study_with_an_unreachable_scheduler_exits_2_naming_the_key(tmp_path, capsys, monkeypatch):
    pytest.importorskip("distributed")
    from camo_sbi import distributed as dist

    monkeypatch.setattr(dist, "CONNECT_TIMEOUT", 1.0)
    address = f"tcp://127.0.0.1:{_free_port()}"
    study = tmp_path / "study.toml"
    study.write_text(STUDY.replace("no-report = true\n", f'no-report = true\nscheduler = "{address}"\n'))
    msg = _exit_2(["run", str(study), "--out", str(tmp_path / "out")], capsys)
    assert msg.startswith(f"camo-sbi: error: {study}: [[model]] 1 (panda): --scheduler: cannot connect to a Dask "
                          f"scheduler at '{address}'"), msg
    assert not (tmp_path / "out" / "panda").exists()  # refused before the entry's run folder


@pytest.mark.parametrize("argv, flag", [
    (["robustness", "--seeds", str(10**18)], "--seeds"),
    (["calibrate", "--subjects", str(10**18)], "--subjects"),
    (["reproduce", "panda", "--runs", str(10**18)], "--runs"),
    (["reproduce", "hrc", "--tasks", str(10**11)], "--tasks"),
])
def test_every_grid_command_bounds_its_counts(argv, flag, tmp_path, capsys):
    """The other commands with counts refuse them the same way, before their run folder exists."""
    msg = _exit_2([*argv, "--out", str(tmp_path / "o")], capsys)
    assert msg.startswith(f"camo-sbi: error: {flag}: ") and "is too large" in msg, msg
    assert not (tmp_path / "o").exists()
