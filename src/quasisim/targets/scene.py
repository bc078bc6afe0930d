"""The evaluation scene shared by every target simulator: hand on a floating base, object, finite table.

The table is a box from the floor (z = 0) up to ``support_height``. Its footprint is sized from the demo:
it covers the object's initial footprint with a margin and contains no human keypoint (of any frame)
that is below the table top, with a clearance. In GRAB clips the hand rises from below the table top
beside the table, so an infinite support plane would collide with it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from quasisim.assets.hand import HandModel
from quasisim.data.demo import Demo
from quasisim.rotations import np_quat_to_mat

if TYPE_CHECKING:
    from quasisim.assets.object import ObjectAsset


@dataclass(frozen=True)
class Table:
    """Axis-aligned box: x in [xmin, xmax], y in [ymin, ymax], z in [0, top] (m)."""

    xmin: float
    xmax: float
    ymin: float
    ymax: float
    top: float

    @property
    def center(self) -> np.ndarray:
        return np.array([(self.xmin + self.xmax) / 2, (self.ymin + self.ymax) / 2, self.top / 2])

    @property
    def half_size(self) -> np.ndarray:
        return np.array([(self.xmax - self.xmin) / 2, (self.ymax - self.ymin) / 2, self.top / 2])

    def contains_xy(self, xy: np.ndarray, pad: float = 0.0) -> np.ndarray:
        """(...,) whether points ``xy`` (..., 2) lie over the table top (grown by ``pad`` m)."""
        x, y = xy[..., 0], xy[..., 1]
        return (x > self.xmin - pad) & (x < self.xmax + pad) & (y > self.ymin - pad) & (y < self.ymax + pad)


@dataclass(frozen=True)
class PhysicsOptions:
    """Target-simulator settings (SI units). ``friction`` is the sliding coefficient on every contact."""

    mujoco_dt: float = 0.002
    pybullet_dt: float = 0.0005
    friction: float = 1.0
    gravity: float = 9.81


@dataclass(frozen=True, eq=False)
class Scene:
    """Everything a target needs to build the same world.

    Attributes:
        hand: parsed hand model.
        base_rot: (3, 3) fixed frame of the base hinges (see :mod:`quasisim.sim.kinematics`).
        obj: object asset (mesh, mass, inertia, convex parts).
        table: the support box.
        object_pos0, object_quat0: initial object pose (m; w x y z).
        fps: control frame rate (Hz).
        physics: simulator settings.
        notes: remarks made while building the scene (shown in reports).
    """

    hand: HandModel
    base_rot: np.ndarray
    obj: ObjectAsset
    table: Table
    object_pos0: np.ndarray
    object_quat0: np.ndarray
    fps: float
    physics: PhysicsOptions = PhysicsOptions()
    notes: tuple[str, ...] = field(default=())


def size_table(
    demo: Demo,
    obj: ObjectAsset,
    margin: float = 0.05,
    clearance: float = 0.04,
    max_half: float = 0.4,
    below_tol: float = 0.01,
) -> tuple[Table, tuple[str, ...]]:
    """Size the table footprint from the demo (see module docstring).

    Args:
        margin: the footprint covers the object's initial footprint grown by this much (m).
        clearance: keypoints below the top stay at least this far outside the footprint (m).
        max_half: largest half-extent of the footprint around the object (m).
        below_tol: a keypoint counts as below the top when it is more than this below it (m); fingertips
            touching the table while grasping sit a few mm under it in motion-capture data.
    """
    top = float(demo.support_height)
    R0 = np_quat_to_mat(demo.object_quat[0])
    v = obj.vertices @ R0.T + demo.object_pos[0]
    need = np.array([v[:, 0].min() - margin, v[:, 0].max() + margin, v[:, 1].min() - margin, v[:, 1].max() + margin])
    c = np.array([(need[0] + need[1]) / 2, (need[2] + need[3]) / 2])
    rect = np.array([c[0] - max_half, c[0] + max_half, c[1] - max_half, c[1] + max_half])
    rect = np.array([min(rect[0], need[0]), max(rect[1], need[1]), min(rect[2], need[2]), max(rect[3], need[3])])
    notes: list[str] = []
    pts = demo.right_joints.reshape(-1, 3)
    below = pts[pts[:, 2] < top - below_tol][:, :2]
    order = np.argsort(np.linalg.norm(below - c, axis=1))
    for x, y in below[order]:
        inside = rect[0] - clearance < x < rect[1] + clearance and rect[2] - clearance < y < rect[3] + clearance
        if not inside:
            continue
        options = []
        if x - clearance >= need[1]:
            options.append((1, x - clearance))  # move xmax left of the point
        if x + clearance <= need[0]:
            options.append((0, x + clearance))  # move xmin right of the point
        if y - clearance >= need[3]:
            options.append((3, y - clearance))
        if y + clearance <= need[2]:
            options.append((2, y + clearance))
        if not options:
            notes.append(
                f"hand keypoint at ({x:.3f}, {y:.3f}) is below the table top inside the object's footprint; kept the footprint"
            )
            continue

        def area(opt: tuple[int, float]) -> float:
            r = rect.copy()
            r[opt[0]] = opt[1]
            return (r[1] - r[0]) * (r[3] - r[2])

        k, val = max(options, key=area)
        rect[k] = val
    return Table(float(rect[0]), float(rect[1]), float(rect[2]), float(rect[3]), top), tuple(notes)


def make_scene(
    demo: Demo,
    hand: HandModel,
    base_rot: np.ndarray,
    obj: ObjectAsset,
    physics: PhysicsOptions | None = None,
) -> Scene:
    table, notes = size_table(demo, obj)
    return Scene(
        hand=hand,
        base_rot=np.asarray(base_rot, dtype=np.float64),
        obj=obj,
        table=table,
        object_pos0=np.asarray(demo.object_pos[0], dtype=np.float64),
        object_quat0=np.asarray(demo.object_quat[0], dtype=np.float64),
        fps=float(demo.fps),
        physics=physics or PhysicsOptions(),
        notes=notes,
    )
