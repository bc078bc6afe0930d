"""Object assets: loading/repair, mass properties, SDF bake + JAX query, caches, convex decomposition."""

from __future__ import annotations

import os
import re
import time
from collections.abc import Callable
from pathlib import Path

import igl
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

import quasisim.assets.object as obj
from helpers import missing_data
from quasisim.assets.object import ObjectAsset, SDFGrid, bake_sdf, hull_gap, load_object, sdf_bucket, sdf_query
from quasisim.errors import InputError

DATA = Path(os.environ.get("QUASISIM_DATA") or Path(__file__).resolve().parents[2] / "shared" / "data")
MESHES = DATA / "meshes"


@pytest.fixture(autouse=True)
def _tmp_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    cache = tmp_path / "cache"
    monkeypatch.setenv("QUASISIM_CACHE", str(cache))
    return cache


def real_mesh(name: str) -> Path:
    path = MESHES / name
    if not path.is_file():
        missing_data(f"development mesh {path} not found (set QUASISIM_DATA)")
    return path


def write_mesh(tmp_path: Path, mesh: trimesh.Trimesh, name: str = "m.ply") -> Path:
    path = tmp_path / name
    mesh.export(path)
    return path


def exact_sdf(asset: ObjectAsset, points: np.ndarray) -> np.ndarray:
    sign = igl.SIGNED_DISTANCE_TYPE_WINDING_NUMBER
    return igl.signed_distance(np.asarray(points, np.float64), asset.vertices, asset.faces, sign)[0]


def points_in_grid(grid: SDFGrid, n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(grid.origin, grid.upper, (n, 3))


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    cos = np.sum(a * b, -1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return np.degrees(np.arccos(np.clip(cos, -1, 1)))


@pytest.fixture
def box(tmp_path: Path) -> ObjectAsset:
    return load_object(write_mesh(tmp_path, trimesh.creation.box((0.04, 0.06, 0.08)), "box.ply"))


@pytest.fixture(scope="module")
def sphere() -> tuple[ObjectAsset, SDFGrid]:
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=0.03)
    asset = ObjectAsset(
        "sphere", Path("sphere"), mesh.vertices, mesh.faces.astype(np.int64), 1.0, np.zeros(3), np.eye(3), "sphere"
    )
    return asset, bake_sdf(asset.vertices, asset.faces, spacing=0.0025, padding=0.01)


# ---------------------------------------------------------------- loading and mass properties


def test_box_mass_and_inertia(tmp_path: Path) -> None:
    a, b, c, rho = 0.04, 0.06, 0.1, 700.0
    mesh = trimesh.creation.box((a, b, c))
    mesh.apply_translation([0.01, -0.02, 0.03])
    asset = load_object(write_mesh(tmp_path, mesh), density=rho)
    m = rho * a * b * c
    assert asset.name == "m" and asset.vertices.dtype == np.float64 and asset.faces.dtype == np.int64
    assert asset.mass == pytest.approx(m, rel=1e-6)  # .ply stores float32 vertices
    np.testing.assert_allclose(asset.com, [0.01, -0.02, 0.03], atol=1e-8)
    expected = m / 12 * np.diag([b**2 + c**2, a**2 + c**2, a**2 + b**2])
    np.testing.assert_allclose(asset.inertia, expected, rtol=1e-5, atol=1e-12)
    np.testing.assert_allclose(asset.bbox, mesh.bounds, atol=1e-8)

    heavy = load_object(write_mesh(tmp_path, mesh), name="brick", mass=0.5)
    assert heavy.name == "brick" and heavy.mass == pytest.approx(0.5)
    np.testing.assert_allclose(heavy.inertia, expected * 0.5 / m, rtol=1e-5, atol=1e-12)
    default = load_object(write_mesh(tmp_path, mesh))
    assert default.mass == pytest.approx(obj.DEFAULT_DENSITY * a * b * c, rel=1e-6)


def test_inside_out_mesh_is_flipped(tmp_path: Path) -> None:
    mesh = trimesh.creation.box((0.02, 0.02, 0.02))
    flipped = trimesh.Trimesh(mesh.vertices, mesh.faces[:, ::-1], process=False)
    asset = load_object(write_mesh(tmp_path, flipped))
    assert asset.to_trimesh().volume == pytest.approx(8e-6)
    assert asset.mass == pytest.approx(obj.DEFAULT_DENSITY * 8e-6)


def test_repairable_hole_is_filled(tmp_path: Path) -> None:
    pytest.importorskip("networkx", reason="trimesh's hole filling needs networkx")
    mesh = trimesh.creation.box((0.02, 0.03, 0.04))
    opened = trimesh.Trimesh(mesh.vertices, mesh.faces[1:], process=False)
    assert not opened.is_watertight
    asset = load_object(write_mesh(tmp_path, opened))
    assert asset.to_trimesh().is_watertight
    assert asset.to_trimesh().volume == pytest.approx(0.02 * 0.03 * 0.04, rel=1e-6)


@pytest.mark.parametrize("kind", ["triangle", "two_sheets"])
def test_unrepairable_open_mesh_raises(tmp_path: Path, kind: str) -> None:
    if kind == "triangle":
        mesh = trimesh.Trimesh([[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0]], [[0, 1, 2]], process=False)
    else:
        sheet = trimesh.Trimesh(
            [[0, 0, 0], [0.01, 0, 0], [0.01, 0.01, 0], [0, 0.01, 0]], [[0, 1, 2], [0, 2, 3]], process=False
        )
        other = sheet.copy()
        other.apply_translation([0, 0, 0.05])
        mesh = trimesh.util.concatenate([sheet, other])
    path = write_mesh(tmp_path, mesh, f"{kind}.ply")
    with pytest.raises(InputError, match="watertight") as err:
        load_object(path)
    assert f"{kind}.ply" in str(err.value) and "\n" not in str(err.value)


def two_boxes_sharing_an_edge(subdivide: bool = False) -> tuple[trimesh.Trimesh, list[tuple[np.ndarray, np.ndarray]]]:
    """Two closed boxes touching along one edge (x = y = 0, |z| <= 15 mm) merged into one mesh: the edge (two
    edges when ``subdivide`` splits it) has four faces and no edge is open. Also returns each box's (lo, hi)."""
    spans = [(np.array([-0.02, -0.02, -0.015]), np.array([0.0, 0.0, 0.015])),
             (np.array([0.0, 0.0, -0.015]), np.array([0.03, 0.02, 0.015]))]  # fmt: skip
    parts = []
    for lo, hi in spans:
        b = trimesh.creation.box(hi - lo)
        b.apply_translation((lo + hi) / 2)
        parts.append(b.subdivide() if subdivide else b)
    mesh = trimesh.util.concatenate(parts)
    mesh.merge_vertices()
    return mesh, spans


def box_sdf(p: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    q = np.abs(p - (lo + hi) / 2) - (hi - lo) / 2
    return np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(q.max(-1), 0)


@pytest.mark.parametrize("subdivide", [False, True])
def test_solids_touching_along_an_edge_are_split_there(tmp_path: Path, subdivide: bool) -> None:
    """A mesh whose edges are shared by four faces (two closed solids touching along an edge, as in a decimated
    TACO tool mesh) is accepted with a warning naming the count: the edge is split so each edge has two faces."""
    mesh, spans = two_boxes_sharing_an_edge(subdivide)
    n_bad = 2 if subdivide else 1
    counts = np.unique(mesh.edges_sorted, axis=0, return_counts=True)[1]
    assert (counts == 4).sum() == n_bad and (counts == 2).sum() == len(counts) - n_bad  # no open edge
    with pytest.warns(RuntimeWarning, match=rf"{n_bad} non-manifold edges? \(shared by more than two faces\)"):
        asset = load_object(write_mesh(tmp_path, mesh, "two_boxes.ply"))
    tm = asset.to_trimesh()
    assert tm.is_watertight and tm.is_winding_consistent
    volume = sum(np.prod(hi - lo) for lo, hi in spans)
    assert asset.volume == pytest.approx(volume, rel=1e-5)
    assert asset.mass == pytest.approx(obj.DEFAULT_DENSITY * volume, rel=1e-5)

    h = 0.002
    grid = asset.sdf(spacing=h, padding=0.01)
    p = points_in_grid(grid, 4000)
    ex = np.minimum(*(box_sdf(p, lo, hi) for lo, hi in spans))  # the union's signed distance
    d = np.asarray(sdf_query(grid, jnp.asarray(p, jnp.float32))[0])
    assert np.abs(d - ex).max() < h / 2
    inside = np.array([[-0.01, -0.01, 0], [0.015, 0.01, 0], [-0.001, -0.001, 0.01], [0.001, 0.001, -0.01]])
    outside = np.array([[0.01, -0.01, 0], [-0.01, 0.01, 0], [0.001, -0.001, 0], [0.04, 0, 0]])  # by the edge too
    d_in, d_out = (np.asarray(sdf_query(grid, jnp.asarray(q, jnp.float32))[0]) for q in (inside, outside))
    assert (d_in < 0).all() and (d_out > 0).all()

    parts = asset.convex_parts()
    assert hull_gap(asset.vertices, parts).max() < 5e-4  # m
    assert (hull_gap(outside[:2], parts) > 0.005).all()  # the empty quadrants stay empty
    total = sum(trimesh.Trimesh(v, f, process=False).volume for v, f in parts)
    assert total == pytest.approx(volume, rel=0.05)


def box_with_fin_or_wall(kind: str) -> trimesh.Trimesh:
    """A 2 cm cube plus a fin (one triangle on an edge: three faces there, two open fin edges) or an inner wall
    (a diagonal square: three faces on each of its four edges, none open)."""
    V = 0.01 * np.array([[2 * (i & 1) - 1, 2 * (i >> 1 & 1) - 1, 2 * (i >> 2 & 1) - 1] for i in range(8)])
    faces = [[0, 2, 3], [0, 3, 1], [4, 5, 7], [4, 7, 6], [0, 4, 6], [0, 6, 2]]
    faces += [[1, 3, 7], [1, 7, 5], [0, 1, 5], [0, 5, 4], [2, 6, 7], [2, 7, 3]]  # diagonals 0-3 and 4-7
    box = trimesh.Trimesh(V, faces, process=False)
    trimesh.repair.fix_normals(box)
    if kind == "wall":
        return trimesh.Trimesh(V, np.vstack([box.faces, [[0, 3, 7], [0, 7, 4]]]), process=False)
    return trimesh.Trimesh(np.vstack([V, [0.02, -0.02, 0]]), np.vstack([box.faces, [[1, 5, 8]]]), process=False)


@pytest.mark.parametrize(
    ("kind", "faults"),
    [("fin", "2 open edges and 1 non-manifold edge"), ("wall", "4 non-manifold edges")],
)
def test_non_manifold_edges_that_cannot_be_split_are_named(tmp_path: Path, kind: str, faults: str) -> None:
    """Edges shared by three faces cannot be split into closed solids: refused, naming them (not "0 open edges")."""
    mesh = box_with_fin_or_wall(kind)
    assert trimesh.Trimesh(mesh.vertices, mesh.faces[:12]).is_watertight
    with pytest.raises(InputError, match="watertight") as err:
        load_object(write_mesh(tmp_path, mesh, f"{kind}.ply"))
    assert f"got {faults} (shared by more than two faces) after trimesh repair" in str(err.value)


def test_missing_and_non_mesh_files_raise(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"nope\.obj"):
        load_object(tmp_path / "nope.obj")
    bad_files = [("notes.txt", "hello"), ("garbage.obj", "this is not a mesh\n"), ("bad.ply", "ply\nxx")]
    for name, text in bad_files:
        (tmp_path / name).write_text(text)
        with pytest.raises(InputError, match=re.escape(name)):
            load_object(tmp_path / name)
    with pytest.raises(InputError, match="mass"):
        load_object(write_mesh(tmp_path, trimesh.creation.box((0.01, 0.01, 0.01))), mass=-1.0)


def test_surface_points(box: ObjectAsset) -> None:
    pts, nrm = box.surface_points(500, seed=3)
    assert pts.shape == nrm.shape == (500, 3)
    np.testing.assert_allclose(np.abs(exact_sdf(box, pts)), 0, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(nrm, axis=1), 1, atol=1e-9)
    # outward: a step along the normal leaves the box
    assert (exact_sdf(box, pts + 1e-3 * nrm) > 0).all()
    again, _ = box.surface_points(500, seed=3)
    np.testing.assert_array_equal(pts, again)


def test_support_points_are_the_hulls_vertices_then_its_faces(box: ObjectAsset) -> None:
    """A box's hull has 8 vertices: all of them come first, then points on its faces (all on the surface,
    normals outward); a finer hull than ``n`` gives ``n`` of its vertices, spread to its extremes."""
    from quasisim.assets.object import farthest_points

    pts, nrm = box.support_points(64)
    assert pts.shape == nrm.shape == (64, 3)
    corners = np.abs(pts[:8])
    np.testing.assert_allclose(corners, np.broadcast_to(corners[0], (8, 3)), atol=1e-12)
    assert len({tuple(np.sign(p)) for p in pts[:8]}) == 8
    np.testing.assert_allclose(np.abs(exact_sdf(box, pts)), 0, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(nrm, axis=1), 1, atol=1e-9)
    assert (exact_sdf(box, pts + 1e-3 * nrm) > 0).all()
    flashlight = load_object(real_mesh("flashlight.obj"))  # a hull of more vertices than asked for: n of them
    hull = flashlight.to_trimesh().convex_hull
    assert len(hull.vertices) > 64
    fpts, _ = flashlight.support_points(64)
    dist = np.linalg.norm(fpts[:, None] - np.asarray(hull.vertices)[None], axis=-1).min(1)
    assert fpts.shape == (64, 3) and dist.max() < 1e-12
    ring = np.stack([np.cos(t := np.linspace(0, 2 * np.pi, 400, endpoint=False)), np.sin(t), 0 * t], axis=1)
    idx = farthest_points(ring, 8)
    assert len(set(idx)) == 8
    gaps = np.diff(np.sort(t[idx]))
    np.testing.assert_allclose(gaps, 2 * np.pi / 8, atol=0.02)  # evenly spread around the ring


# ---------------------------------------------------------------- SDF bake and query


def test_sdf_matches_exact_on_box(box: ObjectAsset) -> None:
    h = 0.003
    grid = box.sdf(spacing=h, padding=0.01)
    assert grid.values.dtype == np.float32 and grid.spacing == pytest.approx(h)
    assert (grid.origin <= box.bbox[0] - 0.01 + 1e-12).all()
    assert (grid.upper >= box.bbox[1] + 0.01 - 1e-12).all()
    p = points_in_grid(grid, 4000)
    ex = exact_sdf(box, p)
    d, n = map(np.asarray, sdf_query(grid, jnp.asarray(p, jnp.float32)))
    assert np.abs(d - ex).max() < h / 2
    assert np.median(np.abs(d - ex)) < h / 20
    far = np.abs(ex) > h
    assert (np.sign(d[far]) == np.sign(ex[far])).all()
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1, atol=1e-5)


def test_sdf_matches_exact_on_real_mesh() -> None:
    asset = load_object(real_mesh("flashlight.obj"))
    h = 0.002
    grid = asset.sdf(spacing=h, padding=0.01)
    p = points_in_grid(grid, 4000, seed=1)
    ex = exact_sdf(asset, p)
    d, _ = sdf_query(grid, jnp.asarray(p, jnp.float32))
    err = np.abs(np.asarray(d) - ex)
    assert np.percentile(err, 99) < h / 2 and np.median(err) < h / 20
    far = np.abs(ex) > h
    assert (np.sign(np.asarray(d)[far]) == np.sign(ex[far])).all()


def test_flat_padded_grids_query_as_the_grid_and_share_one_shape(box: ObjectAsset) -> None:
    """``as_flat``: the same distances and normals, bit for bit, inside, on and outside the grid box (the
    padding is never read), and one array shape for grids of different shapes in one bucket (one compiled
    program)."""
    big = load_object(real_mesh("flashlight.obj"))
    grids = [box.sdf(spacing=0.003, padding=0.01), box.sdf(spacing=0.0031, padding=0.01), big.sdf(spacing=0.003)]
    assert grids[0].shape != grids[1].shape and sdf_bucket(grids[0].values.size) == sdf_bucket(grids[1].values.size)
    flats = [g.as_flat() for g in grids]
    assert flats[0].values.shape == flats[1].values.shape
    assert [sdf_bucket(n) for n in (1, 1 << 17, (1 << 17) + 1, 600_000)] == [1 << 17, 1 << 17, 1 << 18, 1 << 20]
    query = jax.jit(sdf_query)
    for g, f in zip(grids, flats, strict=True):
        rng = np.random.default_rng(0)
        p = rng.uniform(g.origin - 0.02, g.upper + 0.02, (3000, 3))  # some outside the box, beyond every face
        d0, n0 = query(g.as_jax(), jnp.asarray(p, jnp.float32))
        d1, n1 = query(f, jnp.asarray(p, jnp.float32))
        np.testing.assert_array_equal(np.asarray(d1), np.asarray(d0))
        np.testing.assert_array_equal(np.asarray(n1), np.asarray(n0))
        garbage = f._replace(values=f.values.at[g.values.size :].set(-1.0))  # the padding is never read
        np.testing.assert_array_equal(np.asarray(query(garbage, jnp.asarray(p, jnp.float32))[0]), np.asarray(d0))


def test_sphere_normals_and_distance(sphere: tuple[ObjectAsset, SDFGrid]) -> None:
    _, grid = sphere
    rng = np.random.default_rng(2)
    dirs = rng.normal(size=(2000, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    radius = 0.03 + np.concatenate([rng.uniform(-0.004, -0.0015, 1000), rng.uniform(0.0015, 0.008, 1000)])
    p = dirs * radius[:, None]
    d, n = map(np.asarray, jax.jit(sdf_query)(grid.as_jax(), jnp.asarray(p, jnp.float32)))
    assert angle_deg(n, dirs).max() < 5.0
    np.testing.assert_allclose(d, radius - 0.03, atol=0.0005)


def test_gradient_of_distance_is_normal(sphere: tuple[ObjectAsset, SDFGrid]) -> None:
    _, grid = sphere
    arrays = grid.as_jax()
    p = jnp.asarray(points_in_grid(grid, 500, seed=4), jnp.float32)

    def dist(x: jax.Array) -> jax.Array:
        return sdf_query(arrays, x)[0]

    g = np.asarray(jax.jit(jax.vmap(jax.grad(dist)))(p))
    _, n = sdf_query(arrays, p)
    assert np.isfinite(g).all()
    assert angle_deg(g, np.asarray(n)).max() < 0.1  # float32 rounding only
    # the gradient of a (trilinearly interpolated) distance field has length ~ 1 (not at the centre cusp)
    smooth = np.linalg.norm(np.asarray(p), axis=1) > 0.01
    assert np.abs(np.linalg.norm(g[smooth], axis=1) - 1).max() < 0.1
    # batched vs single-point query agree
    d1, n1 = sdf_query(arrays, p[0])
    assert d1.shape == () and n1.shape == (3,)
    np.testing.assert_allclose(d1, dist(p)[0], rtol=1e-6)


def test_float64_query(box: ObjectAsset) -> None:
    grid = box.sdf(spacing=0.004, padding=0.01)
    p = points_in_grid(grid, 100, seed=5)
    with jax.enable_x64(True):
        d64, n64 = sdf_query(grid.as_jax(jnp.float64), jnp.asarray(p, jnp.float64))
        g64 = jax.grad(lambda x: sdf_query(grid, x)[0].sum())(jnp.asarray(p, jnp.float64))
        assert d64.dtype == n64.dtype == g64.dtype == jnp.float64
    d32, _ = sdf_query(grid, jnp.asarray(p, jnp.float32))
    assert d32.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(d64), np.asarray(d32), atol=1e-6)


def test_outside_grid_grows_monotonically(box: ObjectAsset) -> None:
    grid = box.sdf(spacing=0.004, padding=0.005)
    rng = np.random.default_rng(6)
    dirs = rng.normal(size=(20, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    steps = np.linspace(0.0, 0.5, 60)
    p = dirs[:, None, :] * steps[None, :, None]  # rays from the box centre (origin) out to 0.5 m
    d, n = map(np.asarray, sdf_query(grid, jnp.asarray(p, jnp.float32)))
    box_dist = np.linalg.norm(p - np.clip(p, grid.origin, grid.upper), axis=-1)
    outside = box_dist > 0
    assert outside[:, -1].all() and (d[outside] >= box_dist[outside] - 1e-6).all()
    assert (d >= exact_sdf(box, p.reshape(-1, 3)).reshape(d.shape) - 1e-3).all()
    assert (np.diff(d, axis=1)[outside[:, 1:]] > 0).all()
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1, atol=1e-5)
    assert (np.sum(n[:, -1] * dirs, -1) > 0.99).all()  # far away the normal points radially
    grad = jax.jit(jax.vmap(jax.grad(lambda x: sdf_query(grid, x)[0])))
    g = grad(jnp.asarray(p.reshape(-1, 3), jnp.float32))
    assert np.isfinite(np.asarray(g)).all()


def test_bake_coarsens_large_grids(box: ObjectAsset) -> None:
    grid = bake_sdf(box.vertices, box.faces, spacing=0.001, padding=0.01, max_nodes=20_000)
    assert np.prod(grid.shape) <= 20_000 and grid.spacing > 0.001
    assert (grid.origin <= box.bbox[0] - 0.01 + 1e-12).all()


# ---------------------------------------------------------------- disk caches


def counting(monkeypatch: pytest.MonkeyPatch, name: str) -> list[int]:
    calls: list[int] = []
    real: Callable[..., object] = getattr(obj, name)

    def wrapped(*args: object, **kwargs: object) -> object:
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(obj, name, wrapped)
    return calls


def test_sdf_cache(tmp_path: Path, _tmp_cache: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    calls = counting(monkeypatch, "bake_sdf")
    path = write_mesh(tmp_path, trimesh.creation.box((0.03, 0.04, 0.05)))
    first = load_object(path).sdf(0.003, 0.01)
    assert len(calls) == 1
    files = list((_tmp_cache / "sdf").glob("*.npz"))
    assert len(files) == 1

    asset = load_object(path)
    t = time.perf_counter()
    second = asset.sdf(0.003, 0.01)
    assert time.perf_counter() - t < 1.0 and len(calls) == 1
    assert asset.sdf(0.003, 0.01) is second  # in-memory too
    np.testing.assert_array_equal(first.values, second.values)
    np.testing.assert_array_equal(first.origin, second.origin)
    assert first.spacing == second.spacing

    for damage in (b"not a zip file", files[0].read_bytes()[:100]):
        files[0].write_bytes(damage)
        rebuilt = load_object(path).sdf(0.003, 0.01)
        np.testing.assert_array_equal(rebuilt.values, first.values)
        with np.load(files[0]) as z:  # rewritten, readable
            np.testing.assert_array_equal(z["values"], first.values)
    assert len(calls) == 3

    load_object(path).sdf(0.004, 0.01)  # other parameters: other file
    other = load_object(write_mesh(tmp_path, trimesh.creation.box((0.03, 0.04, 0.051)), "other.ply"))
    assert other.content_hash != load_object(path).content_hash
    other.sdf(0.003, 0.01)
    assert len(calls) == 5 and len(list((_tmp_cache / "sdf").glob("*.npz"))) == 3
    assert not list((_tmp_cache / "sdf").glob(".*"))  # no temporary files left behind


def test_convex_parts_of_box_and_cache(box: ObjectAsset, _tmp_cache: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    calls = counting(monkeypatch, "convex_decomposition")
    parts = box.convex_parts()
    assert parts and len(calls) == 1
    volume = 0.0
    for v, f in parts:
        hull = trimesh.Trimesh(v, f, process=False)
        assert len(v) >= 4 and hull.is_watertight and hull.is_convex and hull.volume > 0
        volume += hull.volume
    assert volume == pytest.approx(0.04 * 0.06 * 0.08, rel=0.02)
    assert hull_gap(box.vertices, parts).max() < 1e-6

    (cached_file,) = (_tmp_cache / "coacd").glob("*.npz")
    again = load_object(box.mesh_path).convex_parts()
    assert len(calls) == 1 and len(again) == len(parts)
    for (v1, f1), (v2, f2) in zip(parts, again, strict=True):
        np.testing.assert_array_equal(v1, v2)
        np.testing.assert_array_equal(f1, f2)
    cached_file.write_bytes(b"corrupt")
    assert len(load_object(box.mesh_path).convex_parts()) == len(parts) and len(calls) == 2


def test_convex_parts_cover_real_mesh() -> None:
    asset = load_object(real_mesh("cubesmall.obj"))
    parts = asset.convex_parts()
    for v, f in parts:
        hull = trimesh.Trimesh(v, f, process=False)
        assert len(v) >= 4 and hull.is_watertight and hull.volume > 0
    assert hull_gap(asset.vertices, parts).max() < 5e-4  # m
    total = sum(trimesh.Trimesh(v, f, process=False).volume for v, f in parts)
    assert total == pytest.approx(asset.volume, rel=0.05)
