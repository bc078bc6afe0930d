"""The decision variables of the control optimisation and the simulator controls they stand for.

* :class:`Trajectory` is what is optimised: the PD targets of the hand per frame (floating-base
  coordinates and joint angles, exactly the ``q_targets`` that the target simulators take) plus, while the
  point set is relaxed (alpha > 0), a free force per hand point and frame.
* :func:`sim_controls` turns it into the simulator's per-frame :class:`~quasisim.sim.types.Control`
  (root velocities by finite differences of the base targets, joint PD targets with their velocity).
* :func:`simulate` rolls a trajectory out from rest; :func:`observed_state` turns a target's observation
  into a simulator state.

Units: m, rad, s, N.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from quasisim.rotations import quat_conj, quat_log, quat_mul
from quasisim.sim.step import initial_state, rollout
from quasisim.sim.types import Control, Model, Params, State, pytree

Array = jax.Array
F32 = jnp.float32


@pytree
class Trajectory:
    """Decision variables of the control optimisation.

    Attributes:
        base: (T, 6) base PD targets per frame: x, y, z (m, world) and intrinsic x-y-z angles (rad) about
            the clip's fixed frame ``base_rot`` (see :mod:`quasisim.sim.kinematics`).
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
        """A trajectory of PD targets ``q`` (T, 6 + J) with no free point forces."""
        q = np.asarray(q)
        return Trajectory(
            base=jnp.asarray(q[:, :6], F32),
            joints=jnp.asarray(q[:, 6:], F32),
            point_force=jnp.zeros((len(q) - 1, n_points, 3), F32),
        )


def _axis_quat(axis: int, angle: Array) -> Array:
    half = 0.5 * angle
    v = jnp.zeros((*angle.shape, 3), angle.dtype).at[..., axis].set(jnp.sin(half))
    return jnp.concatenate([jnp.cos(half)[..., None], v], axis=-1)


def root_quats(base: Array, base_quat: Array) -> Array:
    """(T, 4) root orientations ``base_rot Rx(a) Ry(b) Rz(c)`` as quaternions (w, x, y, z)."""
    q = quat_mul(_axis_quat(0, base[:, 3]), quat_mul(_axis_quat(1, base[:, 4]), _axis_quat(2, base[:, 5])))
    return quat_mul(jnp.broadcast_to(base_quat, q.shape), q)


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


def simulate(
    model: Model, params: Params, traj: Trajectory, base_quat: Array, fps: float, obj0: tuple[np.ndarray, np.ndarray]
) -> State:
    """The states (T - 1 frames) of rolling ``traj`` out in ``params`` from rest at its first targets, the
    object at ``obj0`` (position, quaternion)."""
    bq = jnp.asarray(base_quat, F32)
    s0 = start_state(model, traj, bq, obj0[0], obj0[1])
    return rollout(model, params, s0, sim_controls(traj, bq, fps))


simulate_jit = jax.jit(simulate, static_argnames=("fps",))
"""Compiled :func:`simulate` (the model and the start as arguments: one program per size of scene)."""


def observed_state(model: Model, obs: dict[str, np.ndarray], base_quat: Array) -> State:
    """The quasi-physical state of a target observation (contacts start fresh)."""
    q = jnp.asarray(obs["qpos"], F32)
    rq = root_quats(q[None, :6], base_quat)[0]
    s = initial_state(model, q[:3], rq, q[6:], obs["obj_pos"], obs["obj_quat"])
    return dataclasses.replace(
        s,
        qd=jnp.asarray(obs["qvel"][6:], F32),
        obj_vel=jnp.asarray(obs["obj_vel"], F32),
        obj_angvel=jnp.asarray(obs["obj_angvel"], F32),
    )
