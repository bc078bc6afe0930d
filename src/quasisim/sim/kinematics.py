"""Differentiable forward kinematics of a :class:`~quasisim.assets.hand.HandModel` in JAX.

Conventions (the same as MuJoCo's ``mj_kinematics``): a body's frame is its parent's frame composed with
the body's fixed pose, then with each of its joints in order; a hinge rotates about its axis through its
anchor, a slide translates along its axis.

The floating base ("base coordinates") is 3 slides along the world axes and 3 hinges about the axes of a
fixed per-clip frame ``R_base``: the hand root is at ``p = base[:3]`` with orientation
``R = R_base @ Rx(base[3]) @ Ry(base[4]) @ Rz(base[5])``. ``R_base`` is chosen per clip so that the
middle angle stays far from gimbal lock. A full generalized position is ``qfull = [base (6), joints (J)]``.
"""

from __future__ import annotations

import dataclasses
import weakref
from dataclasses import dataclass
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from quasisim.assets.hand import HINGE, HandModel
from quasisim.rotations import axis_angle_to_mat, euler_xyz_to_mat, np_quat_to_mat
from quasisim.sim.types import pytree

Array = jnp.ndarray


class BodyPoses(NamedTuple):
    """World poses of all bodies: ``pos`` (B, 3) m, ``rot`` (B, 3, 3)."""

    pos: Array
    rot: Array


@dataclass(frozen=True, eq=False)
class _Tree:
    """Per-depth batches of bodies so that FK is a handful of vectorised steps (fast to compile): the
    hand's topology, which its programs are compiled for."""

    levels: tuple[np.ndarray, ...]
    roots: np.ndarray
    parent: np.ndarray
    jidx: np.ndarray  # (B, M) joint indices applied in order, -1 = none
    jhinge: np.ndarray  # (B, M) bool


@pytree
class HandGeometry:
    """A hand's geometry and inertia (numpy constants, or array leaves of a pytree): all that differs
    between hands of one topology, such as the human hands that stage 1 builds from each demo.

    Attributes:
        local_rot: (B, 3, 3) body rotations relative to their parents.  local_pos: (B, 3) m.
        joint_axis: (B, M, 3) the axes of the (up to M) joints applied at each body, in order (padded).
        joint_pos: (B, M, 3) their anchors in the body frame (m).
        body_ipos: (B, 3) centres of mass in the body frames (m).  body_inertia: (B, 3, 3) inertia about
            the centre of mass, body frame (kg m^2).  body_mass: (B,) kg.
        kp_pos: (K, 3) keypoints in their body frames (m).  joint_range: (J, 2) lower, upper limits.
    """

    local_rot: Array
    local_pos: Array
    joint_axis: Array
    joint_pos: Array
    body_ipos: Array
    body_inertia: Array
    body_mass: Array
    kp_pos: Array
    joint_range: Array


_TREES: weakref.WeakKeyDictionary[HandModel, tuple[_Tree, HandGeometry]] = weakref.WeakKeyDictionary()


def _tree(model: HandModel) -> tuple[_Tree, HandGeometry]:
    """The hand's FK batches and its geometry as numpy constants, derived once per hand object (a cache that
    lives and dies with the hand)."""
    cached = _TREES.get(model)
    if cached is not None:
        return cached
    B = model.n_bodies
    depth = np.zeros(B, dtype=int)
    for b in range(B):
        depth[b] = depth[model.body_parent[b]] + 1 if model.body_parent[b] >= 0 else 0
    levels = tuple(np.flatnonzero(depth == d) for d in range(1, depth.max() + 1))
    M = max(1, max(len(model.body_joints(b)) for b in range(B)))
    jidx = -np.ones((B, M), dtype=int)
    jhinge = np.ones((B, M), dtype=bool)
    jaxis = np.tile(np.array([0.0, 0.0, 1.0]), (B, M, 1))
    jpos = np.zeros((B, M, 3))
    for b in range(B):
        for m, j in enumerate(model.body_joints(b)):
            jidx[b, m] = j
            jhinge[b, m] = model.joint_type[j] == HINGE
            jaxis[b, m] = model.joint_axis[j]
            jpos[b, m] = model.joint_pos[j]
    Rq = np_quat_to_mat(model.body_iquat)
    geom = HandGeometry(
        local_rot=np_quat_to_mat(model.body_quat), local_pos=model.body_pos, joint_axis=jaxis, joint_pos=jpos,
        body_ipos=model.body_ipos, body_inertia=np.einsum("bij,bj,bkj->bik", Rq, model.body_inertia, Rq),
        body_mass=model.body_mass, kp_pos=model.kp_pos, joint_range=model.joint_range,
    )  # fmt: skip
    _TREES[model] = (_Tree(levels, model.roots, model.body_parent, jidx, jhinge), geom)
    return _TREES[model]


def hand_geometry(model: HandModel, geom: HandGeometry | None = None) -> HandGeometry:
    """``geom``, or the geometry of ``model`` as numpy constants (compiled into the programs that use it)."""
    return _tree(model)[1] if geom is None else geom


def geometry_arrays(model: HandModel) -> HandGeometry:
    """The geometry of ``model`` as float32 JAX arrays, to pass to compiled programs as an argument: one
    program then serves every hand of the same topology."""
    return HandGeometry(*(jnp.asarray(x, jnp.float32) for x in dataclasses.astuple(_tree(model)[1])))


class JointFrames(NamedTuple):
    """World axis (J, 3) and anchor (J, 3) of every joint, as applied in FK."""

    axis: Array
    anchor: Array


def forward_kinematics(
    model: HandModel, root_pos: Array, root_rot: Array, q: Array, geom: HandGeometry | None = None
) -> BodyPoses:
    """World poses of every body for root pose (``root_pos`` (3,), ``root_rot`` (3, 3)) and joints ``q`` (J,);
    a hand set of H hands (:func:`~quasisim.assets.hand.join_hands`) takes one root pose per hand, (H, 3) and
    (H, 3, 3). ``geom``: the hand's geometry as arrays (None: ``model``'s own, as constants)."""
    return forward_kinematics_with_joints(model, root_pos, root_rot, q, geom)[0]


def forward_kinematics_with_joints(
    model: HandModel, root_pos: Array, root_rot: Array, q: Array, geom: HandGeometry | None = None
) -> tuple[BodyPoses, JointFrames]:
    """Body poses and the world frames of the joints (for geometric Jacobians)."""
    tr, g = _tree(model)[0], hand_geometry(model, geom)
    B, J = model.n_bodies, model.n_joints
    dtype = jnp.result_type(root_pos, root_rot, q, g.local_pos)  # as the arithmetic below promotes
    roots = jnp.asarray(tr.roots)
    pos = jnp.zeros((B, 3), dtype).at[roots].set(jnp.reshape(root_pos, (-1, 3)))
    rot = jnp.zeros((B, 3, 3), dtype).at[roots].set(jnp.reshape(root_rot, (-1, 3, 3)))
    jaxis = jnp.zeros((J + 1, 3), dtype)  # row J collects writes of padded (absent) joints
    janchor = jnp.zeros((J + 1, 3), dtype)
    qpad = jnp.concatenate([q, jnp.zeros(1, q.dtype)])  # index -1 -> 0 displacement
    for idx_np in tr.levels:
        # index arrays converted at trace time: JAX caches numpy constants per dtype mode (x64 on/off)
        idx = jnp.asarray(idx_np)
        par = jnp.asarray(tr.parent[idx_np])
        Rp, xp = rot[par], pos[par]
        R = Rp @ g.local_rot[idx_np]
        x = xp + jnp.einsum("nij,nj->ni", Rp, g.local_pos[idx_np])
        for m in range(tr.jidx.shape[1]):
            j = tr.jidx[idx_np, m]
            if (j < 0).all():
                continue
            angle = qpad[jnp.asarray(j)]
            axis, jp, hinge = g.joint_axis[idx_np, m], g.joint_pos[idx_np, m], tr.jhinge[idx_np, m]
            anchor = x + jnp.einsum("nij,nj->ni", R, jp)
            axis_w = jnp.einsum("nij,nj->ni", R, axis)
            jrow = jnp.asarray(np.where(j < 0, J, j))
            jaxis = jaxis.at[jrow].set(axis_w)
            janchor = janchor.at[jrow].set(anchor)
            Rh = R @ axis_angle_to_mat(jnp.asarray(axis, dtype), jnp.where(hinge, angle, 0.0))
            xh = anchor - jnp.einsum("nij,nj->ni", Rh, jp)
            xs = x + axis_w * jnp.where(hinge, 0.0, angle)[:, None]
            R = Rh
            x = jnp.where(hinge[:, None], xh, xs)
        pos = pos.at[idx].set(x)
        rot = rot.at[idx].set(R)
    return BodyPoses(pos, rot), JointFrames(jaxis[:J], janchor[:J])


def bases_to_roots(base: Array, base_rot: Array) -> tuple[Array, Array]:
    """Floating-base coordinates to root poses, hand after hand: bases (6 H,) (per hand: position m, then
    intrinsic x-y-z Euler angles rad about the fixed frame) and frames ``base_rot`` (H, 3, 3) (or (3, 3)
    for one hand) -> root positions (H, 3), rotations (H, 3, 3) = ``base_rot @ R_xyz(angles)``."""
    b = jnp.reshape(base, (-1, 6))
    R = jnp.reshape(base_rot, (-1, 3, 3))
    return b[:, :3], jnp.einsum("hij,hjk->hik", R, euler_xyz_to_mat(b[:, 3:6]))


def fk_full(model: HandModel, base_rot: Array, qfull: Array, geom: HandGeometry | None = None) -> BodyPoses:
    """Forward kinematics from a full generalized position ``[base (6), joints (J)]``; a hand set of H hands
    takes ``[bases (6 H), joints (J)]`` and ``base_rot`` (H, 3, 3)."""
    n = 6 * model.n_hands
    p, R = bases_to_roots(qfull[:n], base_rot)
    return forward_kinematics(model, p, R, qfull[n:], geom)


def points_world(poses: BodyPoses, body: Array | np.ndarray, local: Array) -> Array:
    """World positions (N, 3) of points attached to ``body`` (N,) at body-frame offsets ``local`` (N, 3)."""
    return poses.pos[body] + jnp.einsum("nij,nj->ni", poses.rot[body], local)


def keypoints(model: HandModel, poses: BodyPoses, geom: HandGeometry | None = None) -> Array:
    """Robot keypoints (K, 3) in the order of the hand config."""
    return points_world(poses, model.kp_body, jnp.asarray(hand_geometry(model, geom).kp_pos))
