"""A recording against the body model's geometry: how far the model reaches (`reach_radius`) and
positions far beyond it (`check_units`: "use --ee-units mm"), the FK of the joint columns against
the end-effector columns (`check_ee_matches_fk`), start postures by IK of a first end-effector
sample (`estimate_starts`), and the recorded body's size (`estimate_body_scale`,
`hint_body_scale`).
"""

from __future__ import annotations

import logging
import math

import numpy as np
import torch

from camo_sbi.io.frames import Frame
from camo_sbi.io.schema import EE_COLUMNS, GOAL_COLUMNS, K_SIGMA, Table
from camo_sbi.task import NoiseModel

__all__ = ["BODY_SCALE_RANGE", "EE_FK_TOL_M", "OFFSET_WARN_M", "START_TOL_M", "check_ee_matches_fk",
           "check_units", "estimate_body_scale", "estimate_starts", "hint_body_scale", "reach_radius"]

OFFSET_WARN_M = 0.005
"""A mean offset between ee_* and the FK of the joint columns (or a marker-frame RMS residual)
beyond this is a warning in the run summary and the report."""
UNITS_FACTOR = 10.0
"""A position this many times farther from the base than the model reaches is refused (with a
hint when it would fit in millimetres)."""
START_TOL_M = 0.005
"""An end-effector-only reach must start within this distance (plus the noise allowance) of
the end effector at the model's start posture."""
EE_FK_TOL_M = 0.01
"""With joint and end-effector columns, FK of each row's joints must lie within this distance (plus
the noise allowance) of its ee_* values."""

def check_ee_matches_fk(table: Table, simulator, q: np.ndarray, ee: np.ndarray, noise: NoiseModel) -> str | None:
    """With both spaces recorded, the model's FK of the joint values must land near ee_*: a file
    recorded at another link than ``--ee`` (or for another robot) is refused, not inferred on.
    Returns a warning when the mean of ee_* - FK (a systematic offset: a marker placed off the
    end effector, or a frame a little off) exceeds `OFFSET_WARN_M`, else None."""
    fk = simulator.forward_kinematics(torch.from_numpy(q)).to(torch.float64).numpy()
    dist = np.linalg.norm(fk - ee, axis=1)
    lever = float(np.linalg.norm(ee, axis=1).max())  # joint noise moves the end effector by ~ lever * sigma
    tol = EE_FK_TOL_M + K_SIGMA * (math.sqrt(3) * noise.sigma("cartesian")
                                   + math.sqrt(simulator.n_joints) * lever * noise.sigma("joint"))
    i = int(np.argmax(dist))
    if dist[i] > tol:
        raise ValueError(f"{table.where('ee_x', i)}: the model's end effector at this row's joint values is "
                         f"{dist[i] * 1000:.1f} mm from ee_x, ee_y, ee_z (tolerance {tol * 1000:.1f} mm): was the "
                         f"recording made at another link than the model's end effector (--ee), or is it noisier than "
                         f"the noise model says (--noise-joint-deg {noise.joint_deg:g}, --noise-ee-mm {noise.ee_mm:g})?")
    off = (ee - fk).mean(axis=0)
    if float(np.linalg.norm(off)) > OFFSET_WARN_M:
        return (f"{table.path}: ee_x, ee_y, ee_z lie a systematic {np.linalg.norm(off) * 1000:.1f} mm from the model's "
                f"end effector at the recorded joint values (mean offset ({off[0] * 1000:.1f}, {off[1] * 1000:.1f}, "
                f"{off[2] * 1000:.1f}) mm over {ee.shape[0]} samples): a marker off the end effector, or a frame a "
                f"little off?")
    return None


REACH_SAMPLES = 4096
REACH_MARGIN = 0.02
"""A goal farther from the base than (1 + REACH_MARGIN) x the farthest sampled end-effector
position (plus 1 cm) is reported as out of reach."""


def reach_radius(simulator) -> float:
    """The farthest distance from the base origin of the end effector over `REACH_SAMPLES`
    postures uniform in the model's range (fixed seed), and the start posture [m]."""
    b = simulator.bounds.to(torch.float64).numpy()
    q = np.random.default_rng(0).uniform(b[:, 0], b[:, 1], size=(REACH_SAMPLES, b.shape[0]))
    q = np.vstack([q, np.asarray(simulator.start, dtype=np.float64)[None]])
    fk = simulator.forward_kinematics(torch.from_numpy(q)).to(torch.float64).numpy()
    return float(np.linalg.norm(fk, axis=1).max())


def check_units(table: Table, radius: float, ee_units: str, frame: Frame | None = None) -> None:
    """Positions far beyond the model's reach: with a hint when they would fit in millimetres.
    ``ee_units`` "file": the file states its units (C3D), so no --ee-units hint; ``frame``: the
    transform applied to the positions, named in the message."""
    for c in (*EE_COLUMNS, *GOAL_COLUMNS):
        if c not in table.columns:
            continue
        a = np.abs(table.columns[c])
        i = int(np.argmax(a))
        if a[i] > UNITS_FACTOR * max(radius, 0.05):
            if ee_units == "file":
                hint = (" check the frame (--frame, --frame-from-markers) and the end-effector marker "
                        "(--ee-marker); the units come from the file's POINT:UNITS")
            elif ee_units == "m" and a[i] / 1000 <= 2 * radius:
                hint = " the positions look like millimetres: use --ee-units mm"
            else:
                hint = " check the units (--ee-units) and the frame (--frame)"
            after = f" after the transform of {frame.source}" if frame is not None else ""
            raise ValueError(f"{table.where(c, i)}{after}: {table.columns[c][i]:.6g} m is {a[i] / radius:.3g}x as far "
                             f"as the model reaches ({radius:.3g} m from the base);{hint}")


IK_ITERATIONS = 300
IK_DAMPING = 0.02
IK_MAX_STEP = 0.2
IK_PROGRESS_MIN = 200
"""From this many reaches on, the start-posture IK shows a progress bar and logs its estimated time."""

def _fk_numpy(simulator):
    """q (B, n) float64 -> end-effector positions (B, 3): the simulator's numba kernel when it has
    one (agrees with the reference FK to 1e-12 m, tests/test_simulators.py; thousands of times
    faster than pytorch_kinematics on a batch), else its reference `forward_kinematics`."""
    spec = getattr(simulator, "spec", None)
    if spec is not None and getattr(simulator, "backend", "torch") != "torch":
        from camo_sbi.simulators.kernel import kernel_fk

        return lambda q: kernel_fk(spec, np.ascontiguousarray(q, dtype=np.float64))
    return lambda q: simulator.forward_kinematics(torch.from_numpy(q)).to(torch.float64).numpy()


def estimate_starts(simulator, targets, initial, bounds=None) -> tuple[np.ndarray, np.ndarray]:
    """Start postures whose end effector is at ``targets`` (R, 3): damped least squares from
    ``initial`` (n,) within ``bounds`` (default: the model's range), with a null-space pull
    back towards ``initial`` (the posture nearest the model's start that reaches the point).
    Returns (postures (R, n), residual distances (R,) [m]).

    From `IK_PROGRESS_MIN` reaches on, a progress bar counts the iterations and the time of all
    `IK_ITERATIONS` (an upper bound: it stops when every reach is solved), measured on the first
    iteration, is logged (a warning above a minute)."""
    import time

    from tqdm import tqdm

    fk_numpy = _fk_numpy(simulator)
    b = (simulator.bounds if bounds is None else torch.as_tensor(bounds)).to(torch.float64).numpy()
    x_t = np.asarray(targets, dtype=np.float64).reshape(-1, 3)
    q0 = np.asarray(initial, dtype=np.float64)
    n, r = q0.shape[0], x_t.shape[0]
    q = np.broadcast_to(q0, (r, n)).copy()
    eps = 1e-6
    eye = np.eye(n)
    big = r >= IK_PROGRESS_MIN
    bar = tqdm(total=IK_ITERATIONS, desc=f"start postures (IK of {r} reaches)", unit="it", disable=not big,
               leave=False)
    fk_numpy(q[:1])  # loads (or compiles) the kernel before the timing
    t0 = time.perf_counter()
    for it in range(IK_ITERATIONS):
        if it == 1 and big:
            total = (time.perf_counter() - t0) * IK_ITERATIONS
            logging.getLogger(__name__).log(
                logging.WARNING if total > 60 else logging.INFO,
                "start postures: IK of %d reaches (their first end-effector samples), about %.3g s at most "
                "(%d iterations, measured on the first)", r, total, IK_ITERATIONS)
        bar.update(1)
        pert = np.concatenate([q[:, None, :], q[:, None, :] + eps * eye[None]], axis=1)  # (r, n+1, n)
        fk = fk_numpy(pert.reshape(-1, n)).reshape(r, n + 1, 3)
        x = fk[:, 0]
        e = x_t - x
        if float(np.linalg.norm(e, axis=1).max()) < 1e-6:
            break
        jac = np.transpose(fk[:, 1:] - x[:, None], (0, 2, 1)) / eps  # (r, 3, n)
        jjt = jac @ np.transpose(jac, (0, 2, 1)) + IK_DAMPING ** 2 * np.eye(3)
        dq = np.einsum("rjn,rj->rn", jac, np.linalg.solve(jjt, e[..., None])[..., 0])
        pinv = np.transpose(jac, (0, 2, 1)) @ np.linalg.inv(jjt)  # (r, n, 3)
        null = eye[None] - pinv @ jac
        dq += 0.1 * np.einsum("rnm,rm->rn", null, q0[None] - q)
        step = np.abs(dq).max(axis=1, keepdims=True)
        dq *= np.minimum(1.0, IK_MAX_STEP / np.maximum(step, 1e-12))
        q = np.clip(q + dq, b[:, 0], b[:, 1])
    bar.close()
    return q, np.linalg.norm(x_t - fk_numpy(q), axis=1)


BODY_SCALE_RANGE = (0.85, 1.15)
BODY_SCALE_BOOTSTRAP = 200
BODY_SCALE_WARN = 0.01
"""A body more than 1% larger or smaller than the model (its 90% interval excluding 1) is warned."""


def estimate_body_scale(simulator, q: np.ndarray, ee: np.ndarray, reaches) -> tuple[float, float, float]:
    """The segment-length scale s of a recorded body: least squares of ``ee`` on s * FK(q) (every
    segment s times as long moves the end effector to exactly s * FK(q) in the base frame,
    `KinematicSimulator.scaled`), with a 90% interval from a bootstrap over the reaches (fixed
    seed). Returns (s, lower, upper)."""
    fk = simulator.forward_kinematics(torch.from_numpy(q)).to(torch.float64).numpy()
    num = np.array([float((ee[i] * fk[i]).sum()) for i in reaches])
    den = np.array([float((fk[i] * fk[i]).sum()) for i in reaches])
    s = float(num.sum() / den.sum())
    rng = np.random.default_rng(0)
    boot = []
    for _ in range(BODY_SCALE_BOOTSTRAP):
        k = rng.integers(0, len(reaches), len(reaches))
        boot.append(num[k].sum() / den[k].sum())
    lo, hi = np.quantile(boot, [0.05, 0.95])
    return s, float(lo), float(hi)


def hint_body_scale(table: Table, simulator, q, ee, reaches, noise) -> None:
    """A recording that does not fit the model but fits a body of another size: say so."""
    try:
        check_ee_matches_fk(table, simulator, q, ee, noise)
    except ValueError as exc:
        s, _, _ = estimate_body_scale(simulator, q, ee, reaches)
        if abs(s - 1) > 0.01 and BODY_SCALE_RANGE[0] <= s <= BODY_SCALE_RANGE[1] and hasattr(simulator, "scaled"):
            try:
                check_ee_matches_fk(table, simulator.scaled(s), q, ee, noise)
            except ValueError:
                raise exc from None
            raise ValueError(f"{exc} The recording fits a body {s:.3f} times the model's size: use --body-scale "
                             f"free") from None
        raise
