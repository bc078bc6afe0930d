"""A left hand from a right-hand model: the mirrored model's MuJoCo FK is the reflection of the original's."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest

from quasisim.assets.hand import compile_hand_model, load_hand, resolve_hand_config
from quasisim.assets.mirror import mirror_mjcf, mirror_quat, reflection
from quasisim.errors import InputError, QuasisimError

HANDS = ["shadow", "allegro"]


@pytest.fixture(params=HANDS)
def hand_name(request: pytest.FixtureRequest) -> str:
    request.getfixturevalue(request.param)  # skips the Allegro hand when its URDF is absent
    return request.param


def _random_qpos(m: mujoco.MjModel, rng: np.random.Generator) -> np.ndarray:
    lo = np.where(m.jnt_limited, m.jnt_range[:, 0], -np.pi)
    hi = np.where(m.jnt_limited, m.jnt_range[:, 1], np.pi)
    return rng.uniform(lo, hi)  # hinge and slide joints only: one qpos per joint


def _fk(m: mujoco.MjModel, qpos: np.ndarray) -> mujoco.MjData:
    d = mujoco.MjData(m)
    d.qpos[:] = qpos
    mujoco.mj_kinematics(m, d)
    return d


def _mesh_world(m: mujoco.MjModel, d: mujoco.MjData, g: int) -> tuple[np.ndarray, np.ndarray]:
    mid = m.geom_dataid[g]
    va, vn, fa, fn = m.mesh_vertadr[mid], m.mesh_vertnum[mid], m.mesh_faceadr[mid], m.mesh_facenum[mid]
    v = m.mesh_vert[va : va + vn] @ d.geom_xmat[g].reshape(3, 3).T + d.geom_xpos[g]
    return v, m.mesh_face[fa : fa + fn]


def _signed_volume(v: np.ndarray, f: np.ndarray) -> float:
    return float(np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6)


def _models(name: str) -> tuple[mujoco.MjModel, mujoco.MjModel, np.ndarray]:
    cfg = resolve_hand_config(name)
    right, _ = compile_hand_model(cfg)
    left, _ = compile_hand_model(cfg.for_side("left"))
    return right, left, reflection(cfg.mirror_axis)


def test_mirrored_fk_is_the_reflection(hand_name: str) -> None:
    right, left, M = _models(hand_name)
    assert (right.nbody, right.njnt, right.ngeom, right.nsite) == (left.nbody, left.njnt, left.ngeom, left.nsite)
    rng = np.random.default_rng(0)
    for _ in range(5):
        q = _random_qpos(right, rng)
        dr, dl = _fk(right, q), _fk(left, q)
        R_r, R_l = dr.xmat.reshape(-1, 3, 3), dl.xmat.reshape(-1, 3, 3)
        np.testing.assert_allclose(dl.xpos, dr.xpos @ M, atol=1e-9)
        np.testing.assert_allclose(R_l, M @ R_r @ M, atol=1e-9)
        np.testing.assert_allclose(dl.site_xpos, dr.site_xpos @ M, atol=1e-9)
        np.testing.assert_allclose(dl.geom_xpos, dr.geom_xpos @ M, atol=1e-7)
        np.testing.assert_allclose(dl.xipos, dr.xipos @ M, atol=1e-9)
        for g in np.flatnonzero(right.geom_type == mujoco.mjtGeom.mjGEOM_MESH):
            vr, fr = _mesh_world(right, dr, g)
            vl, fl = _mesh_world(left, dl, g)
            np.testing.assert_allclose(vl, vr @ M, atol=1e-6)  # the same vertices, reflected
            # reversed winding: faces stay outward, so both enclose a positive volume
            assert _signed_volume(vr, fr) > 0 and abs(_signed_volume(vl, fl) - _signed_volume(vr, fr)) < 1e-9


def test_mirrored_masses_and_inertias_match(hand_name: str) -> None:
    right, left, M = _models(hand_name)
    np.testing.assert_allclose(left.body_mass, right.body_mass, rtol=1e-12)
    np.testing.assert_allclose(np.sort(left.body_inertia, axis=1), np.sort(right.body_inertia, axis=1), rtol=1e-9)
    # the full inertia tensors in the body frames are reflections of each other
    for b in range(1, right.nbody):
        Rr = np.zeros(9)
        Rl = np.zeros(9)
        mujoco.mju_quat2Mat(Rr, right.body_iquat[b])
        mujoco.mju_quat2Mat(Rl, left.body_iquat[b])
        Ir = Rr.reshape(3, 3) @ np.diag(right.body_inertia[b]) @ Rr.reshape(3, 3).T
        Il = Rl.reshape(3, 3) @ np.diag(left.body_inertia[b]) @ Rl.reshape(3, 3).T
        np.testing.assert_allclose(Il, M @ Ir @ M, atol=1e-12)
    np.testing.assert_allclose(left.jnt_range, right.jnt_range)


def _chirality(hand_name: str, side: str) -> float:
    """Sign of (thumb tip - wrist) . ((index MCP - wrist) x (little/ring MCP - wrist)) at rest, palm frame."""
    from quasisim.sim.kinematics import fk_full, keypoints

    hand = load_hand(hand_name, side=side)
    q = np.concatenate([np.zeros(6), hand.rest_q()]).astype(np.float32)
    kp = np.asarray(keypoints(hand, fk_full(hand, np.eye(3), q)))
    at = {int(h): kp[i] for i, h in enumerate(hand.kp_human)}
    wrist, thumb, index = at[0], at[4], at[5]
    outer = at.get(17, at[13])
    return float(np.sign(np.dot(thumb - wrist, np.cross(index - wrist, outer - wrist))))


def test_mirrored_hand_has_the_other_chirality(hand_name: str) -> None:
    right, left = _chirality(hand_name, "right"), _chirality(hand_name, "left")
    assert right != 0 and left == -right
    assert right == _chirality("shadow", "right")  # both models are right hands: thumb on the same side


def test_written_mjcf_compiles_and_matches(tmp_path: Path, shadow) -> None:
    cfg = resolve_hand_config("shadow")
    left, _ = compile_hand_model(cfg.for_side("left"))
    out = mirror_mjcf(shadow.source, tmp_path / "left" / "shadow_left.xml", cfg.mirror_axis)
    assert out.is_file() and len(list((tmp_path / "left" / "shadow_left_meshes").glob("*.stl"))) == left.nmesh
    written = mujoco.MjModel.from_xml_path(str(out))
    q = _random_qpos(left, np.random.default_rng(1))
    np.testing.assert_allclose(_fk(written, q).xpos, _fk(left, q).xpos, atol=1e-5)
    np.testing.assert_allclose(written.body_mass, left.body_mass, rtol=1e-6)


def test_side_api_and_round_trip(shadow) -> None:
    left = load_hand("shadow", side="left")
    assert left.name == "shadow-left" and left.config.side == "left"
    builtin = load_hand("shadow-left")
    for f in ("body_pos", "body_quat", "joint_axis", "joint_range", "kp_pos", "body_inertia"):
        np.testing.assert_array_equal(getattr(left, f), getattr(builtin, f))
    back = load_hand("shadow-left", side="right")
    assert back.name == "shadow-right"
    for f in ("body_pos", "body_quat", "joint_axis", "joint_pos", "kp_pos", "body_ipos"):
        np.testing.assert_allclose(getattr(back, f), getattr(shadow, f), atol=1e-12)
    assert load_hand("shadow", side="right") is shadow
    with pytest.raises(QuasisimError, match="valid options: left, right"):
        load_hand("shadow", side="middle")


def test_mirror_quat_is_the_conjugated_rotation() -> None:
    from scipy.spatial.transform import Rotation

    for axis in ("x", "y", "z"):
        M = reflection(axis)
        q = Rotation.random(5, random_state=2).as_quat(scalar_first=True)
        R = Rotation.from_quat(q, scalar_first=True).as_matrix()
        Rm = Rotation.from_quat(mirror_quat(q, M), scalar_first=True).as_matrix()
        np.testing.assert_allclose(Rm, M @ R @ M, atol=1e-12)


def test_edit_errors(tmp_path: Path) -> None:
    y = tmp_path / "h.yaml"
    y.write_text("base: shadow\nname: h\nedits:\n  - {mirror: w}\n")
    with pytest.raises(InputError, match=r"edits\[0\].mirror.*one of x, y, z"):
        load_hand(y)
    y.write_text("base: shadow\nname: h\nedits:\n  - {scale: 0.5, body: robot0:nothumb}\n")
    with pytest.raises(InputError, match=r"edits\[0\].body.*robot0:thbase"):
        load_hand(y)
    y.write_text("base: shadow\nname: h\nedits:\n  - {mirror: x, scale: 0.5, body: robot0:thbase}\n")
    with pytest.raises(InputError, match="either"):
        load_hand(y)
    y.write_text("base: h.yaml\nname: h\n")
    with pytest.raises(InputError, match=r"base.*cycle"):
        load_hand(y)
    y.write_text("base: nohand\nname: h\n")
    with pytest.raises(InputError, match=r"base.*allegro, shadow"):
        load_hand(y)
    y.write_text("base: shadow\nname: h\nside: up\n")
    with pytest.raises(InputError, match=r"side.*right, left"):
        load_hand(y)
