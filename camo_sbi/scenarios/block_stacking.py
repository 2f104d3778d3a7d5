"""The human-robot block-stacking scene of the paper (section V-B), on its own pybullet client.

Why one module of ~800 lines: it is the only module importing pybullet (one adapter per
third-party library); the scene, its reachability test, the collision check and the renderer
all hold the same pybullet client and body ids.

A person with limited mobility stands at a table with 4 coloured blocks; the goal is a
tower in a random order. The person picks a block if they can reach it *and* carry it
to the tower; the robot (a floating gripper) takes the others. This is the only module
outside the tests that imports pybullet, and every pybullet call names this scene's
client (``physicsClientId``), so any number of scenes live side by side.

Frames
------
World: z up, origin on the floor under the table centre, x pointing away from the
person (the table's depth), y across the table. The human model's base frame (floor
under the pelvis, x forward, y to the person's left) is placed at ``base_position``
with yaw ``base_yaw``; `BlockStackingScene.world_to_base` maps world points into it,
and every goal handed to the simulator is expressed in the base frame.

Reachability (the ground truth, and every prediction)
-----------------------------------------------------
For limits theta, block b is the person's if the batched controller (the simulator)

1. reaches b's grasp point (top-face centre + ``grasp_offset`` up) from the start
   posture within the controller tolerance,
2. reaches the tower slot of b (the top of b once placed at its position in the stacking
   order, + ``grasp_offset``) from the grasp posture of step 1, and
3. neither reach brings the right arm (upper arm, forearm, hand) into the table:
   the human is set along each trajectory with ``resetJointState`` and a step collides
   if ``getClosestPoints`` between an arm link and the table is below ``collision_margin``
   (the hand is allowed ``hand_penetration`` of overlap: a grasp puts the fingers on the
   tabletop, and the hand's single box is longer than a grasping hand). Blocks are not
   obstacles (the hand touching its block is the grasp).

Only positive examples are observed: in a training trial the person takes, in stacking
order, the blocks they can; each pick is one `Observation`: by default the reach to the
block (start posture -> grasp point); with ``observe="carry"`` the carry to the tower (grasp
posture -> tower slot), which is what the authors' code observes.
"""

from __future__ import annotations

import math
import os
import tempfile
from dataclasses import dataclass

import numpy as np
import torch

from camo_sbi._validation import (
    as_tensor,
    check_finite,
    check_positive_float,
    check_positive_int,
    check_theta,
    numpy_generator,
)
from camo_sbi.simulators.base import Trajectories
from camo_sbi.task import Observation, contain


def _import_pybullet():
    """pybullet, imported with file descriptor 2 on /dev/null: when first imported it writes
    ``pybullet build time: ...`` to stderr from C, which would land in every command's output."""
    import sys

    if "pybullet" in sys.modules:
        return sys.modules["pybullet"]
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
            try:
                import pybullet
            finally:
                os.dup2(saved, 2)
    finally:
        os.close(saved)
    return pybullet


p = _import_pybullet()

__all__ = [
    "ARM_LINKS",
    "COLOURS",
    "PERSON",
    "ROBOT",
    "OBSERVED_MOTIONS",
    "AllocationMetrics",
    "BlockStackingScene",
    "Reachability",
    "SceneConfig",
    "Trial",
    "allocation_metrics",
]

COLOURS: tuple[str, ...] = ("red", "green", "yellow", "blue")
"""Block colours; every per-block array of this module is in this order."""

PERSON, ROBOT = "person", "robot"

OBSERVED_MOTIONS = ("reach", "carry")
"""What the observer sees of a pick: the reach to the block (default) or the carry to the tower
(the authors' code)."""

ARM_LINKS: tuple[str, ...] = ("right_upper_arm", "right_forearm", "right_hand")
"""Links of the human model checked against the table (the torso and the rigid, hanging
left arm are not: a person may lean on the table edge)."""

HAND_LINK = "right_hand"

_RGBA = {
    "red": (0.86, 0.12, 0.12, 1.0),
    "green": (0.10, 0.68, 0.22, 1.0),
    "yellow": (0.96, 0.84, 0.10, 1.0),
    "blue": (0.12, 0.30, 0.90, 1.0),
}
_MARKER_RGBA = {PERSON: (1.0, 1.0, 1.0, 1.0), ROBOT: (0.05, 0.05, 0.05, 1.0)}


# --------------------------------------------------------------------------------------
# Configuration and trials
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SceneConfig:
    """Geometry of the scene (metres, radians).

    Attributes:
        table_height: tabletop height above the floor.
        table_depth: table size along world x (away from the person).
        table_width: table size along world y.
        standoff: horizontal distance from the person's pelvis (base origin) to the
            table's near edge.
        person_lateral: world y of the person's pelvis (negative: the person stands to
            the table's right, so the right arm is nearer the centre).
        base_yaw: yaw of the human base frame in the world (0: facing the table).
        block_size: edge of the cubic blocks.
        grasp_offset: height of the hand's target above the block's top-face centre
            (the hand's end effector is the centre of a power grasp).
        block_region: ((x_near, x_far), (y_min, y_max)) of block centres, as distances
            from the table's near edge (x) and the table's centre line (y).
        tower_region: same, for the tower location.
        min_gap: minimum free space between two blocks' (or a block's and the tower's)
            bounding circles.
        collision_margin: a step collides if an arm link comes closer than this to the table.
        hand_penetration: overlap of the hand with the table tolerated before a collision.
        collision_stride: check every k-th trajectory step (and always the last one).
    """

    table_height: float = 0.75
    table_depth: float = 1.4
    table_width: float = 2.2
    standoff: float = 0.3
    person_lateral: float = 0.4
    base_yaw: float = 0.0
    block_size: float = 0.05
    grasp_offset: float = 0.02
    block_region: tuple[tuple[float, float], tuple[float, float]] = ((0.05, 1.35), (-1.05, 1.05))
    tower_region: tuple[tuple[float, float], tuple[float, float]] = ((0.10, 0.45), (-0.25, 0.35))
    min_gap: float = 0.03
    collision_margin: float = 0.005
    hand_penetration: float = 0.045
    collision_stride: int = 2

    def __post_init__(self):
        for name in ("table_height", "table_depth", "table_width", "block_size"):
            check_positive_float(getattr(self, name), name)
        for name in ("standoff", "grasp_offset", "min_gap", "hand_penetration"):
            check_positive_float(getattr(self, name), name, allow_zero=True)
        for name in ("person_lateral", "base_yaw", "collision_margin"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"{name}: expected a finite number, got {v!r}")
        check_positive_int(self.collision_stride, "collision_stride")
        for name in ("block_region", "tower_region"):
            (x0, x1), (y0, y1) = getattr(self, name)
            half = 0.5 * self.block_size
            if not (half <= x0 <= x1 <= self.table_depth - half
                    and -0.5 * self.table_width + half <= y0 <= y1 <= 0.5 * self.table_width - half):
                raise ValueError(f"{name}: {getattr(self, name)!r} does not fit on the tabletop")


@dataclass(frozen=True)
class Trial:
    """One block-stacking episode.

    Attributes:
        positions: (4, 3) world positions of the block centres, in `COLOURS` order.
        order: the colours from the bottom of the tower to its top.
        tower: (2,) world xy of the tower.
    """

    positions: np.ndarray
    order: tuple[str, ...]
    tower: np.ndarray

    def __post_init__(self):
        pos = np.asarray(self.positions, dtype=np.float64)
        if pos.shape != (len(COLOURS), 3) or not np.all(np.isfinite(pos)):
            raise ValueError(f"positions: expected finite shape ({len(COLOURS)}, 3), got {pos.shape}")
        if sorted(self.order) != sorted(COLOURS):
            raise ValueError(f"order: expected a permutation of {COLOURS}, got {self.order!r}")
        tower = np.asarray(self.tower, dtype=np.float64)
        if tower.shape != (2,) or not np.all(np.isfinite(tower)):
            raise ValueError(f"tower: expected finite shape (2,), got {tower.shape}")
        object.__setattr__(self, "positions", pos)
        object.__setattr__(self, "order", tuple(self.order))
        object.__setattr__(self, "tower", tower)


@dataclass(frozen=True)
class Reachability:
    """Outcome of the reachability test for M (theta, block) pairs.

    Attributes:
        reached_block: (M,) the controller reached the grasp point.
        reached_tower: (M,) it then reached the tower slot (False where step 1 failed).
        collision: (M,) an arm link hit the table during either reach (checked only
            where both reaches succeeded; False elsewhere).
        reachable: (M,) reached_block & reached_tower & ~collision: the person's task.
        to_block: the M reaches from the start posture to the grasp points.
        to_tower: the M reaches from the grasp postures to the tower slots.
    """

    reached_block: np.ndarray
    reached_tower: np.ndarray
    collision: np.ndarray
    reachable: np.ndarray
    to_block: Trajectories
    to_tower: Trajectories


# --------------------------------------------------------------------------------------
# Allocation metrics
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class AllocationMetrics:
    """Confusion counts and scores with "person" (True) as the positive class.

    Zero denominators: precision with no "person" prediction is 1 if the truth has no
    "person" block either (nothing claimed, nothing missed) and 0 otherwise; recall with
    no "person" block in the truth is 1 if nothing was predicted "person" and 0 otherwise;
    F1 = 2 tp / (2 tp + fp + fn) is 1 when both are empty. The majority baseline always
    predicts the more frequent true class (ties: robot).
    """

    tp: int
    fp: int
    fn: int
    tn: int
    precision: float
    recall: float
    f1: float
    accuracy: float
    majority_label: str
    majority_precision: float
    majority_recall: float
    majority_f1: float
    majority_accuracy: float

    def as_dict(self) -> dict[str, float | int | str]:
        return dict(self.__dict__)


def _scores(tp: int, fp: int, fn: int, tn: int) -> tuple[float, float, float, float]:
    precision = tp / (tp + fp) if tp + fp else float(fn == 0)
    recall = tp / (tp + fn) if tp + fn else float(fp == 0)
    f1 = 2 * tp / (2 * tp + fp + fn) if 2 * tp + fp + fn else 1.0
    total = tp + fp + fn + tn
    accuracy = (tp + tn) / total if total else 1.0
    return precision, recall, f1, accuracy


def _as_bool_labels(y, name: str) -> np.ndarray:
    a = np.asarray(y)
    if a.dtype.kind in "US":
        bad = sorted(set(a.ravel().tolist()) - {PERSON, ROBOT})
        if bad:
            raise ValueError(f"{name}: labels must be {PERSON!r}/{ROBOT!r} or booleans, got {bad}")
        return (a == PERSON).ravel()
    if a.dtype == bool:
        return a.ravel()
    if a.dtype.kind in "iu" and np.isin(a, (0, 1)).all():
        return a.astype(bool).ravel()
    raise TypeError(f"{name}: expected booleans (True = person), 0/1 or 'person'/'robot' labels")


def allocation_metrics(y_true, y_pred) -> AllocationMetrics:
    """Precision, recall and F1 of an allocation ("person" = positive class).

    Args:
        y_true, y_pred: same-shape arrays of booleans (True = person's task), 0/1, or
            "person"/"robot" strings.
    """
    t = _as_bool_labels(y_true, "y_true")
    q = _as_bool_labels(y_pred, "y_pred")
    if t.shape != q.shape:
        raise ValueError(f"y_pred: shape {q.shape} differs from y_true's {t.shape}")
    tp, fp = int(np.sum(t & q)), int(np.sum(~t & q))
    fn, tn = int(np.sum(t & ~q)), int(np.sum(~t & ~q))
    precision, recall, f1, accuracy = _scores(tp, fp, fn, tn)
    majority_person = int(t.sum()) > t.size - int(t.sum())
    if majority_person:
        mp, mr, mf, ma = _scores(tp + fn, fp + tn, 0, 0)
    else:
        mp, mr, mf, ma = _scores(0, 0, tp + fn, fp + tn)
    return AllocationMetrics(tp, fp, fn, tn, precision, recall, f1, accuracy,
                             PERSON if majority_person else ROBOT, mp, mr, mf, ma)


# --------------------------------------------------------------------------------------
# The scene
# --------------------------------------------------------------------------------------


def _yaw_matrix(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class BlockStackingScene:
    """Table, person, 4 blocks and a floating gripper on a private pybullet DIRECT client.

    Args:
        simulator: the human `KinematicSimulator` (`camo_sbi.simulators.human`); its
            ``urdf`` is loaded into the scene and its ``simulate`` drives every reach.
        config: `SceneConfig` (geometry).
        seed: int or numpy Generator for the first trial's layout.

    Use as a context manager or call `close`; closing one scene leaves the others intact.
    """

    def __init__(self, simulator, *, config: SceneConfig | None = None, seed=0):
        config = SceneConfig() if config is None else config
        if not isinstance(config, SceneConfig):
            raise TypeError(f"config: expected SceneConfig, got {type(config).__name__}")
        for attr in ("urdf", "simulate", "start", "joint_names", "n_joints"):
            if not hasattr(simulator, attr):
                raise TypeError(f"simulator: missing attribute {attr!r}")
        self.simulator = simulator
        self.config = config
        self._closed = True
        self.client = p.connect(p.DIRECT)
        if self.client < 0:
            raise RuntimeError("pybullet: could not open a DIRECT client")
        self._closed = False
        try:
            self._build(numpy_generator(seed))
        except BaseException:
            self.close()
            raise

    # --- construction ---------------------------------------------------------------

    def _build(self, rng: np.random.Generator) -> None:
        cfg, cid = self.config, self.client
        # table: one solid box from the floor to the tabletop
        half = [0.5 * cfg.table_depth, 0.5 * cfg.table_width, 0.5 * cfg.table_height]
        col = p.createCollisionShape(p.GEOM_BOX, halfExtents=half, physicsClientId=cid)
        vis = p.createVisualShape(p.GEOM_BOX, halfExtents=half, rgbaColor=(0.62, 0.45, 0.30, 1.0),
                                  physicsClientId=cid)
        self.table_id = p.createMultiBody(0.0, col, vis, basePosition=[0.0, 0.0, half[2]],
                                          physicsClientId=cid)
        floor = p.createVisualShape(p.GEOM_BOX, halfExtents=[2.0, 2.0, 0.001],
                                    rgbaColor=(0.85, 0.85, 0.82, 1.0), physicsClientId=cid)
        self.floor_id = p.createMultiBody(0.0, -1, floor, basePosition=[0.0, 0.0, -0.001],
                                          physicsClientId=cid)
        # the person, from the simulator's URDF text
        self.base_position = np.array([-0.5 * cfg.table_depth - cfg.standoff, cfg.person_lateral, 0.0])
        self.base_rotation = _yaw_matrix(cfg.base_yaw)
        fd, path = tempfile.mkstemp(suffix=".urdf", prefix="camo_human_")
        try:
            with os.fdopen(fd, "w") as fh:
                fh.write(self.simulator.urdf)
            self.human_id = p.loadURDF(
                path, basePosition=self.base_position.tolist(),
                baseOrientation=p.getQuaternionFromEuler([0.0, 0.0, cfg.base_yaw]),
                useFixedBase=True, physicsClientId=cid,
            )
        finally:
            os.unlink(path)
        names = {}
        for j in range(p.getNumJoints(self.human_id, physicsClientId=cid)):
            info = p.getJointInfo(self.human_id, j, physicsClientId=cid)
            names[info[1].decode()] = j
            names.setdefault("link:" + info[12].decode(), j)
        missing = [n for n in self.simulator.joint_names if n not in names]
        if missing:
            raise ValueError(f"simulator: joints {missing} are not in the loaded URDF")
        self.joint_indices = tuple(names[n] for n in self.simulator.joint_names)
        missing = [n for n in ARM_LINKS if "link:" + n not in names]
        if missing:
            raise ValueError(f"simulator: arm links {missing} are not in the loaded URDF")
        self.arm_links = tuple(names["link:" + n] for n in ARM_LINKS)
        self.hand_link = names["link:" + HAND_LINK]
        # blocks, addressed by their own body ids
        s = 0.5 * cfg.block_size
        self.block_ids: dict[str, int] = {}
        bcol = p.createCollisionShape(p.GEOM_BOX, halfExtents=[s, s, s], physicsClientId=cid)
        for k, colour in enumerate(COLOURS):
            bvis = p.createVisualShape(p.GEOM_BOX, halfExtents=[s, s, s], rgbaColor=_RGBA[colour],
                                       physicsClientId=cid)
            self.block_ids[colour] = p.createMultiBody(
                0.1, bcol, bvis, basePosition=[0.0, 0.2 * k, cfg.table_height + s], physicsClientId=cid)
        self.gripper_id = self._make_gripper()
        self.gripper_home = np.array([0.5 * cfg.table_depth + 0.15, 0.0, cfg.table_height + 0.35])
        p.resetBasePositionAndOrientation(self.gripper_id, self.gripper_home.tolist(), [0, 0, 0, 1],
                                          physicsClientId=cid)
        self.tower = np.zeros(2)
        self.order: tuple[str, ...] = COLOURS
        self.set_posture(self.simulator.start)
        if self._collides_now():
            raise ValueError("config: the person's start posture already touches the table; increase standoff")
        self.new_trial(rng)

    def _make_gripper(self) -> int:
        """A floating two-finger gripper: a palm box with two finger boxes (fixed links)."""
        cid = self.client
        grey = (0.55, 0.57, 0.60, 1.0)
        palm = [0.02, 0.06, 0.012]
        finger = [0.01, 0.008, 0.035]
        pc = p.createCollisionShape(p.GEOM_BOX, halfExtents=palm, physicsClientId=cid)
        pv = p.createVisualShape(p.GEOM_BOX, halfExtents=palm, rgbaColor=grey, physicsClientId=cid)
        fc = p.createCollisionShape(p.GEOM_BOX, halfExtents=finger, physicsClientId=cid)
        fv = p.createVisualShape(p.GEOM_BOX, halfExtents=finger, rgbaColor=(0.3, 0.3, 0.33, 1.0),
                                 physicsClientId=cid)
        dz = -(palm[2] + finger[2])
        return p.createMultiBody(
            0.5, pc, pv, basePosition=[0, 0, 1.5],
            linkMasses=[0.05, 0.05], linkCollisionShapeIndices=[fc, fc], linkVisualShapeIndices=[fv, fv],
            linkPositions=[[0, 0.045, dz], [0, -0.045, dz]], linkOrientations=[[0, 0, 0, 1]] * 2,
            linkInertialFramePositions=[[0, 0, 0]] * 2, linkInertialFrameOrientations=[[0, 0, 0, 1]] * 2,
            linkParentIndices=[0, 0], linkJointTypes=[p.JOINT_FIXED] * 2, linkJointAxis=[[0, 0, 1]] * 2,
            physicsClientId=cid,
        )

    # --- lifetime -------------------------------------------------------------------

    @property
    def closed(self) -> bool:
        return self._closed

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError("scene: this BlockStackingScene is closed")

    def close(self) -> None:
        """Disconnect this scene's client (idempotent); other scenes are untouched."""
        if not self._closed:
            self._closed = True
            try:
                p.disconnect(physicsClientId=self.client)
            except p.error:  # pragma: no cover - already gone
                pass

    def __enter__(self) -> BlockStackingScene:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self):  # pragma: no cover - best effort
        try:
            self.close()
        except Exception:
            pass

    # --- frames ---------------------------------------------------------------------

    def world_to_base(self, points) -> np.ndarray:
        """(..., 3) world points -> the human base frame."""
        pts = np.asarray(points, dtype=np.float64)
        return (pts - self.base_position) @ self.base_rotation

    def base_to_world(self, points) -> np.ndarray:
        """(..., 3) human-base-frame points -> world."""
        pts = np.asarray(points, dtype=np.float64)
        return pts @ self.base_rotation.T + self.base_position

    def _table_to_world_xy(self, u: float, v: float) -> tuple[float, float]:
        """(distance from the near edge, offset from the centre line) -> world xy."""
        return u - 0.5 * self.config.table_depth, v

    # --- trials ---------------------------------------------------------------------

    def sample_trial(self, seed) -> Trial:
        """A random layout: non-overlapping blocks, a tower spot and a stacking order."""
        cfg = self.config
        rng = numpy_generator(seed)
        radius = 0.5 * math.sqrt(2.0) * cfg.block_size  # bounding circle of a block
        clearance = 2 * radius + cfg.min_gap
        (tx0, tx1), (ty0, ty1) = cfg.tower_region
        (bx0, bx1), (by0, by1) = cfg.block_region
        for _layout in range(1000):
            tower = np.array(self._table_to_world_xy(rng.uniform(tx0, tx1), rng.uniform(ty0, ty1)))
            xy: list[np.ndarray] = []
            for _attempt in range(200 * len(COLOURS)):
                c = np.array(self._table_to_world_xy(rng.uniform(bx0, bx1), rng.uniform(by0, by1)))
                if all(np.linalg.norm(c - o) >= clearance for o in [tower, *xy]):
                    xy.append(c)
                    if len(xy) == len(COLOURS):
                        break
            if len(xy) == len(COLOURS):
                break
        else:  # pragma: no cover - only with absurd regions
            raise ValueError("config: block_region is too small to place 4 non-overlapping blocks")
        z = cfg.table_height + 0.5 * cfg.block_size
        positions = np.array([[x, y, z] for x, y in xy])
        order = tuple(COLOURS[i] for i in rng.permutation(len(COLOURS)))
        return Trial(positions, order, tower)

    def set_trial(self, trial: Trial) -> None:
        """Move the block bodies to ``trial``'s layout and adopt its order and tower."""
        self._check_open()
        if not isinstance(trial, Trial):
            raise TypeError(f"trial: expected Trial, got {type(trial).__name__}")
        for colour, pos in zip(COLOURS, trial.positions, strict=True):
            p.resetBasePositionAndOrientation(self.block_ids[colour], pos.tolist(), [0, 0, 0, 1],
                                              physicsClientId=self.client)
        self.order, self.tower = trial.order, trial.tower.copy()

    def new_trial(self, seed) -> Trial:
        """Sample a trial with ``seed`` (int or Generator) and set it."""
        trial = self.sample_trial(seed)
        self.set_trial(trial)
        return trial

    def current_trial(self) -> Trial:
        """The current layout, block positions read from the block bodies."""
        pos = self.block_positions()
        return Trial(np.stack([pos[c] for c in COLOURS]), self.order, self.tower)

    # --- goals ----------------------------------------------------------------------

    def block_positions(self) -> dict[str, np.ndarray]:
        """Colour -> (3,) world position of the block body (read from pybullet)."""
        self._check_open()
        return {c: np.array(p.getBasePositionAndOrientation(b, physicsClientId=self.client)[0])
                for c, b in self.block_ids.items()}

    def grasp_points(self) -> np.ndarray:
        """(4, 3) world grasp points (top-face centre + grasp_offset), `COLOURS` order."""
        self._check_open()
        half = 0.5 * self.config.block_size
        out = []
        for colour in COLOURS:
            pos, orn = p.getBasePositionAndOrientation(self.block_ids[colour], physicsClientId=self.client)
            rot = np.array(p.getMatrixFromQuaternion(orn)).reshape(3, 3)
            top = np.asarray(pos) + rot @ np.array([0.0, 0.0, half])
            out.append(top + np.array([0.0, 0.0, self.config.grasp_offset]))
        return np.stack(out)

    def tower_points(self) -> np.ndarray:
        """(4, 3) world hand targets when placing each block on the tower, `COLOURS` order."""
        cfg = self.config
        out = []
        for colour in COLOURS:
            slot = self.order.index(colour)
            z = cfg.table_height + (slot + 1) * cfg.block_size + cfg.grasp_offset
            out.append([self.tower[0], self.tower[1], z])
        return np.array(out)

    def goals(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Grasp and tower goals (4, 3) each, float64, in the human base frame."""
        return (torch.from_numpy(self.world_to_base(self.grasp_points())),
                torch.from_numpy(self.world_to_base(self.tower_points())))

    def trial_goals(self, trials) -> tuple[torch.Tensor, torch.Tensor]:
        """Grasp and tower goals (M, 4, 3) of several trials (each set in turn; base frame)."""
        grasps, towers = [], []
        for trial in trials:
            self.set_trial(trial)
            g, t = self.goals()
            grasps.append(g)
            towers.append(t)
        return torch.stack(grasps), torch.stack(towers)

    # --- collisions -----------------------------------------------------------------

    def set_posture(self, q) -> None:
        """Set the person's joints to ``q`` (n,) (resetJointState on this scene's client)."""
        self._check_open()
        q = np.asarray(q, dtype=np.float64).reshape(-1)
        if q.shape != (len(self.joint_indices),):
            raise ValueError(f"q: expected {len(self.joint_indices)} joint values, got {q.shape[0]}")
        for j, v in zip(self.joint_indices, q, strict=True):
            p.resetJointState(self.human_id, j, float(v), physicsClientId=self.client)

    def _collides_now(self) -> bool:
        cfg, cid = self.config, self.client
        reach = max(cfg.collision_margin, 0.0)
        for link in self.arm_links:
            pts = p.getClosestPoints(self.human_id, self.table_id, reach, linkIndexA=link, physicsClientId=cid)
            limit = -cfg.hand_penetration if link == self.hand_link else cfg.collision_margin
            if any(pt[8] < limit for pt in pts):
                return True
        return False

    def collides(self, q) -> bool:
        """True if the arm hits the table anywhere along the joint trajectory ``q`` (L, n)."""
        q = np.asarray(q, dtype=np.float64)
        if q.ndim != 2 or q.shape[1] != len(self.joint_indices):
            raise ValueError(f"q: expected shape (L, {len(self.joint_indices)}), got {q.shape}")
        steps = list(range(0, q.shape[0], self.config.collision_stride))
        if steps[-1] != q.shape[0] - 1:
            steps.append(q.shape[0] - 1)
        try:
            for t in steps:
                self.set_posture(q[t])
                if self._collides_now():
                    return True
            return False
        finally:
            self.set_posture(self.simulator.start)

    # --- reachability ---------------------------------------------------------------

    def _limits_for(self, theta, m: int) -> torch.Tensor:
        theta = as_tensor(theta, "theta", dtype=torch.float64)
        theta = check_theta(theta, self.simulator.n_joints)
        if theta.shape[0] == 1:
            theta = theta.expand(m, -1)
        elif theta.shape[0] != m:
            raise ValueError(f"theta: expected 1 or {m} limit vectors, got {theta.shape[0]}")
        return theta

    def reachability(self, theta, grasp_goals, tower_goals, *, check_collisions: bool = True) -> Reachability:
        """The reachability test (module docstring) for M blocks at once.

        Args:
            theta: (2n,) limits shared by all blocks, or (M, 2n) one per block.
            grasp_goals, tower_goals: (M, 3) base-frame goals (see `goals`, `trial_goals`).
            check_collisions: run the table check (on the reaches that succeeded only).
        """
        self._check_open()
        sim = self.simulator
        grasp = as_tensor(grasp_goals, "grasp_goals", dtype=torch.float64).reshape(-1, 3)
        tower = as_tensor(tower_goals, "tower_goals", dtype=torch.float64).reshape(-1, 3)
        if grasp.shape != tower.shape:
            raise ValueError(f"tower_goals: expected shape {tuple(grasp.shape)}, got {tuple(tower.shape)}")
        check_finite(grasp, "grasp_goals")
        check_finite(tower, "tower_goals")
        m = grasp.shape[0]
        theta = self._limits_for(theta, m)
        start = as_tensor(sim.start, "simulator.start", dtype=torch.float64).expand(m, -1)
        first = sim.simulate(contain(theta, start), grasp, start).to(dtype=torch.float64)
        last = first.length.long() - 1
        grasp_q = first.q[torch.arange(m), last]
        second = sim.simulate(contain(theta, grasp_q), tower, grasp_q).to(dtype=torch.float64)
        r1 = first.reached.cpu().numpy().astype(bool)
        r2 = r1 & second.reached.cpu().numpy().astype(bool)
        coll = np.zeros(m, dtype=bool)
        if check_collisions:
            for b in np.flatnonzero(r2):
                coll[b] = (self.collides(first.trimmed(int(b)).cpu().numpy())
                           or self.collides(second.trimmed(int(b)).cpu().numpy()))
        return Reachability(r1, r2, coll, r2 & ~coll, first, second)

    def labels(self, theta, trials=None) -> np.ndarray:
        """Person's tasks (True) for ``trials`` (M, 4) or, with None, the current trial (4,)."""
        if trials is None:
            grasp, tower = self.goals()
            return self.reachability(theta, grasp, tower).reachable
        trials = list(trials)
        current = self.current_trial()
        try:
            grasp, tower = self.trial_goals(trials)
        finally:
            self.set_trial(current)
        return self.reachability(theta, grasp.reshape(-1, 3), tower.reshape(-1, 3)).reachable.reshape(
            len(trials), len(COLOURS))

    def observations(self, theta, *, observe: str = "reach") -> tuple[tuple[str, ...], tuple[Observation, ...]]:
        """The person (true limits ``theta``) acting on the current trial.

        Returns the colours the person picks, in stacking order, and one `Observation` per
        pick: with ``observe="reach"`` (the default) the reach from the start posture to the
        block's grasp point; with ``observe="carry"`` (what the authors' code observes) the
        carry from the grasp posture to the block's tower slot, whose start is the grasp
        posture.
        """
        if observe not in OBSERVED_MOTIONS:
            raise ValueError(f"observe: expected one of {OBSERVED_MOTIONS}, got {observe!r}")
        grasp, tower = self.goals()
        res = self.reachability(theta, grasp, tower)
        start = as_tensor(self.simulator.start, "simulator.start", dtype=torch.float64)
        picked, obs = [], []
        for colour in self.order:
            k = COLOURS.index(colour)
            if not res.reachable[k]:
                continue
            picked.append(colour)
            if observe == "reach":
                obs.append(Observation(start.clone(), grasp[k].clone(), res.to_block.trimmed(k, "joint").clone(),
                                       res.to_block.trimmed(k, "cartesian").clone()))
            else:
                q = res.to_tower.trimmed(k, "joint").clone()
                obs.append(Observation(q[0].clone(), tower[k].clone(), q, res.to_tower.trimmed(k, "cartesian").clone()))
        return tuple(picked), tuple(obs)

    # --- rendering ------------------------------------------------------------------

    def reachable_cells(self, theta, *, resolution: float = 0.05) -> np.ndarray:
        """(K, 2) world xy of tabletop cells whose grasp point the person reaches (no carry)."""
        cfg = self.config
        us = np.arange(0.5 * resolution, cfg.table_depth, resolution)
        vs = np.arange(-0.5 * cfg.table_width + 0.5 * resolution, 0.5 * cfg.table_width, resolution)
        uu, vv = np.meshgrid(us, vs, indexing="ij")
        xy = np.stack([uu.ravel() - 0.5 * cfg.table_depth, vv.ravel()], axis=1)
        z = cfg.table_height + cfg.block_size + cfg.grasp_offset
        goals = self.world_to_base(np.column_stack([xy, np.full(len(xy), z)]))
        theta_t = self._limits_for(theta, len(xy))
        sim = self.simulator
        start = as_tensor(sim.start, "simulator.start", dtype=torch.float64).expand(len(xy), -1)
        traj = sim.simulate(contain(theta_t, start), torch.from_numpy(goals), start).to(dtype=torch.float64)
        ok = traj.reached.cpu().numpy().astype(bool)
        for b in np.flatnonzero(ok):
            ok[b] = not self.collides(traj.trimmed(int(b)).cpu().numpy())
        return xy[ok]

    def render(self, out_png, assignment=None, *, region_theta=None, posture=None, width: int = 800,
               height: int = 600, title: str | None = None, camera=None):
        """Render the scene headless (TinyRenderer) to ``out_png``; returns the path.

        Args:
            assignment: optional colour -> "person"/"robot" (or a (4,) bool array, True =
                person): a white (person) or black (robot) marker floats above each block,
                and the gripper hovers over the first robot block of the stacking order.
            region_theta: optional limits (2n,): tabletop cells whose grasp point the
                person reaches with them are tinted green (the reachable region).
            posture: optional (n,) joint posture of the person (default: start).
            camera: optional dict for computeViewMatrixFromYawPitchRoll
                (target, distance, yaw, pitch).
        """
        from matplotlib.figure import Figure
        from matplotlib.patches import Patch

        self._check_open()
        width = check_positive_int(width, "width")
        height = check_positive_int(height, "height")
        cid, cfg = self.client, self.config
        if assignment is not None and not isinstance(assignment, dict):
            flags = _as_bool_labels(assignment, "assignment")
            if flags.shape != (len(COLOURS),):
                raise ValueError(f"assignment: expected {len(COLOURS)} labels, got {flags.shape}")
            assignment = {c: PERSON if f else ROBOT for c, f in zip(COLOURS, flags, strict=True)}
        if assignment is not None:
            bad = {k: v for k, v in assignment.items() if k not in COLOURS or v not in (PERSON, ROBOT)}
            if bad:
                raise ValueError(f"assignment: expected colour -> 'person'/'robot', got {bad}")
        temp: list[int] = []
        try:
            if region_theta is not None:
                cells = self.reachable_cells(region_theta)
                if len(cells):
                    vis = p.createVisualShape(p.GEOM_BOX, halfExtents=[0.025, 0.025, 0.001],
                                              rgbaColor=(0.45, 0.85, 0.45, 1.0), physicsClientId=cid)
                    z = cfg.table_height + 0.0015
                    temp.extend(p.createMultiBody(0.0, -1, vis, basePosition=[x, y, z], physicsClientId=cid)
                                for x, y in cells)
            positions = self.block_positions()
            if assignment is not None:
                for colour, who in assignment.items():
                    vis = p.createVisualShape(p.GEOM_SPHERE, radius=0.022, rgbaColor=_MARKER_RGBA[who],
                                              physicsClientId=cid)
                    pos = positions[colour] + np.array([0, 0, 0.5 * cfg.block_size + 0.05])
                    temp.append(p.createMultiBody(0.0, -1, vis, basePosition=pos.tolist(), physicsClientId=cid))
                robots = [c for c in self.order if assignment.get(c) == ROBOT]
                if robots:
                    hover = positions[robots[0]] + np.array([0, 0, 0.5 * cfg.block_size + 0.12])
                    p.resetBasePositionAndOrientation(self.gripper_id, hover.tolist(), [0, 0, 0, 1],
                                                      physicsClientId=cid)
            tower_vis = p.createVisualShape(p.GEOM_BOX, halfExtents=[0.045, 0.045, 0.002],
                                            rgbaColor=(0.2, 0.2, 0.2, 1.0), physicsClientId=cid)
            temp.append(p.createMultiBody(0.0, -1, tower_vis,
                                          basePosition=[self.tower[0], self.tower[1], cfg.table_height + 0.003],
                                          physicsClientId=cid))
            self.set_posture(self.simulator.start if posture is None else posture)
            cam = {"target": [-0.2, 0.0, 0.75], "distance": 2.9, "yaw": -20.0, "pitch": -42.0}
            cam.update(camera or {})
            view = p.computeViewMatrixFromYawPitchRoll(cam["target"], cam["distance"], cam["yaw"],
                                                       cam["pitch"], 0.0, 2, physicsClientId=cid)
            proj = p.computeProjectionMatrixFOV(50.0, width / height, 0.05, 10.0, physicsClientId=cid)
            img = p.getCameraImage(width, height, view, proj, renderer=p.ER_TINY_RENDERER,
                                   lightDirection=[-1.0, -0.5, 2.0], shadow=0, physicsClientId=cid)
            rgb = np.reshape(np.asarray(img[2], dtype=np.uint8), (height, width, 4))[:, :, :3]
        finally:
            for body in temp:
                p.removeBody(body, physicsClientId=cid)
            p.resetBasePositionAndOrientation(self.gripper_id, self.gripper_home.tolist(), [0, 0, 0, 1],
                                              physicsClientId=cid)
            self.set_posture(self.simulator.start)
        fig = Figure(figsize=(width / 100, height / 100 + 0.4), dpi=100)  # no pyplot: backend untouched
        ax = fig.subplots()
        ax.imshow(rgb)
        ax.set_axis_off()
        handles = []
        if assignment is not None:
            handles += [Patch(facecolor="white", edgecolor="k", label="marker: person"),
                        Patch(facecolor="black", edgecolor="k", label="marker: robot")]
        if region_theta is not None:
            handles.append(Patch(facecolor=(0.45, 0.85, 0.45), label="reachable (grasp)"))
        handles.append(Patch(facecolor=(0.2, 0.2, 0.2), label="tower"))
        ax.legend(handles=handles, loc="upper right", fontsize=8, framealpha=0.85)
        ax.set_title(title or "order (bottom->top): " + ", ".join(self.order), fontsize=9)
        fig.tight_layout()
        out = os.fspath(out_png)
        os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
        fig.savefig(out, format="png")
        return out

    def __repr__(self) -> str:
        state = "closed" if self._closed else f"client={self.client}"
        return f"BlockStackingScene({state}, blocks={self.block_ids})"

