"""Trajectory optimisation in the quasi-physical simulator (optax style: small composable pieces).

* :class:`Trajectory` is what is optimised: the PD targets of the hand per frame (floating-base
  coordinates and joint angles, exactly the ``q_targets`` that the target simulators take) plus, while the
  point set is relaxed (alpha > 0), a free force per hand point and frame.
* :func:`sim_controls` turns it into the simulator's per-frame :class:`~quasisim.sim.types.Control`
  (root velocities by finite differences of the base targets, joint PD targets with their velocity).
* :class:`SysID` is the identified parameter set S (object mass, inertia scale, linear and angular
  velocity damping), in unconstrained coordinates.
* The objective is the paper's ``w_o f_O + w_h f_H`` (appendix "Optimization objective") plus small
  smoothness terms; :func:`make_objective` builds one differentiable function of (trajectory, S, params)
  whose gradient serves both control optimisation and identification (one compiled program).
* :func:`adam_steps` runs Adam with early termination and keeps the best iterate.

Units: m, rad, s, N; losses are in m (translation, keypoints) plus the dimensionless ``1 - |q . q_ref|``.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

from quasisim.kinematics import forward_kinematics, keypoints
from quasisim.rotations import quat_conj, quat_mul, quat_to_mat
from quasisim.sim.step import initial_state, object_pose, rollout
from quasisim.sim.types import Control, Model, Params, State, pytree

Array = jax.Array
F32 = jnp.float32


@pytree
class Trajectory:
    """Decision variables of the control optimisation.

    Attributes:
        base: (T, 6) base PD targets per frame: x, y, z (m, world) and intrinsic x-y-z angles (rad) about
            the clip's fixed frame ``base_rot`` (see :mod:`quasisim.kinematics`).
        joints: (T, J) joint PD targets per frame (rad or m).
        point_force: (T - 1, N, 3) free force on each hand point per frame (N); only acts while alpha > 0.
    """

    base: Array
    joints: Array
    point_force: Array

    @property
    def q_targets(self) -> np.ndarray:
        """(T, 6 + J) PD targets for the target simulators (numpy, float64)."""
        return np.concatenate([np.asarray(self.base, np.float64), np.asarray(self.joints, np.float64)], axis=1)

    @staticmethod
    def from_q(q: np.ndarray, n_points: int) -> Trajectory:
        q = np.asarray(q)
        return Trajectory(
            base=jnp.asarray(q[:, :6], F32),
            joints=jnp.asarray(q[:, 6:], F32),
            point_force=jnp.zeros((len(q) - 1, n_points, 3), F32),
        )


@pytree
class SysID:
    """The identified parameters S in unconstrained coordinates (all scalars).

    ``mass = m0 exp(log_mass)``, ``inertia = I0 exp(log_inertia)``, damping ``softplus(raw)`` (1/s).
    """

    log_mass: Array
    log_inertia: Array
    lin_damp_raw: Array
    ang_damp_raw: Array

    @staticmethod
    def init(lin_damp: float = 0.0, ang_damp: float = 0.0) -> SysID:
        def inv_softplus(x: float) -> float:
            x = max(x, 1e-4)
            return float(np.log(np.expm1(x)))

        return SysID(
            jnp.zeros((), F32), jnp.zeros((), F32), jnp.asarray(inv_softplus(lin_damp), F32),
            jnp.asarray(inv_softplus(ang_damp), F32),
        )  # fmt: skip

    def apply(self, params: Params, mass0: float, inertia0: Array) -> Params:
        """``params`` with the object's S replaced (differentiable in ``self``)."""
        return dataclasses.replace(
            params,
            obj_mass=mass0 * jnp.exp(self.log_mass),
            obj_inertia=jnp.asarray(inertia0, F32) * jnp.exp(self.log_inertia),
            obj_lin_damp=jax.nn.softplus(self.lin_damp_raw),
            obj_ang_damp=jax.nn.softplus(self.ang_damp_raw),
        )

    def describe(self, mass0: float) -> dict[str, float]:
        return {
            "mass_kg": float(mass0 * np.exp(float(self.log_mass))),
            "inertia_scale": float(np.exp(float(self.log_inertia))),
            "lin_damp": float(jax.nn.softplus(self.lin_damp_raw)),
            "ang_damp": float(jax.nn.softplus(self.ang_damp_raw)),
        }


# ---- controls ------------------------------------------------------------------------------------


def _axis_quat(axis: int, angle: Array) -> Array:
    half = 0.5 * angle
    v = jnp.zeros((*angle.shape, 3), angle.dtype).at[..., axis].set(jnp.sin(half))
    return jnp.concatenate([jnp.cos(half)[..., None], v], axis=-1)


def root_quats(base: Array, base_quat: Array) -> Array:
    """(T, 4) root orientations ``base_rot Rx(a) Ry(b) Rz(c)`` as quaternions (w, x, y, z)."""
    q = quat_mul(_axis_quat(0, base[:, 3]), quat_mul(_axis_quat(1, base[:, 4]), _axis_quat(2, base[:, 5])))
    return quat_mul(jnp.broadcast_to(base_quat, q.shape), q)


def quat_log(q: Array) -> Array:
    """Rotation vector (..., 3) of unit quaternions (..., 4), shortest arc; smooth at the identity."""
    q = q * jnp.where(q[..., :1] < 0, -1.0, 1.0)
    v = q[..., 1:]
    s2 = jnp.sum(v * v, axis=-1, keepdims=True)
    s = jnp.sqrt(jnp.maximum(s2, 1e-20))
    angle = 2.0 * jnp.arctan2(s, q[..., :1])
    scale = jnp.where(s2 > 1e-12, angle / s, 2.0 / jnp.maximum(q[..., :1], 1e-6))
    return v * scale


def sim_controls(traj: Trajectory, base_quat: Array, fps: float) -> Control:
    """Per-frame simulator controls (T - 1 frames) that drive the hand along ``traj``'s PD targets:
    root linear/angular velocity from frame t to t + 1, joint targets of frame t + 1 and their velocity."""
    rq = root_quats(traj.base, base_quat)
    rel = quat_mul(rq[1:], quat_conj(rq[:-1]))
    dj = jnp.diff(traj.joints, axis=0) * fps
    return Control(
        root_vel=jnp.diff(traj.base[:, :3], axis=0) * fps,
        root_angvel=quat_log(rel) * fps,
        tau=jnp.zeros_like(dj),
        q_target=traj.joints[1:],
        qd_target=dj,
        point_force=traj.point_force,
    )


def start_state(model: Model, traj: Trajectory, base_quat: Array, obj_pos0: np.ndarray, obj_quat0: np.ndarray) -> State:
    """The resting state at frame 0: hand at the first targets, object at the demo's first pose."""
    rq = root_quats(traj.base[:1], base_quat)[0]
    return initial_state(model, traj.base[0, :3], rq, traj.joints[0], obj_pos0, obj_quat0)


# ---- objective -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Weights:
    """Weights of the objective terms (paper: w_o = w_h = 1).

    Attributes:
        obj_pos: object translation term ``|t - t_ref|`` (per m).  obj_rot: ``1 - |q . q_ref|``.
        hand: mean keypoint distance f_H (per m).  points: mean distance of corresponding hand points (per m).
        smooth: squared second differences of the base and joint targets (per (m or rad)^2).
        point_force: squared free point forces (per N^2), keeps the relaxed points near their bodies.
    """

    obj_pos: float = 1.0
    obj_rot: float = 1.0
    hand: float = 1.0
    points: float = 0.0
    smooth: float = 1.0e-3
    point_force: float = 1.0e-4

    def arrays(self, **override: float) -> dict[str, Array]:
        """The weights as JAX scalars (the objective's ``weights`` argument)."""
        d = {**dataclasses.asdict(self), **override}
        return {k: jnp.asarray(v, F32) for k, v in d.items()}


def _safe_norm(x: Array) -> Array:
    return jnp.sqrt(jnp.sum(x * x, axis=-1) + 1e-12)


@dataclass(frozen=True, eq=False)
class Reference:
    """What the hand and object should do (world frame, frames 1..T-1 after the rollout's start).

    Attributes:
        obj_pos: (F, 3) object frame origin.  obj_quat: (F, 4) w x y z.
        keypoints: (F, K, 3) human keypoints for the robot's metric keypoints (K = ``kp_index`` size).
        kp_index: (K,) robot keypoint indices that enter f_H.
        points: (F, P, 3) target positions of hand points (stage 1: the human point set) or None.
        point_index: (P,) the hand point that should follow each target point.
        frame_weight: (F,) per-frame weight of the object terms (1 by default).
    """

    obj_pos: np.ndarray
    obj_quat: np.ndarray
    keypoints: np.ndarray
    kp_index: np.ndarray
    points: np.ndarray | None = None
    point_index: np.ndarray | None = None
    frame_weight: np.ndarray | None = None


def hand_keypoints(model: Model, states: State) -> Array:
    """(F, K, 3) world positions of all robot keypoints along a rollout."""

    def one(s: State) -> Array:
        poses = forward_kinematics(model.hand, s.root_pos, quat_to_mat(s.root_quat), s.q)
        return model.to_world(keypoints(model.hand, poses))

    return jax.vmap(one)(states)


def hand_point_positions(model: Model, params: Params, states: State, index: np.ndarray) -> Array:
    """(F, P, 3) world positions of hand points ``index`` (including the relaxed offsets)."""
    body = jnp.asarray(model.point_body[index])
    local = model.point_local[index]

    def one(s: State) -> Array:
        poses = forward_kinematics(model.hand, s.root_pos, quat_to_mat(s.root_quat), s.q)
        p = poses.pos[body] + jnp.einsum("nij,nj->ni", poses.rot[body], local)
        return model.to_world(p + params.alpha * s.delta[index])

    return jax.vmap(one)(states)


def tracking_terms(model: Model, params: Params, states: State, ref: Reference) -> dict[str, Array]:
    """Per-term tracking errors of a rollout (each a scalar mean over frames)."""
    pos, quat = object_pose(model, states)
    fw = jnp.ones(len(ref.obj_pos), F32) if ref.frame_weight is None else jnp.asarray(ref.frame_weight, F32)
    fw = fw / jnp.mean(fw)
    t_err = _safe_norm(pos - jnp.asarray(ref.obj_pos, F32))
    r_err = 1.0 - jnp.abs(jnp.sum(quat * jnp.asarray(ref.obj_quat, F32), axis=-1))
    kp = hand_keypoints(model, states)[:, ref.kp_index]
    out = {
        "obj_pos": jnp.mean(fw * t_err),
        "obj_rot": jnp.mean(fw * r_err),
        "hand": jnp.mean(_safe_norm(kp - jnp.asarray(ref.keypoints, F32))),
    }
    if ref.points is not None:
        hp = hand_point_positions(model, params, states, np.asarray(ref.point_index))
        out["points"] = jnp.mean(_safe_norm(hp - jnp.asarray(ref.points, F32)))
    return out


def make_objective(
    model: Model, ref: Reference, base_quat: np.ndarray, fps: float, obj0: tuple[np.ndarray, np.ndarray],
    mass0: float, inertia0: np.ndarray,
) -> Callable[[Trajectory, SysID, Params, dict[str, Array]], tuple[Array, dict[str, Array]]]:  # fmt: skip
    """``objective(traj, sysid, params, weights) -> (loss, terms)``: roll ``traj`` out from the demo's first
    object pose in the simulator ``params`` (with S from ``sysid``) and score it against ``ref``.

    ``weights`` is :meth:`Weights.arrays` (array leaves, so that changing them does not recompile)."""
    bq = jnp.asarray(base_quat, F32)

    def objective(
        traj: Trajectory, sysid: SysID, params: Params, weights: dict[str, Array]
    ) -> tuple[Array, dict[str, Array]]:
        p = sysid.apply(params, mass0, inertia0)
        s0 = start_state(model, traj, bq, obj0[0], obj0[1])
        states = rollout(model, p, s0, sim_controls(traj, bq, fps))
        terms = tracking_terms(model, p, states, ref)
        terms["smooth"] = jnp.mean(jnp.diff(traj.base, 2, axis=0) ** 2) + jnp.mean(
            jnp.diff(traj.joints, 2, axis=0) ** 2
        )
        terms["point_force"] = jnp.mean(jnp.sum(traj.point_force**2, -1)) * p.alpha
        loss = sum(weights[k] * v for k, v in terms.items())
        return loss, terms

    return objective


def simulate(
    model: Model, params: Params, traj: Trajectory, base_quat: np.ndarray, fps: float,
    obj0: tuple[np.ndarray, np.ndarray],
) -> State:  # fmt: skip
    """The states (T - 1 frames) of rolling ``traj`` out in ``params`` (for outputs and reports)."""
    bq = jnp.asarray(base_quat, F32)
    s0 = start_state(model, traj, bq, obj0[0], obj0[1])
    return rollout(model, params, s0, sim_controls(traj, bq, fps))


# ---- optimisation loop ---------------------------------------------------------------------------


@dataclass(frozen=True)
class StepBudget:
    """Adam steps for one simulator of the curriculum (paper: 100 control, 1000 identification steps).

    Attributes:
        control_steps, sysid_steps: maximum steps.  control_lr, sysid_lr: Adam step sizes.
        patience: stop after this many steps without a relative improvement of ``min_rel_improvement``.
    """

    control_steps: int = 100
    sysid_steps: int = 1000
    control_lr: float = 5.0e-4
    sysid_lr: float = 5.0e-4
    patience: int = 20
    min_rel_improvement: float = 1.0e-3


@dataclass
class StepLog:
    """Loss history of one optimisation run."""

    losses: list[float] = dataclasses.field(default_factory=list)
    terms: list[dict[str, float]] = dataclasses.field(default_factory=list)
    best: float = float("inf")
    wall_s: float = 0.0
    stopped_early: bool = False


def adam_steps(
    value_and_grad: Callable[[Any], tuple[tuple[Array, dict[str, Array]], Any]],
    x0: Any,
    steps: int,
    lr: float,
    patience: int,
    min_rel_improvement: float,
    mask: Callable[[Any], Any] | None = None,
    on_step: Callable[[int, float], None] | None = None,
) -> tuple[Any, StepLog]:
    """Minimise with Adam; return the best iterate (the loss is evaluated before each update, so the
    returned point is one whose loss was measured) and the loss history. ``mask`` zeroes gradient
    leaves that must stay fixed. Stops early after ``patience`` steps without a relative improvement."""
    tx = optax.adam(lr)
    x, st = x0, tx.init(x0)
    log = StepLog()
    best_x, since = x0, 0
    t0 = time.perf_counter()
    for k in range(steps + 1):
        (loss, terms), g = value_and_grad(x)
        lv = float(loss)
        if not np.isfinite(lv):
            log.stopped_early = True
            break
        log.losses.append(lv)
        log.terms.append({n: float(v) for n, v in terms.items()})
        if lv < log.best * (1.0 - min_rel_improvement) or k == 0:
            since = 0
        else:
            since += 1
        if lv < log.best:
            log.best, best_x = lv, x
        if on_step is not None:
            on_step(k, lv)
        if k == steps or since >= patience:
            log.stopped_early = k < steps
            break
        if mask is not None:
            g = mask(g)
        upd, st = tx.update(g, st, x)
        x = optax.apply_updates(x, upd)
    log.wall_s = time.perf_counter() - t0
    return best_x, log
