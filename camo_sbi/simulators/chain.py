"""URDF -> serial kinematic chain: the only module importing pytorch_kinematics.

`load_chain` parses URDF text (or a path) once and gives a `KinematicChain` holding

* a plain `ChainSpec` (numpy float64 constants: joint origins, axes, limits, tool
  transform) from which `kernel.py` generates its fused code, and
* the pytorch_kinematics (pk) serial chain used for the reference FK and Jacobian
  (`reference_fk`, `reference_jacobian`), cached per dtype/device.

Precision: pk converts URDF ``rpy`` origins with float32 maths. Here every origin is
computed in float64 from the URDF numbers, entries within 1e-9 of 0 or +-1 are snapped
(``rpy="1.57079632679 0 0"`` is a quarter turn), and the very same constants are put
into the pk frames. pk and the generated kernel therefore share bit-identical
constants; both match PyBullet to ~1e-7 m (PyBullet's own rounding).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytorch_kinematics as pk
import torch
from pytorch_kinematics.urdf_parser_py.urdf import URDF
from pytorch_kinematics.urdf_parser_py.xml_reflection import core as _xml_core

__all__ = ["ChainSpec", "KinematicChain", "load_chain", "read_urdf", "scale_urdf"]

_SNAP = 1e-9
_MOVABLE = {"revolute": "revolute", "continuous": "revolute", "prismatic": "prismatic"}


@dataclass(frozen=True, eq=False)
class ChainSpec:
    """Plain description of an actuated serial chain (all arrays float64 numpy).

    Pose of joint frame k (k = 0..n-1, base to tip)::

        T_k = T_{k-1} @ origins[k] @ motion_k(q_k),      T_{-1} = I (base link frame)
        motion_k = rotation about axes[k] by q_k (revolute) or translation q_k * axes[k]
        end effector pose = T_{n-1} @ tip

    Attributes:
        joint_names: (n,) actuated joint names, base to tip.
        joint_types: (n,) "revolute" or "prismatic".
        origins: (n, 4, 4) fixed transform from the previous joint frame (the base link
            for k = 0) to joint frame k at q_k = 0; fixed and locked joints folded in.
        axes: (n, 3) unit joint axes in their own joint frame.
        limits: (n, 2) URDF [lower, upper] (continuous joints: [-pi, pi]).
        tip: (4, 4) fixed transform from the last joint frame to the end-effector link.
        base_link, end_effector: link names.
    """

    joint_names: tuple[str, ...]
    joint_types: tuple[str, ...]
    origins: np.ndarray
    axes: np.ndarray
    limits: np.ndarray
    tip: np.ndarray
    base_link: str
    end_effector: str
    _digest: str = field(default="", repr=False)

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    @property
    def digest(self) -> str:
        """sha256 of every constant: identifies the chain for kernel caching."""
        return self._digest

    def joint_frames(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Plain float64 numpy poses at posture q (..., n): ((..., n, 4, 4) each joint frame
        before its own motion, i.e. ``T_{k-1} @ origins[k]`` (its centre and axis), and the
        (..., 4, 4) end-effector pose), in the base link frame."""
        q = np.asarray(q, dtype=np.float64)
        batch = q.shape[:-1]
        T = np.broadcast_to(np.eye(4), (*batch, 4, 4)).copy()
        frames = []
        for k in range(self.n_joints):
            T = T @ self.origins[k]
            frames.append(T)
            M = np.broadcast_to(np.eye(4), (*batch, 4, 4)).copy()
            if self.joint_types[k] == "revolute":
                M[..., :3, :3] = _axis_angle(self.axes[k], q[..., k])
            else:
                M[..., :3, 3] = q[..., k, None] * self.axes[k]
            T = T @ M
        return np.stack(frames, axis=-3), T @ self.tip

    def fk_numpy(self, q: np.ndarray) -> np.ndarray:
        """Plain float64 numpy FK from the spec (for checks): q (..., n) -> (..., 3)."""
        return self.joint_frames(q)[1][..., :3, 3]


def _axis_angle(a: np.ndarray, ang: np.ndarray) -> np.ndarray:
    c, s = np.cos(ang)[..., None, None], np.sin(ang)[..., None, None]
    K = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return c * np.eye(3) + s * K + (1.0 - c) * np.outer(a, a)


def _snap(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=np.float64)
    for v in (0.0, 1.0, -1.0):
        a[np.abs(a - v) < _SNAP] = v
    return a


def _check_finite(values, what: str) -> None:
    """ValueError ``urdf: <what> contains nan`` (or inf) unless every number in ``values`` is finite."""
    if values is None:
        return
    a = np.asarray(values, dtype=np.float64)
    if not np.isfinite(a).all():
        bad = "nan" if np.isnan(a).any() else "inf"
        raise ValueError(f"urdf: {what} contains {bad}")


def _check_urdf_numbers(robot) -> None:
    """Every origin xyz/rpy, axis and limit in the URDF must be finite (checked before any kernel code)."""
    for j in robot.joints:
        if j.origin is not None:
            _check_finite(j.origin.xyz, f"joint {j.name!r} origin xyz")
            _check_finite(j.origin.rpy, f"joint {j.name!r} origin rpy")
        _check_finite(j.axis, f"joint {j.name!r} axis")
        if j.limit is not None:
            for side in ("lower", "upper"):
                _check_finite(getattr(j.limit, side, None), f"joint {j.name!r} limit {side}")
    for link in robot.links:
        origin = getattr(link, "origin", None)
        if origin is not None:
            _check_finite(origin.xyz, f"link {link.name!r} origin xyz")
            _check_finite(origin.rpy, f"link {link.name!r} origin rpy")


def _check_name(name, what: str) -> None:
    """A URDF name must be a non-empty string without control characters or surrounding spaces."""
    if not isinstance(name, str) or not name:
        raise ValueError(f"urdf: a {what} has no name")
    if name != name.strip() or any(ord(ch) < 32 or ord(ch) == 127 for ch in name):
        raise ValueError(f"urdf: {what} name {name!r} contains a control character or surrounding spaces")


def _check_urdf_structure(robot) -> None:
    """Names unique and clean, every joint between known links, each link the child of at most one
    joint, and no cycle: a tree, checked before anything walks it (a cycle would walk forever)."""
    for kind, items in (("link", robot.links), ("joint", robot.joints)):
        seen = set()
        for item in items:
            _check_name(item.name, kind)
            if item.name in seen:
                raise ValueError(f"urdf: duplicate {kind} name {item.name!r}")
            seen.add(item.name)
    links = {link.name for link in robot.links}
    parent_of: dict[str, tuple[str, str]] = {}
    for j in robot.joints:
        for side in ("parent", "child"):
            if getattr(j, side) not in links:
                raise ValueError(f"urdf: joint {j.name!r} names {side} link {getattr(j, side)!r}, "
                                 "which is not in the URDF")
        if j.child in parent_of:
            raise ValueError(f"urdf: link {j.child!r} is the child of two joints, "
                             f"{parent_of[j.child][0]!r} and {j.name!r} (a URDF is a tree)")
        parent_of[j.child] = (j.name, j.parent)
    for start in (link.name for link in robot.links):
        seen, link = {start}, start
        while link in parent_of:
            jname, link = parent_of[link]
            if link in seen:
                raise ValueError(f"urdf: joint {jname!r} closes a cycle through link {link!r} "
                                 "(a URDF is a tree)")
            seen.add(link)


def _check_mimic(path, movable: list[str]) -> None:
    """Mimic joints are not simulated (a follower would need its leader's angle): refused by name."""
    for j in path:
        mimic = getattr(j, "mimic", None)
        if mimic is not None and j.name in movable:
            raise ValueError(f"urdf: joint {j.name!r} is a <mimic> joint (following {mimic.joint!r}), "
                             "which is not supported: make it fixed, or an independent joint without <mimic>")


def _pose(origin) -> np.ndarray:
    """URDF <origin xyz rpy> -> exact float64 4x4 (R = Rz(yaw) Ry(pitch) Rx(roll))."""
    T = np.eye(4)
    if origin is None:
        return T
    xyz = [0.0, 0.0, 0.0] if origin.xyz is None else origin.xyz
    r, p, y = [0.0, 0.0, 0.0] if origin.rpy is None else origin.rpy
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    T[:3, :3] = _snap(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )
    T[:3, 3] = np.asarray(xyz, dtype=np.float64)
    return T


@contextlib.contextmanager
def _quiet_parser():
    """Silence urdf_parser_py's stderr chatter (unknown tags such as <contact>) while parsing."""
    old = _xml_core.on_error
    _xml_core.on_error = lambda message: None
    try:
        yield
    finally:
        _xml_core.on_error = old


def read_urdf(urdf) -> str:
    """URDF text from text or a path (str / os.PathLike). TypeError/ValueError naming ``urdf``;
    a message never quotes a file's text (only a short one-line string, taken as a path)."""
    if isinstance(urdf, str) and "<robot" not in urdf and ("\n" in urdf or "\0" in urdf or len(urdf) > 4096):
        raise ValueError(f"urdf: not a URDF (no <robot> element in its {len(urdf):,} characters)")
    if isinstance(urdf, os.PathLike) or (isinstance(urdf, str) and "<robot" not in urdf):
        path = Path(urdf)
        if not path.is_file():
            raise ValueError(f"urdf: not URDF text and no such file: {str(urdf)[:200]!r}")
        return path.read_text()
    if not isinstance(urdf, str):
        raise TypeError(f"urdf: expected URDF text or a path, got {type(urdf).__name__}")
    return urdf


def scale_urdf(urdf, factor: float) -> str:
    """URDF text with every joint origin's translation (``<joint><origin xyz>``) scaled by ``factor``.

    A body ``factor`` times as tall, with every segment length off by that much (geometry and
    inertia are left as they are: kinematics only). ValueError for a non-positive factor.
    """
    import xml.etree.ElementTree as ET

    factor = float(factor)
    if not (np.isfinite(factor) and factor > 0):
        raise ValueError(f"factor: expected a finite number > 0, got {factor}")
    root = ET.fromstring(read_urdf(urdf))
    for joint in root.iter("joint"):
        origin = joint.find("origin")
        if origin is not None and origin.get("xyz"):
            xyz = [float(v) * factor for v in origin.get("xyz").split()]
            origin.set("xyz", " ".join(repr(v) for v in xyz))
    return ET.tostring(root, encoding="unicode")


class KinematicChain:
    """A parsed serial chain: `spec` (plain constants) + pk reference FK / Jacobian.

    Build with `load_chain`. ``urdf`` holds the URDF text.
    """

    def __init__(self, urdf_text: str, spec: ChainSpec, pk_chain):
        self.urdf = urdf_text
        self.spec = spec
        self._pk = {(torch.float64, "cpu"): pk_chain}

    @property
    def joint_names(self) -> list[str]:
        return list(self.spec.joint_names)

    @property
    def n_joints(self) -> int:
        return self.spec.n_joints

    def pk_chain(self, dtype: torch.dtype, device) -> pk.SerialChain:
        """The pk serial chain converted to ``dtype``/``device`` (cached)."""
        key = (dtype, str(torch.device(device)))
        ch = self._pk.get(key)
        if ch is None:
            import copy

            ch = copy.deepcopy(self._pk[(torch.float64, "cpu")]).to(dtype=dtype, device=device)
            self._pk[key] = ch
        return ch

    def reference_fk(self, q: torch.Tensor) -> torch.Tensor:
        """pk forward kinematics: q (..., n) -> end-effector position (..., 3), q's dtype/device."""
        flat = q.reshape(-1, self.n_joints)
        if flat.shape[0] == 0:
            return q.new_zeros(*q.shape[:-1], 3)
        ch = self.pk_chain(q.dtype, q.device)
        pos = ch.forward_kinematics(flat).get_matrix()[:, :3, 3]
        return pos.reshape(*q.shape[:-1], 3)

    def reference_jacobian(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """pk ``chain.jacobian(q, ret_eef_pose=True)``: q (B, n) -> (J (B, 6, n), pose (B, 4, 4)).

        J rows 0-2 are the linear (position) part in the base frame.
        """
        ch = self.pk_chain(q.dtype, q.device)
        return ch.jacobian(q, ret_eef_pose=True)


def load_chain(urdf, end_effector: str, joints=None, *, base_link: str | None = None) -> KinematicChain:
    """Parse ``urdf`` (text or path) into the serial chain ``base_link`` -> ``end_effector``.

    Args:
        urdf: URDF text or a path to a .urdf file.
        end_effector: name of the end-effector link.
        joints: names of the actuated joints (subset of the movable joints on the path,
            listed base to tip); the other movable joints are locked at 0. None: all.
        base_link: root of the chain (default: the URDF root link).

    Raises ValueError naming the argument (urdf, end_effector, joints, base_link).
    """
    text = read_urdf(urdf)
    try:
        with _quiet_parser():
            robot = URDF.from_xml_string(text)
    except Exception as exc:  # the parser raises assorted types on malformed XML
        raise ValueError(f"urdf: cannot parse URDF ({' '.join(str(exc).split())[:300]})") from exc
    _check_urdf_structure(robot)
    try:
        root = robot.get_root()
    except Exception as exc:  # e.g. two roots
        raise ValueError(f"urdf: no single root link ({' '.join(str(exc).split())[:300]})") from exc
    _check_urdf_numbers(robot)
    if not isinstance(end_effector, str) or end_effector not in robot.link_map:
        raise ValueError(f"end_effector: no link named {end_effector!r} in the URDF")
    base = root if base_link is None else base_link
    if base not in robot.link_map:
        raise ValueError(f"base_link: no link named {base!r} in the URDF")

    # path of joints base -> end effector
    path, link = [], end_effector
    while link != base:
        if link not in robot.parent_map:
            raise ValueError(f"base_link: {base!r} is not an ancestor of end_effector {end_effector!r}")
        jname, link = robot.parent_map[link]
        path.append(robot.joint_map[jname])
    path.reverse()
    movable = [j.name for j in path if j.type in _MOVABLE]
    _check_mimic(path, movable)
    for j in path:
        if j.type not in _MOVABLE and j.type != "fixed":
            raise ValueError(f"urdf: joint {j.name!r} has unsupported type {j.type!r}")
    if joints is None:
        active = movable
    else:
        if isinstance(joints, str):
            raise TypeError("joints: expected a sequence of joint names, got a str")
        active = list(joints)
        unknown = [n for n in active if n not in movable]
        if unknown:
            raise ValueError(f"joints: {unknown} are not movable joints between {base!r} and {end_effector!r} (movable: {movable})")
        if len(set(active)) != len(active):
            raise ValueError(f"joints: duplicate names in {active}")
        if active != [n for n in movable if n in active]:
            raise ValueError(f"joints: must be listed base to tip, in the order {movable}")
    if not active:
        raise ValueError(f"joints: no movable joint between {base!r} and {end_effector!r}")

    # exact float64 constants per URDF joint (link origin folded in, as pk does)
    exact = {}
    for j in robot.joints:
        T = _pose(j.origin)
        child = robot.link_map.get(j.child)
        if child is not None and getattr(child, "origin", None) is not None:
            T = _pose(child.origin) @ T
        axis = np.array([1.0, 0.0, 0.0] if j.axis is None else j.axis, dtype=np.float64)
        nrm = np.linalg.norm(axis)
        if j.type in _MOVABLE and not nrm > 0:
            raise ValueError(f"urdf: joint {j.name!r} has a zero axis")
        axis = _snap(axis / nrm) if nrm > 0 else np.array([0.0, 0.0, 1.0])
        exact[j.name] = (T, axis)

    # fold into the ChainSpec
    names, types, origins, axes, limits = [], [], [], [], []
    acc = np.eye(4)
    for j in path:
        T, axis = exact[j.name]
        acc = acc @ T
        if j.name not in active:  # fixed or locked at 0
            continue
        typ = _MOVABLE[j.type]
        lim = j.limit
        if j.type == "continuous" or lim is None or lim.lower is None or lim.upper is None:
            if typ == "prismatic":
                raise ValueError(f"urdf: prismatic joint {j.name!r} has no <limit lower upper>")
            lohi = (-np.pi, np.pi)
        else:
            lohi = (float(lim.lower), float(lim.upper))
        if not (np.isfinite(lohi).all() and lohi[0] <= lohi[1]):
            raise ValueError(f"urdf: joint {j.name!r} has invalid limits {lohi}")
        names.append(j.name)
        types.append(typ)
        origins.append(acc)
        axes.append(axis)
        limits.append(lohi)
        acc = np.eye(4)
    spec_arrays = (np.stack(origins), np.stack(axes), np.array(limits, dtype=np.float64), acc)
    h = hashlib.sha256()
    h.update(repr((names, types, base, end_effector)).encode())
    for a in spec_arrays:
        h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
    spec = ChainSpec(tuple(names), tuple(types), *spec_arrays, base_link=base,
                     end_effector=end_effector, _digest=h.hexdigest())
    for a in spec_arrays:
        a.setflags(write=False)

    # pk chain with the exact constants in every frame (and locked joints made fixed)
    try:
        with _quiet_parser():
            full = pk.build_chain_from_urdf(text)
    except Exception as exc:
        raise ValueError(f"urdf: pytorch_kinematics cannot build the chain ({exc})") from exc
    f64 = torch.float64
    stack = [full._root]  # pk frames are named by their child link
    while stack:
        fr = stack.pop()
        stack.extend(fr.children)
        fr.link.offset = None
        if fr.joint.name in exact:
            T, axis = exact[fr.joint.name]
            old = fr.joint
            jt = old.joint_type if (old.joint_type == "fixed" or old.name in active or old.name not in movable) else "fixed"
            fr.joint = pk.Joint(old.name, offset=pk.Transform3d(matrix=torch.tensor(T, dtype=f64), dtype=f64),
                                joint_type=jt, axis=torch.tensor(axis, dtype=f64), dtype=f64,
                                limits=old.limits if jt != "fixed" else None,
                                velocity_limits=old.velocity_limits, effort_limits=old.effort_limits)
        else:
            fr.joint = pk.Joint(fr.joint.name, dtype=f64)
    serial = pk.SerialChain(full, end_effector, "" if base_link is None else base_link, dtype=f64)
    pk_names = serial.get_joint_parameter_names()
    if list(pk_names) != names:
        raise ValueError(f"urdf: pytorch_kinematics joint order {pk_names} differs from {names}")
    return KinematicChain(text, spec, serial)
