"""The evaluation scene shared by every target simulator: hand(s) on floating bases, object, finite table.

A robot hand enters a scene one way: as a :class:`Placement`, the hand and the fixed frame of its floating
base. A scene holds one placement (the demo's right hand) or two (right, then the mirrored left hand of a
demo with ``left_joints``). Everything indexed over hands follows that order: the control vector is the
concatenation ``[right (6 + J), left (6 + J)]`` (:attr:`Scene.dof_slices`) and robot keypoints index the
human keypoints ``[right_joints, left_joints]`` (:attr:`Scene.kp_human`: left-hand indices 21..41).
Building the scene of a demo (its object, its robot hands) is :mod:`quasisim.targets.build`.

The table is a box from the floor (z = 0) up to ``support_height``. Its footprint is sized from the demo:
it covers the object's initial footprint with a margin and contains no human keypoint (of any frame, of
either hand) that is below the table top, with a clearance. In GRAB clips the hand rises from below the
table top beside the table, and ARCTIC's objects start on a small stand with hands passing below its
top beside it, so an infinite support plane would collide with them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from quasisim.assets.hand import HandModel
from quasisim.data.demo import N_KEYPOINTS, SIDES, Demo
from quasisim.errors import QuasisimError
from quasisim.rotations import np_mat_to_quat, np_quat_to_mat

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
    """Target-simulator settings (SI units). ``friction`` is the sliding coefficient on every contact;
    ``gain_scale`` multiplies every PD gain (kp and kv) of the hands (1; else a perturbed target,
    :mod:`quasisim.targets.perturb`). ``contact_margin`` (m, <= 0; MuJoCo only) is the margin of every hand
    collision geom: below 0 a hand's contact pushes only once the shapes overlap by more than
    ``-contact_margin`` (MuJoCo adds a pair's two margins): a thinner object under the fingers, a grasp that
    squeezes less; the object's contact with the table is unchanged."""

    mujoco_dt: float = 0.002
    pybullet_dt: float = 0.0005
    friction: float = 1.0
    gravity: float = 9.81
    gain_scale: float = 1.0
    contact_margin: float = 0.0

    def __post_init__(self) -> None:
        if not -0.01 <= self.contact_margin <= 0.0:
            raise QuasisimError(
                f"physics.contact_margin: expected a margin in [-0.01, 0] m, got {self.contact_margin!r}"
            )


@dataclass(frozen=True, eq=False)
class Placement:
    """One robot hand on its floating base.

    Attributes:
        hand: parsed hand model.
        base_rot: (3, 3) fixed frame of the base hinges (see :mod:`quasisim.sim.kinematics`); stored as float64.
        side: the demo's hand it follows, ``"right"`` or ``"left"`` (:data:`quasisim.data.demo.SIDES`).
    """

    hand: HandModel
    base_rot: np.ndarray
    side: str = "right"

    def __post_init__(self) -> None:
        object.__setattr__(self, "base_rot", np.asarray(self.base_rot, dtype=np.float64))
        if self.side not in SIDES:
            raise ValueError(f"Placement: side {self.side!r}, expected one of {', '.join(SIDES)}")


def place_hands(hands: Sequence[HandModel], base_rots: Sequence[np.ndarray]) -> tuple[Placement, ...]:
    """Each of ``hands`` on its base frame (3, 3) of ``base_rots``, in the demo's hand order (right, left)."""
    if not 1 <= len(hands) <= len(SIDES) or len(hands) != len(base_rots):
        raise ValueError(f"place_hands: {len(hands)} hand(s), {len(base_rots)} base frame(s); expected 1 or 2 of each")
    return tuple(Placement(h, R, s) for h, R, s in zip(hands, base_rots, SIDES, strict=False))


@dataclass(frozen=True, eq=False)
class Scene:
    """Everything a target needs to build the same world.

    Attributes:
        placements: the robot hands on their bases, right then left (one or two).
        obj: object asset (mesh, mass, inertia, convex parts).
        table: the support box.
        object_pos0, object_quat0: initial object pose (m; w x y z).
        fps: control frame rate (Hz).
        physics: simulator settings.
        notes: remarks made while building the scene (shown in reports).
    """

    placements: tuple[Placement, ...]
    obj: ObjectAsset
    table: Table
    object_pos0: np.ndarray
    object_quat0: np.ndarray
    fps: float
    physics: PhysicsOptions = PhysicsOptions()
    notes: tuple[str, ...] = field(default=())

    @property
    def hands(self) -> tuple[HandModel, ...]:
        """The hands in control order: ``(right,)`` or ``(right, left)``."""
        return tuple(p.hand for p in self.placements)

    @property
    def base_rots(self) -> tuple[np.ndarray, ...]:
        """(3, 3) base frame of each hand of :attr:`hands`."""
        return tuple(p.base_rot for p in self.placements)

    @property
    def base_quat(self) -> np.ndarray:
        """(H, 4) :attr:`base_rots` as quaternions (w x y z)."""
        return np_mat_to_quat(np.stack(self.base_rots))

    @property
    def sides(self) -> tuple[str, ...]:
        """The demo's hand each of :attr:`hands` follows: ``("right",)`` or ``("right", "left")``."""
        return tuple(p.side for p in self.placements)

    @property
    def prefixes(self) -> tuple[str, ...]:
        """Name prefix of each hand in the simulators' models: ``hand/`` alone, ``rhand/`` and ``lhand/``."""
        return ("hand/",) if len(self.placements) == 1 else ("rhand/", "lhand/")

    @property
    def dof_slices(self) -> tuple[slice, ...]:
        """Columns of each hand (6 base + J joints) in the control vector."""
        out, start = [], 0
        for h in self.hands:
            out.append(slice(start, start + 6 + h.n_joints))
            start += 6 + h.n_joints
        return tuple(out)

    @property
    def n_dof(self) -> int:
        """Length of the control vector: sum over hands of 6 + J."""
        return self.dof_slices[-1].stop

    @property
    def kp_human(self) -> np.ndarray:
        """(K,) for every robot keypoint of every hand, its index into the human keypoints of all hands
        (``Demo.human_joints``: hand ``i``'s keypoints are offset by 21 i)."""
        return np.concatenate([h.kp_human + N_KEYPOINTS * i for i, h in enumerate(self.hands)])

    @property
    def kp_metric(self) -> np.ndarray:
        """(K,) whether each robot keypoint (all hands) counts in MPJPE and the hand term."""
        return np.concatenate([h.kp_metric for h in self.hands])

    def joint_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(D,) lower and upper bounds of the control vector: -inf/inf for the base coordinates and
        unlimited joints, the joint limits otherwise."""
        lo, hi = [], []
        for h in self.hands:
            lo += [np.full(6, -np.inf), np.where(h.joint_limited, h.joint_range[:, 0], -np.inf)]
            hi += [np.full(6, np.inf), np.where(h.joint_limited, h.joint_range[:, 1], np.inf)]
        return np.concatenate(lo), np.concatenate(hi)


def size_table(
    demo: Demo,
    obj: ObjectAsset,
    margin: float = 0.05,
    clearance: float = 0.04,
    max_half: float = 0.4,
    below_tol: float = 0.01,
    stand_half: float = 0.03,
) -> tuple[Table, tuple[str, ...]]:
    """Size the table footprint from the demo (see module docstring).

    When hand keypoints below the top lie within ``clearance`` of the object's footprint (ARCTIC: fingers
    under the edges of an object that rests on a small stand), the support becomes a stand instead: the
    largest box (cut as above) around a square of half-size ``stand_half`` under the object's centre of mass
    at frame 0 that keeps those keypoints ``clearance`` away; one note says so.

    Args:
        margin: the footprint covers the object's initial footprint grown by this much (m).
        clearance: keypoints below the top stay at least this far outside the footprint (m).
        max_half: largest half-extent of the footprint around the object (m).
        below_tol: a keypoint counts as below the top when it is more than this below it (m); fingertips
            touching the table while grasping sit a few mm under it in motion-capture data.
        stand_half: half-size of the smallest support, a square under the object's centre of mass (m).
    """
    top = float(demo.support_height)
    R0 = np_quat_to_mat(demo.object_quat[0])
    v = obj.vertices @ R0.T + demo.object_pos[0]
    need = np.array([v[:, 0].min() - margin, v[:, 0].max() + margin, v[:, 1].min() - margin, v[:, 1].max() + margin])
    c = np.array([(need[0] + need[1]) / 2, (need[2] + need[3]) / 2])
    pts = demo.human_joints.reshape(-1, 3)  # every hand's keypoints
    below = pts[pts[:, 2] < top - below_tol][:, :2]
    rect, stuck = _carve(_around(c, max_half, need), need, below, c, clearance)
    if not stuck:
        return Table(float(rect[0]), float(rect[1]), float(rect[2]), float(rect[3]), top), ()
    com = (R0 @ np.asarray(obj.com) + demo.object_pos[0])[:2]
    stand = np.array([com[0] - stand_half, com[0] + stand_half, com[1] - stand_half, com[1] + stand_half])
    rect, stuck_stand = _carve(_around(c, max_half, stand), stand, below, com, clearance)
    notes = [
        f"{len(stuck)} hand keypoint(s) below the table top within {clearance * 100:g} cm of the object's footprint: "
        f"the support is a stand under the object's centre of mass ({stand_half * 200:g} cm square or larger) "
        "that keeps them clear"
    ]
    if stuck_stand:
        x, y = stuck_stand[0]
        notes.append(
            f"{len(stuck_stand)} hand keypoint(s) below the table top over the stand, e.g. at ({x:.3f}, {y:.3f}); "
            "kept the stand"
        )
    return Table(float(rect[0]), float(rect[1]), float(rect[2]), float(rect[3]), top), tuple(notes)


def _around(c: np.ndarray, half: float, need: np.ndarray) -> np.ndarray:
    """[xmin, xmax, ymin, ymax]: the square of half-size ``half`` around ``c`` (2,), grown to cover ``need``."""
    rect = np.array([c[0] - half, c[0] + half, c[1] - half, c[1] + half])
    return np.array([min(rect[0], need[0]), max(rect[1], need[1]), min(rect[2], need[2]), max(rect[3], need[3])])


def _carve(
    rect: np.ndarray, need: np.ndarray, below: np.ndarray, c: np.ndarray, clearance: float
) -> tuple[np.ndarray, list[tuple[float, float]]]:
    """Cut ``rect`` [xmin, xmax, ymin, ymax] (m) so that no point of ``below`` (N, 2), nearest to ``c`` first,
    lies within ``clearance`` of it, never cutting into ``need``; each cut moves the one side that keeps the
    most area. Returns the rectangle and the points that could not be cleared (kept)."""
    rect = rect.copy()
    stuck: list[tuple[float, float]] = []
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
            stuck.append((float(x), float(y)))
            continue

        def area(opt: tuple[int, float]) -> float:
            r = rect.copy()
            r[opt[0]] = opt[1]
            return (r[1] - r[0]) * (r[3] - r[2])

        k, val = max(options, key=area)
        rect[k] = val
    return rect, stuck


def make_scene(
    demo: Demo, placements: Sequence[Placement], obj: ObjectAsset, physics: PhysicsOptions | None = None
) -> Scene:
    """The scene of ``demo`` with its robot hands ``placements``, one per hand of the demo (``demo.sides``:
    right, then left for a demo with ``left_joints``) in that order, and object ``obj``."""
    placements = tuple(placements)
    n, sides = len(placements), demo.sides
    if n == 0 or n > len(sides):
        raise ValueError(f"make_scene: demo {demo.name} has {len(sides)} hand(s), the scene was given {n}")
    if n < len(sides):  # a one-hand code path reached with a two-hand demo
        raise QuasisimError(
            f"{demo.path or demo.name}: a demo with two hands (left_joints); this command handles one-hand demos "
            "only (two hands: quasisim retarget, evaluate, transfer, bench transfer)"
        )
    if tuple(p.side for p in placements) != sides:
        got = ", ".join(p.side for p in placements)
        raise ValueError(f"make_scene: placements for hands ({got}), demo {demo.name} has ({', '.join(sides)})")
    table, notes = size_table(demo, obj)
    return Scene(
        placements=placements,
        obj=obj,
        table=table,
        object_pos0=np.asarray(demo.object_pos[0], dtype=np.float64),
        object_quat0=np.asarray(demo.object_quat[0], dtype=np.float64),
        fps=float(demo.fps),
        physics=physics or PhysicsOptions(),
        notes=notes,
    )
