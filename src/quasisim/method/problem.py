"""A demonstration set up for transfer: the target's scene and the quasi-physical simulator of the same scene.

This is the one place that builds the simulator for a demo (:func:`make_problem`); the stages, MPC, the
prediction benchmark and the tests all start from it.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

from quasisim.assets.hand import HandModel, join_hands
from quasisim.assets.object import ObjectAsset
from quasisim.data.demo import Demo
from quasisim.method.retarget import RetargetResult, retarget_hands
from quasisim.optim.objective import Reference, TrackingObjective, make_objective
from quasisim.optim.trajectory import Trajectory, simulate, split_q
from quasisim.sim.build import default_params
from quasisim.sim.kinematics import fk_full, points_world
from quasisim.sim.types import Model, Params, State
from quasisim.targets.build import demo_hands, scene_for
from quasisim.targets.quasi_target import scene_model
from quasisim.targets.scene import Placement, Scene, place_hands


@dataclass(frozen=True, eq=False)
class Problem:
    """``demo`` to be transferred to the robot hands placed in ``scene`` (``scene.placements``: right, then
    left); ``model`` is the quasi-physical simulator of ``scene`` (its hands as one hand set, ``model.hand``)."""

    demo: Demo
    scene: Scene
    model: Model

    @property
    def placements(self) -> tuple[Placement, ...]:
        """The robot hands on their base frames, right then left (:attr:`Scene.placements`)."""
        return self.scene.placements

    @property
    def obj(self) -> ObjectAsset:
        return self.scene.obj

    @property
    def base_rots(self) -> np.ndarray:
        """(H, 3, 3) the base frames of the simulator's hands."""
        return np.stack(self.scene.base_rots)

    @property
    def base_quat(self) -> np.ndarray:
        """(H, 4) :attr:`base_rots` as quaternions (w x y z)."""
        return self.scene.base_quat

    @property
    def hand_joints(self) -> tuple[int, ...]:
        """The simulator trajectory's hand layout (:class:`~quasisim.optim.trajectory.Trajectory`)."""
        return self.model.hand.hand_joints

    def trajectory(self, q: np.ndarray) -> Trajectory:
        """The simulator trajectory of the targets' PD targets ``q`` (T, D) (no free point forces)."""
        return Trajectory.from_q(q, self.model.n_points, self.hand_joints)

    @property
    def obj0(self) -> tuple[np.ndarray, np.ndarray]:
        """The demo's first object pose (position (3,), quaternion (4,) w x y z)."""
        return self.demo.object_pos[0], self.demo.object_quat[0]

    def params(self, contact: dict[str, float]) -> Params:
        """The simulator with contact settings ``contact`` (a curriculum stage) and the object's nominal S."""
        return default_params(self.model, self.obj.mass, self.obj.inertia, contact, hand=join_hands(self.scene.hands))

    def reference(self, points: np.ndarray | None = None, point_index: np.ndarray | None = None) -> Reference:
        """The demo as the objective's reference: the hands' metric keypoints, the object, optional points."""
        hand = self.model.hand
        return Reference.from_demo(self.demo, hand.kp_human, np.flatnonzero(hand.kp_metric), points, point_index)

    def objective(self, ref: Reference) -> TrackingObjective:
        """:func:`~quasisim.optim.objective.make_objective` for this problem."""
        return make_objective(
            self.model, ref, self.base_quat, self.demo.fps, self.obj0, self.obj.mass, self.obj.inertia
        )

    def simulate(self, params: Params, traj: Trajectory) -> State:
        """The states (T - 1 frames) of ``traj`` rolled out from the demo's first frame."""
        return simulate(self.model, params, traj, self.base_quat, self.demo.fps, self.obj0)

    def points_at(self, q: np.ndarray) -> np.ndarray:
        """(N, 3) world positions of the simulator's hand points at the targets' generalized position ``q`` (D,)."""
        qs = np.concatenate(split_q(np.asarray(q), self.hand_joints))
        base_rots = jnp.asarray(self.base_rots, jnp.float32)
        poses = fk_full(self.model.hand, base_rots, jnp.asarray(qs, jnp.float32), self.model.hand_geom)
        return np.asarray(points_world(poses, self.model.point_body, self.model.point_local))

    @property
    def point_hand(self) -> np.ndarray:
        """(N,) the hand (0: right, 1: left) of each simulator hand point."""
        return self.model.hand.body_hand[np.asarray(self.model.point_body)]


def make_problem(
    demo: Demo, placements: tuple[Placement, ...], substeps: int, n_candidates: int, obj: ObjectAsset | None = None,
    table_points: str = "hull",
) -> Problem:  # fmt: skip
    """The scene (table sized from the demo; the demo's object unless ``obj``) and the simulator (``substeps``
    per frame, origin at the object's first position; ``table_points``: :class:`~quasisim.sim.build.SimOptions`)
    for ``demo`` and its robot hands ``placements`` (one per hand of the demo, right then left). The
    quasi-physical simulator of two hands holds both as one hand set (:func:`~quasisim.assets.hand.join_hands`: one kinematic root per hand), whose points are the
    points of each hand sampled on its own (so a hand has the same points alone and in a pair)."""
    scene = scene_for(demo, placements, obj)
    return Problem(demo, scene, scene_model(scene, substeps, n_candidates, demo.object_pos[0], table_points))


def fitted_problem(
    demo: Demo, hands: tuple[HandModel, ...], fits: tuple[RetargetResult, ...], substeps: int, n_candidates: int,
    obj: ObjectAsset | None = None,
) -> tuple[Problem, np.ndarray]:  # fmt: skip
    """:func:`make_problem` for ``demo`` with ``hands`` (one per side of the demo) on the base frames of their
    keypoint fits ``fits``, and the fits' PD targets (T, D) in the targets' layout (right hand, then left)."""
    placements = place_hands(hands, [f.base_rot for f in fits])
    prob = make_problem(demo, placements, substeps, n_candidates, obj)
    return prob, np.concatenate([f.q for f in fits], axis=1)


def kinematic_problem(demo: Demo, hand: str, substeps: int, n_candidates: int) -> tuple[Problem, np.ndarray]:
    """:func:`fitted_problem` of the kinematic retarget of ``demo`` to robot hand ``hand`` (a name or YAML;
    a two-hand demo gets it and its mirror image)."""
    hands = demo_hands(hand, demo.sides)
    return fitted_problem(demo, hands, retarget_hands(hands, demo), substeps, n_candidates)
