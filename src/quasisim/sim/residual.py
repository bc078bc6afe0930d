"""Residual physics networks (paper appendix "Parameterized residual physics"), in equinox.

* The **local** network looks at each of the ``n_contacts`` deepest hand-object contacts: the ``n_local``
  object surface samples and hand points nearest to the contact (within ``local_radius``), each with a
  learned type embedding, its position relative to the contact point, its velocity and its normal (zeros
  for hand points). A PointNet (shared per-point MLP, max-pool) and a head predict a residual normal force
  and a residual tangential force (3 numbers in the contact frame) for that pair.
* The **global** network looks at the ``n_global`` object and hand points nearest to the contact region
  (within ``global_radius``) in the same way and predicts a residual force and torque at the object's
  centre of mass.

* The **control transformation** (paper appendix "Controlling the hand in Bullet and Isaac Gym") looks at
  the ``n_global`` object and hand points nearest to the contact region and at the frame's control (root
  velocities, joint target error ``q* - q`` and target velocities) and predicts a residual of that control:
  the quasi-physical simulator applies ``u + g(state, u)`` where the target is given ``u``, so that the
  simulator driven by the target's PD targets moves as the target does.

All are evaluated once per frame on the frame's starting state; the last layers start at zero, so the
initial residual is exactly zero. Sizes are configuration (:class:`ResidualConfig`); the defaults are far
smaller than the paper's ([128, 256, 512, 1024] per-point, [512, 256, 128] head, 100 and 500 points) so that
fitting runs on a CPU.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp

Array = jax.Array


@dataclass(frozen=True)
class ResidualConfig:
    """Sizes of the residual networks (see module docstring). Distances in m."""

    embed: int = 8
    point_hidden: tuple[int, ...] = (32, 64)
    head_hidden: tuple[int, ...] = (64, 32)
    n_contacts: int = 16
    n_local: int = 16
    n_global: int = 64
    local_radius: float = 0.05
    global_radius: float = 0.10
    force_scale: float = 1.0  # N: outputs are multiplied by this
    torque_scale: float = 0.05  # N m
    control_pos_scale: float = 0.02  # rad (m for slide joints): joint-target residuals
    control_vel_scale: float = 0.05  # m/s, rad/s: root and joint velocity residuals


class PointNet(eqx.Module):
    """Type embedding + shared per-point MLP, masked max-pool, MLP head."""

    embed: Array
    point_mlp: eqx.nn.MLP
    head: eqx.nn.MLP

    def __init__(self, cfg: ResidualConfig, out: int, key: Array, extra: int = 0) -> None:
        k1, k2, k3 = jax.random.split(key, 3)
        self.embed = 0.1 * jax.random.normal(k1, (2, cfg.embed))
        width = cfg.point_hidden[-1]
        self.point_mlp = _mlp(cfg.embed + 9, cfg.point_hidden[:-1], width, k2)
        head = _mlp(width + extra, cfg.head_hidden, out, k3)
        last = head.layers[-1]
        last = eqx.tree_at(lambda l: (l.weight, l.bias), last, (jnp.zeros_like(last.weight), jnp.zeros_like(last.bias)))
        self.head = eqx.tree_at(lambda h: h.layers[-1], head, last)

    def __call__(self, feats: Array, kind: Array, mask: Array, extra: Array | None = None) -> Array:
        """``feats`` (P, 9) position, velocity, normal; ``kind`` (P,) 0 object / 1 hand; ``mask`` (P,) valid;
        ``extra`` (E,) more head input (the control, for the control transformation)."""
        x = jnp.concatenate([self.embed[kind], feats], axis=-1)
        h = jax.vmap(self.point_mlp)(x)
        h = jnp.where(mask[:, None], h, -1e9)
        g = jnp.max(h, axis=0)
        g = jnp.where(jnp.any(mask), g, jnp.zeros_like(g))
        return self.head(g if extra is None else jnp.concatenate([g, extra]))


def _mlp(inp: int, hidden: tuple[int, ...], out: int, key: Array) -> eqx.nn.MLP:
    if not hidden:
        return eqx.nn.MLP(inp, out, 0, 1, activation=jax.nn.relu, key=key)
    mlp = eqx.nn.MLP(inp, out, hidden[0], len(hidden), activation=jax.nn.relu, key=key)
    # widths may differ per layer: rebuild the linear layers with the requested sizes
    sizes = [inp, *hidden, out]
    keys = jax.random.split(key, len(sizes) - 1)
    layers = tuple(eqx.nn.Linear(a, b, key=k) for a, b, k in zip(sizes[:-1], sizes[1:], keys, strict=True))
    return eqx.tree_at(lambda m: m.layers, mlp, layers)


class ResidualNets(eqx.Module):
    local: PointNet
    glob: PointNet
    cfg: ResidualConfig = eqx.field(static=True)

    def __init__(self, cfg: ResidualConfig, seed: int = 0) -> None:
        kl, kg = jax.random.split(jax.random.PRNGKey(seed))
        self.local = PointNet(cfg, 3, kl)
        self.glob = PointNet(cfg, 6, kg)
        self.cfg = cfg


class ControlTransform(eqx.Module):
    """The control transformation for ``n_hands`` hands of ``n_joints`` joints in all (see module docstring)."""

    net: PointNet
    cfg: ResidualConfig = eqx.field(static=True)

    def __init__(self, cfg: ResidualConfig, n_joints: int, n_hands: int = 1, seed: int = 0) -> None:
        n = 6 * n_hands + 2 * n_joints
        self.net = PointNet(cfg, n, jax.random.PRNGKey(seed + 7919), extra=n)
        self.cfg = cfg


class ResidualInput(NamedTuple):
    """What the networks see, all in the object frame (m, m/s).

    obj_pts, obj_vel, obj_nrm: (M, 3) object surface samples, their velocities and normals.
    hand_pts, hand_vel: (K, 3) candidate hand points and velocities.
    depth: (K,) contact depth ``d_c - sd`` of the hand points (> 0 in contact).
    contact_pt, contact_nrm: (K, 3) nearest surface points and normals of the hand points.
    """

    obj_pts: Array
    obj_vel: Array
    obj_nrm: Array
    hand_pts: Array
    hand_vel: Array
    depth: Array
    contact_pt: Array
    contact_nrm: Array


def nearest_points(points: Array, center: Array, k: int, radius: float) -> tuple[Array, Array]:
    """Indices (k,) of the ``k`` of ``points`` (P, 3) nearest to ``center`` (3,) and whether each is within ``radius``."""
    d = jnp.linalg.norm(points - center, axis=-1)
    neg, idx = jax.lax.top_k(-jax.lax.stop_gradient(d), k)
    return idx, -neg <= radius


def _region(x: ResidualInput, center: Array, n: int, radius: float) -> tuple[Array, Array, Array]:
    """Features (2n, 9), kinds (2n,) and mask (2n,) of the object and hand points nearest to ``center``."""
    oi, om = nearest_points(x.obj_pts, center, min(n, x.obj_pts.shape[0]), radius)
    hi, hm = nearest_points(x.hand_pts, center, min(n, x.hand_pts.shape[0]), radius)
    fo = jnp.concatenate([x.obj_pts[oi] - center, x.obj_vel[oi], x.obj_nrm[oi]], -1)
    fh = jnp.concatenate([x.hand_pts[hi] - center, x.hand_vel[hi], jnp.zeros_like(x.hand_vel[hi])], -1)
    kinds = jnp.concatenate([jnp.zeros(len(oi), jnp.int32), jnp.ones(len(hi), jnp.int32)])
    return jnp.concatenate([fo, fh]), kinds, jnp.concatenate([om, hm])


def residual_forces(nets: ResidualNets, x: ResidualInput) -> tuple[Array, Array, Array]:
    """Residual wrench on the object (6,) in the object frame (force, torque about the centre of mass —
    positions in ``x`` are relative to it), the local per-contact forces (n_contacts, 3) on the object in
    the object frame, and the indices (n_contacts,) of the hand points they act at."""
    cfg = nets.cfg
    n_c = min(cfg.n_contacts, x.hand_pts.shape[0])
    depth, idx = jax.lax.top_k(jax.lax.stop_gradient(x.depth), n_c)
    active = depth > 0

    def one(i: Array) -> Array:
        feats, kinds, mask = _region(x, x.contact_pt[i], cfg.n_local, cfg.local_radius)
        out = nets.local(feats, kinds, mask)
        n = x.contact_nrm[i]
        t1 = jnp.cross(n, jnp.where(jnp.abs(n[0]) < 0.9, jnp.array([1.0, 0, 0]), jnp.array([0, 1.0, 0])))
        t1 = t1 / jnp.linalg.norm(t1)
        t2 = jnp.cross(n, t1)
        return cfg.force_scale * (out[0] * n + out[1] * t1 + out[2] * t2)

    local = jax.vmap(one)(idx) * active[:, None]
    feats, kinds, mask = _region(x, _contact_center(x), cfg.n_global // 2, cfg.global_radius)
    g = nets.glob(feats, kinds, mask) * jnp.any(active)
    wrench = jnp.concatenate([cfg.force_scale * g[:3], cfg.torque_scale * g[3:]])
    return wrench, local, idx


def _contact_center(x: ResidualInput) -> Array:
    """The contact region's centre (contact points weighted by depth), or an object point when none."""
    w = jnp.maximum(x.depth, 0.0)
    return jnp.where(jnp.sum(w) > 0, jnp.sum(w[:, None] * x.contact_pt, 0) / (jnp.sum(w) + 1e-12), x.obj_pts[0])


def control_residual(ct: ControlTransform, x: ResidualInput, control: Array, n_hands: int = 1) -> Array:
    """The control transformation's residual (6 H + 2J,) of ``control`` = (root velocities (3 H,), root
    angular velocities (3 H,), joint target errors ``q* - q`` (J,), joint target velocities (J,)) of H hands,
    in the same layout and units: velocities scaled by ``control_vel_scale``, joint targets by
    ``control_pos_scale``."""
    cfg = ct.cfg
    feats, kinds, mask = _region(x, _contact_center(x), cfg.n_global // 2, cfg.global_radius)
    out = ct.net(feats, kinds, mask, control)
    J = (control.shape[0] - 6 * n_hands) // 2
    scale = jnp.concatenate([jnp.full(6 * n_hands, cfg.control_vel_scale), jnp.full(J, cfg.control_pos_scale),
                             jnp.full(J, cfg.control_vel_scale)])  # fmt: skip
    return out * scale
