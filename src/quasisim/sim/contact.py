"""The parameterized spring-damper contact model with persistent friction anchors (DESIGN section 3).

A point ``p`` touches a surface when its signed distance ``sd < d_c``. With penetration ``d = d_c - sd``
(> 0) and penetration rate ``d' = -n . (v_p - v_a)``:

    normal force on the surface owner     F_n = -max(k_n d + k_d d d', 0) n
    static friction (spring to anchor a)  F_s = k_f T_n (p - a),   T_n = I - n n^T
    sliding (|F_s| > mu |F_n|)           F_t = mu |F_n| along the tangential slip velocity (implicit, see
                                          :func:`friction`); the anchor moves onto the cone

The damping term multiplies ``d * d'`` (Hunt-Crossley form: continuous at first touch) and acts against
the rate of penetration. A new contact stores its anchor at the nearest surface point; leaving the contact
distance drops it. The point itself receives the opposite force.

Besides the forces, :func:`spring_damper` returns their stiffness ``K`` and damping ``D`` (3 x 3 per
contact, ``dF = K (dp - da) + D (dv_p - dv_a)``) that the simulator uses for its linearly implicit step.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

Array = jnp.ndarray
ANCHOR_KEEP = 1.0e-3  # m beyond d_c within which a separated contact keeps its friction anchor
SLIP_VELOCITY = 1.0e-4  # m/s below which sliding friction is linear in the slip velocity


class ContactForces(NamedTuple):
    """Per-contact results (leading axis = points).

    Attributes:
        force: (N, 3) force on the surface owner at each point (0 when not in contact).
        K: (N, 3, 3) stiffness, D: (N, 3, 3) damping (see module docstring).
        anchor: (N, 3) updated anchors (world).  active: (N,) 1 where in contact.
        normal_mag: (N,) |F_n|.
    """

    force: Array
    K: Array
    D: Array
    anchor: Array
    active: Array
    normal_mag: Array


class NormalContact(NamedTuple):
    """The normal part of the contacts and what friction needs (see :func:`normal_contact`)."""

    act: Array  # (N,) 1 in contact
    fn: Array  # (N,) normal force magnitude
    f_normal: Array  # (N, 3)
    K_normal: Array  # (N, 3, 3)
    D: Array  # (N, 3, 3)
    T: Array  # (N, 3, 3) tangent projector
    disp: Array  # (N, 3) tangential stretch of the friction spring
    anchor: Array  # (N, 3) current anchors (world)
    p: Array  # (N, 3)
    keep: Array  # (N,) bool: within d_c + ANCHOR_KEEP, the anchor is kept


def normal_contact(
    p: Array,
    sd: Array,
    n: Array,
    v_rel: Array,
    anchor: Array,
    was_active: Array,
    d_c: Array,
    k_n: Array,
    k_d: Array,
    linear_damping: bool = False,
) -> NormalContact:
    """Normal spring-damper forces for points ``p`` (N, 3) with signed distances ``sd`` (N,) and outward unit
    normals ``n`` (N, 3); ``v_rel`` (N, 3) = point velocity - surface material velocity; ``anchor`` (N, 3)
    world anchors of the previous step, valid where ``was_active`` (N,) is 1.

    The damping force is ``k_d d d'`` (the paper's form) or, with ``linear_damping``, ``k_d d'`` (used for
    the table, whose resting penetration is too small for ``d d'`` to damp anything)."""
    inside = sd < d_c
    keep = sd < d_c + ANCHOR_KEEP  # anchors survive brief separations (contacts flicker at rest)
    act = inside.astype(p.dtype)
    d = jnp.where(inside, d_c - sd, 0.0)
    d_rate = -jnp.sum(n * v_rel, axis=-1)
    c = k_d * jnp.ones_like(d) if linear_damping else k_d * d
    fn = jnp.maximum(k_n * d + c * d_rate, 0.0) * act
    pushing = (fn > 0).astype(p.dtype)
    nn = n[:, :, None] * n[:, None, :]
    dk = jnp.zeros_like(d) if linear_damping else k_d * d_rate
    K = jnp.maximum(k_n + dk, 0.0)[:, None, None] * nn * pushing[:, None, None]
    D = (c * pushing)[:, None, None] * nn
    nearest = p - sd[:, None] * n  # nearest surface point: the anchor of a new contact
    a = jnp.where((was_active > 0)[:, None], anchor, nearest)
    T = jnp.eye(3, dtype=p.dtype) - nn
    disp = jnp.einsum("nij,nj->ni", T, p - a)
    return NormalContact(act, fn, -fn[:, None] * n, K, D, T, disp, a, p, keep)


def friction(
    nc: NormalContact, k_f: Array, mu: Array, v_rel: Array, v_slip: float = SLIP_VELOCITY, eps: float = 1e-12
) -> ContactForces:
    """Add friction to the normal contacts ``nc``; ``v_rel`` (N, 3) = point velocity - surface velocity.

    A contact sticks while its spring stays inside the cone (``k_f |T (p - a)| <= mu |F_n|``): it pulls with
    ``k_f T (p - a)`` and adds ``k_f T`` to ``K``. Beyond the cone it slides: the anchor moves onto the cone
    and, while it slips faster than ``v_slip``, the friction is Coulomb's, ``mu |F_n|`` along the tangential
    slip velocity ``v_t``, written as the viscous force ``c v_t`` with ``c = mu |F_n| / |v_t|`` and put in
    ``D``: an implicit step then never reverses a slip (explicit Coulomb friction chatters: the force flips
    the slip every step). A slower contact beyond the cone sticks with its spring clamped onto the cone.
    """
    s_norm = jnp.sqrt(jnp.sum(nc.disp * nc.disp, axis=-1) + eps)
    limit = mu * nc.fn
    reach = limit / jnp.maximum(k_f, eps)  # longest stretch inside the cone (m)
    over = (s_norm > reach) & (nc.act > 0)  # separated (but kept) contacts hold their anchor
    disp = jnp.where(over[:, None], nc.disp * (reach / s_norm)[:, None], nc.disp)  # spring clamped to the cone
    anchor = nc.p - disp - (nc.p - nc.anchor - nc.disp)  # keep the anchor's normal offset
    v_t = jnp.einsum("nij,nj->ni", nc.T, v_rel)
    v_norm = jnp.sqrt(jnp.sum(v_t * v_t, axis=-1) + eps)
    slide = over & (v_norm > v_slip)  # beyond the cone and slipping; slow contacts stick on the cone
    c = limit / v_norm
    f_fric = jnp.where(slide[:, None], c[:, None] * v_t, k_f * disp) * nc.act[:, None]
    a_new = jnp.where(slide[:, None], nc.p - reach[:, None] * v_t / v_norm[:, None], anchor)
    a_new = jnp.where(nc.keep[:, None], a_new, nc.p)  # far from the surface: re-taken at the next touch
    stick = (~slide).astype(nc.p.dtype) * nc.act
    K = nc.K_normal + (k_f * stick)[:, None, None] * nc.T
    D = nc.D + (c * slide)[:, None, None] * nc.T
    return ContactForces(nc.f_normal + f_fric, K, D, a_new, nc.act, nc.fn)


def spring_damper(
    p: Array,
    sd: Array,
    n: Array,
    v_rel: Array,
    anchor: Array,
    was_active: Array,
    d_c: Array,
    k_n: Array,
    k_d: Array,
    k_f: Array,
    mu: Array,
) -> ContactForces:
    """Normal and friction forces with the stick/slide decision on the current stretch (see the module
    docstring); :func:`normal_contact` + :func:`friction`."""
    return friction(normal_contact(p, sd, n, v_rel, anchor, was_active, d_c, k_n, k_d), k_f, mu, v_rel)


def table_sdf(w: Array, table: Array) -> tuple[Array, Array]:
    """Signed distance of points ``w`` (M, 3) to the top face of the table box (xmin, xmax, ymin, ymax, top):
    ``z - top`` inside the footprint, +1 m (no contact) outside. Normal +z."""
    inside = (w[:, 0] > table[0]) & (w[:, 0] < table[1]) & (w[:, 1] > table[2]) & (w[:, 1] < table[3])
    sd = jnp.where(inside, w[:, 2] - table[4], 1.0)
    n = jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0], w.dtype), w.shape)
    return sd, n
