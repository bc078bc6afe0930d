"""The decision variables of the control optimisation and the simulator controls they stand for.

* :class:`Trajectory` is what is optimised: the PD targets of the hand per frame (floating-base
  coordinates and joint angles, exactly the ``q_targets`` that the target simulators take) plus, while the
  point set is relaxed (alpha > 0), a free force per hand point and frame.
* :func:`sim_controls` turns it into the simulator's per-frame :class:`~quasisim.sim.types.Control`
  (root velocities by finite differences of the base targets, joint PD targets with their velocity).
* :func:`simulate` rolls a trajectory out from rest; :func:`observed_state` turns a target's observation
  into a simulator state.
* :func:`bucket_frames`, :func:`pad_frames`, :func:`first_frames`: compiled programs over a whole clip take
  its frames padded to the next multiple of :data:`FRAME_BUCKET`, so that clips of 51 to 60 frames share
  one program (the simulator is causal: frames after the clip's end change nothing before it).

Units: m, rad, s, N.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from quasisim.rotations import quat_conj, quat_log, quat_mul
from quasisim.sim.step import initial_state, rollout
from quasisim.sim.types import Control, Model, Params, State, pytree, static
from quasisim.tracecache import cached_jit

Array = jax.Array
F32 = jnp.float32
FRAME_BUCKET = 10
"""Whole-clip programs run on the frames padded to a multiple of this: one compiled program per 10 frames of
clip length instead of one per length (a 58-frame clip after 60-frame ones recompiled every stage 1-2
program, ~200 s on one core; BENCHMARKS.md, "A leaner curriculum, compile flags, clip length")."""


@pytree
class Trajectory:
    """Decision variables of the control optimisation.

    Attributes:
        base: (T, 6 H) base PD targets per frame of each of the H hands: x, y, z (m, world) and intrinsic
            x-y-z angles (rad) about the hand's fixed frame ``base_rot`` (see :mod:`quasisim.sim.kinematics`).
        joints: (T, J) joint PD targets per frame (rad or m), all hands' joints in order.
        point_force: (T - 1, N, 3) free force on each hand point per frame (N); only acts while alpha > 0.
        hand_joints: (static) joints of each hand when there are two or more (``HandModel.hand_joints``);
            empty for one hand. The target simulators' layout puts each hand's base before its joints.
    """

    base: Array
    joints: Array
    point_force: Array
    hand_joints: tuple[int, ...] = static(default=())

    @property
    def q_targets(self) -> np.ndarray:
        """(T, D) PD targets for the target simulators (numpy, float64): ``[base (6), joints (J)]`` per hand."""
        return join_q(np.asarray(self.base, np.float64), np.asarray(self.joints, np.float64), self.hand_joints)

    @staticmethod
    def from_q(q: np.ndarray, n_points: int, hand_joints: tuple[int, ...] = ()) -> Trajectory:
        """A trajectory of the target simulators' PD targets ``q`` (T, D) with no free point forces."""
        base, joints = split_q(np.asarray(q), hand_joints)
        return Trajectory(
            base=jnp.asarray(base, F32),
            joints=jnp.asarray(joints, F32),
            point_force=jnp.zeros((len(q) - 1, n_points, 3), F32),
            hand_joints=hand_layout(hand_joints),
        )


def bucket_frames(n_frames: int) -> int:
    """The padded length of a clip of ``n_frames`` frames: the next multiple of :data:`FRAME_BUCKET`."""
    return -(-n_frames // FRAME_BUCKET) * FRAME_BUCKET


def hold_last(x: Array, extra: int) -> Array:
    """``x`` (T, ...) followed by ``extra`` copies of its last frame (JAX arrays; traced values too)."""
    return x if extra == 0 else jnp.concatenate([x, jnp.repeat(x[-1:], extra, axis=0)])


def pad_frames(traj: Trajectory, n_frames: int) -> Trajectory:
    """``traj`` (T frames) continued to ``n_frames`` >= T frames: the last PD targets held, no point forces
    after the clip's end (works on arrays and on traced values)."""
    extra = n_frames - traj.base.shape[0]
    if extra < 0:
        raise ValueError(f"cannot pad a {traj.base.shape[0]}-frame trajectory to {n_frames} frames")
    if extra == 0:
        return traj
    force = jnp.concatenate([traj.point_force, jnp.zeros((extra, *traj.point_force.shape[1:]), F32)])
    return dataclasses.replace(
        traj, base=hold_last(traj.base, extra), joints=hold_last(traj.joints, extra), point_force=force
    )


def first_frames(traj: Trajectory, n_frames: int) -> Trajectory:
    """The first ``n_frames`` frames of ``traj`` (or of a gradient with its structure): undoes :func:`pad_frames`."""
    if traj.base.shape[0] == n_frames:
        return traj
    return dataclasses.replace(
        traj, base=traj.base[:n_frames], joints=traj.joints[:n_frames], point_force=traj.point_force[: n_frames - 1]
    )


def hand_layout(hand_joints: tuple[int, ...]) -> tuple[int, ...]:
    """:attr:`Trajectory.hand_joints` for hands of ``hand_joints`` joints: empty for one hand, so that every
    one-hand trajectory has the same tree structure (and compiled programs)."""
    return tuple(int(j) for j in hand_joints) if len(hand_joints) > 1 else ()


def _hand_columns(hand_joints: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Columns of the bases and of the joints in the target layout ``[base_1, joints_1, base_2, joints_2, ...]``."""
    base, joints, start = [], [], 0
    for J in hand_joints:
        base.append(np.arange(start, start + 6))
        joints.append(np.arange(start + 6, start + 6 + J))
        start += 6 + J
    return np.concatenate(base), np.concatenate(joints)


def split_q(q: np.ndarray, hand_joints: tuple[int, ...] = ()) -> tuple[np.ndarray, np.ndarray]:
    """Target layout (..., D) -> bases (..., 6 H) and joints (..., J) (``hand_joints``: see :class:`Trajectory`)."""
    if len(hand_joints) <= 1:
        return q[..., :6], q[..., 6:]
    b, j = _hand_columns(hand_joints)
    return q[..., b], q[..., j]


def join_q(base: np.ndarray, joints: np.ndarray, hand_joints: tuple[int, ...] = ()) -> np.ndarray:
    """Inverse of :func:`split_q`."""
    q = np.concatenate([base, joints], axis=-1)
    if len(hand_joints) <= 1:
        return q
    b, j = _hand_columns(hand_joints)
    out = np.empty_like(q)
    out[..., b], out[..., j] = base, joints
    return out


def _axis_quat(axis: int, angle: Array) -> Array:
    half = 0.5 * angle
    v = jnp.zeros((*angle.shape, 3), angle.dtype).at[..., axis].set(jnp.sin(half))
    return jnp.concatenate([jnp.cos(half)[..., None], v], axis=-1)


def root_quats(base: Array, base_quat: Array) -> Array:
    """(T, H, 4) root orientations ``base_rot Rx(a) Ry(b) Rz(c)`` of each hand as quaternions (w, x, y, z)
    from bases (T, 6 H) and the hands' base frames ``base_quat`` (H, 4) (or (4,): one hand)."""
    b = base.reshape(base.shape[0], -1, 6)
    q = quat_mul(_axis_quat(0, b[..., 3]), quat_mul(_axis_quat(1, b[..., 4]), _axis_quat(2, b[..., 5])))
    return quat_mul(jnp.broadcast_to(jnp.reshape(base_quat, (-1, 4)), q.shape), q)


def root_positions(base: Array) -> Array:
    """(T, H, 3) root positions from bases (T, 6 H)."""
    return base.reshape(base.shape[0], -1, 6)[..., :3]


def sim_controls(traj: Trajectory, base_quat: Array, fps: float) -> Control:
    """Per-frame simulator controls (T - 1 frames) that drive the hands along ``traj``'s PD targets:
    root linear/angular velocities from frame t to t + 1, joint targets of frame t + 1 and their velocity."""
    rq = root_quats(traj.base, base_quat)
    rel = quat_mul(rq[1:], quat_conj(rq[:-1]))
    dj = jnp.diff(traj.joints, axis=0) * fps
    return Control(
        root_vel=jnp.diff(root_positions(traj.base), axis=0) * fps,
        root_angvel=quat_log(rel) * fps,
        tau=jnp.zeros_like(dj),
        q_target=traj.joints[1:],
        qd_target=dj,
        point_force=traj.point_force,
    )


def start_state(model: Model, traj: Trajectory, base_quat: Array, obj_pos0: np.ndarray, obj_quat0: np.ndarray) -> State:
    """The resting state at frame 0: hand at the first targets, object at the demo's first pose."""
    rq = root_quats(traj.base[:1], base_quat)[0]
    return initial_state(model, root_positions(traj.base[:1])[0], rq, traj.joints[0], obj_pos0, obj_quat0)


def simulate(
    model: Model, params: Params, traj: Trajectory, base_quat: Array, fps: float, obj0: tuple[np.ndarray, np.ndarray]
) -> State:
    """The states (T - 1 frames) of rolling ``traj`` out in ``params`` from rest at its first targets, the
    object at ``obj0`` (position, quaternion)."""
    bq = jnp.asarray(base_quat, F32)
    s0 = start_state(model, traj, bq, obj0[0], obj0[1])
    return rollout(model, params, s0, sim_controls(traj, bq, fps))


_simulate_padded = cached_jit(simulate, static_argnames=("fps",))


def simulate_jit(
    model: Model, params: Params, traj: Trajectory, base_quat: Array, fps: float, obj0: tuple[np.ndarray, np.ndarray]
) -> State:
    """Compiled :func:`simulate` (the model and the start as arguments: one program per size of scene and
    :func:`bucket_frames` of the clip's length): the states of ``traj``'s T - 1 frames."""
    n = traj.base.shape[0]
    states = _simulate_padded(model, params, pad_frames(traj, bucket_frames(n)), base_quat, fps, obj0)
    return jax.tree.map(lambda x: x[: n - 1], states)


def observed_state(model: Model, obs: dict[str, np.ndarray], base_quat: Array) -> State:
    """The quasi-physical state of a target observation (contacts start fresh)."""
    hj = model.hand.hand_joints
    base, joints = (jnp.asarray(x, F32) for x in split_q(np.asarray(obs["qpos"]), hj))
    rq = root_quats(base[None], base_quat)[0]
    s = initial_state(model, root_positions(base[None])[0], rq, joints, obs["obj_pos"], obs["obj_quat"])
    return dataclasses.replace(
        s,
        qd=jnp.asarray(split_q(np.asarray(obs["qvel"]), hj)[1], F32),
        obj_vel=jnp.asarray(obs["obj_vel"], F32),
        obj_angvel=jnp.asarray(obs["obj_angvel"], F32),
    )
