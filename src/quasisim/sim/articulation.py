"""Articulated-body terms in reduced coordinates: geometric Jacobians, mass matrix, bias forces.

Generalized coordinates are the hand joints ``q`` (J,) with the root pose given (the quasi-physical
simulator drives the root kinematically), or, with ``base`` given, the floating base coordinates of
:mod:`quasisim.sim.kinematics` followed by the joints (6 + J; used to compare with MuJoCo).

    M(q) = sum_b m_b Jv_b^T Jv_b + Jw_b^T I_b Jw_b + diag(armature)        (Jv at the body's centre of mass)
    bias(q, qd) = C(q, qd) qd + g(q),   C qd = (dM/dt) qd - 1/2 d/dq (qd^T M qd),   g = -sum_b Jv_b^T m_b g_vec

so that ``M qdd + bias = tau`` (MuJoCo's ``qfrc_bias`` convention).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from quasisim.assets.hand import HINGE, HandModel
from quasisim.rotations import axis_angle_to_mat
from quasisim.sim.kinematics import (
    BodyPoses,
    HandGeometry,
    bases_to_roots,
    forward_kinematics_with_joints,
    hand_geometry,
)

Array = jnp.ndarray


class BodyJacobians(NamedTuple):
    """World poses and Jacobians of the body origins: ``jv``, ``jw`` (B, 3, n) for n coordinates."""

    poses: BodyPoses
    jv: Array
    jw: Array


def ancestor_mask(model: HandModel) -> np.ndarray:
    """(B, J) bool: joint j moves body b (j sits on b or on one of b's ancestors). Evaluated when a
    function is traced, not per step."""
    B, J = model.n_bodies, model.n_joints
    mask = np.zeros((B, J), bool)
    for b in range(B):
        a = b
        while a >= 0:  # up to the hand's root (parent -1)
            mask[b, model.joint_body == a] = True
            a = int(model.body_parent[a])
    return mask


def body_jacobians(
    model: HandModel,
    root_pos: Array,
    root_rot: Array,
    q: Array,
    base: Array | None = None,
    base_rot: Array | None = None,
    geom: HandGeometry | None = None,
) -> BodyJacobians:
    """Poses and geometric Jacobians of every body origin.

    With ``base`` (6,) and ``base_rot`` (3, 3), ``root_pos``/``root_rot`` are ignored and the first six
    coordinates are the floating base (3 world slides, 3 intrinsic hinges about ``base_rot``'s axes).
    ``geom``: the hand's geometry as arrays (None: ``model``'s own, as constants).
    """
    if base is not None:
        root_pos, root_rot = bases_to_roots(base, base_rot)
    poses, frames = forward_kinematics_with_joints(model, root_pos, root_rot, q, geom)
    mask = jnp.asarray(ancestor_mask(model), dtype=poses.pos.dtype)  # (B, J)
    hinge = jnp.asarray(model.joint_type == HINGE)
    rel = poses.pos[:, None, :] - frames.anchor[None, :, :]  # (B, J, 3)
    ax = jnp.broadcast_to(frames.axis[None], rel.shape)
    jv = jnp.where(hinge[None, :, None], jnp.cross(ax, rel), ax) * mask[..., None]
    jw = jnp.where(hinge[None, :, None], ax, 0.0) * mask[..., None]
    jv, jw = jnp.swapaxes(jv, 1, 2), jnp.swapaxes(jw, 1, 2)  # (B, 3, J)
    if base is not None:
        B = model.n_bodies
        eye = jnp.eye(3, dtype=jv.dtype)
        R1 = base_rot @ axis_angle_to_mat(eye[0], base[3])
        R2 = R1 @ axis_angle_to_mat(eye[1], base[4])
        axes = jnp.stack([base_rot[:, 0], R1[:, 1], R2[:, 2]])  # (3, 3) world hinge axes
        r = poses.pos - base[:3]  # (B, 3)
        jv_rot = jnp.cross(axes[None, :, :], r[:, None, :])  # (B, 3 axes, 3)
        jv_base = jnp.concatenate([jnp.broadcast_to(eye, (B, 3, 3)), jnp.swapaxes(jv_rot, 1, 2)], axis=2)
        jw_base = jnp.concatenate([jnp.zeros((B, 3, 3), jv.dtype), jnp.broadcast_to(axes.T, (B, 3, 3))], axis=2)
        jv = jnp.concatenate([jv_base, jv], axis=2)
        jw = jnp.concatenate([jw_base, jw], axis=2)
    return BodyJacobians(poses, jv, jw)


def mass_matrix(model: HandModel, bj: BodyJacobians, armature: Array, geom: HandGeometry | None = None) -> Array:
    """Joint-space mass matrix (n, n) from body Jacobians; ``armature`` (n,) is added on the diagonal."""
    g = hand_geometry(model, geom)
    R = bj.poses.rot
    r = jnp.einsum("bij,bj->bi", R, jnp.asarray(g.body_ipos, R.dtype))  # origin -> com, world
    jv_com = bj.jv + jnp.cross(jnp.swapaxes(bj.jw, 1, 2), r[:, None, :]).swapaxes(1, 2)
    I_w = R @ jnp.asarray(g.body_inertia, R.dtype) @ jnp.swapaxes(R, 1, 2)
    m = jnp.asarray(g.body_mass, R.dtype)
    n = jv_com.shape[-1]
    jv_flat = jv_com.reshape(-1, n)
    jw_I = jnp.sum(I_w[:, :, :, None] * bj.jw[:, None, :, :], axis=2).reshape(-1, n)
    M = jv_flat.T @ (jnp.repeat(m, 3)[:, None] * jv_flat) + bj.jw.reshape(-1, n).T @ jw_I
    return M + jnp.diag(armature)


def gravity_bias(model: HandModel, bj: BodyJacobians, gravity: Array, geom: HandGeometry | None = None) -> Array:
    """g(q) (n,): generalized force that holds the bodies against ``gravity`` (3,) m/s^2."""
    g = hand_geometry(model, geom)
    R = bj.poses.rot
    r = jnp.einsum("bij,bj->bi", R, jnp.asarray(g.body_ipos, R.dtype))
    jv_com = bj.jv + jnp.cross(jnp.swapaxes(bj.jw, 1, 2), r[:, None, :]).swapaxes(1, 2)
    m = jnp.asarray(g.body_mass, R.dtype)
    return -jnp.einsum("b,bik,i->k", m, jv_com, gravity)


def bias_forces(
    model: HandModel,
    q: Array,
    qd: Array,
    armature: Array,
    gravity: Array,
    root_pos: Array | None = None,
    root_rot: Array | None = None,
    base_rot: Array | None = None,
) -> Array:
    """``C(q, qd) qd + g(q)`` by differentiating the mass matrix (Christoffel form).

    ``q`` is the joint vector (root given by ``root_pos``/``root_rot``) or, with ``base_rot``, the full
    ``[base (6), joints]`` vector.
    """

    def M_of(qq: Array) -> Array:
        if base_rot is not None:
            bj = body_jacobians(model, None, None, qq[6:], base=qq[:6], base_rot=base_rot)  # type: ignore[arg-type]
        else:
            bj = body_jacobians(model, root_pos, root_rot, qq)  # type: ignore[arg-type]
        return mass_matrix(model, bj, armature)

    Mdot_qd = jax.jvp(lambda qq: M_of(qq) @ qd, (q,), (qd,))[1]
    dT_dq = jax.grad(lambda qq: 0.5 * qd @ M_of(qq) @ qd)(q)
    if base_rot is not None:
        bj = body_jacobians(model, None, None, q[6:], base=q[:6], base_rot=base_rot)  # type: ignore[arg-type]
    else:
        bj = body_jacobians(model, root_pos, root_rot, q)  # type: ignore[arg-type]
    return Mdot_qd - dT_dq + gravity_bias(model, bj, gravity)
