"""The parameterized spring-damper contact model with persistent friction anchors (DESIGN section 3).

A point ``p`` touches a surface when its signed distance ``sd < d_c``. With penetration ``d = d_c - sd``
(> 0) and penetration rate ``d' = -n . (v_p - v_a)``:

    normal force on the surface owner     F_n = -max(k_n d + k_d d d', 0) n
    static friction (spring to anchor a)  F_s = k_f T_n (p - a),   T_n = I - n n^T
    sliding (|F_s| > mu |F_n|)           F_t = mu |F_n| F_s / |F_s|, and the anchor slides along so that
                                          the spring sits on the friction cone: a <- p - (mu |F_n| / |F_s|) T_n (p - a)

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
    dt: float = 0.0,
    eps: float = 1e-9,
) -> ContactForces:
    """Contact forces for points ``p`` (N, 3) with signed distances ``sd`` (N,) and outward unit normals
    ``n`` (N, 3) of the surface; ``v_rel`` (N, 3) = point velocity - surface material velocity;
    ``anchor`` (N, 3) world anchors of the previous step, valid where ``was_active`` (N,) is 1.

    ``dt`` caps the friction stiffness reported in ``K`` so that the spring's predicted stretch after a step
    of ``dt`` cannot exceed the friction cone (an implicit step must not make a contact stickier than the
    cone allows)."""
    inside = sd < d_c
    act = inside.astype(p.dtype)
    d = jnp.where(inside, d_c - sd, 0.0)
    d_rate = -jnp.sum(n * v_rel, axis=-1)
    fn = jnp.maximum(k_n * d + k_d * d * d_rate, 0.0) * act
    pushing = (fn > 0).astype(p.dtype)
    f_normal = -fn[:, None] * n

    nearest = p - sd[:, None] * n  # nearest surface point: the anchor of a new contact
    a = jnp.where((was_active > 0)[:, None], anchor, nearest)
    T = jnp.eye(3, dtype=p.dtype) - n[:, :, None] * n[:, None, :]
    disp = jnp.einsum("nij,nj->ni", T, p - a)
    fs = k_f * disp
    fs_norm = jnp.sqrt(jnp.sum(fs * fs, axis=-1) + eps)
    limit = mu * fn
    slide = fs_norm > limit
    scale = jnp.where(slide, limit / fs_norm, 1.0)
    f_fric = fs * scale[:, None] * act[:, None]
    a_new = jnp.where(slide[:, None], p - disp * scale[:, None], a)
    a_new = jnp.where(inside[:, None], a_new, p)  # no contact: the anchor is re-taken at the next touch

    nn = n[:, :, None] * n[:, None, :]
    stick = (~slide).astype(p.dtype) * act
    pred = disp + dt * jnp.einsum("nij,nj->ni", T, v_rel)
    k_t = jnp.minimum(k_f, limit / jnp.sqrt(jnp.sum(pred * pred, axis=-1) + eps))
    K = (
        jnp.maximum(k_n + k_d * d_rate, 0.0)[:, None, None] * nn * pushing[:, None, None]
        + (k_t * stick)[:, None, None] * T
    )
    D = (k_d * d)[:, None, None] * nn * pushing[:, None, None]
    return ContactForces(f_normal + f_fric, K, D, a_new, act, fn)


def table_sdf(w: Array, table: Array) -> tuple[Array, Array]:
    """Signed distance of points ``w`` (M, 3) to the top face of the table box (xmin, xmax, ymin, ymax, top):
    ``z - top`` inside the footprint, +1 m (no contact) outside. Normal +z."""
    inside = (w[:, 0] > table[0]) & (w[:, 0] < table[1]) & (w[:, 1] > table[2]) & (w[:, 1] < table[3])
    sd = jnp.where(inside, w[:, 2] - table[4], 1.0)
    n = jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0], w.dtype), w.shape)
    return sd, n
