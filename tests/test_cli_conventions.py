"""The command line's conventions (issue 28) and its signal handling (issue 25).

Lazy parser, --help contents, --version, python -m camo_sbi, -v/-q and warnings through
logging, --json, study files, re-runs of a finished grid that build nothing, compile_time apart
from wall_time, and in-process calls that leave SIGTERM to the caller.
"""

from __future__ import annotations

import io
import json
import logging
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import pandas as pd
import pytest

from camo_sbi.experiments import cli
from camo_sbi.experiments.cli import main

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("numpy", "torch", "pandas", "matplotlib", "scipy", "numba", "pybullet", "pyabc", "sbi", "arviz",
         "dask", "pytorch_kinematics")
TINY = ["compare", "--model", "panda", "--methods", "naive", "--budgets", "20", "--seeds", "1", "--tasks", "2",
        "--test-goals", "2"]


def _python(code: str, *args, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code, *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=300, **kwargs)


def _imported(code: str) -> list[str]:
    """The heavy modules imported by running ``code`` in a fresh interpreter."""
    probe = f"{code}\nimport sys\nprint(sorted(m for m in {HEAVY!r} if m in sys.modules))"
    res = _python(probe)
    assert res.returncode == 0, res.stderr[-3000:]
    return json.loads(res.stdout.strip().splitlines()[-1].replace("'", '"'))


# ----------------------------------------------------------------------------- lazy imports, help


def test_the_parser_and_help_import_nothing_heavy():
    assert _imported("from camo_sbi.experiments.cli import build_parser\nbuild_parser()") == []
    code = ("import contextlib, io\nfrom camo_sbi.experiments.cli import main\n"
            "for argv in (['--help'], ['compare', '--help'], ['reproduce', 'hrc', '--help'], ['--version']):\n"
            "    with contextlib.suppress(SystemExit), contextlib.redirect_stdout(io.StringIO()):\n"
            "        main(argv)")
    assert _imported(code) == []


def _help(argv) -> str:
    out = io.StringIO()
    with pytest.raises(SystemExit) as exc, __import__("contextlib").redirect_stdout(out):
        main([*argv, "--help"])
    assert exc.value.code == 0
    return out.getvalue()


def _all_commands():
    yield from ([c.name] for c in cli.COMMANDS)
    yield from (["reproduce", c.name] for c in cli.REPRODUCE)


@pytest.mark.parametrize("argv", list(_all_commands()), ids=" ".join)
def test_every_command_help_shows_defaults_lists_and_examples(argv):
    from camo_sbi.inference.registry import names
    from camo_sbi.simulators.registry import get_model, model_names

    text = _help(argv)
    command = next(c for c in (*cli.COMMANDS, *cli.REPRODUCE) if c.name == argv[-1])
    examples = text.split("examples:\n", 1)[1]
    assert examples.strip().startswith(f"camo-sbi {' '.join(argv)}")  # ends with runnable examples
    assert "(default: " in text or "default: " in text
    if "methods" in command.lists:
        assert all(f"  {m}: " in text for m in names())
    if "subjects" in command.lists:
        assert all(p in text for m in model_names() for p in get_model(m).subjects())
    if "human" in command.lists:
        assert all(p in text for p in get_model("human").profiles)


def test_compare_help_shows_each_default_value():
    from camo_sbi.experiments import compare

    text = " ".join(_help(["compare"]).split())
    p = __import__("argparse").ArgumentParser()
    compare.add_arguments(p)
    for action in p._actions:
        if action.option_strings and action.nargs != 0 and action.default not in (None, []):
            assert f"default: {action.default}" in text or "default" in (action.help or ""), action.dest


def test_top_level_help_lists_commands_methods_and_examples():
    from camo_sbi.inference.registry import names

    text = _help([])
    assert all(c.name in text for c in cli.COMMANDS) and "reproduce" in text
    assert all(f"  {m}: " in text for m in names())
    assert "examples:\n  camo-sbi compare --seeds 1 --tasks 2 --out runs/quickstart" in text


def test_light_copies_agree_with_their_sources():
    """Names repeated in light modules so that --help needs no torch or pybullet."""
    from camo_sbi.experiments import reproduce_hrc
    from camo_sbi.experiments.subjects import subject_names
    from camo_sbi.inference.camo import CamoConfig
    from camo_sbi.scenarios.block_stacking import OBSERVED_MOTIONS
    from camo_sbi.simulators import IMPAIRED_PROFILES
    from camo_sbi.simulators.registry import HUMAN_PROFILES

    assert HUMAN_PROFILES == tuple(IMPAIRED_PROFILES) == tuple(subject_names("human"))
    assert reproduce_hrc.OBSERVED_MOTIONS == OBSERVED_MOTIONS
    assert reproduce_hrc.CAMO_BANDWIDTH == CamoConfig().bandwidth
    from camo_sbi.experiments import recording_args
    from camo_sbi.io import recordings

    assert recording_args.MAX_REACHES == recordings.MAX_REACHES


def test_version_and_python_dash_m(capsys):
    from camo_sbi import __version__

    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0 and capsys.readouterr().out.strip() == f"camo-sbi {__version__}"
    res = subprocess.run([sys.executable, "-m", "camo_sbi", "--help"], cwd=ROOT, capture_output=True, text=True,
                         timeout=120)
    assert res.returncode == 0 and res.stdout.startswith("usage: camo-sbi") and "examples:" in res.stdout
    assert "pybullet build time" not in res.stdout + res.stderr


def test_pybullet_banner_is_silenced():
    res = _python("import camo_sbi.scenarios.block_stacking")
    assert res.returncode == 0, res.stderr[-2000:]
    assert "pybullet build time" not in res.stdout + res.stderr


# ----------------------------------------------------------------------------- signals (issue 25)


def test_in_process_main_installs_no_signal_handler(monkeypatch, tmp_path):
    from camo_sbi.experiments import run

    seen = {}

    def fake(args):
        seen["sigterm"] = signal.getsignal(signal.SIGTERM)
        seen["sigint"] = signal.getsignal(signal.SIGINT)
        raise KeyboardInterrupt

    monkeypatch.setattr(run, "main", fake)
    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    with pytest.raises(KeyboardInterrupt):  # propagates to the caller, not taken for exit 130
        main(["run", str(tmp_path / "s.toml")])
    assert (seen["sigterm"], seen["sigint"]) == before
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == before


def test_sigterm_stops_a_process_that_calls_main_in_process(tmp_path):
    """As `timeout` does to a test run: the process stops, no later code runs (before the fix the
    CLI's handler turned it into exit code 143 of the call and the caller went on)."""
    out, after = tmp_path / "grid", tmp_path / "after"
    grid = [*TINY[:TINY.index("--seeds")], "--seeds", "40", "--tasks", "2", "--no-report", "--out", str(out)]
    code = (f"from camo_sbi.experiments.cli import main\nmain({grid!r})\n"
            f"open({str(after)!r}, 'w').write('the caller went on')")
    proc = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 300  # a hang guard, not a timing assertion
        while not (out / "manifest.json").is_file():
            assert proc.poll() is None, proc.stderr.read().decode()[-3000:]
            assert time.monotonic() < deadline, "compare never started"
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stderr.close()
    assert rc == -signal.SIGTERM
    assert not after.exists()


@pytest.mark.parametrize("sig, code, word", [(signal.SIGINT, 130, "interrupted"), (signal.SIGTERM, 143, "terminated")])
def test_a_signal_dropped_in_a_weakref_callback_is_raised_again(sig, code, word, monkeypatch, tmp_path, capsys):
    """The handler can run inside a weakref callback that C code triggers (seen: h5py writing a
    posterior; the SIGINT test's grid then ran to its end): Python drops an exception raised
    there, so the entry point raises it again and the command stops at its next instruction."""
    import weakref

    from camo_sbi.experiments import run

    reached = []

    class Thing:
        pass

    def stopped_in_a_callback(args):
        thing = Thing()
        ref = weakref.ref(thing, lambda _: signal.raise_signal(sig))  # noqa: F841 - keeps the callback
        del thing  # the callback runs, the handler raises inside it, Python drops that exception
        reached.append("after the callback")
        time.sleep(5)  # the signal raised again ends this at once
        reached.append("the end")
        return 0

    monkeypatch.setattr(run, "main", stopped_in_a_callback)
    hook = sys.unraisablehook
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)  # as at a terminal (xdist may differ)
    try:
        assert cli.console_main(["run", str(tmp_path / "s.toml")]) == code
    finally:
        signal.signal(signal.SIGINT, previous)
    assert reached == ["after the callback"]
    err = capsys.readouterr().err
    assert f"{word}: finished cells are saved" in err and "Exception ignored" not in err
    assert sys.unraisablehook is hook  # restored


@pytest.mark.parametrize("sig, code, word", [(signal.SIGINT, 130, "interrupted"), (signal.SIGTERM, 143, "terminated")])
def test_a_signal_caught_inside_the_command_still_gives_its_exit_code(sig, code, word, monkeypatch, tmp_path, capsys):
    """A library that catches the KeyboardInterrupt (or Terminated) lets the command run to its
    end: the console entry point still exits 130/143 and says what happened."""
    from camo_sbi.experiments import run

    def swallowing(args):
        try:
            signal.raise_signal(sig)
            time.sleep(5)  # the handler raises before this ends
        except KeyboardInterrupt:  # Terminated is one
            pass
        return 0

    monkeypatch.setattr(run, "main", swallowing)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)  # as at a terminal (xdist may differ)
    sigterm = signal.getsignal(signal.SIGTERM)
    try:
        assert cli.console_main(["run", str(tmp_path / "s.toml")]) == code
        # restored by the entry point (checked before this test restores its own)
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
        assert signal.getsignal(signal.SIGTERM) is sigterm
    finally:
        signal.signal(signal.SIGINT, previous)
    err = capsys.readouterr().err
    assert f"{word}: the signal was caught inside the command, which ran to its end (exit code 0" in err


# ----------------------------------------------------------------------------- messages


def test_warnings_are_one_line_through_logging_and_quiet_hides_them():
    from tqdm import tqdm

    stream = io.StringIO()
    with cli._messages(logging.WARNING, stream):
        bar = tqdm(total=2, file=stream, desc="grid")
        warnings.warn("method 'abc-smc' after 2 task(s): fallback: low ESS", RuntimeWarning, stacklevel=1)
        logging.getLogger("camo_sbi.x").info("a note, not shown at WARNING")
        bar.update()
        bar.close()
    lines = stream.getvalue().replace("\r", "\n").splitlines()
    hit = [ln for ln in lines if "fallback" in ln]
    assert hit == ["camo-sbi: warning: RuntimeWarning: method 'abc-smc' after 2 task(s): fallback: low ESS"]
    assert "a note" not in stream.getvalue()
    quiet = io.StringIO()
    with cli._messages(logging.ERROR, quiet), warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.warn("hidden", RuntimeWarning, stacklevel=1)
    assert quiet.getvalue() == ""
    verbose = io.StringIO()
    with cli._messages(logging.INFO, verbose):
        logging.getLogger("camo_sbi.x").info("a note")
    assert verbose.getvalue() == "camo-sbi: a note\n"
    assert not logging.getLogger("camo_sbi").handlers  # nothing left behind


def test_quiet_disables_every_progress_bar_and_restores_tqdm():
    from tqdm import tqdm

    with cli._progress_bars(False):
        assert tqdm(total=1).disable
    bar = tqdm(total=1, file=io.StringIO())
    assert not bar.disable
    bar.close()


# ----------------------------------------------------------------------------- a finished grid


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A small finished compare with its report (naive and the baselines: no numba kernel compiles)."""
    out = tmp_path_factory.mktemp("finished") / "grid"
    assert main([*TINY, "--out", str(out)]) == 0
    return out


def _state(out: Path) -> dict:
    return {p.name: p.stat().st_mtime_ns for p in (out / "report.html", out / "error_vs_tasks.png",
                                                    out / "wall_time.png")}


def test_rerun_of_a_finished_grid_builds_nothing_and_imports_no_torch(finished):
    before = _state(finished)
    code = (f"from camo_sbi.experiments.cli import main\nassert main({[*TINY, '--out', str(finished)]!r}) == 0")
    imported = _imported(code)
    assert not {"torch", "numba", "pybullet", "matplotlib"} & set(imported)
    assert _state(finished) == before  # report and figures kept: their inputs did not change


def test_cli_options_are_no_settings_of_a_run(finished):
    """-v/-q/--json change what is printed, never a result: a re-run with them is not refused."""
    manifest = (finished / "manifest.json").read_text()
    assert main(["-q", *TINY, "-v", "--json", "--out", str(finished)]) == 0
    assert (finished / "manifest.json").read_text() == manifest
    assert not set(cli.CLI_OPTIONS) & set(json.loads(manifest)["settings"])


def test_a_deleted_figure_or_a_changed_input_is_rebuilt(finished, tmp_path):
    import shutil

    from camo_sbi.diagnostics.report import report_is_current

    out = tmp_path / finished.name  # the same name: the same default title
    shutil.copytree(finished, out)
    assert report_is_current(out, out / "report.html")
    (out / "wall_time.png").unlink()
    figure_before = (out / "error_vs_tasks.png").stat().st_mtime_ns
    assert main([*TINY, "--no-report", "--out", str(out)]) == 0
    assert (out / "wall_time.png").is_file()  # the missing figure was drawn again
    assert (out / "error_vs_tasks.png").stat().st_mtime_ns != figure_before  # with its sibling
    cfg = json.loads((out / "config.json").read_text())
    (out / "config.json").write_text(json.dumps({**cfg, "note": "edited"}))
    assert not report_is_current(out, out / "report.html")  # an input changed: the report is rebuilt


def test_json_summary(finished, capsys):
    capsys.readouterr()
    assert main(["--json", *TINY, "--out", str(finished)]) == 0
    captured = capsys.readouterr()
    summary = json.loads(captured.out)  # stdout holds only the JSON; the usual output went to stderr
    assert "cells, " in captured.err
    assert summary["command"] == "compare" and summary["exit_code"] == 0 and summary["error"] is None
    assert summary["out"] == str(finished) and "report.html" not in " ".join(summary["written"])
    assert summary["cells_written"] == 0
    assert set(summary["statuses"]) == {"naive", "nominal", "oracle"}
    assert summary["statuses"]["naive"] == {"ok": 2}  # one result per number of tasks
    assert summary["headline"]["at"] == {"n_tasks": 2, "budget": 20}
    assert summary["headline"]["mean"]["oracle"]["cartesian_error_mm"] == 0.0
    assert summary["headline"]["mean"]["naive"]["cartesian_error_mm"] > 0


def test_json_summary_of_bad_input_names_the_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--json", *TINY[:TINY.index("--budgets") + 1], "0", "--out", str(tmp_path / "x")])
    assert exc.value.code == 2
    captured = capsys.readouterr()
    summary = json.loads(captured.out)
    assert summary["exit_code"] == 2 and summary["error"].startswith("--budgets")
    assert captured.err.strip().splitlines()[-1].startswith("camo-sbi: error: --budgets")


# ----------------------------------------------------------------------------- compile_time


def test_compile_time_is_measured_apart_from_wall_time(monkeypatch):
    """A method that compiles a numba kernel inside its run: the compilation is compile_time, and a
    second run, with the kernel compiled, has none."""
    import numba
    import numpy as np

    from camo_sbi.inference import registry
    from camo_sbi.inference.baselines import NominalConfig, run_nominal
    from camo_sbi.inference.registry import Capabilities, Implementation, MethodSpec, run_method
    from tests.test_distributed import _toy_task

    kernels = {}

    def run(task, observations, *, budget, seed, config):
        if "k" not in kernels:
            kernels["k"] = numba.njit(lambda x: (x * 2.0).sum())
        kernels["k"](np.ones(3))
        return run_nominal(task, observations, budget=budget, seed=seed, config=config)

    impl = Implementation(run, NominalConfig)
    monkeypatch.setitem(registry._REGISTRY, "jit", MethodSpec("jit", "test", lambda: impl,
                                                              Capabilities(spaces=(), simulates=False)))
    task = _toy_task()
    t0 = time.perf_counter()
    first = run_method("jit", task, budget=1, seed=0)
    elapsed = time.perf_counter() - t0
    assert first.compile_time > 0
    assert first.wall_time + first.compile_time <= elapsed
    second = run_method("jit", task, budget=1, seed=0)
    assert second.compile_time == 0.0


def test_import_time_is_measured_apart_from_wall_time(monkeypatch):
    """A method whose run would import a slow library (here one that sleeps 0.3 s on import): with
    the import in its ``setup`` it is import_time, before the clock, never in wall_time (elapsed
    covers both only once); a second run imports nothing. Also through run_method_sequence, where
    the import lands on the first result only (a non-continual method reruns per k)."""
    from camo_sbi.inference import registry
    from camo_sbi.inference.baselines import NominalConfig, run_nominal
    from camo_sbi.inference.registry import (
        Capabilities,
        Implementation,
        MethodSpec,
        run_method,
        run_method_sequence,
    )
    from tests.test_distributed import _toy_task

    state = {"imported": 0}

    def slow_import():
        if not state["imported"]:
            time.sleep(0.3)
        state["imported"] += 1

    def run(task, observations, *, budget, seed, config):
        assert state["imported"], "the run started before its setup"
        return run_nominal(task, observations, budget=budget, seed=seed, config=config)

    impl = Implementation(run, NominalConfig, setup=slow_import)
    monkeypatch.setitem(registry._REGISTRY, "slowimport", MethodSpec(
        "slowimport", "test", lambda: impl, Capabilities(spaces=(), simulates=False)))
    task = _toy_task()
    t0 = time.perf_counter()
    first = run_method("slowimport", task, budget=1, seed=0)
    elapsed = time.perf_counter() - t0
    assert first.import_time >= 0.3
    assert first.wall_time + first.compile_time + first.import_time <= elapsed  # counted once, apart
    second = run_method("slowimport", task, budget=1, seed=0)
    assert second.import_time < 0.3  # imported already: nothing slept
    state["imported"] = 0
    seq = run_method_sequence("slowimport", task, budget=1, seed=0)
    assert len(seq) >= 2 and seq[0].import_time >= 0.3 and all(r.import_time < 0.3 for r in seq[1:])


def test_npe_imports_sbi_in_its_setup_not_in_its_run():
    """NPE's run imports sbi lazily (train_npe); its setup imports the same modules first."""
    import ast
    import inspect
    import sys

    from camo_sbi.inference import sbi_adapter
    from camo_sbi.inference.registry import get_method

    impl = get_method("npe").load()
    assert impl.setup is sbi_adapter.import_sbi
    impl.setup()
    tree = ast.parse(inspect.getsource(sbi_adapter.train_npe).lstrip())
    used = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module.startswith("sbi")}
    assert used and all(m in sys.modules for m in used), used


def test_compare_records_compile_time_beside_wall_time(finished):
    df = pd.read_csv(finished / "results.csv")
    metrics = set(df.metric)
    assert {"wall_time", "compile_time", "import_time"} <= metrics
    assert (df[df.metric == "compile_time"].value >= 0).all()
    assert (df[df.metric == "import_time"].value >= 0).all()


# ----------------------------------------------------------------------------- study files

STUDY = """\
name = "two small grids"
methods = ["naive"]
budgets = [20]
seeds = 1
tasks = 1
test-goals = 2
no-report = true

[[model]]
model = "panda"

[[model]]
name = "panda-wrist"
model = "panda"
subjects = ["wrist_restricted"]
"""


def test_study_file_runs_every_entry_and_is_recorded(tmp_path, capsys):
    study = tmp_path / "study.toml"
    study.write_text(STUDY)
    out = tmp_path / "out"
    assert main(["run", str(study), "--out", str(out)]) == 0
    for name, subject in (("panda", "shoulder_restricted"), ("panda-wrist", "wrist_restricted")):
        df = pd.read_csv(out / name / "results.csv")
        assert set(df.subject) == {subject} and set(df.method) == {"naive", "nominal", "oracle"}
        manifest = json.loads((out / name / "manifest.json").read_text())
        assert manifest["settings"]["study"] == {"file": str(study), "entry": name}
        assert manifest["settings"]["tasks"] == 1 and manifest["settings"]["test_goals"] == 2
    table = pd.read_csv(out / "results.csv")
    assert len(table) == sum(len(pd.read_csv(out / n / "results.csv")) for n in ("panda", "panda-wrist"))
    assert (out / "study.toml").read_text() == STUDY
    recorded = json.loads((out / "study.json").read_text())
    assert recorded["entries"]["panda-wrist"].startswith("camo-sbi compare ")
    capsys.readouterr()
    assert main(["run", str(study), "--out", str(out), "--dry-run"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines == list(recorded["entries"].values())


@pytest.mark.parametrize("edit, needle", [
    ('budgets = [20]', "unknown key 'budgetz'"),
    ('tasks = 1', "--tasks"),
    ('methods = ["naive"]', "unknown method"),
    ('[[model]]\nmodel = "panda"\n', "needs at least one [[model]]"),
    ('seeds = 1', "invalid TOML"),
])
def test_bad_study_file_exits_2_naming_file_and_key(edit, needle, tmp_path, capsys):
    text = {"budgets = [20]": STUDY.replace("budgets = [20]", "budgetz = [20]"),
            "tasks = 1": STUDY.replace("tasks = 1", "tasks = 0"),
            'methods = ["naive"]': STUDY.replace('methods = ["naive"]', 'methods = ["naïve"]'),
            '[[model]]\nmodel = "panda"\n': STUDY.split("[[model]]")[0],
            "seeds = 1": STUDY.replace("seeds = 1", "seeds = = 1")}[edit]
    study = tmp_path / "bad.toml"
    study.write_text(text)
    with pytest.raises(SystemExit) as exc:
        main(["run", str(study), "--out", str(tmp_path / "out")])
    assert exc.value.code == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert line.startswith(f"camo-sbi: error: {study}") and needle in line, line
    assert not (tmp_path / "out" / "panda" / "cells").exists()


def test_the_documented_study_example_is_a_valid_study(capsys, tmp_path):
    from camo_sbi.experiments.run import EXAMPLE, compare_argvs, load_study

    path = ROOT / "docs" / "study_example.toml"
    assert path.read_text().split("\n", 1)[1] in (ROOT / "docs" / "commands" / "index.md").read_text()  # shown there
    assert main(["run", str(path), "--dry-run"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 2 and all(line.startswith("camo-sbi compare --methods camo,camo-hull") for line in lines)
    example = tmp_path / "help_example.toml"  # the example `camo-sbi run --help` shows
    example.write_text(EXAMPLE)
    assert len(compare_argvs(load_study(example)[0], example, tmp_path / "out")) == 2
