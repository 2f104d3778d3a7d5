"""Security (issue #25): a file is data, never code.

* URDF names (joints, links, base, end effector) and the .urdf path never enter generated
  kernel source: an injection attempt in any of them runs nothing, and the chain is simulated
  from the very source a benign chain gets. The cached module is named by the sha256 of its
  source and checked against it before import.
"""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
from pathlib import Path
from xml.sax.saxutils import escape

import numpy as np
import pytest

from camo_sbi.experiments.cli import main as cli_main

ONE_JOINT = """<?xml version="1.0"?>
<robot name="one">
  <link name="{base}"/><link name="{link}"/><link name="{tip}"/>
  <joint name="{joint}" type="revolute"><parent link="{base}"/><child link="{link}"/>
    <origin xyz="0 0 0.1" rpy="0 0 0"/><axis xyz="0 0 1"/><limit lower="-2" upper="2" effort="1" velocity="1"/>
  </joint>
  <joint name="{tool}" type="fixed"><parent link="{link}"/><child link="{tip}"/><origin xyz="0.3 0 0" rpy="0 0 0"/></joint>
</robot>
"""
BENIGN = {"base": "base", "link": "l1", "tip": "tip", "joint": "j1", "tool": "tool"}

#: each would create the file PWNED in the working directory if it were pasted into Python source
PAYLOADS = [
    'x"""; import os; os.system("touch PWNED"); """',
    "x'''; import os; os.system('touch PWNED'); '''",
    'x\nimport os; os.system("touch PWNED")\n',
    'x\\"""; import os; os.system("touch PWNED") #',
    "x\"; __import__('os').system('touch PWNED'); \"",
    "x}; __import__('os').system('touch PWNED'); {",
]


def _attr(s: str) -> str:
    """``s`` as an XML attribute value (newlines kept as character references)."""
    return escape(s, {'"': "&quot;", "\n": "&#10;"})


def _urdf(**names) -> str:
    return ONE_JOINT.format(**{k: _attr(v) for k, v in {**BENIGN, **names}.items()})


SAFE_PAYLOADS = [p for p in PAYLOADS if "\n" not in p]


def test_payloads_survive_the_urdf_parser():
    """The attack is real: the parsed chain holds the hostile names verbatim."""
    from camo_sbi.simulators.chain import load_chain

    for p in SAFE_PAYLOADS:
        spec = load_chain(_urdf(base=p + "b", tip=p + "t", joint=p + "j"), p + "t").spec
        assert (spec.base_link, spec.end_effector, spec.joint_names) == (p + "b", p + "t", (p + "j",))


@pytest.mark.parametrize("field", ["base", "link", "tip", "joint", "tool"])
@pytest.mark.parametrize("payload", PAYLOADS)
def test_generated_source_holds_no_name(field, payload):
    from camo_sbi.simulators.chain import load_chain
    from camo_sbi.simulators.kernel import generate_source

    ee = payload if field == "tip" else "tip"
    if "\n" in payload:  # a control character in a name is refused before anything is built
        kind = "joint" if field in ("joint", "tool") else "link"
        with pytest.raises(ValueError, match=f"^urdf: {kind} name '.*' contains a control character"):
            load_chain(_urdf(**{field: payload}), ee)
        return
    benign = load_chain(_urdf(), "tip").spec
    hostile = load_chain(_urdf(**{field: payload}), ee).spec
    for dtype in (np.float32, np.float64):
        src = generate_source(hostile, dtype)
        assert "PWNED" not in src and "system" not in src
        assert src == generate_source(benign, dtype)  # names are not part of the code at all


def test_hostile_urdf_runs_nothing_from_the_cli(tmp_path, monkeypatch, capsys):
    """Every name field and the file path hostile at once: simulated, exit 0, no file created."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("CAMO_SBI_KERNEL_CACHE", str(tmp_path / "kernels"))
    from camo_sbi.simulators import kernel

    monkeypatch.setattr(kernel, "_loaded", {})
    names = dict(zip(["base", "link", "tip", "joint", "tool"], SAFE_PAYLOADS, strict=True))
    urdf = tmp_path / (PAYLOADS[0].replace("/", "_") + ".urdf")
    urdf.write_text(_urdf(**names))
    code = cli_main(["demo", "--urdf", str(urdf), "--ee", names["tip"], "--batch", "8",
                     "--out", str(tmp_path / "demo.png")])
    assert code == 0
    assert (tmp_path / "demo.png").is_file()
    assert not list(tmp_path.rglob("PWNED")) and not Path("/PWNED").exists()
    cached = sorted((tmp_path / "kernels").glob("camo_sbi_kernel_*.py"))
    assert cached and all("PWNED" not in p.read_text() for p in cached)


def test_control_character_in_a_name_exits_2_naming_it(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    urdf = tmp_path / "arm.urdf"
    urdf.write_text(_urdf(joint=PAYLOADS[2]))
    with pytest.raises(SystemExit) as exc:
        cli_main(["demo", "--urdf", str(urdf), "--ee", "tip", "--batch", "8", "--out", str(tmp_path / "d.png")])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"camo-sbi: error: --urdf: {urdf}: urdf: joint name 'x\\nimport os"), err
    assert not list(tmp_path.rglob("PWNED"))


def test_cached_module_is_named_by_its_source_digest_and_checked_before_import(tmp_path, monkeypatch):
    """A cached module whose bytes differ from the generated source is never imported as is."""
    import hashlib
    import warnings

    from camo_sbi.simulators import kernel
    from camo_sbi.simulators.chain import load_chain

    d = tmp_path / "kernels"
    monkeypatch.setenv("CAMO_SBI_KERNEL_CACHE", str(d))
    monkeypatch.setattr(kernel, "_loaded", {})
    spec = load_chain(_urdf(), "tip").spec
    src = kernel.generate_source(spec, np.float64)
    name = f"camo_sbi_kernel_{hashlib.sha256(src.encode()).hexdigest()[:32]}"
    os.mkdir(d, 0o700)
    path = d / f"{name}.py"
    path.write_text(src + '\nopen("PLANTED", "w").close()\n')
    monkeypatch.chdir(tmp_path)
    # the planted file is replaced by the generated source before anything is imported
    with warnings.catch_warnings():
        warnings.simplefilter("error", kernel.KernelCacheWarning)
        mod = kernel.load_kernel(spec, np.float64)
    assert not (tmp_path / "PLANTED").exists()
    assert path.read_text() == src and mod.__file__ == str(path)

    # and a file that cannot be made to match (written behind our back after the check) is refused
    monkeypatch.setattr(kernel, "_loaded", {})
    real = kernel.atomic_write_bytes
    monkeypatch.setattr(kernel, "atomic_write_bytes", lambda p, data: real(p, data + b"\nopen('PLANTED', 'w')\n"))
    path.write_text("# stale\n")
    with pytest.warns(kernel.KernelCacheWarning, match="differs from the generated kernel source"):
        kernel.load_kernel(spec, np.float64)
    assert not (tmp_path / "PLANTED").exists()


# ------------------------------------------------------------------------------ URDF structure

_J = ('<joint name="{name}" type="revolute"><parent link="{parent}"/><child link="{child}"/>'
      '<axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/>{extra}</joint>')


def _tree(links, joints) -> str:
    body = "".join(f'<link name="{n}"/>' for n in links)
    body += "".join(_J.format(extra="", **j) if "extra" not in j else _J.format(**j) for j in joints)
    return f'<?xml version="1.0"?><robot name="t">{body}</robot>'


CHAIN = [dict(name="j1", parent="base", child="l1"), dict(name="j2", parent="l1", child="tip")]


@pytest.mark.parametrize("links, joints, ee, message", [
    (["base", "l1", "tip"], [*CHAIN, dict(name="j3", parent="tip", child="l1")], "tip",
     "link 'l1' is the child of two joints, 'j1' and 'j3' \\(a URDF is a tree\\)"),
    (["a", "b", "base", "l1", "tip"], [*CHAIN, dict(name="ja", parent="a", child="b"),
                                       dict(name="jb", parent="b", child="a")], "tip",
     "joint 'j[ab]' closes a cycle through link '[ab]' \\(a URDF is a tree\\)"),
    (["base", "l1", "tip"], [*CHAIN, dict(name="j1", parent="tip", child="x")], "tip", "duplicate joint name 'j1'"),
    (["base", "l1", "l1", "tip"], CHAIN, "tip", "duplicate link name 'l1'"),
    (["base", "l1", "tip"], [CHAIN[0], dict(CHAIN[1], extra='<mimic joint="j1" multiplier="2" offset="0.1"/>')],
     "tip", r"joint 'j2' is a <mimic> joint \(following 'j1'\), which is not supported"),
    (["base", "l1", "tip"], [CHAIN[0], dict(CHAIN[1], parent="nowhere")], "tip",
     "joint 'j2' names parent link 'nowhere', which is not in the URDF"),
])
def test_malformed_urdf_tree_is_refused_naming_the_joint_or_link(links, joints, ee, message):
    from camo_sbi.simulators.chain import load_chain

    with pytest.raises(ValueError, match=f"^urdf: {message}"):
        load_chain(_tree(links, joints), ee)


def test_mimic_joint_off_the_chain_is_harmless():
    from camo_sbi.simulators.chain import load_chain

    joints = [*CHAIN, dict(name="g", parent="l1", child="finger", extra='<mimic joint="j2"/>')]
    assert load_chain(_tree(["base", "l1", "tip", "finger"], joints), "tip").joint_names == ["j1", "j2"]


def test_cyclic_urdf_exits_2_from_the_console(tmp_path):
    """As a user runs it: one line naming the joint, exit 2, no hang (the bound is only a guard)."""
    import subprocess
    import sys

    urdf = tmp_path / "cycle.urdf"
    urdf.write_text(_tree(["a", "b", "base", "l1", "tip"], [*CHAIN, dict(name="ja", parent="a", child="b"),
                                                           dict(name="jb", parent="b", child="a")]))
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    proc = subprocess.run([sys.executable, "-m", "camo_sbi", "demo", "--urdf", str(urdf), "--ee", "tip",
                           "--out", str(tmp_path / "d.png")], capture_output=True, text=True, timeout=600, env=env)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines()[-1].startswith(f"camo-sbi: error: --urdf: {urdf}: urdf: joint 'j")
    assert "closes a cycle" in proc.stderr and "Traceback" not in proc.stderr


# ------------------------------------------------------------------------------ NPE posterior files


class _Payload:
    """Unpickling this would create ``marker``: what a hostile .pt file does."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


@pytest.fixture(scope="module")
def npe_file(tmp_path_factory):
    """A saved per-task NPE posterior (2 tasks, with an MLP embedding) and the run's samples."""
    from camo_sbi.inference.registry import run_method
    from tests.test_abc_smc import toy_task
    from tests.test_npe import TINY

    d = tmp_path_factory.mktemp("npe")
    toy = toy_task()
    res = run_method("npe", toy, toy.observations[:2], budget=300, seed=0,
                     config={**TINY, "workdir": str(d), "embedding": "mlp", "embedding_dim": 8})
    return Path(res.extras["posterior_path"]), res


def test_npe_posterior_is_tensors_plus_json_and_reloads_exactly(npe_file):
    import json

    import torch

    from camo_sbi.inference.npe_posterior import load_posterior

    path, res = npe_file
    meta = json.loads(path.with_name(path.name + ".json").read_text())
    assert meta["format"] == "camo_sbi.npe.posterior/2" and meta["n_tasks"] == 2
    assert meta["architecture"]["embedding"] == "mlp" and meta["architecture"]["embedding_dim"] == 8
    torch.load(path, weights_only=True)  # loads with the safe unpickler: tensors and containers only
    post = load_posterior(path)
    theta = torch.from_numpy(res.samples[:40])
    assert torch.isfinite(post.log_prob(theta)).all()


def _copy_npe(npe_file, dest: Path) -> Path:
    import shutil

    path = npe_file[0]
    dest.mkdir()
    shutil.copy(path, dest / path.name)
    shutil.copy(path.with_name(path.name + ".json"), dest / (path.name + ".json"))
    return dest / path.name


@pytest.mark.parametrize("matching_digest", [False, True])
def test_npe_posterior_with_a_pickle_payload_runs_nothing(npe_file, tmp_path, matching_digest):
    """The payload is refused by name whether or not its sha256 was also forged into the metadata."""
    import hashlib
    import json

    import torch

    from camo_sbi.inference.npe_posterior import load_posterior

    path = _copy_npe(npe_file, tmp_path / "run")
    marker = tmp_path / "PWNED"
    torch.save({"format": "camo_sbi.npe.posterior/2", "state_dict": _Payload(marker)}, path)
    if matching_digest:
        meta_path = path.with_name(path.name + ".json")
        meta = json.loads(meta_path.read_text())
        meta["sha256"] = hashlib.sha256(path.read_bytes()).hexdigest()
        meta_path.write_text(json.dumps(meta))
    message = "cannot be loaded as a camo_sbi NPE posterior" if matching_digest else "sha256 differs"
    with pytest.raises(ValueError, match=f"^path: {path}: {message}"):
        load_posterior(path)
    assert not marker.exists()


def test_damaged_npe_posterior_is_refused_naming_the_file(npe_file, tmp_path):
    from camo_sbi.inference.npe_posterior import load_posterior

    path = _copy_npe(npe_file, tmp_path / "run")
    data = bytearray(path.read_bytes())
    mid = len(data) // 2
    data[mid:mid + 200] = bytes(b ^ 0xFF for b in data[mid:mid + 200])
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match=f"^path: {path}: sha256 differs from its metadata"):
        load_posterior(path)
    path.with_name(path.name + ".json").unlink()
    with pytest.raises(ValueError, match=f"^path: {path}: its metadata {path.name}.json is missing"):
        load_posterior(path)


# ------------------------------------------------------------------------------ numba's own cache

_KDE_RUN = """
import warnings, numpy as np
warnings.simplefilter("always")
from camo_sbi.inference import kde
out = np.empty(3)
kde._log_kernel_sums(np.zeros((3, 2)), np.ones((2, 4)), out)
print(kde._log_kernel_sums._cache.cache_path)
"""


def _run_kde(env) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", _KDE_RUN], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1]), **env})


@pytest.mark.slow  # in the slow tier for the default tier's 4-minute budget (issue 28)
def test_numba_cache_dir_that_is_shared_is_never_read(tmp_path):
    """NUMBA_CACHE_DIR world-writable with a planted index file: one warning, compiled in memory,
    the pickle never runs. The same planted file in a private directory does run: the check is real."""
    import shutil

    primed = tmp_path / "primed"
    first = _run_kde({"NUMBA_CACHE_DIR": str(primed)})
    assert first.returncode == 0, first.stderr
    sub = Path(first.stdout.strip().splitlines()[-1])
    assert sub.is_relative_to(primed) and list(sub.glob("*.nbi"))  # cached there, not in the package
    marker = tmp_path / "PWNED"
    for private in (False, True):
        shared = tmp_path / f"shared-{private}"
        shutil.copytree(primed, shared)
        for p in shared.rglob("*.nbi"):
            p.write_bytes(pickle.dumps(_Payload(marker)))
        for d in (shared, *[p for p in shared.rglob("*") if p.is_dir()]):
            os.chmod(d, 0o700 if private else 0o777)
        proc = _run_kde({"NUMBA_CACHE_DIR": str(shared)})
        if not private:
            assert proc.returncode == 0, proc.stderr
            assert not marker.exists(), "a planted pickle ran"
            warned = [ln for ln in proc.stderr.splitlines() if "NumbaCacheWarning" in ln]
            assert len(warned) == 1 and f"numba cache {shared} is writable by group or others (mode 777)" in warned[0]
    assert marker.exists()  # read from the private copy: the planted file is live


def test_numba_cache_defaults_to_a_private_user_directory(tmp_path):
    import stat

    package = Path(__file__).resolve().parents[1] / "camo_sbi"

    def numba_files():  # (files an older camo_sbi left there may exist: none may be added or rewritten)
        return {p: p.stat().st_mtime_ns for p in package.rglob("*.nb[ic]")}

    before = numba_files()
    proc = _run_kde({"XDG_CACHE_HOME": str(tmp_path / "xdg"), "NUMBA_CACHE_DIR": ""})
    assert proc.returncode == 0, proc.stderr
    root = tmp_path / "xdg" / "camo_sbi" / "numba"
    assert Path(proc.stdout.strip().splitlines()[-1]).parent == root
    assert stat.S_IMODE(root.stat().st_mode) == 0o700
    assert numba_files() == before  # nothing of numba's written inside the package
