"""One way to name the body model on every command: ``--model NAME`` (a registered model) or ``--urdf``.

    add_model_arguments(parser, limits=True)   # --model and its settings (--height/--sex: human)
                                               # | --urdf/--ee/--start/--joints
                                               # [--limits FILE.json --degrees]
    spec = model_from_args(args)                # a picklable `ModelSpec`
    sim = spec.build()                          # cached per process (worker processes rebuild it)

The models, their settings and their subjects come from `camo_sbi.simulators.registry`, read
when the parser is built: ``--model``'s choices and each setting's flag are the registered ones.

A `ModelSpec` carries everything needed to rebuild the simulator in another process: the
model name and its settings (the human's height and sex), or the URDF path with the sha256 of
its text, the end-effector link, the actuated joints and the start posture. A worker that finds
a URDF whose text no longer matches the digest refuses it instead of simulating another robot.

Ground-truth limits of a synthetic subject (``--limits FILE.json``)::

    {"joint_name": [lo, hi], ...}      radians; degrees with --degrees (prismatic joints: metres)

Every actuated joint must be named exactly once, no other name may appear, and each pair
must satisfy ``bound_lo <= lo <= start <= hi <= bound_hi`` (the URDF range, the start
posture): otherwise ValueError naming the file and the joint (exit 2 on the command line).

Subjects: for a registered model its named profiles (`camo_sbi.simulators.registry`,
``--subjects``), or a ``--limits`` file; for a URDF the ``--limits`` file is the subject
(its file stem is the subject's name in the tables), and ``--subjects`` is refused.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from camo_sbi._files import read_json, read_text
from camo_sbi.simulators import registry

if TYPE_CHECKING:  # torch is imported where limits are built: the CLI's parser imports this module
    import torch

__all__ = ["ModelSpec", "add_model_arguments", "build_simulator", "load_limits", "model_from_args",
           "parse_floats", "subject_list", "subject_limits"]

_SIMS: dict = {}


@dataclass(frozen=True)
class ModelSpec:
    """What is needed to rebuild a simulator in any process (plain, hashable, picklable).

    Attributes:
        kind: a registered model's name ("panda", "human", ...) or "urdf".
        settings: ((name, value), ...) the model's settings set on the command line, in the
            order the model declares them (the human's ``height_m`` and ``sex``); the others
            keep the model's defaults.
        urdf: URDF path (kind "urdf").  digest: sha256 of its text.  ee: end-effector link.
        start: start posture (radians/metres) or None (the model's default).
        joints: actuated joint names or None (every movable joint on the path).
        limits: ground-truth limits ((joint, lo, hi), ...) in radians, or None.
        limits_name: the subject's name (the --limits file stem).
    """

    kind: str = "panda"
    settings: tuple[tuple[str, Any], ...] = ()
    urdf: str | None = None
    digest: str | None = None
    ee: str | None = None
    start: tuple[float, ...] | None = None
    joints: tuple[str, ...] | None = None
    limits: tuple[tuple[str, float, float], ...] | None = None
    limits_name: str | None = None

    @property
    def name(self) -> str:
        """Task name in tables: the model's name or the URDF file stem."""
        return Path(self.urdf).stem if self.kind == "urdf" else self.kind

    @property
    def is_default(self) -> bool:
        """A built-in model with its default settings and no --limits (keeps old cell keys)."""
        return self.kind != "urdf" and self == ModelSpec(kind=self.kind)

    def _flat(self) -> dict:
        d = asdict(self)
        settings = dict(d.pop("settings"))
        return {"kind": d.pop("kind"), **settings, **d}

    def key(self) -> dict:
        """The settings that identify the model (for cell keys; the path itself is not part of it),
        the model's settings beside ``kind`` (``{"kind": "human", "height_m": 1.6}``)."""
        d = self._flat()
        d.pop("urdf")
        return {k: v for k, v in d.items() if v is not None}

    def to_json(self) -> str:
        """Every field, the URDF path included, and the model's settings as keys of their own, as
        JSON (stored with saved posteriors: the report rebuilds the very body from it)."""
        return json.dumps(self._flat(), sort_keys=True, default=str)

    def build(self):
        """The simulator, built once per process (per registration of the model)."""
        key = _cache_key(self)
        if key not in _SIMS:
            _SIMS[key] = _build(self)
        return _SIMS[key]


def _cache_key(spec: ModelSpec) -> tuple:
    """The spec and the registered model it names (a model registered anew is built anew)."""
    return spec, None if spec.kind == "urdf" else registry.get_model(spec.kind)


def build_simulator(spec: ModelSpec):
    return spec.build()


def _digest(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def _build(spec: ModelSpec):
    from camo_sbi.simulators import from_urdf

    kwargs = {}
    if spec.start is not None:
        kwargs["start"] = list(spec.start)
    if spec.joints is not None:
        kwargs["joints"] = list(spec.joints)
    if spec.kind != "urdf":
        return registry.build_model(spec.kind, dict(spec.settings), **kwargs)
    path = Path(spec.urdf)
    text = read_text(path, f"--urdf: {path}")
    if spec.digest is not None and _digest(text) != spec.digest:
        raise ValueError(f"--urdf: {path} changed since the run was set up (sha256 differs)")
    try:
        return from_urdf(text, spec.ee, **kwargs)
    except ValueError as exc:
        flag = {"end_effector": "--ee", "start": "--start", "joints": "--joints"}.get(str(exc).split(":")[0],
                                                                                     "--urdf")
        raise ValueError(f"{flag}: {path}: {exc}") from exc


def parse_floats(text, flag: str) -> tuple[float, ...]:
    """``"0.1, -0.2, 0"`` -> (0.1, -0.2, 0.0); ValueError naming ``flag``."""
    items = [t.strip() for t in str(text).split(",")]
    try:
        values = tuple(float(t) for t in items)
    except ValueError as exc:
        raise ValueError(f"{flag}: expected comma-separated numbers, got {text!r}") from exc
    if not values or not all(math.isfinite(v) for v in values):
        raise ValueError(f"{flag}: expected finite comma-separated numbers, got {text!r}")
    return values


def add_model_arguments(p: argparse.ArgumentParser, *, limits: bool = True) -> None:
    """The shared model options (and, for synthetic studies, ``--limits``/``--degrees``)."""
    g = p.add_argument_group("body model", "a registered model (--model) or any serial-chain URDF (--urdf)")
    g.add_argument("--model", choices=registry.model_names(), default=None,
                   help="registered body model (default: panda)")
    for flag, (setting, owners) in _setting_flags().items():
        g.add_argument(flag, type=setting.type, choices=setting.choices, default=None,
                       help=f"{', '.join(owners)}: {setting.help}")
    g.add_argument("--urdf", type=Path, default=None, help="URDF file of your own robot or body")
    g.add_argument("--ee", default=None, help="with --urdf: end-effector link name")
    g.add_argument("--start", default=None, help='start posture "q1,q2,..." (radians/metres, joint order)')
    g.add_argument("--joints", default=None, help="with --urdf: actuated joints a,b,... (default: all on the path)")
    if limits:
        g.add_argument("--limits", type=Path, default=None,
                       help='ground-truth limits JSON {"joint": [lo, hi], ...} (radians; required with --urdf)')
        g.add_argument("--degrees", action="store_true",
                       help="the --limits file is in degrees (prismatic joints stay in metres)")


def _setting_flags() -> dict:
    """{flag: (the Setting, [models declaring it])} over the registered models."""
    out: dict = {}
    for name in registry.model_names():
        for s in registry.get_model(name).settings:
            out.setdefault(s.flag, (s, []))[1].append(name)
    return out


def model_from_args(args, *, build: bool = True) -> ModelSpec:
    """A validated `ModelSpec` from the options of `add_model_arguments` (builds the model once).

    ``build=False``: the spec without building the simulator, so --ee, --start, --joints and
    --height are not checked against the model (with --limits it is still built: the limits are
    read against it). For a re-run whose cells are all finished (`compare`): their keys were
    computed from the same, then validated, options.
    """
    urdf = getattr(args, "urdf", None)
    model = getattr(args, "model", None)
    if urdf is not None and model is not None:
        raise ValueError("--model: give --model or --urdf, not both")
    if urdf is None:
        for flag in ("ee", "joints"):
            if getattr(args, flag, None) is not None:
                raise ValueError(f"--{flag}: only with --urdf")
        model = model or "panda"
    elif getattr(args, "ee", None) is None:
        raise ValueError("--ee: --urdf needs the end-effector link name (--ee LINK)")
    if urdf is None and model not in registry.model_names():
        raise ValueError(f"--model: unknown body model {model!r}; known: {', '.join(registry.model_names())}")
    declared = () if urdf is not None else registry.get_model(model).settings
    for flag, (setting, owners) in _setting_flags().items():
        if getattr(args, setting.dest, None) is not None and setting not in declared:
            raise ValueError(f"{flag}: only with --model {' or '.join(owners)}")
    start = parse_floats(args.start, "--start") if getattr(args, "start", None) is not None else None
    joints = None
    if getattr(args, "joints", None) is not None:
        joints = tuple(t.strip() for t in str(args.joints).split(",") if t.strip())
        if not joints:
            raise ValueError("--joints: give at least one joint name")
    if urdf is not None:
        path = Path(urdf)
        if not path.is_file():
            raise ValueError(f"--urdf: no such file {path}")
        spec = ModelSpec(kind="urdf", urdf=str(path.resolve()), digest=_digest(read_text(path, f"--urdf: {path}")),
                         ee=args.ee,
                         start=start, joints=joints)
    else:
        values = {s.name: getattr(args, s.dest, None) for s in declared}
        spec = ModelSpec(kind=model, settings=registry.get_model(model).settings_from(values), start=start)
    path = getattr(args, "limits", None)
    if not build and path is None:
        return spec
    try:
        sim = spec.build()  # validates --ee / --start / --joints and the model's settings before any work
    except ValueError as exc:
        flag = next((s.flag for s in declared if str(exc).startswith(s.name)), None)
        if flag is None:
            raise
        raise ValueError(f"{flag}: {exc}") from exc
    if path is not None:
        lim = load_limits(path, sim, degrees=bool(getattr(args, "degrees", False)))
        spec = ModelSpec(**{**asdict(spec), "limits": tuple((j, float(lo), float(hi)) for j, (lo, hi)
                                                             in zip(sim.joint_names, lim.tolist(), strict=True)),
                            "limits_name": Path(path).stem})
        _SIMS[_cache_key(spec)] = sim
    return spec


def load_limits(path, sim, *, degrees: bool = False) -> torch.Tensor:
    """(n, 2) float64 radians from a ``{"joint": [lo, hi]}`` JSON file, checked against ``sim``.

    ValueError starting with ``--limits: FILE`` and naming the joint on: unreadable JSON,
    unknown or missing joint names, a pair that is not two numbers, lo > hi, a pair outside
    the model's range, or one that does not contain the start posture.
    """
    import torch

    path = Path(path)
    where = f"--limits: {path}"
    data = read_json(path, where)
    if not isinstance(data, dict):
        raise ValueError(f'{where}: expected a JSON object {{"joint_name": [lo, hi], ...}}')
    names = list(sim.joint_names)
    unknown = [k for k in data if k not in names]
    if unknown:
        raise ValueError(f"{where}: unknown joint {unknown[0]!r}; the model's joints: {', '.join(names)}")
    missing = [j for j in names if j not in data]
    if missing:
        raise ValueError(f"{where}: joint {missing[0]!r} is missing (every joint needs [lo, hi]; missing: "
                         f"{', '.join(missing)}; the model's joints, in order: {', '.join(names)})")
    types = sim.spec.joint_types
    b, s = sim.bounds.to(torch.float64), sim.start.to(torch.float64)
    out = torch.empty(len(names), 2, dtype=torch.float64)
    for i, j in enumerate(names):
        pair = data[j]
        if (not isinstance(pair, list) or len(pair) != 2
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                           for v in pair)):
            raise ValueError(f"{where}: joint {j!r}: expected [lo, hi] (two finite numbers), got {pair!r}")
        lo, hi = (math.radians(v) if degrees and types[i] == "revolute" else float(v) for v in pair)
        tol = 1e-9
        if lo > hi:
            raise ValueError(f"{where}: joint {j!r}: lo {pair[0]} > hi {pair[1]}")
        if lo < b[i, 0] - tol or hi > b[i, 1] + tol:
            raise ValueError(f"{where}: joint {j!r}: [{lo:.6g}, {hi:.6g}] rad lies outside the model's range "
                             f"[{float(b[i, 0]):.6g}, {float(b[i, 1]):.6g}]"
                             + ("" if degrees else " (degrees? use --degrees)"))
        if not lo - tol <= s[i] <= hi + tol:
            raise ValueError(f"{where}: joint {j!r}: [{lo:.6g}, {hi:.6g}] does not contain the start posture "
                             f"{float(s[i]):.6g} (set --start inside the limits)")
        out[i, 0], out[i, 1] = max(lo, float(b[i, 0])), min(hi, float(b[i, 1]))
    return out


def subject_list(spec: ModelSpec, subjects: str | None, *, default_all: bool = False) -> list[str]:
    """Subject names for a study: the --limits file's, or profiles of a registered model."""
    if spec.limits is not None:
        if subjects:
            raise ValueError("--subjects: the --limits file is the subject; give one or the other")
        return [spec.limits_name]
    if spec.kind == "urdf":
        raise ValueError("--limits: a URDF model needs the subject's true limits (--limits FILE.json)")
    if subjects:
        items = [t.strip() for t in str(subjects).split(",") if t.strip()]
        if not items:
            raise ValueError("--subjects: give at least one profile")
        return items
    names = registry.subject_names(spec.kind)
    return names if default_all else names[:1]


def subject_limits(spec: ModelSpec, sim, name: str) -> torch.Tensor:
    """(2n,) float64 true limits of subject ``name``: the --limits file, or a named profile."""
    import torch

    if spec.limits is not None:
        if name != spec.limits_name:
            raise ValueError(f"subject: {name!r} is not the --limits subject {spec.limits_name!r}")
        return torch.tensor([v for _, lo, hi in spec.limits for v in (lo, hi)], dtype=torch.float64)
    try:
        return registry.subject_theta(sim, spec.kind, name)
    except ValueError as exc:
        raise ValueError(f"--subjects: {exc}") from exc
