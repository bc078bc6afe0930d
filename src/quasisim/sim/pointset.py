"""Points sampled on (and in a thin shell around) a hand's collision surface, attached to its bodies.

Used for the quasi-physical point set (contacts), for the Chamfer-distance metric and for rendering.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
import trimesh

from quasisim.assets.hand import Geom, HandModel
from quasisim.assets.object import quiet_trimesh
from quasisim.rotations import np_quat_to_mat
from quasisim.sim.kinematics import fk_full, points_world
from quasisim.tracecache import cached_jit


@dataclass(frozen=True, eq=False)
class HandPoints:
    """Points attached to hand bodies: ``body`` (N,), body-frame ``local`` (N, 3) and ``normal`` (N, 3)."""

    body: np.ndarray
    local: np.ndarray
    normal: np.ndarray

    @property
    def n(self) -> int:
        return len(self.body)


def geom_mesh(g: Geom) -> trimesh.Trimesh:
    """A trimesh of one geom in its body's frame."""
    s = g.size
    if g.type == "box":
        m = trimesh.creation.box(extents=2 * s)
    elif g.type == "capsule":
        m = trimesh.creation.capsule(height=2 * s[1], radius=s[0], count=[16, 16])
    elif g.type == "cylinder":
        m = trimesh.creation.cylinder(radius=s[0], height=2 * s[1], sections=24)
    elif g.type == "sphere":
        m = trimesh.creation.icosphere(subdivisions=2, radius=s[0])
    elif g.type == "ellipsoid":
        m = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
        m.apply_scale(s)
    elif g.type == "mesh":
        m = trimesh.Trimesh(g.vertices, g.faces, process=False)
    else:
        raise ValueError(f"geom {g.name}: type {g.type} has no surface to sample")
    T = np.eye(4)
    T[:3, :3] = np_quat_to_mat(g.quat)
    T[:3, 3] = g.pos
    m.apply_transform(T)
    return m


def sample_hand_points(
    hand: HandModel, spacing: float, offset: float, seed: int = 0, count: int | None = None
) -> HandPoints:
    """Sample points every ~``spacing`` m on each collision geom and push them out by U(0, ``offset``).

    Points that fall inside another collision geom of the same body are dropped (overlapping boxes).
    With ``count``, the spacing is chosen for at least ~1.25 ``count`` points (denser where overlapping
    geoms drop points) and ``count`` of them are drawn (in body order), whatever the hand's size.
    """
    with quiet_trimesh():
        if count is None:
            return _sample(hand, spacing, offset, seed)
        spacing = float(np.sqrt(sum(geom_mesh(g).area for g in hand.collision_geoms()) / (1.25 * count)))
        for _ in range(4):  # overlapping geoms drop points: sample more densely until there are enough
            pts = _sample(hand, spacing, offset, seed)
            if pts.n >= count:
                break
            spacing *= float(np.sqrt(pts.n / (1.25 * count)))
        else:
            raise ValueError(f"hand {hand.name}: {pts.n} points sampled, fewer than the point set's count {count}")
        keep = np.sort(np.random.default_rng(seed).choice(pts.n, count, replace=False))
        return HandPoints(pts.body[keep], pts.local[keep], pts.normal[keep])


def inside_convex(m: trimesh.Trimesh, pts: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """(N,) whether ``pts`` (N, 3) lie inside the convex hull of ``m`` by more than ``tol`` m: every face
    plane ``n . p <= n . v0`` holds. A collision geom is convex (box, capsule, ...) or collides as its convex
    hull (MuJoCo's meshes). Unlike trimesh's ``contains``, which casts ambiguous rays again in directions drawn
    from a generator seeded by OS entropy, the answer is the same in every process."""
    hull = m.convex_hull
    n = hull.face_normals
    return np.all(pts @ n.T - np.sum(n * hull.triangles[:, 0], axis=1) < -tol, axis=1)


def _sample(hand: HandModel, spacing: float, offset: float, seed: int) -> HandPoints:
    rng = np.random.default_rng(seed)
    geoms = hand.collision_geoms()
    meshes = [geom_mesh(g) for g in geoms]
    bodies, locs, norms = [], [], []
    for g, m in zip(geoms, meshes, strict=True):
        n = max(4, round(m.area / spacing**2))
        pts, fid = trimesh.sample.sample_surface_even(m, n, seed=int(rng.integers(1 << 31)))
        if len(pts) == 0:
            continue
        nrm = m.face_normals[fid]
        pts = pts + nrm * rng.uniform(0.0, offset, (len(pts), 1))
        keep = np.ones(len(pts), bool)
        for h, mh in zip(geoms, meshes, strict=True):
            if h is not g and h.body == g.body and mh.is_watertight:
                keep &= ~inside_convex(mh, pts)
        bodies.append(np.full(int(keep.sum()), g.body))
        locs.append(pts[keep])
        norms.append(nrm[keep])
    return HandPoints(np.concatenate(bodies), np.concatenate(locs), np.concatenate(norms))


def surface_points_over_time(hand: HandModel, base_rot: np.ndarray, qpos: np.ndarray, pts: HandPoints) -> np.ndarray:
    """(T, N, 3) world positions of ``pts`` for hand configurations ``qpos`` (T, 6 + J)."""
    f32 = lambda x: jnp.asarray(x, dtype=jnp.float32)  # noqa: E731
    out = _points_over_frames(hand, f32(base_rot), f32(qpos), jnp.asarray(pts.body, jnp.int32), f32(pts.local))
    return np.asarray(out, dtype=np.float64)


@cached_jit(static_argnames=("hand",))
def _points_over_frames(
    hand: HandModel, base_rot: jax.Array, qpos: jax.Array, body: jax.Array, local: jax.Array
) -> jax.Array:
    """(T, N, 3) points attached to ``body`` (N,) at offsets ``local`` (N, 3) for every frame of ``qpos``; a
    traced program kept on disk (:mod:`quasisim.tracecache`), compiled once per hand and shapes."""
    return jax.vmap(lambda q: points_world(fk_full(hand, base_rot, q), body, local))(qpos)
