"""The body-model registry (`camo_sbi.simulators.registry`): one table of models and subjects.

A toy planar arm registered in ONE place (`toy_model`) runs ``compare`` end to end and gets its
posterior-predictive figures in the report; the Panda's and the human's subjects keep the
thetas the tables before the registry gave (golden values computed at commit d128a24).
"""

from __future__ import annotations

import argparse
import json
import re

import numpy as np
import pytest
import torch

from camo_sbi.experiments.cli import main as cli_main
from camo_sbi.simulators import registry
from camo_sbi.simulators.registry import (
    ONE_JOINT,
    ModelDef,
    Setting,
    fraction_profile,
    register_model,
)

# a 3-joint planar arm (joints about z, links along x), end effector "tip"
PLANAR_URDF = """<?xml version="1.0"?>
<robot name="planar3">
  <link name="base"/><link name="l1"/><link name="l2"/><link name="l3"/><link name="tip"/>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/>
    <origin xyz="0 0 0.5" rpy="0 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-2.5" upper="2.5" effort="1" velocity="1"/></joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/>
    <origin xyz="{a} 0 0" rpy="0 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-2.5" upper="2.5" effort="1" velocity="1"/></joint>
  <joint name="j3" type="revolute"><parent link="l2"/><child link="l3"/>
    <origin xyz="{b} 0 0" rpy="0 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-2.5" upper="2.5" effort="1" velocity="1"/></joint>
  <joint name="tool" type="fixed"><parent link="l3"/><child link="tip"/>
    <origin xyz="{c} 0 0" rpy="0 0 0"/></joint>
</robot>
"""


def _planar(scale: float = 1.0, start=None):
    from camo_sbi.simulators import from_urdf

    urdf = PLANAR_URDF.format(a=0.3 * scale, b=0.25 * scale, c=0.15 * scale)
    return from_urdf(urdf, "tip", start=start if start is not None else [0.3, 0.8, 0.5])


@pytest.fixture
def toy_model():
    """The toy arm in the registry for one test (and out of it afterwards)."""
    defn = register_model(ModelDef(
        "toy_planar", _planar,
        profiles={"stiff_elbow": fraction_profile({1: 0.4})},
        paper_joint="j1",
        settings=(Setting("scale", "--toy-scale", float, help="link length scale"),),
        description="a 3-joint planar arm (test)"))
    yield defn
    if "toy_planar" in registry.model_names():
        registry.unregister_model("toy_planar")


def _section(html: str, sid: str) -> str:
    m = re.search(rf'<section id="{sid}">(.*?)</section>', html, re.S)
    assert m, f"no section {sid}"
    return m.group(1)


@pytest.mark.slow  # a whole compare (camo, naive, nominal, oracle) and two reports: tens of seconds
def test_a_registered_model_runs_compare_and_the_report(toy_model, tmp_path, capsys):
    from camo_sbi.diagnostics import arviz_io, report

    out = tmp_path / "toy"
    assert cli_main(["compare", "--model", "toy_planar", "--toy-scale", "1.2", "--subjects", "stiff_elbow",
                     "--methods", "camo,naive", "--budgets", "40", "--seeds", "1", "--tasks", "1",
                     "--test-goals", "2", "--out", str(out)]) == 0
    idata = arviz_io.load_netcdf(next((out / "posteriors").glob("*.nc")))
    spec = json.loads(idata.posterior.attrs["model_spec"])
    assert spec["kind"] == "toy_planar" and spec["scale"] == 1.2  # the setting is stored for the report
    sim, why = report._simulator("toy_planar", idata)
    assert why is None
    np.testing.assert_array_equal(sim.chain.spec.origins, _planar(1.2).chain.spec.origins)

    section = _section((out / "report.html").read_text(), "posterior-predictive")
    assert "not available" not in section and 'class="error"' not in section
    assert "posterior-predictive reaches of camo" in section  # the figure, drawn with the toy arm

    # the same run without the model registered: the section says so as a marked error naming it
    registry.unregister_model("toy_planar")
    sim, why = report._simulator("toy_planar", idata)
    assert sim is None and isinstance(why, report.UnknownModel) and "'toy_planar'" in why
    page = report.write_report(out, tmp_path / "again.html", force=True)
    section = _section(page.read_text(), "posterior-predictive")
    assert 'class="error"' in section and "toy_planar" in section and "register" in section


def test_a_registered_model_is_on_the_command_line(toy_model, capsys):
    from camo_sbi.experiments.models import (
        ModelSpec,
        add_model_arguments,
        model_from_args,
        subject_limits,
        subject_list,
    )

    p = argparse.ArgumentParser()
    add_model_arguments(p)
    args = p.parse_args(["--model", "toy_planar", "--toy-scale", "0.8"])
    spec = model_from_args(args)
    assert spec == ModelSpec(kind="toy_planar", settings=(("scale", 0.8),))
    assert spec.key() == {"kind": "toy_planar", "scale": 0.8} and not spec.is_default
    assert subject_list(spec, None, default_all=True) == ["stiff_elbow"]
    sim = spec.build()
    theta = subject_limits(spec, sim, "stiff_elbow").reshape(-1, 2)
    assert theta[1].tolist() == pytest.approx([0.8 - 0.4 * 3.3, 0.8 + 0.4 * 1.7])
    assert theta[0].tolist() == [-2.5, 2.5]
    one = subject_limits(spec, sim, ONE_JOINT).reshape(-1, 2)
    assert one[0].tolist() == pytest.approx([0.3 - 0.5, 0.3 + 0.5])
    # a setting of one model is refused for another, naming the flag
    with pytest.raises(ValueError, match="--toy-scale: only with --model toy_planar"):
        model_from_args(p.parse_args(["--model", "panda", "--toy-scale", "2"]))
    with pytest.raises(ValueError, match="--height: only with --model human"):
        model_from_args(p.parse_args(["--model", "toy_planar", "--height", "1.6"]))
    # --help lists the model and its subjects
    with pytest.raises(SystemExit):
        cli_main(["compare", "--help"])
    text = capsys.readouterr().out
    assert "toy_planar" in text and "stiff_elbow" in text and "--toy-scale" in text


def test_register_refuses_duplicates_and_bad_definitions(toy_model):
    with pytest.raises(ValueError, match="name: .*'toy_planar' is already registered"):
        register_model(ModelDef("toy_planar", _planar))
    with pytest.raises(ValueError, match="name: .*'panda' is already registered"):
        register_model(ModelDef("panda", _planar))
    with pytest.raises(ValueError, match="name: 'urdf' is reserved"):
        ModelDef("urdf", _planar)
    with pytest.raises(TypeError, match="build"):
        ModelDef("x", "not callable")
    with pytest.raises(TypeError, match="profiles"):
        ModelDef("x", _planar, profiles={"a": 3})
    with pytest.raises(ValueError, match="settings"):
        register_model(ModelDef("y", _planar, settings=(Setting("scale", "--toy-scale", int),)))
    with pytest.raises(TypeError, match="defn"):
        register_model("toy")
    with pytest.raises(ValueError, match="model: unknown body model 'nobody'"):
        registry.get_model("nobody")
    with pytest.raises(ValueError, match="subject: unknown profile 'x' of model 'toy_planar'"):
        registry.subject_theta(_planar(), "toy_planar", "x")
    with pytest.raises(ValueError, match="fractions"):
        fraction_profile({0: 1.5})
    assert "y" not in registry.model_names()


def test_model_choices_come_from_the_registry_at_parser_build_time(toy_model):
    from camo_sbi.experiments.models import add_model_arguments

    p = argparse.ArgumentParser()
    add_model_arguments(p)
    action = next(a for a in p._actions if a.dest == "model")
    assert tuple(action.choices) == registry.model_names() and "toy_planar" in action.choices


# thetas of every Panda and human subject from the tables before the registry (commit d128a24:
# experiments.subjects.subject_theta over subject_names, ONE_JOINT and INFORMATIVE_PROFILES)
GOLDEN = {
    ('panda', 'shoulder_restricted'): [
        -0.89013, 0.89013, -1.1516600000000001, 0.13115999999999983, -2.9671, 2.9671, -3.1416, 0.0,
        -2.9671, 2.9671, -0.0873, 3.8223, -2.9671, 2.9671
    ],
    ('panda', 'elbow_restricted'): [
        -2.9671, 2.9671, -1.8326, 1.8326, -1.18684, 1.18684, -2.5916799999999998, -1.6492, -2.9671,
        2.9671, -0.0873, 3.8223, -2.9671, 2.9671
    ],
    ('panda', 'wrist_restricted'): [
        -2.9671, 2.9671, -1.8326, 1.8326, -2.9671, 2.9671, -3.1416, 0.0, -0.89013, 0.89013, 1.07351,
        2.24639, -0.3406299999999999, 1.43963
    ],
    ('panda', 'mixed_restricted'): [
        -1.48355, 1.48355, -1.3088000000000002, 0.5237999999999999, -2.9671, 2.9671, -2.7488,
        -1.178, -2.9671, 2.9671, 0.74185, 2.69665, -2.9671, 2.9671
    ],
    ('panda', 'one_joint_restricted'): [
        -0.5, 0.5, -1.8326, 1.8326, -2.9671, 2.9671, -3.1416, 0.0, -2.9671, 2.9671, -0.0873, 3.8223,
        -2.9671, 2.9671
    ],
    ('panda', 'informative_shoulder'): [
        -0.89013, 0.89013, -1.1516600000000001, 0.13115999999999983, -2.9671, 2.9671, -3.1416, 0.0,
        -2.9671, 2.9671, -0.0873, 3.8223, -2.9671, 2.9671
    ],
    ('panda', 'informative_elbow'): [
        -2.9671, 2.9671, -1.8326, 1.8326, -1.18684, 1.18684, -2.5916799999999998, -1.6492, -2.9671,
        2.9671, -0.0873, 3.8223, -2.9671, 2.9671
    ],
    ('human', 'frozen_shoulder'): [
        -0.4363323129985824, 1.3962634015954636, -0.7853981633974483, 0.7853981633974483,
        -0.6108652381980153, 1.6580627893946132, -0.3490658503988659, 1.3962634015954636,
        -0.4363323129985824, 0.6981317007977318, 0.0, 2.6179938779914944, -1.3962634015954636,
        1.3962634015954636, -1.2217304763960306, 1.3962634015954636, -0.5235987755982988,
        0.3490658503988659
    ],
    ('human', 'elbow_flexion_contracture'): [
        -0.4363323129985824, 1.3962634015954636, -0.7853981633974483, 0.7853981633974483,
        -1.0471975511965976, 3.141592653589793, -0.5235987755982988, 3.141592653589793,
        -1.5707963267948966, 1.2217304763960306, 0.6108652381980153, 2.0943951023931953,
        -1.3962634015954636, 1.3962634015954636, -1.2217304763960306, 1.3962634015954636,
        -0.5235987755982988, 0.3490658503988659
    ],
    ('human', 'restricted_wrist'): [
        -0.4363323129985824, 1.3962634015954636, -0.7853981633974483, 0.7853981633974483,
        -1.0471975511965976, 3.141592653589793, -0.5235987755982988, 3.141592653589793,
        -1.5707963267948966, 1.2217304763960306, 0.0, 2.6179938779914944, -1.3962634015954636,
        1.3962634015954636, -0.5235987755982988, 0.5235987755982988, -0.17453292519943295,
        0.17453292519943295
    ],
    ('human', 'hemiparesis_mild'): [
        -0.4363323129985824, 1.3962634015954636, -0.7853981633974483, 0.7853981633974483,
        -0.6981317007977318, 2.0943951023931953, -0.5235987755982988, 1.5707963267948966,
        -0.5235987755982988, 1.2217304763960306, 0.2617993877991494, 2.443460952792061,
        -0.5235987755982988, 1.3962634015954636, -0.5235987755982988, 1.3962634015954636,
        -0.5235987755982988, 0.3490658503988659
    ],
    ('human', 'one_joint_restricted'): [
        -0.4363323129985824, 1.3962634015954636, -0.7853981633974483, 0.7853981633974483,
        -0.2382006122008506, 0.7617993877991494, -0.5235987755982988, 3.141592653589793,
        -1.5707963267948966, 1.2217304763960306, 0.0, 2.6179938779914944, -1.3962634015954636,
        1.3962634015954636, -1.2217304763960306, 1.3962634015954636, -0.5235987755982988,
        0.3490658503988659
    ],
    ('human', 'informative_shoulder'): [
        -0.4363323129985824, 1.3962634015954636, -0.7853981633974483, 0.7853981633974483,
        -0.13089969389957468, 1.1257373675363425, -0.034906585039886584, 1.064650843716541,
        -1.5707963267948966, 1.2217304763960306, 0.0, 2.6179938779914944, -1.3962634015954636,
        1.3962634015954636, -1.2217304763960306, 1.3962634015954636, -0.5235987755982988,
        0.3490658503988659
    ],
    ('human', 'informative_elbow'): [
        -0.4363323129985824, 1.3962634015954636, -0.7853981633974483, 0.7853981633974483,
        -1.0471975511965976, 3.141592653589793, -0.5235987755982988, 3.141592653589793,
        -1.5707963267948966, 1.2217304763960306, 0.4886921905584123, 1.2740903539558606,
        -1.3962634015954636, 1.3962634015954636, -1.2217304763960306, 1.3962634015954636,
        -0.5235987755982988, 0.3490658503988659
    ],
}


@pytest.mark.parametrize("model", ["panda", "human"])
def test_builtin_subjects_keep_their_thetas(model):
    from camo_sbi.experiments import subjects
    from camo_sbi.experiments.models import ModelSpec
    from camo_sbi.simulators import human, panda

    sim = ModelSpec(kind=model).build()
    direct = {"panda": panda, "human": human}[model]()  # the same body as before the registry
    assert list(sim.joint_names) == list(direct.joint_names)
    assert torch.equal(sim.bounds, direct.bounds) and torch.equal(sim.start, direct.start)
    names = registry.get_model(model).subjects()
    assert sorted(names) == sorted(n for m, n in GOLDEN if m == model)
    assert subjects.subject_names(model) == [n for n in names if n != ONE_JOINT and "informative" not in n]
    for name in names:
        theta = registry.subject_theta(sim, model, name)
        # to a tolerance, not bit for bit: torch picks its vector kernels by CPU (FMA or not)
        assert theta.dtype == torch.float64, name
        np.testing.assert_allclose(theta.numpy(), GOLDEN[(model, name)], rtol=1e-12, atol=1e-12, err_msg=name)
        np.testing.assert_allclose(subjects.subject_theta(sim, model, name).numpy(), GOLDEN[(model, name)],
                                   rtol=1e-12, atol=1e-12, err_msg=name)
