"""Rigid objects: watertight mesh, mass properties, signed-distance grid and convex decomposition.

All lengths are metres in the object frame. The signed-distance field (negative inside) is baked
once per mesh and parameter set with libigl and cached on disk, as is the CoACD convex decomposition
used by MuJoCo/PyBullet; cache files are keyed by the sha256 of the mesh content and the parameters and
written atomically, and a corrupt cache file is ignored and rebuilt. :func:`sdf_query` is the
JAX-side lookup (trilinear interpolation with an analytic gradient) used by the differentiable
simulator.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, NamedTuple

import igl
import jax
import jax.numpy as jnp
import numpy as np
import trimesh

from quasisim.errors import InputError
from quasisim.files import (
    cache_dir,  # $QUASISIM_CACHE or ~/.cache/quasisim
    save_npz_atomic,
)

DEFAULT_DENSITY = 500.0  # kg/m^3
SIZE_RANGE = (0.005, 2.0)  # m, largest extent of a hand-held object's mesh (in metres)
SDF_MAX_NODES = 600_000  # the grid is coarsened beyond this (bake ~10 s for a 30k-vertex mesh on 2 cores)
# grids are padded to at least this many nodes, so that objects up to about the size of a mug share one compiled
# program (BENCHMARKS.md, "A shorter curriculum, one compiled program for every GRAB object, ...")
SDF_MIN_NODES = 1 << 17
COACD_MAX_FACES = 2000  # CoACD input is simplified (igl.qslim) to this many faces
COACD_SETTINGS: dict[str, Any] = {  # measured: every dev mesh < 20 s, hulls cover the mesh (see tests)
    "preprocess_resolution": 30,
    "resolution": 1000,
    "mcts_iterations": 60,
    "mcts_nodes": 12,
    "mcts_max_depth": 2,
}
_CACHE_VERSION = 1


def _cache_file(kind: str, content_hash: str, params: dict[str, Any]) -> tuple[Path, str]:
    blob = json.dumps({"v": _CACHE_VERSION, "kind": kind, "mesh": content_hash, **params}, sort_keys=True)
    key = hashlib.sha256(blob.encode()).hexdigest()
    return cache_dir() / kind / f"{key}.npz", key


def _read_cache(path: Path, key: str, names: tuple[str, ...]) -> dict[str, np.ndarray] | None:
    """Arrays from a cache file, or None when it is missing, unreadable, corrupt or for another key."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            if str(z["key"]) != key:
                return None
            return {n: np.asarray(z[n]) for n in names}
    except Exception:  # any damage (truncated zip, missing array, ...) means: rebuild
        return None


def _write_cache(path: Path, key: str, **arrays: np.ndarray) -> None:
    try:
        save_npz_atomic(path, key=np.asarray(key), **arrays)
    except OSError as e:  # a read-only cache must not stop the run
        warnings.warn(f"could not write cache file {path}: {e}", RuntimeWarning, stacklevel=3)


class SDFArrays(NamedTuple):
    """Grid arrays for JAX (a pytree: close over it or pass it through ``jit``).

    ``values`` is the (nx, ny, nz) grid, or, with ``dims`` (3,) = (nx, ny, nz) given, the grid flattened in
    C order and padded at its end to a longer length (:meth:`SDFGrid.as_flat`): grids of many objects then have
    one shape, so one compiled program serves them all."""

    origin: jax.Array  # (3,) m
    spacing: jax.Array  # () m
    values: jax.Array  # (nx, ny, nz) m, or (L,) with L >= nx ny nz when dims is given
    dims: jax.Array | None = None  # (3,) int32 node counts of a flat ``values``


@dataclass(frozen=True, eq=False)
class SDFGrid:
    """Signed distance sampled on a regular grid (negative inside).

    Attributes:
        origin: (3,) object-frame position of node [0, 0, 0], m.
        spacing: distance between neighbouring nodes, m (same on all axes).
        values: (nx, ny, nz) float32 signed distance at the nodes, m.
    """

    origin: np.ndarray
    spacing: float
    values: np.ndarray

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.values.shape)  # type: ignore[return-value]

    @property
    def upper(self) -> np.ndarray:
        """(3,) object-frame position of the last node, m."""
        return self.origin + self.spacing * (np.asarray(self.shape) - 1)

    def as_jax(self, dtype: Any = jnp.float32) -> SDFArrays:
        return SDFArrays(
            jnp.asarray(self.origin, dtype), jnp.asarray(self.spacing, dtype), jnp.asarray(self.values, dtype)
        )

    def as_flat(self, dtype: Any = jnp.float32) -> SDFArrays:
        """The grid flattened and padded to :func:`sdf_bucket` nodes (the padding is never read): the same
        distances as :meth:`as_jax` from arrays of one of a few lengths, whatever the object's grid shape."""
        flat = self.values.reshape(-1)
        padded = np.zeros(sdf_bucket(flat.size), np.float32)
        padded[: flat.size] = flat
        return SDFArrays(
            jnp.asarray(self.origin, dtype), jnp.asarray(self.spacing, dtype), jnp.asarray(padded, dtype),
            jnp.asarray(self.shape, jnp.int32),
        )  # fmt: skip


def sdf_bucket(n: int, smallest: int = SDF_MIN_NODES) -> int:
    """The padded length of a flattened grid of ``n`` nodes: the next power of two, at least ``smallest``.
    Every hand-held object whose grid fits ``smallest`` nodes (the six GRAB objects at 3 mm) shares one
    compiled program per hand and stage; larger grids pad below 2x (one length for every object, 600,000
    nodes, measured 13-36 % slower in the simulator's forward and backward pass than the unpadded grid,
    BENCHMARKS.md)."""
    return max(smallest, 1 << max(int(n) - 1, 0).bit_length())


def bake_sdf(
    vertices: np.ndarray,
    faces: np.ndarray,
    spacing: float = 0.002,
    padding: float = 0.02,
    max_nodes: int = SDF_MAX_NODES,
) -> SDFGrid:
    """Exact signed distance (libigl) of a watertight mesh at the nodes of a regular grid.

    The grid covers the mesh bounding box plus ``padding`` (m) on every side, centred on the box, with
    nodes ``spacing`` (m) apart. The sign comes from libigl's fast winding number (robust, and exact
    away from the surface). If the grid would have more than ``max_nodes`` nodes the spacing is
    increased until it fits, so ``result.spacing`` can be larger than requested.
    """
    if not (spacing > 0 and padding >= 0):
        raise ValueError(f"bake_sdf: need spacing > 0 and padding >= 0, got {spacing}, {padding}")
    V = np.ascontiguousarray(vertices, np.float64)
    F = np.ascontiguousarray(faces, np.int64)
    lo, hi = V.min(0) - padding, V.max(0) + padding
    while True:
        shape = np.maximum(np.ceil((hi - lo) / spacing).astype(np.int64) + 1, 2)
        if int(np.prod(shape)) <= max_nodes:
            break
        spacing *= max(1.01, (np.prod(shape) / max_nodes) ** (1 / 3))
    origin = 0.5 * (lo + hi) - 0.5 * spacing * (shape - 1)
    axes = [origin[i] + spacing * np.arange(shape[i]) for i in range(3)]
    nodes = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    dist = igl.signed_distance(nodes, V, F, igl.SIGNED_DISTANCE_TYPE_FAST_WINDING_NUMBER)[0]
    return SDFGrid(origin, float(spacing), dist.reshape(tuple(shape)).astype(np.float32))


def _safe_norm(v: jax.Array) -> jax.Array:
    """|v| along the last axis with a zero (not NaN) gradient at v = 0."""
    sq = jnp.sum(v * v, axis=-1)
    ok = sq > 0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, sq, 1.0)), 0.0)


def _normalize(v: jax.Array) -> jax.Array:
    n = _safe_norm(v)
    return v / jnp.where(n > 0, n, 1.0)[..., None]


def sdf_query(grid: SDFGrid | SDFArrays, points: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Signed distance and outward unit normal at object-frame points (pure JAX; jit/vmap/grad safe).

    Args:
        grid: baked grid (:class:`SDFGrid` or its :meth:`SDFGrid.as_jax` arrays).
        points: (..., 3) object-frame positions, m; float32 or float64.

    Returns:
        dist (...,) m, negative inside: trilinear interpolation of the node values. Outside the grid
        box it is the value at the nearest point ``c`` of the box plus ``|p - c|``, so it keeps growing.
        normal (..., 3): inside the box, the normalised analytic gradient of the trilinear interpolant
        (``jax.grad`` of dist gives the same direction); outside, ``normalize(p - c + max(d(c), 0)
        n(c))``, i.e. the direction from the surface point estimated at ``c`` to ``p``, continuous at the
        box and radial far away.
    """
    g = grid.as_jax() if isinstance(grid, SDFGrid) else grid
    return _sdf_query(g, points)


@jax.jit
def _sdf_query(g: SDFArrays, points: jax.Array) -> tuple[jax.Array, jax.Array]:
    points = jnp.asarray(points)
    dtype = jnp.result_type(points.dtype, jnp.float32)
    batch = points.shape[:-1]
    p = points.reshape(-1, 3).astype(dtype)
    vals = g.values.astype(dtype)
    origin, h = g.origin.astype(dtype), g.spacing.astype(dtype)
    dims = jnp.asarray(vals.shape, jnp.int32) if g.dims is None else g.dims
    ny, nz = dims[1], dims[2]
    size = dims.astype(dtype)
    c = jnp.clip(p, origin, origin + h * (size - 1))  # nearest point of the grid box
    u = (c - origin) / h  # continuous node index
    i0 = jax.lax.stop_gradient(jnp.clip(jnp.floor(u), 0, size - 2))
    t = u - i0  # (N, 3) in [0, 1]
    i = i0.astype(jnp.int32)
    base = (i[:, 0] * ny + i[:, 1]) * nz + i[:, 2]
    offsets = jnp.asarray([(dx * ny + dy) * nz + dz for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)])
    v = vals.reshape(-1)[base[:, None] + offsets].reshape(-1, 2, 2, 2)  # corner values [n, x, y, z]
    tx, ty, tz = t[:, 0, None], t[:, 1, None], t[:, 2, None]

    def lerp(a: jax.Array, b: jax.Array, s: jax.Array) -> jax.Array:
        return a + s * (b - a)

    vz, dvz = lerp(v[..., 0], v[..., 1], tz[..., None]), v[..., 1] - v[..., 0]  # (N, 2, 2) over [x, y]
    vyz, dvy = lerp(vz[..., 0], vz[..., 1], ty), vz[..., 1] - vz[..., 0]  # (N, 2) over x
    dvz_y = lerp(dvz[..., 0], dvz[..., 1], ty)
    d_in = lerp(vyz[:, 0], vyz[:, 1], tx[:, 0])
    grad = (
        jnp.stack(
            [vyz[:, 1] - vyz[:, 0], lerp(dvy[:, 0], dvy[:, 1], tx[:, 0]), lerp(dvz_y[:, 0], dvz_y[:, 1], tx[:, 0])], -1
        )
        / h
    )  # analytic d(d_in)/dp
    n_in = _normalize(grad)
    off = p - c
    outside_dist = _safe_norm(off)
    dist = d_in + outside_dist
    n_out = _normalize(off + jnp.maximum(d_in, 0.0)[:, None] * n_in)
    normal = jnp.where((outside_dist > 0)[:, None], n_out, n_in)
    return dist.reshape(batch), normal.reshape((*batch, 3))


def _simplify(vertices: np.ndarray, faces: np.ndarray, n_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """Quadric edge-collapse decimation (libigl qslim) to at most ``n_faces`` faces."""
    out = igl.qslim(np.asfortranarray(vertices, np.float64), np.asfortranarray(faces, np.int32), n_faces)
    return np.asarray(out[0], np.float64), np.asarray(out[1], np.int64)


def hull_gap(points: np.ndarray, parts: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """Euclidean distance (m) of each of ``points`` (N, 3) outside the union of convex ``parts``; 0 inside."""
    P = np.ascontiguousarray(points, np.float64)
    gap = np.full(len(P), np.inf)
    for v, f in parts:
        d = igl.signed_distance(
            P,
            np.ascontiguousarray(v, np.float64),
            np.ascontiguousarray(f, np.int64),
            igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL,
        )[0]
        gap = np.minimum(gap, np.maximum(d, 0.0))
    return gap


def convex_decomposition(
    vertices: np.ndarray, faces: np.ndarray, threshold: float = 0.05, max_hulls: int = -1, seed: int = 0
) -> list[tuple[np.ndarray, np.ndarray]]:
    """CoACD approximate convex decomposition of a watertight mesh.

    Meshes with more than :data:`COACD_MAX_FACES` faces are first simplified with ``igl.qslim``; when
    the input is a closed manifold CoACD's (slow) remeshing step is skipped. Settings are in
    :data:`COACD_SETTINGS`. Each part is the convex hull of CoACD's part; flat parts are dropped. The
    simplification moves the surface slightly: on the dev meshes (1k-31k vertices) no mesh vertex is
    more than ~0.3 mm outside the union of the hulls (see :func:`hull_gap`).

    Returns:
        list of (vertices (V, 3) float64 m, faces (F, 3) int64), each a closed convex triangle mesh.
    """
    import coacd  # loaded only when a decomposition is not cached yet (a native library, slow to load)

    if hasattr(coacd, "set_log_level"):
        coacd.set_log_level("error")
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    V_in, F_in = _simplify(V, F, COACD_MAX_FACES) if len(F) > COACD_MAX_FACES else (V, F)
    closed = trimesh.Trimesh(V_in, F_in, process=False).is_watertight
    parts = coacd.run_coacd(
        coacd.Mesh(V_in, F_in),
        threshold=threshold,
        max_convex_hull=max_hulls,
        preprocess_mode="off" if closed else "on",
        seed=seed,
        **COACD_SETTINGS,
    )
    min_volume = 1e-9 * abs(trimesh.Trimesh(V, F, process=False).volume)
    hulls = []
    for pv, _ in parts:
        try:
            hull = trimesh.convex.convex_hull(np.asarray(pv, np.float64))
        except Exception:  # qhull rejects flat or tiny point sets
            continue
        if len(hull.vertices) >= 4 and hull.volume > min_volume:
            hulls.append(hull)
    if not hulls:
        hulls = [trimesh.convex.convex_hull(V)]
    return [(np.asarray(h.vertices, np.float64), np.asarray(h.faces, np.int64)) for h in hulls]


@contextlib.contextmanager
def quiet_trimesh() -> Iterator[None]:
    """Silence trimesh's "only got n/m samples" notices while sampling (the level is restored afterwards)."""
    log = logging.getLogger("trimesh")
    level = log.level
    log.setLevel(logging.ERROR)
    try:
        yield
    finally:
        log.setLevel(level)


@dataclass(frozen=True, eq=False)
class ObjectAsset:
    """A rigid object. Build it with :func:`load_object`.

    Attributes:
        name: label (file stem by default).
        mesh_path: the mesh file it was loaded from.
        vertices: (V, 3) float64 object-frame vertex positions, m; the mesh is watertight, each edge shared by
            two faces (vertices repeat a position where solids touched along an edge, see :func:`load_object`).
        faces: (F, 3) int64 vertex indices, counter-clockwise seen from outside.
        mass: kg.
        com: (3,) centre of mass, object frame, m.
        inertia: (3, 3) inertia tensor about the centre of mass, object-frame axes, kg m^2.
        content_hash: sha256 of the vertex and face bytes (cache key).
    """

    name: str
    mesh_path: Path
    vertices: np.ndarray
    faces: np.ndarray
    mass: float
    com: np.ndarray
    inertia: np.ndarray
    content_hash: str
    _memo: dict[Any, Any] = field(default_factory=dict, init=False, repr=False)

    @property
    def bbox(self) -> np.ndarray:
        """(2, 3) min and max corner of the mesh, object frame, m."""
        return np.stack([self.vertices.min(0), self.vertices.max(0)])

    @property
    def volume(self) -> float:
        """m^3."""
        return float(self.to_trimesh().volume)

    def to_trimesh(self) -> trimesh.Trimesh:
        if "trimesh" not in self._memo:
            self._memo["trimesh"] = trimesh.Trimesh(self.vertices, self.faces, process=False)
        return self._memo["trimesh"]

    def sdf(self, spacing: float = 0.002, padding: float = 0.02) -> SDFGrid:
        """Signed-distance grid (see :func:`bake_sdf`), baked on first use and cached on disk."""
        memo_key = ("sdf", float(spacing), float(padding))
        if memo_key in self._memo:
            return self._memo[memo_key]
        params = {"spacing": float(spacing), "padding": float(padding), "max_nodes": SDF_MAX_NODES}
        path, key = _cache_file("sdf", self.content_hash, params)
        z = _read_cache(path, key, ("origin", "spacing", "values"))
        if z is not None and z["values"].ndim == 3 and z["origin"].shape == (3,):
            grid = SDFGrid(z["origin"].astype(np.float64), float(z["spacing"]), z["values"].astype(np.float32))
        else:
            grid = bake_sdf(self.vertices, self.faces, spacing, padding)
            _write_cache(path, key, origin=grid.origin, spacing=np.asarray(grid.spacing), values=grid.values)
        self._memo[memo_key] = grid
        return grid

    def convex_parts(self, threshold: float = 0.05, max_hulls: int = -1) -> list[tuple[np.ndarray, np.ndarray]]:
        """Convex decomposition (see :func:`convex_decomposition`), cached on disk.

        Returns:
            list of (vertices (V, 3) float64 m, faces (F, 3) int64) convex hulls in the object frame.
        """
        memo_key = ("coacd", float(threshold), int(max_hulls))
        if memo_key in self._memo:
            return self._memo[memo_key]
        params = {
            "threshold": float(threshold),
            "max_hulls": int(max_hulls),
            "max_faces": COACD_MAX_FACES,
            **COACD_SETTINGS,
        }
        path, key = _cache_file("coacd", self.content_hash, params)
        z = _read_cache(path, key, ("vertices", "faces", "n_vertices", "n_faces"))
        if z is not None:
            vs = np.split(z["vertices"].astype(np.float64), np.cumsum(z["n_vertices"])[:-1])
            fs = np.split(z["faces"].astype(np.int64), np.cumsum(z["n_faces"])[:-1])
            parts = list(zip(vs, fs, strict=True))
        else:
            parts = convex_decomposition(self.vertices, self.faces, threshold, max_hulls)
            _write_cache(
                path,
                key,
                vertices=np.concatenate([v for v, _ in parts]),
                faces=np.concatenate([f for _, f in parts]),
                n_vertices=np.array([len(v) for v, _ in parts]),
                n_faces=np.array([len(f) for _, f in parts]),
            )
        self._memo[memo_key] = parts
        return parts

    def surface_points(self, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """``n`` roughly evenly spaced surface points (trimesh's Poisson-disk-like sampling).

        Returns:
            points (n, 3) object frame, m; normals (n, 3) outward unit face normals.
        """
        mesh = self.to_trimesh()
        pts, idx = _even_samples(mesh, n, seed)
        return pts, np.asarray(mesh.face_normals[idx], np.float64)

    def support_points(self, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """``n`` points of the object's convex hull: its vertices (the farthest-point subset of ``n`` when it
        has more), topped up with evenly spaced points on its faces. A plane (the table) touches the object
        only on its hull, and a body lying on it rests on hull vertices: a cylinder on the rim points of its
        lowest side facet. Samples of the mesh's surface cover a curved side too sparsely for that, and the
        body rocks or rolls between a few of them.

        Returns:
            points (n, 3) object frame, m; normals (n, 3) outward unit normals (the hull's vertex normals at
            vertices, its face normals on faces).
        """
        with quiet_trimesh():
            hull = self.to_trimesh().convex_hull
            verts, vnorm = np.asarray(hull.vertices, np.float64), np.asarray(hull.vertex_normals, np.float64)
            if len(verts) >= n:
                keep = farthest_points(verts, n)
                return verts[keep], vnorm[keep]
        pts, idx = _even_samples(hull, n - len(verts), seed)
        return np.vstack([verts, pts]), np.vstack([vnorm, hull.face_normals[idx]]).astype(np.float64)


def _even_samples(mesh: trimesh.Trimesh, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` roughly evenly spaced points (n, 3) on ``mesh`` and their faces (n,): trimesh's even sampler,
    topped up with area-weighted samples where it returns fewer."""
    with quiet_trimesh():
        pts, idx = trimesh.sample.sample_surface_even(mesh, n, seed=seed)
        if len(pts) < n:
            more, more_idx = trimesh.sample.sample_surface(mesh, n - len(pts), seed=seed + 1)
            pts, idx = np.vstack([pts, more]), np.concatenate([idx, more_idx])
    return np.asarray(pts[:n], np.float64), np.asarray(idx[:n])


def farthest_points(x: np.ndarray, n: int) -> np.ndarray:
    """Indices of ``n`` of the points ``x`` (N, 3), each the farthest from those chosen before it, starting
    with the point farthest from their centroid (greedy farthest-point sampling: an even spread that keeps
    the extremes)."""
    chosen = [int(np.argmax(np.linalg.norm(x - x.mean(0), axis=1)))]
    dist = np.linalg.norm(x - x[chosen[0]], axis=1)
    for _ in range(n - 1):
        chosen.append(int(np.argmax(dist)))
        dist = np.minimum(dist, np.linalg.norm(x - x[chosen[-1]], axis=1))
    return np.asarray(chosen)


def _edge_faults(mesh: trimesh.Trimesh) -> tuple[int, int]:
    """(open, non-manifold): how many of the mesh's edges one face uses, and how many more than two faces use."""
    counts = np.unique(mesh.edges_sorted, axis=0, return_counts=True)[1]
    return int((counts == 1).sum()), int((counts > 2).sum())


def _plural(n: int, what: str) -> str:
    return f"{n} {what}{'' if n == 1 else 's'}"


def _faults_text(mesh: trimesh.Trimesh) -> str:
    """What keeps ``mesh`` from being closed, e.g. "2 open edges and 1 non-manifold edge (shared by ...)"."""
    n_open, n_multi = _edge_faults(mesh)
    faults = [_plural(n_open, "open edge")] if n_open or not n_multi else []
    if n_multi:
        faults.append(f"{_plural(n_multi, 'non-manifold edge')} (shared by more than two faces)")
    return " and ".join(faults)


def _split_nonmanifold(mesh: trimesh.Trimesh) -> trimesh.Trimesh | None:
    """``mesh`` with its vertices duplicated along edges that more than two faces share (libigl's
    split_nonmanifold), so that each edge has two faces: the same triangles, so the same volume and winding
    number (solids touching along an edge stay touching, each closed); None unless that gives a closed mesh with
    consistent winding."""
    V, F, _ = igl.split_nonmanifold(
        np.ascontiguousarray(mesh.vertices, np.float64), np.ascontiguousarray(mesh.faces, np.int64)
    )
    split = trimesh.Trimesh(V, F, process=False)
    return split if split.is_watertight and split.is_winding_consistent else None


def load_object(
    mesh_path: str | Path, name: str | None = None, density: float = DEFAULT_DENSITY, mass: float | None = None
) -> ObjectAsset:
    """Read a mesh file (metres, object frame) into an :class:`ObjectAsset`.

    Coincident vertices are merged and degenerate faces dropped. A mesh that is not watertight, or whose
    winding is inconsistent or inward, is repaired with trimesh (fill_holes, fix_normals); where more than two
    faces then share an edge (solids touching along an edge) but no edge is open, the mesh is split along
    those edges (libigl split_nonmanifold; a RuntimeWarning names their count). If it is still not
    closed, :class:`~quasisim.errors.InputError` is raised naming the open and non-manifold edges. The mass is
    ``density`` (kg/m^3) times the volume unless ``mass`` (kg) is given; the inertia is that of a uniform solid.
    """
    path = Path(mesh_path)
    if not path.is_file():
        raise InputError(path, "mesh", "an existing mesh file (.obj, .ply, .stl, ...)", "no such file")
    st = path.stat()
    fields = _read_object(path.resolve(), st.st_mtime_ns, st.st_size, float(density), mass)
    return ObjectAsset(name=name or path.stem, **fields)  # a fresh asset (its own caches) every call


def _repaired(path: Path, mesh: trimesh.Trimesh) -> tuple[trimesh.Trimesh, int]:
    """``mesh`` closed by trimesh (fill_holes, fix_normals) and, where more than two faces are left sharing an
    edge but no edge is open, split there (:func:`_split_nonmanifold`), and the number of edges split;
    :class:`~quasisim.errors.InputError` naming the open and non-manifold edges if it is still not closed."""
    try:
        trimesh.repair.fill_holes(mesh)
        trimesh.repair.fix_normals(mesh)
        mesh.merge_vertices()
    except ImportError as e:  # trimesh's repair needs networkx
        raise InputError(
            path,
            "mesh",
            "a watertight (closed) triangle mesh with consistent winding",
            f"{_faults_text(mesh)}; repair unavailable ({e})",
        ) from None
    n_open, n_multi = _edge_faults(mesh)
    split = _split_nonmanifold(mesh) if n_multi and not n_open else None
    if split is not None:
        return split, n_multi
    if not mesh.is_watertight:
        raise InputError(
            path,
            "mesh",
            "a watertight (closed) triangle mesh",
            f"{_faults_text(mesh)} after trimesh repair (fill_holes, fix_normals)",
        )
    return mesh, 0


@lru_cache(maxsize=16)
def _read_object(path: Path, mtime_ns: int, size: int, density: float, mass: float | None) -> dict[str, Any]:
    """The checked mesh and its mass properties, kept for the same file (path, modification time, size) and
    settings (arrays read-only: every asset of the file shares them)."""
    try:
        mesh = trimesh.load(path, process=False, force="mesh")
    except Exception as e:
        raise InputError(
            path, "mesh", "a readable triangle mesh file", " ".join(f"{type(e).__name__}: {e}".split())[:200]
        ) from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError(path, "mesh", "a triangle mesh with at least one face", "no triangles")
    # the size first: vertices far out (or not finite) would overflow trimesh's vertex merging
    used = mesh.vertices[np.unique(mesh.faces)]
    extent = float(np.ptp(used, axis=0).max()) if np.isfinite(used).all() else np.inf
    if not SIZE_RANGE[0] <= extent <= SIZE_RANGE[1]:
        lo, hi = SIZE_RANGE
        raise InputError(
            path, "mesh", f"an object {lo * 1e3:g} mm to {hi:g} m across (vertices in metres)", f"{extent:.3g} m across"
        )
    mesh.merge_vertices()
    f = mesh.faces
    mesh.update_faces((f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2]))
    mesh.remove_unreferenced_vertices()
    n_split = 0
    if not (mesh.is_watertight and mesh.is_winding_consistent):
        mesh, n_split = _repaired(path, mesh)
    with np.errstate(divide="ignore", invalid="ignore"):  # trimesh divides by a zero volume (refused below)
        volume = float(mesh.volume)
    if volume < 0:
        mesh.invert()
        volume = -volume
    if not volume > 0:
        raise InputError(
            path, "mesh", "a watertight (closed) mesh enclosing a positive volume", f"volume {volume:.3g} m^3"
        )
    if mass is not None:
        if not (np.isfinite(mass) and mass > 0):
            raise InputError(path, "mass", "a positive mass in kg", repr(mass))
        density = mass / volume
    if not (np.isfinite(density) and density > 0):
        raise InputError(path, "density", "a positive density in kg/m^3", repr(density))
    mesh.density = float(density)
    if n_split:  # said once the mesh is accepted (and once per file: the result is kept)
        warnings.warn(
            f"{path}: {_plural(n_split, 'non-manifold edge')} (shared by more than two faces): split with libigl "
            "split_nonmanifold so that each edge has two faces (the same triangles and solid)",
            RuntimeWarning,
            stacklevel=3,
        )
    V = np.ascontiguousarray(mesh.vertices, np.float64)
    F = np.ascontiguousarray(mesh.faces, np.int64)
    digest = hashlib.sha256(V.tobytes() + F.tobytes()).hexdigest()
    out = {
        "mesh_path": path, "vertices": V, "faces": F, "mass": float(mesh.mass),
        "com": np.asarray(mesh.center_mass, np.float64), "inertia": np.asarray(mesh.moment_inertia, np.float64),
        "content_hash": digest,
    }  # fmt: skip
    for a in (V, F, out["com"], out["inertia"]):
        a.flags.writeable = False
    return out
