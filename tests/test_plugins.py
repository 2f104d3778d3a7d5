"""Methods and body models from another installed package (entry points, `camo_sbi._plugins`).

The slow test builds a tiny plug-in package in a temporary folder, installs it with pip into a
folder of its own (``pip install --target``; the commands it then runs see it through
PYTHONPATH, as a package installed in the venv is seen, through its ``.dist-info`` metadata),
and runs ``camo-sbi compare --workers 2`` on its method and its body model: the CLI, ``--help``
and the spawned worker processes all find them. A target folder rather than the venv itself,
so that the tests running beside it (pytest-xdist) never see a method they do not expect; it is
removed with the temporary folder.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import warnings
from importlib import metadata
from pathlib import Path

import pandas as pd
import pytest

from camo_sbi import _plugins
from camo_sbi.inference import registry

ROOT = Path(__file__).resolve().parents[1]
CAMO_SBI = Path(sys.executable).with_name("camo-sbi")

METHOD = '''
"""A plug-in method: the point halfway between the observed min/max and the nominal limits."""
import time
from dataclasses import dataclass

import numpy as np

from camo_sbi.inference.baselines import point_result
from camo_sbi.inference.contract import check_run_args
from camo_sbi.inference.registry import Capabilities, Implementation, MethodSpec, register


@dataclass(frozen=True)
class HalfwayConfig:
    share: float = 0.5


def run(task, observations, *, budget, seed, config=None):
    t0 = time.perf_counter()
    config, budget, seed, observations, prior = check_run_args(task, observations, budget, seed, config,
                                                               HalfwayConfig)
    q = np.concatenate([o.q.numpy() for o in observations])
    seen = np.stack([q.min(0), q.max(0)], 1).reshape(-1)
    outer = prior.outer_theta().numpy()
    return point_result("toy-halfway", outer + config.share * (seen - outer), len(observations), t0)


register(MethodSpec("toy-halfway", "halfway between the observed range and the nominal limits (plug-in)",
                    lambda: Implementation(run, HalfwayConfig),
                    Capabilities(spaces=("joint",), simulates=False, posterior=False)))
'''

MODEL = '''
"""A plug-in body model: the 7-joint test arm, shipped with the package."""
from pathlib import Path

from camo_sbi.simulators import from_urdf
from camo_sbi.simulators.registry import ModelDef, fraction_profile

URDF = Path(__file__).with_name("arm7.urdf")
START = [0.0, 0.4, 0.0, -1.1, 0.0, 0.7, 0.0]


def toy_arm(start=None):
    return from_urdf(URDF.read_text(), "tool", start=START if start is None else start)


def model():
    return ModelDef("toy-arm", toy_arm, profiles={"elbow_half": fraction_profile({3: 0.5})},
                    description="the 7-joint test arm (plug-in)")
'''

PYPROJECT = '''
[build-system]
requires = ["setuptools>=61"]
build-backend = "setuptools.build_meta"

[project]
name = "camo-plugin-toy"
version = "0.0.1"

[project.entry-points."camo_sbi.methods"]
toy-halfway = "camo_plugin_toy.method"

[project.entry-points."camo_sbi.models"]
toy-arm = "camo_plugin_toy.model:model"

[tool.setuptools]
packages = ["camo_plugin_toy"]

[tool.setuptools.package-data]
camo_plugin_toy = ["arm7.urdf"]
'''


def _plugin_package(root: Path) -> Path:
    src = root / "camo-plugin-toy"
    pkg = src / "camo_plugin_toy"
    pkg.mkdir(parents=True)
    (src / "pyproject.toml").write_text(textwrap.dedent(PYPROJECT))
    (pkg / "__init__.py").write_text("")
    (pkg / "method.py").write_text(METHOD)
    (pkg / "model.py").write_text(MODEL)
    (pkg / "arm7.urdf").write_text((ROOT / "tests" / "data" / "arm7.urdf").read_text())
    return src


@pytest.mark.slow  # pip builds and installs a package, then a grid runs in two spawned workers (~1 min)
def test_an_installed_plugin_is_seen_by_the_cli_help_and_worker_processes(tmp_path):
    src = _plugin_package(tmp_path)
    target = tmp_path / "site"
    pip = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
                          "--no-index", "--target", str(target), str(src)], capture_output=True, text=True,
                         timeout=600)
    assert pip.returncode == 0, pip.stderr[-2000:]
    assert list(target.glob("camo_plugin_toy-0.0.1.dist-info/entry_points.txt"))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(target), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep),
           "COLUMNS": "200"}

    def cli(*argv):
        return subprocess.run([str(CAMO_SBI), *argv], capture_output=True, text=True, timeout=900, env=env,
                              cwd=tmp_path)

    top = cli("--help")
    assert top.returncode == 0 and "toy-halfway: halfway between the observed range" in top.stdout
    assert "toy-arm: elbow_half" in top.stdout
    assert "toy-arm" in cli("compare", "--help").stdout
    out = tmp_path / "grid"
    run = cli("compare", "--model", "toy-arm", "--subjects", "elbow_half", "--methods", "toy-halfway",
              "--budgets", "50", "--seeds", "2", "--tasks", "2", "--workers", "2", "--out", str(out))
    assert run.returncode == 0, run.stderr[-3000:]
    df = pd.read_csv(out / "results.csv")
    assert set(df.method) == {"toy-halfway", "naive", "nominal", "oracle"} and set(df.task) == {"toy-arm"}
    assert (df.status == "ok").all() and df.seed.nunique() == 2
    # the plug-in's estimate is halfway between naive's and nominal's, so its limit error is too
    err = df[(df.metric == "limit_error_deg") & (df.n_tasks == 2)].pivot_table(index="seed", columns="method",
                                                                                values="value")
    assert (err["toy-halfway"] <= (err["naive"] + err["nominal"]) / 2 + 1e-6).all()


def test_a_broken_plugin_warns_naming_it_and_the_others_load(monkeypatch):
    """One entry point that fails to import is a warning naming it; the next one still registers."""
    good = metadata.EntryPoint("good", "camo_sbi.inference.registry:MethodSpec", "camo_sbi.methods")
    broken = metadata.EntryPoint("broken", "camo_plugin_that_is_not_installed", "camo_sbi.methods")
    seen = []

    def make():
        seen.append("called")
        return registry.MethodSpec("plugin-probe", "probe", lambda: None, registry.Capabilities())

    monkeypatch.setattr(_plugins, "_LOADED", set())
    monkeypatch.setattr(_plugins, "_FOUND", [metadata.EntryPoints([broken, good])])
    monkeypatch.setattr(metadata.EntryPoint, "load", lambda ep: make if ep.name == "good"
                        else __import__(ep.value))
    registered = []
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        _plugins.load("camo_sbi.methods", registered.append, registry.MethodSpec)
        _plugins.load("camo_sbi.methods", registered.append, registry.MethodSpec)  # once per process
    assert [s.name for s in registered] == ["plugin-probe"] and seen == ["called"]
    msgs = [str(x.message) for x in w]
    assert len(msgs) == 1 and msgs[0].startswith("plug-in: camo_sbi.methods entry point 'broken'")
    assert "ModuleNotFoundError" in msgs[0]
    with pytest.raises(ValueError, match="^group: "):
        _plugins.load("camo_sbi.other", registered.append, registry.MethodSpec)
