"""Synthetic example demonstrations: format, hand realism, contact without penetration, smooth motion."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from quasisim.data import synthetic
from quasisim.data.demo import BONES, FINGERTIPS, Demo, load_demo
from quasisim.errors import QuasisimError
from quasisim.rotations import np_quat_to_mat, quat_angle_deg

THUMB_TIP = 4
GRASP_FRAME = 30  # fingers closed at frame n/2 for the default 60 frames


@pytest.fixture(scope="module")
def written(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Demo, trimesh.Trimesh]]:
    """Every example written once, then read back from disk (float32 as stored)."""
    out = tmp_path_factory.mktemp("examples")
    paths = synthetic.write_examples(out)
    demos = {}
    for p in paths:
        d = load_demo(p)
        demos[d.name] = (d, trimesh.load(d.object_mesh_path, force="mesh"))
    return demos


def _object_frame(d: Demo) -> np.ndarray:
    """(T, 21, 3) keypoints in the object frame (m)."""
    R = np_quat_to_mat(d.object_quat)
    return np.einsum("tji,tkj->tki", R, d.right_joints - d.object_pos[:, None])


def _surface_distance(d: Demo, mesh: trimesh.Trimesh) -> np.ndarray:
    """(T, 21) signed distance of keypoints to the mesh (m), positive outside."""
    local = _object_frame(d)
    return -trimesh.proximity.signed_distance(mesh, local.reshape(-1, 3)).reshape(local.shape[:2])


def test_write_examples_files(tmp_path: Path) -> None:
    paths = synthetic.write_examples(tmp_path)
    assert [p.name for p in paths] == [f"{n}.npz" for n in synthetic.EXAMPLES]
    names = sorted(p.name for p in tmp_path.rglob("*") if p.is_file())  # no temporary files left
    assert names == sorted([f"{n}.{ext}" for n in synthetic.EXAMPLES for ext in ("npz", "obj")])
    for name, p in zip(synthetic.EXAMPLES, paths, strict=True):
        d = load_demo(p)
        assert d.name == name
        assert d.n_frames == 60 and d.fps == 20.0
        assert d.object_mesh_path == (tmp_path / "meshes" / f"{name}.obj").resolve()
        assert trimesh.load(d.object_mesh_path, force="mesh").is_watertight


def test_write_example_custom_length(tmp_path: Path) -> None:
    d = load_demo(synthetic.write_example("cube_lift", tmp_path, n_frames=90, fps=30.0))
    assert d.n_frames == 90 and d.fps == 30.0
    assert d.object_pos[-1, 2] - d.object_pos[0, 2] > 0.08


def test_unknown_name_and_bad_length() -> None:
    with pytest.raises(QuasisimError, match=r"unknown example 'sphere_throw'.*cube_lift"):
        synthetic.make_example("sphere_throw")
    with pytest.raises(ValueError, match="n_frames"):
        synthetic.make_example("cube_lift", n_frames=5)


def test_deterministic_and_seed_is_rigid() -> None:
    a, _ = synthetic.make_example("cylinder_lift_turn")
    b, _ = synthetic.make_example("cylinder_lift_turn")
    np.testing.assert_array_equal(a.right_joints, b.right_joints)
    c, _ = synthetic.make_example("cylinder_lift_turn", seed=3)
    assert np.abs(c.object_pos[0, :2] - a.object_pos[0, :2]).max() > 1e-3 or not np.allclose(
        c.object_quat, a.object_quat
    )
    # the whole scene moved rigidly: the hand relative to the object is unchanged
    np.testing.assert_allclose(_object_frame(c), _object_frame(a), atol=1e-9)
    assert c.object_pos[0, 2] == pytest.approx(a.object_pos[0, 2])


@pytest.mark.parametrize("name", synthetic.EXAMPLES)
def test_hand_is_a_realistic_right_hand(written: dict, name: str) -> None:
    d, _ = written[name]
    J = d.right_joints
    lengths = np.stack([np.linalg.norm(J[:, b] - J[:, a], axis=-1) for a, b in BONES], axis=1)
    assert (lengths.max(axis=0) - lengths.min(axis=0)).max() < 1e-4
    phalanges = lengths[:, [i for i, (a, _) in enumerate(BONES) if a != 0]]
    assert phalanges.min() > 0.015 and phalanges.max() < 0.045
    mcp = np.linalg.norm(J[:, [5, 9, 13, 17]] - J[:, :1], axis=-1)
    assert mcp.min() > 0.08 and mcp.max() < 0.095
    cmc = np.linalg.norm(J[:, 1] - J[:, 0], axis=-1)
    assert np.all(np.abs(cmc - 0.038) < 0.005)
    # right hand: the fingers flex towards n = (J5 - J0) x (J17 - J0) on every frame
    n = np.cross(J[:, 5] - J[:, 0], J[:, 17] - J[:, 0])
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    for base, tip in ((5, 8), (9, 12), (13, 16), (17, 20)):
        assert np.all(np.einsum("ti,ti->t", J[:, tip] - J[:, base], n) > 0.005), (base, tip)


@pytest.mark.parametrize("name", synthetic.EXAMPLES)
def test_contact_without_penetration(written: dict, name: str) -> None:
    d, mesh = written[name]
    dist = _surface_distance(d, mesh)
    assert dist.min() > 0.003  # no keypoint inside (or touching) the object, ever
    grasp = dist[GRASP_FRAME:]
    assert np.all((grasp[:, THUMB_TIP] > 0.003) & (grasp[:, THUMB_TIP] < 0.012))
    others = grasp[:, [t for t in FINGERTIPS if t != THUMB_TIP]]
    in_contact = (others > 0.003) & (others < 0.012)
    assert np.all(in_contact.sum(axis=1) >= 1)
    # approach from afar
    assert dist[0].min() > 0.1
    # the object moves rigidly with the hand once grasped: contacts stay where they are
    local = _object_frame(d)[GRASP_FRAME:]
    assert np.abs(local - local[0]).max() < 1e-3
    # opposing grasp: thumb tip on the other side of the object than the other grasping tips
    centre = mesh.bounds.mean(axis=0)
    g = [t for t, c in zip(FINGERTIPS[1:], in_contact[0], strict=True) if c]
    assert np.dot(local[0, THUMB_TIP] - centre, local[0, g].mean(axis=0) - centre) < 0


@pytest.mark.parametrize("name", synthetic.EXAMPLES)
def test_object_rests_then_is_lifted(written: dict, name: str) -> None:
    d, mesh = written[name]
    R = np_quat_to_mat(d.object_quat)
    world = np.einsum("tij,vj->tvi", R, mesh.vertices) + d.object_pos[:, None]
    assert world[0, :, 2].min() == pytest.approx(d.support_height, abs=1e-4)
    assert world[..., 2].min() > d.support_height - 1e-4  # never through the table
    assert np.abs(d.object_pos[: GRASP_FRAME + 1] - d.object_pos[0]).max() < 1e-3
    assert quat_angle_deg(d.object_quat[0], d.object_quat[: GRASP_FRAME + 1]).max() < 0.1
    assert 0.08 <= d.object_pos[-1, 2] - d.object_pos[0, 2] <= 0.15
    assert d.right_joints[..., 2].min() > d.support_height  # the hand stays above the table top
    turned = quat_angle_deg(d.object_quat[0], d.object_quat[-1])
    if name == "cylinder_lift_turn":
        assert 45.0 <= turned <= 60.0
    else:
        assert turned < 1.0


@pytest.mark.parametrize("name", synthetic.EXAMPLES)
def test_motion_is_smooth(written: dict, name: str) -> None:
    d, _ = written[name]
    vel = np.diff(d.right_joints, axis=0) * d.fps
    assert np.linalg.norm(vel, axis=-1).max() < 1.5
    acc = np.diff(vel, axis=0) * d.fps
    assert np.linalg.norm(acc, axis=-1).max() < 10.0  # m/s^2: no velocity jumps
    q = d.object_quat
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-5)
    assert np.all(np.sum(q[1:] * q[:-1], axis=-1) > 0.99)
