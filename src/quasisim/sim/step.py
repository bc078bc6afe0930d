"""Time stepping of the parameterized quasi-physical simulator.

One substep (``dt``), with the hand's points ``p_i`` attached to their bodies (plus ``alpha * delta_i``):

1. Contacts: hand points against the object's SDF and object surface samples against the table top
   (:mod:`quasisim.sim.contact`), giving forces ``F_i`` on the object, their stiffness ``K_i`` and damping ``D_i``.
2. Object (6 DoF at its centre of mass, generalized velocity ``nu = (v, w)``), linearly implicit Euler:
   ``(M_o + dt D_o + dt^2 K_o) nu+ = (M_o + dt D_o) nu + dt F_o + dt^2 sum_i B_i^T K_i v_i`` where
   ``B_i = [I, -[r_i]x]`` maps ``nu`` to the velocity of the object point under ``p_i``, ``K_o = sum B_i^T K_i B_i``
   and ``F_o`` holds contact forces, gravity, velocity damping, gyroscopic torque and the residual wrench.
3. Hand: each hand's root follows its velocity controls (kinematic); the joints obey
   ``M(q) qdd = u + (1 - alpha) J^T f - g(q) - c qd - k q + f_limit`` (f: reaction of the contacts, with the
   object already moved), integrated linearly implicitly in joint space with the contact stiffness projected
   through the body Jacobians. Coriolis/centrifugal terms of the light finger links and the fictitious
   forces of the kinematic root are neglected.
4. Relaxed points (alpha > 0): ``m_p delta'' = alpha (f_i + a_i)``, implicit per point.

Velocities are updated first and positions with the new velocities (semi-implicit Euler). Each frame
first picks the ``n_candidates`` hand points closest to the object (broad phase); only those are tested
for contact during the frame's substeps.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp

from quasisim.assets.object import SDFArrays, sdf_query
from quasisim.rotations import quat_mul, quat_to_mat, skew
from quasisim.sim.articulation import BodyJacobians, body_jacobians, gravity_bias, mass_matrix
from quasisim.sim.contact import ContactForces, NormalContact, friction, normal_contact, table_sdf
from quasisim.sim.kinematics import hand_geometry
from quasisim.sim.residual import ResidualInput, control_residual, residual_forces
from quasisim.sim.types import Control, Model, Params, State

Array = jax.Array


class Points(NamedTuple):
    """A subset of the hand points: body index (K,) and body-frame offset (K, 3)."""

    body: Array
    local: Array


def _integrate_quat(q: Array, w: Array, dt: float) -> Array:
    """q+ = normalize(q + dt/2 [0, w] q) for world-frame angular velocities ``w`` (..., 3), ``q`` (..., 4)."""
    dq = 0.5 * dt * quat_mul(jnp.concatenate([jnp.zeros((*w.shape[:-1], 1), q.dtype), w], axis=-1), q)
    q = q + dq
    return q / jnp.linalg.norm(q, axis=-1, keepdims=True)


def solve3(A: Array, b: Array) -> Array:
    """Batched solve of (N, 3, 3) systems by the adjugate (XLA's batched LU is ~50x slower on CPU)."""
    c0 = jnp.cross(A[:, 1], A[:, 2])
    c1 = jnp.cross(A[:, 2], A[:, 0])
    c2 = jnp.cross(A[:, 0], A[:, 1])
    det = jnp.sum(A[:, 0] * c0, axis=-1)
    adj_t = jnp.stack([c0, c1, c2], axis=-1)
    return jnp.einsum("nij,nj->ni", adj_t, b) / det[:, None]


def _mm(a: Array, b: Array) -> Array:
    """Batched 3x3 products as fused elementwise ops."""
    return jnp.sum(a[..., :, :, None] * b[..., None, :, :], axis=-2)


def _sandwich_blocks(r: Array, K: Array) -> tuple[Array, Array, Array, Array]:
    """Per point blocks of ``B^T K B`` with ``B = [I, -[r]x]``: (K, -K S, S K, -S K S), S = [r]x."""
    S = skew(r)
    KS = _mm(K, S)
    return K, -KS, _mm(S, K), -_mm(S, KS)


def _assemble(blocks: tuple[Array, Array, Array, Array]) -> Array:
    a, b, c, d = blocks
    return jnp.concatenate([jnp.concatenate([a, b], -1), jnp.concatenate([c, d], -1)], -2)


def _sandwich_sum(r: Array, K: Array) -> Array:
    """``sum_i B_i^T K_i B_i`` (6, 6)."""
    return _assemble(tuple(jnp.sum(x, 0) for x in _sandwich_blocks(r, K)))  # type: ignore[arg-type]


def _sandwich_segments(r: Array, K: Array, seg: Array, n: int) -> Array:
    """``sum_{i in b} B_i^T K_i B_i`` per segment ``b`` (n, 6, 6)."""
    return _assemble(tuple(jax.ops.segment_sum(x, seg, num_segments=n) for x in _sandwich_blocks(r, K)))  # type: ignore[arg-type]


def _project(J: Array, K: Array) -> Array:
    """``sum_b J_b^T K_b J_b`` for (B, 6, n) Jacobians and (B, 6, 6) matrices, as one matrix product."""
    n = J.shape[-1]
    KJ = jnp.sum(K[:, :, :, None] * J[:, None, :, :], axis=2)  # batched small products: fused, not dot_general
    return J.reshape(-1, n).T @ KJ.reshape(-1, n)


def _wrench(r: Array, f: Array) -> Array:
    """Per point ``B^T f`` (N, 6) = (f, r x f)."""
    return jnp.concatenate([f, jnp.cross(r, f)], axis=-1)


def _twist_at(r: Array, nu: Array) -> Array:
    """Velocity (N, 3) at offsets ``r`` of a rigid twist ``nu = (v, w)``."""
    return nu[:3] + jnp.cross(nu[3:], r)


def sdf_lookup(model: Model, pts: Array) -> tuple[Array, Array]:
    """Object-frame signed distance (N,) and outward normal (N, 3) by trilinear interpolation."""
    return sdf_query(SDFArrays(model.sdf_origin, model.sdf_spacing, model.sdf_values, model.sdf_dims), pts)


def object_origin(model: Model, state: State) -> tuple[Array, Array]:
    """Object frame origin (3,) and rotation (3, 3) from the centre-of-mass state."""
    R = quat_to_mat(state.obj_quat)
    return state.obj_pos - R @ model.obj_com, R


def hand_points(model: Model, params: Params, state: State, pts: Points) -> tuple[Array, Array, BodyJacobians]:
    """World positions (K, 3) of ``pts``, their offsets from their body origins (K, 3), body Jacobians."""
    bj = body_jacobians(model.hand, state.root_pos, quat_to_mat(state.root_quat), state.q, geom=model.hand_geom)
    pos, rot = bj.poses
    r = jnp.einsum("nij,nj->ni", rot[pts.body], pts.local)
    return pos[pts.body] + r + params.alpha * state.delta, r, bj


class Contacts(NamedTuple):
    """The contacts of one substep: the object frame, both contact sets and their forces (world frame)."""

    origin: Array  # (3,) object frame origin
    R_o: Array  # (3, 3) object rotation
    nu: Array  # (6,) object twist (v, w) at the centre of mass
    rh: Array  # (K, 3) hand points relative to the centre of mass
    rt: Array  # (M, 3) object surface samples relative to the centre of mass
    Nh: NormalContact  # hand points against the object's SDF
    Nt: NormalContact  # object surface samples against the table top
    C: ContactForces  # forces on the object at the hand points (with friction and residual point forces)
    Ct: ContactForces  # forces of the table on the object


def point_velocities(
    model: Model, state: State, ctrl: Control, bj: BodyJacobians, pts: Points, p: Array, r: Array, alpha: Array
) -> Array:
    """(K, 3) world velocities of the hand points: joint motion, their hand's root velocity controls and,
    while relaxed, the points' own offset velocity."""
    vb = jnp.sum(bj.jv * state.qd, axis=-1)
    wb = jnp.sum(bj.jw * state.qd, axis=-1)
    h = jnp.asarray(model.hand.body_hand)[pts.body]  # (K,) the hand of each point
    return (
        vb[pts.body]
        + jnp.cross(wb[pts.body], r)
        + ctrl.root_vel[h]
        + jnp.cross(ctrl.root_angvel[h], p - state.root_pos[h])
        + alpha * state.delta_vel
    )


def contacts(model: Model, params: Params, state: State, p: Array, v: Array, res_point: Array | None) -> Contacts:
    """Hand points (positions ``p``, velocities ``v``) against the object's SDF and object surface samples
    against the table: spring-damper normal forces and friction (:mod:`quasisim.sim.contact`)."""
    origin, R_o = object_origin(model, state)
    com = state.obj_pos
    nu = jnp.concatenate([state.obj_vel, state.obj_angvel])
    sd, n_loc = sdf_lookup(model, (p - origin) @ R_o)
    n = n_loc @ R_o.T
    anchor_w = origin + state.anchor @ R_o.T
    rh = p - com
    s = params.contact_scale
    Nh = normal_contact(
        p, sd, n, v - _twist_at(rh, nu), anchor_w, state.in_contact, params.d_c, params.k_n * s, params.k_d * s
    )
    w = origin + model.obj_surface @ R_o.T
    rt = w - com
    sd_t, n_t = table_sdf(w, model.table)
    Nt = normal_contact(
        w, sd_t, n_t, _twist_at(rt, nu), state.table_anchor, state.table_contact, jnp.zeros((), w.dtype),
        params.table_k_n, params.table_k_d, linear_damping=True,
    )  # fmt: skip
    C = friction(Nh, params.k_f * s, params.mu, v - _twist_at(rh, nu))
    if res_point is not None:
        C = C._replace(force=C.force + res_point)
    Ct = friction(Nt, params.table_k_f, params.table_mu, _twist_at(rt, nu))
    return Contacts(origin, R_o, nu, rh, rt, Nh, Nt, C, Ct)


def object_step(model: Model, params: Params, state: State, c: Contacts, v: Array, res_wrench: Array | None) -> Array:
    """The object's new twist (6,): ``(M_o + dt D_o + dt^2 K_o) nu+ = (M_o + dt D_o) nu + dt F_o + dt^2 sum_i
    B_i^T K_i v_i`` (contact stiffness and damping linearised about the current state)."""
    dt, m, eye3 = model.dt, params.obj_mass, jnp.eye(3, dtype=v.dtype)
    I_w = c.R_o @ params.obj_inertia @ c.R_o.T
    om, vel = state.obj_angvel, state.obj_vel
    W = jnp.sum(_wrench(c.rh, c.C.force), 0) - jnp.sum(_wrench(c.rt, c.Ct.force), 0)
    W = W + jnp.concatenate(
        [
            m * params.gravity - params.obj_lin_damp * m * vel,
            -jnp.cross(om, I_w @ om) - params.obj_ang_damp * (I_w @ om),
        ]
    )
    if res_wrench is not None:
        W = W + res_wrench
    K_o = _sandwich_sum(c.rh, c.C.K) + _sandwich_sum(c.rt, c.Ct.K)
    D_o = _sandwich_sum(c.rh, c.C.D) + _sandwich_sum(c.rt, c.Ct.D)
    M_o = jax.scipy.linalg.block_diag(m * eye3, I_w)
    D_o = D_o + jax.scipy.linalg.block_diag(params.obj_lin_damp * m * eye3, params.obj_ang_damp * I_w)
    hand_motion = jnp.sum(_wrench(c.rh, jnp.einsum("nij,nj->ni", c.C.K, v)), 0)
    A = M_o + dt * D_o + dt * dt * K_o
    return jnp.linalg.solve(A, (M_o + dt * D_o) @ c.nu + dt * W + dt * dt * hand_motion)


def hand_reaction(model: Model, c: Contacts, nu_new: Array) -> Array:
    """(K, 3) contact forces on the hand points against the moved object (reaction, linearised)."""
    dt = model.dt
    du, du_old = _twist_at(c.rh, nu_new), _twist_at(c.rh, c.nu)
    return -(c.C.force - dt * jnp.einsum("nij,nj->ni", c.C.K, du) - jnp.einsum("nij,nj->ni", c.C.D, du - du_old))


def joint_step(
    model: Model, params: Params, state: State, ctrl: Control, bj: BodyJacobians, pts: Points, r: Array,
    c: Contacts, f_hand: Array, frac: Array | float,
) -> Array:  # fmt: skip
    """The joints' new velocities (J,): ``M(q) qdd = u + (1 - alpha) J^T f - g(q) - c qd - k q + f_limit``,
    linearly implicit with the contact stiffness and damping projected through the body Jacobians."""
    dt, hand = model.dt, model.hand
    B = hand.n_bodies
    one_m_a = 1.0 - params.alpha
    Wb = jax.ops.segment_sum(_wrench(r, f_hand), pts.body, num_segments=B)  # (B, 6) about body origins
    J6 = jnp.concatenate([bj.jv, bj.jw], axis=1)  # (B, 6, J)
    tau_c = one_m_a * (J6.reshape(-1, J6.shape[-1]).T @ Wb.reshape(-1))
    K_h = one_m_a * _project(J6, _sandwich_segments(r, c.C.K, pts.body, B))
    D_h = one_m_a * _project(J6, _sandwich_segments(r, c.C.D, pts.body, B))

    q, qd = state.q, state.qd
    jr = hand_geometry(hand, model.hand_geom).joint_range
    lo, hi = jnp.asarray(jr[:, 0]), jnp.asarray(jr[:, 1])
    limited = jnp.asarray(hand.joint_limited)
    below, above = limited & (q < lo), limited & (q > hi)
    f_lim = params.limit_k * (jnp.where(below, lo - q, 0.0) + jnp.where(above, hi - q, 0.0))
    k_j = params.joint_stiffness + params.limit_k * (below | above)
    q_star = ctrl.q_target - (1.0 - frac) * (dt * model.substeps) * ctrl.qd_target
    tau_pd = params.joint_kp * (q_star - q) + params.joint_kv * (ctrl.qd_target - qd)
    tau_j = (
        ctrl.tau
        + tau_pd
        - gravity_bias(hand, bj, params.gravity, model.hand_geom)
        - params.joint_damping * qd
        - params.joint_stiffness * q
        + f_lim
    )
    M = mass_matrix(hand, bj, params.armature, model.hand_geom)
    D = D_h + jnp.diag(params.joint_damping + params.joint_kv)
    A_h = M + dt * D + dt * dt * (K_h + jnp.diag(k_j + params.joint_kp))
    return jnp.linalg.solve(A_h, (M + dt * D) @ qd + dt * (tau_c + tau_j))


def relaxed_point_step(model: Model, params: Params, state: State, ctrl: Control, c: Contacts, f_hand: Array) -> Array:
    """The relaxed points' new offset velocities (K, 3): ``m_p delta'' = alpha (f_i + a_i)``, implicit per point."""
    dt, a = model.dt, params.alpha
    mp = params.point_mass * jnp.eye(3, dtype=f_hand.dtype)
    rhs_p = jnp.einsum("nij,nj->ni", mp + dt * a * c.C.D, state.delta_vel) + dt * a * (f_hand + ctrl.point_force)
    return solve3(mp + dt * a * c.C.D + dt * dt * a * c.C.K, rhs_p)


def substep(
    model: Model,
    params: Params,
    state: State,
    ctrl: Control,
    pts: Points,
    res_wrench: Array | None = None,
    frac: Array | float = 1.0,
    res_point: Array | None = None,
) -> State:
    """Advance ``state`` by ``model.dt``; the point arrays of ``state``/``ctrl`` are those of ``pts``.

    ``frac`` in (0, 1] is the position of this substep's end within the frame (for the PD targets).
    ``res_wrench`` (6,) is an extra force and torque on the object's centre of mass (world); ``res_point``
    (K, 3) extra forces on the object at the hand points, with their reactions on the hand (residual physics).
    Steps 1-4 of the module docstring: contacts, object, joints, relaxed points; positions then follow
    the new velocities (semi-implicit Euler).
    """
    dt = model.dt
    p, r, bj = hand_points(model, params, state, pts)
    v = point_velocities(model, state, ctrl, bj, pts, p, r, params.alpha)
    c = contacts(model, params, state, p, v, res_point)
    nu_new = object_step(model, params, state, c, v, res_wrench)
    f_hand = hand_reaction(model, c, nu_new)
    qd_new = joint_step(model, params, state, ctrl, bj, pts, r, c, f_hand, frac)
    dv_new = relaxed_point_step(model, params, state, ctrl, c, f_hand)
    return State(
        root_pos=state.root_pos + dt * ctrl.root_vel,
        root_quat=_integrate_quat(state.root_quat, ctrl.root_angvel, dt),
        q=state.q + dt * qd_new,
        qd=qd_new,
        delta=state.delta + dt * dv_new,
        delta_vel=dv_new,
        obj_pos=state.obj_pos + dt * nu_new[:3],
        obj_quat=_integrate_quat(state.obj_quat, nu_new[3:], dt),
        obj_vel=nu_new[:3],
        obj_angvel=nu_new[3:],
        anchor=(c.C.anchor - c.origin) @ c.R_o,
        in_contact=c.Nh.keep.astype(p.dtype),
        table_anchor=c.Ct.anchor,
        table_contact=c.Nt.keep.astype(p.dtype),
    )


def select_candidates(model: Model, params: Params, state: State) -> Array:
    """Indices (K,) of the hand points closest to the object surface (broad phase for one frame)."""
    all_pts = Points(jnp.asarray(model.point_body), model.point_local)
    p, _, _ = hand_points(model, params, state, all_pts)
    origin, R_o = object_origin(model, state)
    sd, _ = sdf_lookup(model, (p - origin) @ R_o)
    _, idx = jax.lax.top_k(-jax.lax.stop_gradient(sd), model.n_candidates)
    return idx


def residual_input(model: Model, params: Params, state: State, pts: Points, sub: State) -> tuple[ResidualInput, Array]:
    """What the residual networks and the control transformation see of ``state`` (object frame, about the
    centre of mass; ``pts``/``sub``: the frame's candidate hand points) and the object's rotation (3, 3)."""
    p, r, bj = hand_points(model, params, sub, pts)
    vb = jnp.einsum("bij,j->bi", bj.jv, sub.qd)
    wb = jnp.einsum("bij,j->bi", bj.jw, sub.qd)
    v = vb[pts.body] + jnp.cross(wb[pts.body], r)
    origin, R = object_origin(model, state)
    com = state.obj_pos
    v_obj_at_p = state.obj_vel + jnp.cross(state.obj_angvel, p - com)
    p_loc = (p - origin) @ R
    sd, n_loc = sdf_lookup(model, p_loc)
    surf_w = origin + model.obj_surface @ R.T
    x = ResidualInput(
        obj_pts=model.obj_surface - model.obj_com,
        obj_vel=(state.obj_vel + jnp.cross(state.obj_angvel, surf_w - com)) @ R,
        obj_nrm=model.obj_normals,
        hand_pts=p_loc - model.obj_com,
        hand_vel=(v - v_obj_at_p) @ R,
        depth=params.d_c - sd,
        contact_pt=p_loc - sd[:, None] * n_loc - model.obj_com,
        contact_nrm=n_loc,
    )
    return x, R


def residual_terms(model: Model, params: Params, x: ResidualInput, R: Array) -> tuple[Array, Array]:
    """The residual networks' wrench (6,) on the object and per-point forces (K, 3), world frame."""
    nets = eqx.combine(params.residual, model.residual_static)
    wrench, local, idx = residual_forces(nets, x)
    wrench_w = jnp.concatenate([R @ wrench[:3], R @ wrench[3:]]) * params.residual_global_on
    point = jnp.zeros((len(x.hand_pts), 3), wrench.dtype).at[idx].add(local @ R.T) * params.residual_local_on
    return wrench_w, point


def transformed_control(model: Model, params: Params, state: State, ctrl: Control, x: ResidualInput) -> Control:
    """The control transformation: ``u + g(state, u)`` for the frame's root velocities, joint targets and
    joint target velocities (:func:`quasisim.sim.residual.control_residual`)."""
    ct = eqx.combine(params.control_transform, model.control_transform_static)
    u = jnp.concatenate([ctrl.root_vel.ravel(), ctrl.root_angvel.ravel(), ctrl.q_target - state.q, ctrl.qd_target])
    n, J = ctrl.root_vel.size, ctrl.q_target.shape[0]
    d = control_residual(ct, x, u, n // 3)
    return dataclasses.replace(
        ctrl, root_vel=ctrl.root_vel + d[:n].reshape(-1, 3), root_angvel=ctrl.root_angvel + d[n : 2 * n].reshape(-1, 3),
        q_target=ctrl.q_target + d[2 * n : 2 * n + J], qd_target=ctrl.qd_target + d[2 * n + J :],
    )  # fmt: skip


def frame(model: Model, params: Params, state: State, ctrl: Control, res_wrench: Array | None = None) -> State:
    """``model.substeps`` substeps under one frame's control (with a broad phase at the frame's start).

    With ``params.residual`` set, the residual networks are evaluated once on the frame's starting state and
    their forces held over the frame; with ``params.control_transform`` set, the frame's control is
    transformed first (:func:`transformed_control`); ``res_wrench`` adds an external wrench (6,) on the object."""
    idx = select_candidates(model, params, state)
    pts = Points(jnp.asarray(model.point_body)[idx], model.point_local[idx])
    sub = dataclasses.replace(
        state,
        delta=state.delta[idx],
        delta_vel=state.delta_vel[idx],
        anchor=state.anchor[idx],
        in_contact=state.in_contact[idx],
    )
    res_point = None
    if params.residual is not None or params.control_transform is not None:
        x, R = residual_input(model, params, state, pts, sub)
        if params.control_transform is not None:
            ctrl = transformed_control(model, params, state, ctrl, x)
        if params.residual is not None:
            w_res, res_point = residual_terms(model, params, x, R)
            res_wrench = w_res if res_wrench is None else res_wrench + w_res
    sub_ctrl = dataclasses.replace(ctrl, point_force=ctrl.point_force[idx])

    def body(s: State, k: Array) -> tuple[State, None]:
        frac = (k + 1.0) / model.substeps
        return substep(model, params, s, sub_ctrl, pts, res_wrench, frac, res_point), None

    s, _ = jax.lax.scan(body, sub, jnp.arange(model.substeps, dtype=state.q.dtype))
    # points outside the broad phase: free relaxed motion under their own actuation, no contact
    T = model.dt * model.substeps
    dv = state.delta_vel + T * params.alpha * ctrl.point_force / params.point_mass
    return dataclasses.replace(
        s,
        delta=(state.delta + T * dv).at[idx].set(s.delta),
        delta_vel=dv.at[idx].set(s.delta_vel),
        anchor=state.anchor.at[idx].set(s.anchor),
        in_contact=jnp.zeros_like(state.in_contact).at[idx].set(s.in_contact),
    )


def rollout(model: Model, params: Params, state0: State, controls: Control, checkpoint: bool = True) -> State:
    """Roll out ``controls`` (a :class:`Control` with a leading frame axis F) from ``state0``.

    Returns the states after each frame (leading axis F). With ``checkpoint`` the substeps of a frame are
    recomputed in the backward pass (memory grows with frames, not substeps).
    """

    def one(s: State, c: Control) -> State:
        return frame(model, params, s, c)

    f = jax.checkpoint(one) if checkpoint else one

    def body(s: State, c: Control) -> tuple[State, State]:
        s = f(s, c)
        return s, s

    _, states = jax.lax.scan(body, state0, controls)
    return states


def initial_state(model: Model, root_pos: Array, root_quat: Array, q: Array, obj_pos: Array, obj_quat: Array) -> State:
    """A resting state from world-frame poses: hand roots (H, 3), (H, 4) (or (3,), (4,) for one hand) and
    joints ``q``; object frame origin and orientation."""
    f32 = jnp.float32
    R = quat_to_mat(jnp.asarray(obj_quat, f32))
    com = model.to_sim(jnp.asarray(obj_pos, f32)) + R @ model.obj_com
    N, M = model.n_points, model.obj_surface.shape[0]
    z3 = jnp.zeros(3, dtype=f32)
    q = jnp.asarray(q, f32)
    return State(
        root_pos=model.to_sim(jnp.reshape(jnp.asarray(root_pos, f32), (-1, 3))),
        root_quat=jnp.reshape(jnp.asarray(root_quat, f32), (-1, 4)),
        q=q,
        qd=jnp.zeros_like(q),
        delta=jnp.zeros((N, 3), f32),
        delta_vel=jnp.zeros((N, 3), f32),
        obj_pos=com,
        obj_quat=jnp.asarray(obj_quat, f32),
        obj_vel=z3,
        obj_angvel=z3,
        anchor=jnp.zeros((N, 3), f32),
        in_contact=jnp.zeros(N, f32),
        table_anchor=jnp.zeros((M, 3), f32),
        table_contact=jnp.zeros(M, f32),
    )


def object_pose(model: Model, states: State) -> tuple[Array, Array]:
    """World object-frame origin (..., 3) and orientation (..., 4) of (batched) states."""
    R = quat_to_mat(states.obj_quat)
    return model.to_world(states.obj_pos - jnp.einsum("...ij,j->...i", R, model.obj_com)), states.obj_quat
