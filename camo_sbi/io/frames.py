"""Rigid transforms from a motion-capture lab's frame to the model's base frame.

``p_model = R @ p_lab + t`` (R a proper 3x3 rotation, t in metres). A frame file (``--frame``) is
JSON, one of::

    {"rotation": [[r11, r12, r13], [r21, r22, r23], [r31, r32, r33]], "translation": [x, y, z]}
    {"quaternion": [w, x, y, z], "translation": [x, y, z]}

`frame_from_markers` estimates the transform from three or more markers whose positions in the
model's base frame are known (Kabsch / orthogonal Procrustes) and returns the RMS residual
of the fit: the offset the transform leaves, in metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from camo_sbi._files import read_json

__all__ = ["Frame", "frame_from_markers", "load_frame", "load_marker_positions", "read_json_object"]

MAX_TRANSLATION_M = 1000.0
"""A lab frame's translation beyond this many metres is refused (millimetres typed as metres, or worse)."""

ROTATION_TOL = 1e-4
"""|R^T R - I| and |det R - 1| beyond this: not a rotation (a file typed by hand keeps ~5 digits)."""


@dataclass(frozen=True)
class Frame:
    """A rigid transform lab -> model base: ``p_model = rotation @ p_lab + translation``."""

    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,) metres
    residual_m: float = float("nan")  # RMS fit residual when estimated from markers
    source: str = ""

    def apply(self, points: np.ndarray) -> np.ndarray:
        """(..., 3) lab points -> model base frame."""
        return np.asarray(points, dtype=np.float64) @ self.rotation.T + self.translation


def _read_json(path, flag: str):
    path = Path(path)
    data = read_json(path, f"{flag} {path}")
    if not isinstance(data, dict):
        raise ValueError(f"{flag} {path}: expected a JSON object")
    return path, data


read_json_object = _read_json
"""``(path, data)`` of a JSON object file; one ValueError naming ``flag`` and the file otherwise."""


def _vector(value, n: int, what: str) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{what}: expected {n} numbers, got {value!r}") from None
    if a.shape != (n,) or not np.isfinite(a).all():
        raise ValueError(f"{what}: expected {n} finite numbers, got {str(value)[:80]}")
    return a


def _check_rotation(r: np.ndarray, what: str) -> np.ndarray:
    if r.shape != (3, 3) or not np.isfinite(r).all():
        raise ValueError(f"{what}: expected a 3x3 matrix of finite numbers")
    ortho = float(np.abs(r.T @ r - np.eye(3)).max())
    det = float(np.linalg.det(r))
    if ortho > ROTATION_TOL or abs(det - 1.0) > ROTATION_TOL:
        raise ValueError(f"{what}: not a rotation (|R^T R - I| = {ortho:.2g}, det = {det:.4g}; a mirror or "
                         f"a scaled matrix is not a rigid transform)")
    return r


def load_frame(path, flag: str = "--frame") -> Frame:
    """The transform in the JSON file ``path`` (see the module docstring). Errors name ``flag``,
    the file and the key."""
    path, data = _read_json(path, flag)
    unknown = sorted(set(data) - {"rotation", "quaternion", "translation"})
    if unknown:
        raise ValueError(f"{flag} {path}: key {unknown[0]!r} is unknown (expected rotation or quaternion, "
                         f"and translation)")
    if "translation" not in data:
        raise ValueError(f"{flag} {path}: key 'translation' is missing ([x, y, z] in metres)")
    t = _vector(data["translation"], 3, f"{flag} {path}: key 'translation'")
    if float(np.abs(t).max()) > MAX_TRANSLATION_M:
        raise ValueError(f"{flag} {path}: key 'translation': {float(np.abs(t).max()):.3g} m is farther than "
                         f"{MAX_TRANSLATION_M:g} m from the lab's origin; the translation is in metres")
    if ("rotation" in data) == ("quaternion" in data):
        raise ValueError(f"{flag} {path}: give exactly one of 'rotation' (3x3) or 'quaternion' ([w, x, y, z])")
    if "rotation" in data:
        try:
            r = np.asarray(data["rotation"], dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"{flag} {path}: key 'rotation': expected a 3x3 matrix of numbers") from None
        r = _check_rotation(r, f"{flag} {path}: key 'rotation'")
    else:
        w, x, y, z = _vector(data["quaternion"], 4, f"{flag} {path}: key 'quaternion'")
        norm = math.sqrt(w * w + x * x + y * y + z * z)
        if abs(norm - 1.0) > 1e-3:
            raise ValueError(f"{flag} {path}: key 'quaternion': [w, x, y, z] must have norm 1, got {norm:.6g}")
        w, x, y, z = w / norm, x / norm, y / norm, z / norm
        r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    return Frame(r, t, source=str(path))


def load_marker_positions(path, names, flag: str = "--marker-positions") -> dict[str, np.ndarray]:
    """{marker: (3,) position in the model's base frame [m]} for ``names``, from a JSON object."""
    path, data = _read_json(path, flag)
    out = {}
    for n in names:
        if n not in data:
            raise ValueError(f"{flag} {path}: marker {n!r} is missing (it has: {', '.join(map(str, data))})")
        out[n] = _vector(data[n], 3, f"{flag} {path}: marker {n!r}")
    return out


def frame_from_markers(lab: dict[str, np.ndarray], model: dict[str, np.ndarray], flag: str = "--frame-from-markers",
                       ) -> Frame:
    """The rigid transform taking the markers' ``lab`` positions onto their ``model`` positions
    (least squares, Kabsch), with the RMS residual in metres."""
    names = list(model)
    if len(names) < 3:
        raise ValueError(f"{flag}: needs at least three markers, got {len(names)}")
    a = np.stack([np.asarray(lab[n], dtype=np.float64) for n in names])
    b = np.stack([np.asarray(model[n], dtype=np.float64) for n in names])
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    sv = np.linalg.svd(b - cb, compute_uv=False)
    if sv[1] < 1e-3 * max(sv[0], 1e-12) or sv[0] < 1e-6:
        raise ValueError(f"{flag}: the markers {', '.join(names)} are collinear in the model frame: they do not "
                         f"fix a rotation")
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    t = cb - r @ ca
    resid = float(np.sqrt(np.mean(np.sum((a @ r.T + t - b) ** 2, axis=1))))
    return Frame(r, t, residual_m=resid, source=f"markers {', '.join(names)}")
