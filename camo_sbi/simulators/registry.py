"""The body models every command can name (``--model NAME``), with their subjects, in one table.

    register_model(ModelDef(name, build, profiles, paper_joint=..., informative=..., settings=...))
    get_model(name) / model_names() / unregister_model(name)
    build_model(name, {"height_m": 1.6}, start=[...])   # the simulator
    subject_names(name) / subject_theta(sim, name, subject)

Why here: the simulators layer defines the models, so the table from a name to its builder, its
ground-truth subjects (the impairment profiles of the Panda and of the human) and the settings a
command line may pass it live next to them. The commands (`camo_sbi.experiments`), the
subjects and the report (`camo_sbi.diagnostics.report`, which rebuilds a run's body from its
stored settings) all read this table, so adding a body model is one `register_model` call.

Nothing heavy is imported here: the command line builds ``--model``'s choices, the settings'
flags and the profile lists of ``--help`` from the table without torch; builders and theta
makers import the model when they are called.

Subjects of a model (each a (2n,) float64 theta ``[lo_1, hi_1, ...]`` made from the simulator):

* ``profiles``: the named subjects (``--subjects``; the first is a study's default);
* `ONE_JOINT`: the authors' ground truth, the model's ``paper_joint`` restricted to the start
  +- 0.5 rad, every other joint at its full range (models without a paper joint have none);
* ``informative``: the subjects of ``reproduce panda --setting informative`` (their restricted
  bounds bind on reaches to goals of the nominal workspace).

`fraction_profile` is the Panda's rule, usable by any model: restricting joint j to a fraction
f keeps ``lo = s - f (s - L)``, ``hi = s + f (U - s)`` around the start posture s.

Worker processes (``--workers N``, a Dask scheduler) are fresh interpreters: they know the
models registered when this module is imported there. A model registered at run time (a
script, a notebook, a test) runs in-process (``--workers 1``), or is registered by a module
its workers import too; a worker that meets an unknown model stops with ``model: unknown body
model``, never builds another body. A model another installed package declares (entry point
``camo_sbi.models``, `camo_sbi._plugins`) is read by every process, workers included.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import partial
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import torch

__all__ = ["HUMAN_PROFILES", "ModelDef", "ONE_JOINT", "PANDA_FRACTIONS", "Setting", "build_model",
           "fraction_profile", "get_model", "model_names", "register_model", "subject_names", "subject_theta",
           "unregister_model"]

ONE_JOINT = "one_joint_restricted"
"""The authors' ground truth: ONE restricted joint (the model's ``paper_joint``), start +- 0.5 rad,
every other joint at its full range (their shoulder roll [pi/2 - 0.5, pi/2 + 0.5] around pi/2)."""
_ONE_JOINT_HALF_WIDTH = 0.5
RESERVED = ("urdf",)
"""Names no registered model may take: ``--urdf`` models are described by their file."""


@dataclass(frozen=True)
class Setting:
    """A command-line setting of a body model, passed to its ``build`` as ``name=value``.

    Attributes:
        name: the keyword of ``build`` (and the key in a run's stored model settings).
        flag: the command-line option (``--height``); models sharing a flag share the option.
        type: converts the option's text (float, int or str).
        choices: the allowed values, or None.
        help: one line for ``--help``.
    """

    name: str
    flag: str
    type: Callable[[str], Any] = float
    choices: tuple | None = None
    help: str = ""

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name.isidentifier():
            raise ValueError(f"name: expected a Python identifier, got {self.name!r}")
        if not isinstance(self.flag, str) or not self.flag.startswith("--") or len(self.flag) < 3:
            raise ValueError(f"flag: expected an option like '--height', got {self.flag!r}")
        if not callable(self.type):
            raise TypeError(f"type: expected a callable, got {type(self.type).__name__}")
        if self.choices is not None:
            object.__setattr__(self, "choices", tuple(self.choices))

    @property
    def dest(self) -> str:
        """The argparse destination of `flag` (``--body-scale`` -> ``body_scale``)."""
        return self.flag[2:].replace("-", "_")


@dataclass(frozen=True, eq=False)
class ModelDef:
    """One body model: how to build it and who its subjects are.

    Attributes:
        name: the ``--model`` value and the task's name in tables.
        build: ``build(**settings, start=None)`` -> the simulator (a `KinematicSimulator`);
            ``start`` (a list, radians/metres) is passed only when the command line sets it.
        profiles: {subject name: ``theta(sim)`` -> (2n,) float64 true limits}, the named
            subjects in their listed order.
        paper_joint: the joint the `ONE_JOINT` subject restricts, or None (no such subject).
        informative: {subject name: ``theta(sim)``}, the subjects of the informative design.
        settings: the `Setting` s ``build`` accepts from the command line.
        description: one line for ``--help``.
    """

    name: str
    build: Callable[..., Any]
    profiles: Mapping[str, Callable[[Any], torch.Tensor]] = field(default_factory=dict)
    paper_joint: str | None = None
    informative: Mapping[str, Callable[[Any], torch.Tensor]] = field(default_factory=dict)
    settings: tuple[Setting, ...] = ()
    description: str = ""

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name or self.name.strip() != self.name:
            raise ValueError(f"name: expected a non-empty name without spaces around it, got {self.name!r}")
        if self.name in RESERVED:
            raise ValueError(f"name: {self.name!r} is reserved (--urdf models)")
        if not callable(self.build):
            raise TypeError(f"build: expected a callable, got {type(self.build).__name__}")
        for what in ("profiles", "informative"):
            table = getattr(self, what)
            if not isinstance(table, Mapping):
                raise TypeError(f"{what}: expected a mapping {{name: theta(sim)}}, got {type(table).__name__}")
            for key, maker in table.items():
                if not isinstance(key, str) or not key or key == ONE_JOINT:
                    raise ValueError(f"{what}: invalid subject name {key!r}")
                if not callable(maker):
                    raise TypeError(f"{what}: {key!r} needs a callable theta(sim), got {type(maker).__name__}")
            object.__setattr__(self, what, MappingProxyType(dict(table)))
        both = set(self.profiles) & set(self.informative)
        if both:
            raise ValueError(f"informative: {sorted(both)[0]!r} is also a profile")
        if self.paper_joint is not None and not isinstance(self.paper_joint, str):
            raise TypeError(f"paper_joint: expected a joint name or None, got {type(self.paper_joint).__name__}")
        settings = tuple(self.settings)
        if not all(isinstance(s, Setting) for s in settings):
            raise TypeError("settings: expected a tuple of Setting")
        if len({s.name for s in settings}) != len(settings) or len({s.flag for s in settings}) != len(settings):
            raise ValueError("settings: two settings share a name or a flag")
        object.__setattr__(self, "settings", settings)

    def subjects(self) -> list[str]:
        """Every subject name this model knows: its profiles, `ONE_JOINT`, its informative ones."""
        return [*self.profiles, *((ONE_JOINT,) if self.paper_joint else ()), *self.informative]

    def settings_from(self, values: Mapping) -> tuple[tuple[str, Any], ...]:
        """((name, value), ...) of the declared settings set (not None) in ``values``, in declared order."""
        return tuple((s.name, values[s.name]) for s in self.settings if values.get(s.name) is not None)


_MODELS: dict[str, ModelDef] = {}


def register_model(defn: ModelDef) -> ModelDef:
    """Add ``defn`` to the table (ValueError naming ``name`` if that name is taken).

    A setting flag another model declares differently (type or choices) is refused: models
    sharing a flag share the one command-line option.
    """
    if not isinstance(defn, ModelDef):
        raise TypeError(f"defn: expected a ModelDef, got {type(defn).__name__}")
    if defn.name in _MODELS:
        raise ValueError(f"name: a body model named {defn.name!r} is already registered")
    for s in defn.settings:
        for other in _MODELS.values():
            for t in other.settings:
                if t.flag == s.flag and (t.name, t.type, t.choices) != (s.name, s.type, s.choices):
                    raise ValueError(f"settings: {s.flag} of {defn.name!r} differs from {other.name!r}'s")
    _MODELS[defn.name] = defn
    return defn


def unregister_model(name: str) -> ModelDef:
    """Remove and return the model called ``name`` (tests; ValueError if unknown)."""
    get_model(name)
    return _MODELS.pop(name)


def _load_plugins() -> None:
    """The body models other installed packages declare (entry points ``camo_sbi.models``; once
    per process, `camo_sbi._plugins`)."""
    from camo_sbi import _plugins

    _plugins.load("camo_sbi.models", register_model, ModelDef)


def get_model(name: str) -> ModelDef:
    """The registered model called ``name`` (ValueError naming ``model`` and the known names)."""
    if isinstance(name, str) and name not in _MODELS:
        _load_plugins()
    if not isinstance(name, str) or name not in _MODELS:
        raise ValueError(f"model: unknown body model {name!r}; known: {', '.join(_MODELS)}")
    return _MODELS[name]


def model_names() -> tuple[str, ...]:
    """The registered model names, in registration order (built-in, then plug-ins)."""
    _load_plugins()
    return tuple(_MODELS)


def build_model(name: str, settings: Mapping | None = None, **kwargs):
    """The simulator of model ``name`` with its declared ``settings`` (others and None ignored)."""
    defn = get_model(name)
    return defn.build(**dict(defn.settings_from(settings or {})), **kwargs)


def subject_names(name: str) -> list[str]:
    """The named profiles of model ``name`` (a study's subjects by default)."""
    return list(get_model(name).profiles)


def subject_theta(sim, name: str, subject: str) -> torch.Tensor:
    """(2n,) float64 true limits of ``subject`` (a profile, `ONE_JOINT` or informative) of model ``name``."""
    defn = get_model(name)
    if subject == ONE_JOINT:
        if defn.paper_joint is None:
            raise ValueError(f"subject: model {name!r} has no paper joint, hence no {ONE_JOINT!r} subject")
        return _one_joint(sim, defn.paper_joint)
    maker = defn.profiles.get(subject) or defn.informative.get(subject)
    if maker is None:
        raise ValueError(f"subject: unknown profile {subject!r} of model {name!r}; known: "
                         f"{', '.join(defn.subjects())}")
    return maker(sim)


def _one_joint(sim, joint: str):
    import torch

    b, s = sim.bounds.to(torch.float64), sim.start.to(torch.float64)
    lim = b.clone()
    j = list(sim.joint_names).index(joint)
    lim[j, 0] = max(float(b[j, 0]), float(s[j]) - _ONE_JOINT_HALF_WIDTH)
    lim[j, 1] = min(float(b[j, 1]), float(s[j]) + _ONE_JOINT_HALF_WIDTH)
    return lim.reshape(-1)


def _fraction_limits(fractions: Mapping[int, float], sim):
    import torch

    b = sim.bounds.to(torch.float64)
    s = sim.start.to(torch.float64)
    lo, hi = b[:, 0].clone(), b[:, 1].clone()
    for j, f in fractions.items():
        lo[j] = s[j] - f * (s[j] - b[j, 0])
        hi[j] = s[j] + f * (b[j, 1] - s[j])
    return torch.stack([lo, hi], dim=1).reshape(-1)


def fraction_profile(fractions: Mapping[int, float]) -> Callable[[Any], torch.Tensor]:
    """``theta(sim)`` keeping, for each {joint index: f}, the fraction f of the range on each side of
    the start posture (every other joint at its full range)."""
    if not isinstance(fractions, Mapping) or not all(
            isinstance(j, int) and j >= 0 and isinstance(f, (int, float)) and 0 <= f <= 1
            for j, f in fractions.items()):
        raise ValueError(f"fractions: expected {{joint index: fraction in [0, 1]}}, got {fractions!r}")
    return partial(_fraction_limits, MappingProxyType(dict(fractions)))


# ----------------------------------------------------------------------------- the built-in models

PANDA_FRACTIONS: Mapping[str, Mapping[int, float]] = MappingProxyType({
    "shoulder_restricted": {0: 0.3, 1: 0.35},
    "elbow_restricted": {2: 0.4, 3: 0.3},
    "wrist_restricted": {4: 0.3, 5: 0.3, 6: 0.3},
    "mixed_restricted": {0: 0.5, 1: 0.5, 3: 0.5, 5: 0.5},
})
"""The Panda's profiles: {joint index: fraction of the range kept on each side of the start}."""

HUMAN_PROFILES = ("frozen_shoulder", "elbow_flexion_contracture", "restricted_wrist", "hemiparesis_mild")
"""The names of `camo_sbi.simulators.human.IMPAIRED_PROFILES` (defined there, in degrees with their
clinical sources), repeated so that the table and ``--help`` need no torch; ``tests/test_cli_conventions.py``
checks that the two agree."""

_INFORMATIVE = {
    "panda": {"informative_shoulder": PANDA_FRACTIONS["shoulder_restricted"],
              "informative_elbow": PANDA_FRACTIONS["elbow_restricted"]},
    "human": {"informative_shoulder": {2: 0.3, 3: 0.3}, "informative_elbow": {5: 0.3}},
}
"""With the fraction rule: each restricted bound, relaxed alone, moves >= 1 mm of about half or
more of the reaches to goals from the nominal workspace (every run of the informative design
reports its own ``binding_test_fraction``)."""


def _panda(**kwargs):
    from camo_sbi.simulators.panda import panda

    return panda(**kwargs)


def _human(**kwargs):
    from camo_sbi.simulators.human import human

    return human(**kwargs)


def _impaired(profile: str, sim):
    import torch

    from camo_sbi.simulators.human import impaired_limits

    return torch.as_tensor(impaired_limits(sim, profile), dtype=torch.float64)


register_model(ModelDef(
    "panda", _panda,
    profiles={name: fraction_profile(f) for name, f in PANDA_FRACTIONS.items()},
    paper_joint="panda_joint1",
    informative={name: fraction_profile(f) for name, f in _INFORMATIVE["panda"].items()},
    description="Franka Emika Panda, 7 joints"))
register_model(ModelDef(
    "human", _human,
    profiles={name: partial(_impaired, name) for name in HUMAN_PROFILES},
    paper_joint="shoulder_flexion",
    informative={name: fraction_profile(f) for name, f in _INFORMATIVE["human"].items()},
    settings=(Setting("height_m", "--height", float, help="standing height in metres"),
              Setting("sex", "--sex", str, choices=("male", "female"), help="anthropometry")),
    description="9-DOF human torso and right arm (anthropometric)"))
