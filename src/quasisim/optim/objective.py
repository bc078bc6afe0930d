"""The tracking objective (paper appendix "Optimization objective"), one implementation for every stage.

``loss = w_o f_O + w_h f_H`` plus small regularisers, with

* ``f_O``: object translation ``|t - t_ref|`` (m) and rotation ``1 - |q . q_ref|`` (dimensionless), means
  over frames;
* ``f_H``: the mean distance (m) of the robot's metric keypoints to the human keypoints;
* ``points`` (stage 1d): the mean distance of hand points to their targets (the human point set);
* ``smooth``: squared second differences of the PD targets; ``point_force``: squared free point forces.

:func:`make_objective` scores a whole clip from its first frame (stages 1-2, S identification);
:func:`make_window_objective` a few frames from an observed state (MPC); :func:`window_costs` candidate
windows measured in a target (sampling MPC); :func:`clip_cost` a whole rollout in a target (selection). All
of them call :func:`tracking_errors`.

The objectives are pytrees (the clip's model, reference and start as array leaves, not closed-over
constants), differentiated and compiled by module-level functions (:func:`objective_value_and_grad`,
:func:`objective_value`): one compiled program serves every clip of equal sizes (a clip's frames
padded to a multiple of ten), within a process and, through the persistent compilation cache, across
processes.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import jax
import jax.numpy as jnp
import numpy as np

from quasisim.data.demo import Demo
from quasisim.optim.sysid import SysID
from quasisim.optim.trajectory import (
    Trajectory,
    bucket_frames,
    first_frames,
    hold_last,
    pad_frames,
    sim_controls,
    simulate,
)
from quasisim.rotations import quat_to_mat
from quasisim.sim.kinematics import forward_kinematics, keypoints, points_world
from quasisim.sim.step import object_pose, rollout
from quasisim.sim.types import Model, Params, State, pytree, static
from quasisim.tracecache import cached_jit


class Rollout(Protocol):
    """What :func:`clip_cost` reads of a target's rollout (:class:`quasisim.targets.TargetRollout`, which sits
    above this module: the targets judge with it)."""

    object_pos: np.ndarray
    object_quat: np.ndarray
    kp_human: np.ndarray
    kp_metric: np.ndarray

    @property
    def instability(self) -> str: ...

    @property
    def robot_keypoints(self) -> np.ndarray: ...


Array = jax.Array
F32 = jnp.float32
Objective = Callable[[Trajectory, SysID, Params, dict[str, Array]], tuple[Array, dict[str, Array]]]


@dataclass(frozen=True)
class Weights:
    """Weights of the objective terms (values: ``configs/transfer.yaml``; paper: w_o = w_h = 1).

    Attributes:
        obj_pos: object translation term (per m).  obj_rot: ``1 - |q . q_ref|``.
        hand: mean keypoint distance f_H (per m).  points: mean distance of corresponding hand points (per m).
        smooth: squared second differences of the base and joint targets (per (m or rad)^2).
        point_force: squared free point forces (per N^2), keeps the relaxed points near their bodies.
    """

    obj_pos: float
    obj_rot: float
    hand: float
    points: float
    smooth: float
    point_force: float

    def arrays(self, **override: float) -> dict[str, Array]:
        """The weights as JAX scalars (the objective's ``weights`` argument; changing them never recompiles)."""
        d = {**dataclasses.asdict(self), **override}
        return {k: jnp.asarray(v, F32) for k, v in d.items()}


@pytree
class Reference:
    """What the hand and object should do (world frame, frames 1..T-1 after the rollout's start).

    Attributes:
        obj_pos: (F, 3) object frame origin.  obj_quat: (F, 4) w x y z.
        keypoints: (F, K, 3) human keypoints for the robot keypoints ``kp_index`` (K,).
        points: (F, P, 3) target positions of hand points (stage 1: the human point set) or None.
        point_index: (P,) the hand point that should follow each target point.
    """

    obj_pos: Array
    obj_quat: Array
    keypoints: Array
    kp_index: Array
    points: Array | None = None
    point_index: Array | None = None

    @staticmethod
    def from_demo(
        demo: Demo, kp_human: np.ndarray, kp_index: np.ndarray, points: np.ndarray | None = None,
        point_index: np.ndarray | None = None,
    ) -> Reference:  # fmt: skip
        """The demo's frames 1..T-1; robot keypoint ``kp_index[k]`` follows human keypoint ``kp_human[kp_index[k]]``
        (an index into the keypoints of all the demo's hands, ``Demo.human_joints``); ``points`` (T, P, 3) per
        frame, when given."""
        f, i = (lambda x: jnp.asarray(x, F32)), (lambda x: jnp.asarray(x, jnp.int32))
        return Reference(
            obj_pos=f(demo.object_pos[1:]), obj_quat=f(demo.object_quat[1:]),
            keypoints=f(demo.human_joints[1:, kp_human[kp_index]]), kp_index=i(kp_index),
            points=None if points is None else f(points[1:]), point_index=None if point_index is None else i(point_index),
        )  # fmt: skip


def hand_keypoints(model: Model, states: State) -> Array:
    """(F, K, 3) world positions of all robot keypoints along a rollout."""

    def one(s: State) -> Array:
        poses = forward_kinematics(model.hand, s.root_pos, quat_to_mat(s.root_quat), s.q, model.hand_geom)
        return model.to_world(keypoints(model.hand, poses, model.hand_geom))

    return jax.vmap(one)(states)


def hand_point_positions(model: Model, params: Params, states: State, index: Array) -> Array:
    """(F, P, 3) world positions of hand points ``index`` (including the relaxed offsets)."""
    body = model.point_body[index]
    local = model.point_local[index]

    def one(s: State) -> Array:
        poses = forward_kinematics(model.hand, s.root_pos, quat_to_mat(s.root_quat), s.q, model.hand_geom)
        return model.to_world(points_world(poses, body, local) + params.alpha * s.delta[index])

    return jax.vmap(one)(states)


def _norm(x: Array) -> Array:
    return jnp.sqrt(jnp.sum(x * x, axis=-1) + 1e-12)


def frame_mean(err: Array, frame_w: Array | None) -> Array:
    """Mean of per-frame errors ``err`` (F, ...): over everything when ``frame_w`` is None, else the
    ``frame_w`` (F,)-weighted mean over frames of each frame's mean (frames of weight 0 drop out of the
    value even where their errors are not finite)."""
    if frame_w is None:
        return jnp.mean(err)
    per_frame = jnp.mean(err, axis=tuple(range(1, err.ndim))) if err.ndim > 1 else err
    return jnp.sum(jnp.where(frame_w > 0, frame_w * per_frame, 0.0)) / jnp.maximum(jnp.sum(frame_w), 1.0)


def tracking_errors(
    pos: Array, quat: Array, kp: Array, ref_pos: Array, ref_quat: Array, ref_kp: Array, frame_w: Array | None = None
) -> dict[str, Array]:
    """The object and hand terms from an object trajectory ``pos`` (F, 3), ``quat`` (F, 4) and keypoints
    ``kp`` (F, K, 3) against their references (any simulator's: the quasi-physical one or a target's)."""
    return {
        "obj_pos": frame_mean(_norm(pos - jnp.asarray(ref_pos, F32)), frame_w),
        "obj_rot": frame_mean(1.0 - jnp.abs(jnp.sum(quat * jnp.asarray(ref_quat, F32), axis=-1)), frame_w),
        "hand": frame_mean(_norm(kp - jnp.asarray(ref_kp, F32)), frame_w),
    }


def tracking_terms(
    model: Model, params: Params, states: State, ref: Reference, frame_w: Array | None = None
) -> dict[str, Array]:
    """The tracking terms of a rollout ``states`` (F frames) against ``ref`` (each a scalar mean over frames)."""
    pos, quat = object_pose(model, states)
    kp = hand_keypoints(model, states)[:, ref.kp_index]
    terms = tracking_errors(pos, quat, kp, ref.obj_pos, ref.obj_quat, ref.keypoints, frame_w)
    if ref.points is not None:
        hp = hand_point_positions(model, params, states, ref.point_index)
        terms["points"] = frame_mean(_norm(hp - jnp.asarray(ref.points, F32)), frame_w)
    return terms


def smoothness(base: Array, joints: Array, frame_w: Array | None = None) -> Array:
    """Mean squared second differences of the base (T, 6) and joint (T, J) PD targets (0 for T < 3); with
    ``frame_w`` (T - 1,) over frames 1..T-1, only the differences that end on a frame of weight > 0."""
    if base.shape[0] < 3:
        return jnp.zeros((), F32)
    w = None if frame_w is None else frame_w[1:]  # difference i spans frames i, i + 1, i + 2
    return frame_mean(jnp.diff(base, 2, axis=0) ** 2, w) + frame_mean(jnp.diff(joints, 2, axis=0) ** 2, w)


def weighted_sum(terms: dict[str, Array], weights: dict[str, Array]) -> Array:
    """``sum_k weights[k] * terms[k]``."""
    return sum(weights[k] * v for k, v in terms.items())  # type: ignore[return-value]


def clip_cost(demo: Demo, rollout: Rollout, weights: Weights) -> float:
    """J of a target's rollout over the whole clip (frames 1..T-1 against ``demo``): ``obj_pos``, ``obj_rot``
    and ``hand`` of :func:`tracking_errors` with ``weights``; infinity when the rollout is unstable. The
    judge of :meth:`quasisim.targets.base.Target.judge` (selection, stage 3's rounds)."""
    if rollout.instability:
        return float("inf")
    ref_kp = demo.human_joints[1:, rollout.kp_human[rollout.kp_metric]]
    terms = tracking_errors(
        rollout.object_pos[1:], rollout.object_quat[1:], rollout.robot_keypoints[1:],
        demo.object_pos[1:], demo.object_quat[1:], ref_kp,
    )  # fmt: skip
    w = {k: np.float32(v) for k, v in weights.arrays().items()}
    return float(weighted_sum({k: terms[k] for k in ("obj_pos", "obj_rot", "hand")}, w))


@pytree
class TrackingObjective:
    """``objective(traj, sysid, params, weights) -> (loss, terms)``: roll ``traj`` out from the demo's first
    object pose (``obj_pos0``, ``obj_quat0``) in the simulator ``params`` (with S from ``sysid``, relative to
    the nominal ``mass0`` kg, ``inertia0`` (3, 3) kg m^2) and score it against ``ref``. One differentiable
    function serves control optimisation and identification (one compiled program:
    :attr:`value_and_grad`).

    ``ref`` and ``frame_w`` run over the clip's frames padded to :func:`~quasisim.optim.trajectory.bucket_frames`
    (``frame_w`` 1 on the clip's frames 1..T-1, 0 after): a trajectory of the clip's T frames is padded to
    them (:func:`~quasisim.optim.trajectory.pad_frames`), and frames after the clip's end weigh nothing."""

    model: Model
    ref: Reference
    base_quat: Array
    obj_pos0: Array
    obj_quat0: Array
    mass0: Array
    inertia0: Array
    frame_w: Array
    fps: float = static()

    @property
    def n_frames(self) -> int:
        """The padded number of frames (the length of every trajectory the compiled programs take)."""
        return int(self.frame_w.shape[0]) + 1

    def __call__(
        self, traj: Trajectory, sysid: SysID, params: Params, weights: dict[str, Array]
    ) -> tuple[Array, dict[str, Array]]:
        traj = pad_frames(traj, self.n_frames)
        p = sysid.apply(params, self.mass0, self.inertia0)
        states = simulate(self.model, p, traj, self.base_quat, self.fps, (self.obj_pos0, self.obj_quat0))
        terms = tracking_terms(self.model, p, states, self.ref, self.frame_w)
        terms["smooth"] = smoothness(traj.base, traj.joints, self.frame_w)
        terms["point_force"] = frame_mean(jnp.sum(traj.point_force**2, -1), self.frame_w) * p.alpha
        return weighted_sum(terms, weights), terms

    @property
    def value_and_grad(self) -> Callable[..., Any]:
        """``(traj, sysid, params, weights) -> ((loss, terms), (d/dtraj, d/dsysid))``, compiled."""
        return functools.partial(objective_value_and_grad, self)

    def with_substeps(self, substeps: int) -> TrackingObjective:
        """The same objective in a simulator stepping ``substeps`` times per frame (dt = 1 / (fps substeps))."""
        if substeps == self.model.substeps:
            return self
        model = dataclasses.replace(self.model, substeps=substeps, dt=1.0 / (self.fps * substeps))
        return dataclasses.replace(self, model=model)

    @property
    def value(self) -> Callable[..., Any]:
        """``(traj, sysid, params, weights) -> (loss, terms)``, compiled: the forward pass alone (about a
        quarter of :attr:`value_and_grad`'s time). The two are compiled apart, and over a contact-rich
        rollout their values can differ by far more than rounding (BENCHMARKS.md, "a cheaper restart guard")."""
        return functools.partial(objective_value, self)


def objective_value_and_grad(
    objective: TrackingObjective, traj: Trajectory, sysid: SysID, params: Params, weights: dict[str, Array]
) -> tuple[tuple[Array, dict[str, Array]], tuple[Trajectory, SysID]]:
    """The objective's value and its gradient with respect to the trajectory (of the clip's T frames) and S,
    by the compiled program of the padded length (:func:`padded_value_and_grad`)."""
    n = traj.base.shape[0]
    (loss, terms), (g, gs) = padded_value_and_grad(
        objective, pad_frames(traj, objective.n_frames), sysid, params, weights
    )
    return (loss, terms), (first_frames(g, n), gs)


def objective_value(
    objective: TrackingObjective, traj: Trajectory, sysid: SysID, params: Params, weights: dict[str, Array]
) -> tuple[Array, dict[str, Array]]:
    """The objective's value and terms, without the gradient (compiled for the padded length)."""
    return padded_value(objective, pad_frames(traj, objective.n_frames), sysid, params, weights)


@cached_jit
def padded_value_and_grad(
    objective: TrackingObjective, traj: Trajectory, sysid: SysID, params: Params, weights: dict[str, Array]
) -> tuple[tuple[Array, dict[str, Array]], tuple[Trajectory, SysID]]:
    """:func:`objective_value_and_grad` of a trajectory of ``objective.n_frames`` frames."""
    return jax.value_and_grad(lambda t, s: objective(t, s, params, weights), argnums=(0, 1), has_aux=True)(traj, sysid)


@cached_jit
def padded_value(
    objective: TrackingObjective, traj: Trajectory, sysid: SysID, params: Params, weights: dict[str, Array]
) -> tuple[Array, dict[str, Array]]:
    """:func:`objective_value` of a trajectory of ``objective.n_frames`` frames."""
    return objective(traj, sysid, params, weights)


def make_objective(
    model: Model, ref: Reference, base_quat: np.ndarray, fps: float, obj0: tuple[np.ndarray, np.ndarray],
    mass0: float, inertia0: np.ndarray,
) -> TrackingObjective:  # fmt: skip
    """The :class:`TrackingObjective` of a clip (arrays as float32 leaves; ``ref`` over the clip's frames
    1..T-1, padded here to :func:`~quasisim.optim.trajectory.bucket_frames` (T) - 1 frames)."""
    f = lambda x: jnp.asarray(x, F32)  # noqa: E731
    n = ref.obj_pos.shape[0]
    extra = bucket_frames(n + 1) - 1 - n
    held = {k: hold_last(getattr(ref, k), extra) for k in ("obj_pos", "obj_quat", "keypoints")}
    points = None if ref.points is None else hold_last(ref.points, extra)
    ref = dataclasses.replace(ref, **held, points=points)
    frame_w = f(np.arange(n + extra) < n)
    return TrackingObjective(
        model, ref, f(base_quat), f(obj0[0]), f(obj0[1]), f(mass0), f(inertia0), frame_w, float(fps)
    )


def padded(x: np.ndarray, horizon: int) -> np.ndarray:
    """``x`` (T, ...) followed by ``horizon`` copies of its last frame (windows past the clip's end)."""
    return np.concatenate([x, np.repeat(x[-1:], horizon, 0)])


def window_references(demo: Demo, kp_human: np.ndarray, kp_index: np.ndarray, horizon: int) -> list[np.ndarray]:
    """The references of MPC windows, padded by ``horizon`` frames: object positions (T + H, 3), quaternions
    (T + H, 4) and the human keypoints of robot keypoints ``kp_index`` (T + H, K, 3); ``kp_human`` indexes
    the keypoints of all the demo's hands (``Demo.human_joints``)."""
    kp = demo.human_joints[:, kp_human[kp_index]]
    return [padded(x, horizon) for x in (demo.object_pos, demo.object_quat, kp)]


@pytree
class WindowObjective:
    """``f(win, s0, params, ref_pos, ref_quat, ref_kp, frame_w, weights) -> (loss, terms)`` over one MPC window:
    ``win`` (q + 1 frames of PD targets, the first being the targets the step starts from) rolled out from
    the observed state ``s0``; references (q, ...) for the window's frames; ``frame_w`` (q,) masks frames
    past the clip's end; robot keypoints ``kp_index`` (K,) follow the references' keypoints."""

    model: Model
    base_quat: Array
    kp_index: Array
    fps: float = static()

    def __call__(
        self, win: Trajectory, s0: State, params: Params, ref_pos: Array, ref_quat: Array, ref_kp: Array,
        frame_w: Array, weights: dict[str, Array],
    ) -> tuple[Array, dict[str, Array]]:  # fmt: skip
        states = rollout(self.model, params, s0, sim_controls(win, self.base_quat, self.fps))
        ref = Reference(ref_pos, ref_quat, ref_kp, self.kp_index)
        terms = tracking_terms(self.model, params, states, ref, frame_w)
        terms["smooth"] = smoothness(win.base, win.joints)
        return weighted_sum(terms, weights), terms


def make_window_objective(model: Model, base_quat: np.ndarray, fps: float, kp_index: np.ndarray) -> WindowObjective:
    """The :class:`WindowObjective` of a clip."""
    return WindowObjective(model, jnp.asarray(base_quat, F32), jnp.asarray(kp_index, jnp.int32), float(fps))


@functools.partial(jax.jit, static_argnames=("n_base",))
def window_costs(
    pos: Array, quat: Array, kp: Array, wins: Array, ref_pos: Array, ref_quat: Array, ref_kp: Array,
    frame_w: Array, weights: dict[str, Array], n_base: int = 6,
) -> Array:  # fmt: skip
    """(N,) the MPC window objective of N candidate windows measured in a target: object trajectories
    ``pos`` (N, H, 3), ``quat`` (N, H, 4), keypoints ``kp`` (N, H, K, 3), the windows' PD targets ``wins``
    (N, H + 1, D) whose first ``n_base`` columns are base coordinates and the rest joints (one hand: 6 + J;
    two hands: both bases first); references (H, ...) and ``frame_w`` (H,) as in :func:`make_window_objective`."""

    def one(p: Array, q: Array, k: Array, w: Array) -> Array:
        terms = tracking_errors(p, q, k, ref_pos, ref_quat, ref_kp, frame_w)
        terms["smooth"] = smoothness(w[:, :n_base], w[:, n_base:])
        return weighted_sum(terms, weights)

    return jax.vmap(one)(pos, quat, kp, wins)
