"""Pytrees of the quasi-physical simulator (Brax/MJX style): Model, Params, State, Control.

* :class:`Model` is fixed per scene: geometry and sizes (array leaves for geometry so that one compiled
  rollout serves scenes of equal sizes; counts and the hand's kinematic tree are static metadata).
* :class:`Params` are the simulator's parameters: every curriculum quantity (alpha, d_c, k_n, k_f, k_d,
  mu), the identified object parameters S (mass, inertia, velocity damping), gravity, the table contact,
  joint properties and the residual networks with their on/off switches. All are array leaves, so
  changing them never recompiles and gradients flow to every one of them.
* :class:`State` is the full dynamic state including persistent friction anchors.
* :class:`Control` is one frame's control, held over the frame's substeps.

SI units throughout: m, kg, s, N, rad.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

Array = jax.Array


def pytree(cls: type) -> type:
    """Register a frozen dataclass as a pytree; fields with ``metadata={"static": True}`` are metadata."""
    cls = dataclasses.dataclass(frozen=True)(cls)
    data, meta = [], []
    for f in dataclasses.fields(cls):
        (meta if f.metadata.get("static") else data).append(f.name)
    jax.tree_util.register_dataclass(cls, data_fields=data, meta_fields=meta)
    return cls


def static(**kw: Any) -> Any:
    return dataclasses.field(metadata={"static": True}, **kw)


@pytree
class Model:
    """The simulated scene.

    Attributes:
        hand: the parsed :class:`~quasisim.assets.hand.HandModel` (static); for two hands, the hand set of
            :func:`~quasisim.assets.hand.join_hands` (one root per hand, joints and points concatenated).
        point_body: (N,) int32 body index of each hand point.
        point_local: (N, 3) hand points in their body frames.
        sdf_values: (L,) object signed distances (m), negative inside, at the nodes of an (nx, ny, nz) grid
            (``sdf_dims``) flattened in C order and padded to a power of two ``L``
            (:meth:`~quasisim.assets.object.SDFGrid.as_flat`: one compiled program for the objects of a bucket).
        sdf_dims: (3,) int32 nx, ny, nz.
        sdf_origin: (3,) object-frame position of grid node (0, 0, 0).  sdf_spacing: () grid spacing (m).
        obj_com: (3,) centre of mass in the object frame.
        obj_surface: (M, 3) object samples (object frame) used for table contact, on the convex hull's
            surface by default (``SimOptions.table_points``).
        obj_normals: (M, 3) their outward normals.
        table: (5,) xmin, xmax, ymin, ymax, top of the table box (m), in simulator coordinates.
        offset: (3,) world position of the simulator's origin (positions in State are relative to it, which
            keeps float32 resolution at micrometres; use :meth:`to_world` / :meth:`to_sim`).
        hand_geom: the hand's geometry as array leaves (:class:`~quasisim.sim.kinematics.HandGeometry`) for a
            hand built per demo (stage 1's human hand: one compiled program for every demo), or None (the
            hand's own geometry, compiled in as constants).
        dt: substep (s).  substeps: substeps per frame.
        n_candidates: hand points examined for contact in each frame (the closest to the object at the
            frame's start; a broad phase that bounds the per-substep cost).
        residual_static: the non-array part of the residual networks (their arrays live in Params).
        control_transform_static: the same for the control transformation.
    """

    hand: Any = static()
    point_body: Array = None  # type: ignore[assignment]
    point_local: Array = None  # type: ignore[assignment]
    sdf_values: Array = None  # type: ignore[assignment]
    sdf_dims: Array = None  # type: ignore[assignment]
    sdf_origin: Array = None  # type: ignore[assignment]
    sdf_spacing: Array = None  # type: ignore[assignment]
    obj_com: Array = None  # type: ignore[assignment]
    obj_surface: Array = None  # type: ignore[assignment]
    obj_normals: Array = None  # type: ignore[assignment]
    table: Array = None  # type: ignore[assignment]
    offset: Array = None  # type: ignore[assignment]
    hand_geom: Any = None
    dt: float = static(default=0.001)
    substeps: int = static(default=50)
    n_candidates: int = static(default=128)
    residual_static: Any = static(default=None)
    control_transform_static: Any = static(default=None)

    def to_world(self, x: Array) -> Array:
        return x + self.offset

    def to_sim(self, x: Array) -> Array:
        return x - self.offset

    @property
    def n_points(self) -> int:
        return len(self.point_body)

    @property
    def n_joints(self) -> int:
        return self.hand.n_joints


@pytree
class Params:
    """Simulator parameters (all array leaves; see module docstring).

    Attributes:
        alpha: point-set relaxation in [0, 1] (0: rigid articulated hand).
        d_c: contact distance threshold (m).  k_n: contact stiffness (N/m per point).
        k_f: friction spring stiffness (N/m per point).  k_d: contact damping (N s/m^2, multiplies d * d').
        mu: friction coefficient.
        contact_scale: multiplies k_n, k_f and k_d: the curriculum keeps the paper's values, this maps them
            to this simulator's units (calibrated against MuJoCo, see docs/simulator.md).
        table_k_n, table_k_d, table_k_f, table_mu: the same for object-table contact (per surface sample;
            the table's damping is linear, ``table_k_d d'`` in N s/m).
        obj_mass: (kg).  obj_inertia: (3, 3) about the centre of mass, object axes (kg m^2).
        obj_lin_damp, obj_ang_damp: velocity damping rates (1/s).
        gravity: (3,) m/s^2.
        point_mass: mass of one hand point for the relaxed point dynamics (kg).
        joint_damping: (J,) N m s/rad.  joint_stiffness: (J,) N m/rad (towards 0).  armature: (J,) kg m^2.
        joint_kp, joint_kv: (J,) gains of the joint actuators' PD law (N m/rad, N m s/rad); 0 gives the
            paper's pure force control, the target's gains make the controls PD targets as in the targets.
        limit_k: joint-limit penalty stiffness (N m/rad).
        residual: the array leaves of the residual networks (``eqx.filter(nets, eqx.is_array)``) or None;
            see :func:`quasisim.sim.build.attach_residual`.
        residual_local_on, residual_global_on: 0/1 switches multiplying the residual forces.
        control_transform: the array leaves of the control transformation or None; see
            :func:`quasisim.sim.build.attach_control_transform`.
    """

    alpha: Array
    d_c: Array
    k_n: Array
    k_f: Array
    k_d: Array
    mu: Array
    contact_scale: Array
    table_k_n: Array
    table_k_d: Array
    table_k_f: Array
    table_mu: Array
    obj_mass: Array
    obj_inertia: Array
    obj_lin_damp: Array
    obj_ang_damp: Array
    gravity: Array
    point_mass: Array
    joint_damping: Array
    joint_stiffness: Array
    armature: Array
    limit_k: Array
    joint_kp: Array
    joint_kv: Array
    residual: Any = None
    residual_local_on: Array = None  # type: ignore[assignment]
    residual_global_on: Array = None  # type: ignore[assignment]
    control_transform: Any = None

    def replace(self, **kw: Any) -> Params:
        """A copy with some leaves replaced (cast to the dtype of the leaf they replace)."""

        def cast(k: str, v: Any) -> Any:
            old = getattr(self, k)
            return v if k in NETWORKS or old is None else jnp.asarray(v, jnp.asarray(old).dtype)

        return dataclasses.replace(self, **{k: cast(k, v) for k, v in kw.items()})


NETWORKS = ("residual", "control_transform")  # Params fields holding network weights (pytrees, not arrays)


@pytree
class State:
    """Dynamic state.

    Attributes:
        root_pos: (H, 3) position of each hand's root (H = 1 for one hand).  root_quat: (H, 4) w x y z.
        q, qd: (J,) joint positions and velocities.
        delta, delta_vel: (N, 3) free displacement of the relaxed points from their bodies and its velocity.
        obj_pos: (3,) object centre of mass (world).  obj_quat: (4,) object orientation.
        obj_vel, obj_angvel: (3,) linear and angular velocity (world).
        anchor: (N, 3) friction anchors in the object frame.  in_contact: (N,) 1 while in contact.
        table_anchor: (M, 3) table friction anchors (world).  table_contact: (M,) 1 while in contact.
    """

    root_pos: Array
    root_quat: Array
    q: Array
    qd: Array
    delta: Array
    delta_vel: Array
    obj_pos: Array
    obj_quat: Array
    obj_vel: Array
    obj_angvel: Array
    anchor: Array
    in_contact: Array
    table_anchor: Array
    table_contact: Array


@pytree
class Control:
    """One frame's control, held over its substeps.

    The joint force is ``tau + kp (q* - q) + kv (qd* - qd)`` with ``q*`` moving linearly over the frame to
    ``q_target`` at velocity ``qd_target`` (the same PD law and interpolation as the target simulators).

    Attributes:
        root_vel, root_angvel: (H, 3) each hand root's linear (m/s) and angular (rad/s, world) velocity.
        tau: (J,) joint forces (N m).  q_target: (J,) joint targets at the frame's end (rad).
        qd_target: (J,) joint target velocity over the frame (rad/s).
        point_force: (N, 3) free actuation of the relaxed points (N), used while alpha > 0.
    """

    root_vel: Array
    root_angvel: Array
    tau: Array
    q_target: Array
    qd_target: Array
    point_force: Array
