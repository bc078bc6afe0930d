"""`quasisim convert grab|arctic` and the numpy MANO forward pass, on small synthetic files in the released
layouts (a synthetic MANO model pickle with a chumpy-like array and a scipy sparse regressor, a GRAB sequence
npz, an ARCTIC raw sequence); nothing of the real datasets or MANO is used."""

from __future__ import annotations

import json
import pickle
import types
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
import trimesh
from click.testing import CliRunner

from helpers import swapped_modules
from quasisim.cli import main
from quasisim.data import mano
from quasisim.data.convert_raw import RawOptions, convert_arctic, convert_grab
from quasisim.data.demo import load_demo
from quasisim.errors import InputError
from quasisim.rotations import np_quat_to_mat

PARENTS = [-1, 0, 1, 2, 0, 4, 5, 0, 7, 8, 0, 10, 11, 0, 13, 14]
# a right hand at rest (m), MANO joint order: wrist; index, middle, little, ring, thumb (3 each); palm +z
REST = np.array([
    [0, 0, 0],
    [0.025, 0.09, 0], [0.025, 0.13, 0], [0.025, 0.155, 0],
    [0.005, 0.095, 0], [0.005, 0.14, 0], [0.005, 0.168, 0],
    [-0.035, 0.075, 0], [-0.035, 0.105, 0], [-0.035, 0.125, 0],
    [-0.015, 0.09, 0], [-0.015, 0.13, 0], [-0.015, 0.155, 0],
    [0.025, 0.03, 0.01], [0.04, 0.055, 0.02], [0.05, 0.075, 0.025],
])  # fmt: skip
TIPS = np.array([[0.055, 0.095, 0.03], [0.025, 0.177, 0], [0.005, 0.19, 0], [-0.015, 0.177, 0], [-0.035, 0.145, 0]])
TIP_PARENT = (15, 3, 6, 12, 9)  # thumb, index, middle, ring, little


class Ch:
    """Pickles like a chumpy ``Ch`` (module ``chumpy.ch``): its state is a dict with the value under ``x``."""

    def __init__(self, x: np.ndarray) -> None:
        self.x = x

    def __getstate__(self) -> dict:
        return {"x": self.x, "_dirty_vars": set(), "_itr": None, "_make_dense": False}


Ch.__module__ = "chumpy.ch"


def _model_arrays(seed: int = 0) -> dict:
    """A valid small MANO-like model: 778 vertices; joint k regressed from two vertices straddling REST[k]."""
    rng = np.random.default_rng(seed)
    v = rng.normal(0, 0.01, (mano.N_VERTS, 3)) + np.array([0, 0.08, 0])
    d = rng.normal(0, 0.003, (16, 3))
    v[:16], v[100:116] = REST + d, REST - d
    v[list(mano.TIP_VERTS)] = TIPS
    reg = np.zeros((16, mano.N_VERTS))
    reg[np.arange(16), np.arange(16)] = reg[np.arange(16), 100 + np.arange(16)] = 0.5
    near = np.argmin(np.linalg.norm(v[:, None] - REST[None], axis=-1), axis=1)
    near[list(mano.TIP_VERTS)] = TIP_PARENT
    weights = np.eye(16)[near] * 0.9 + 0.1 * np.eye(16)[np.array(PARENTS)[near].clip(0)]
    q, _ = np.linalg.qr(rng.normal(size=(45, 45)))
    return {
        "v_template": v, "J_regressor": sp.csc_matrix(reg), "weights": weights,
        "kintree_table": np.array([[2**32 - 1, *PARENTS[1:]], list(range(16))], dtype=np.int64),
        "shapedirs": Ch(rng.normal(0, 1e-3, (mano.N_VERTS, 3, 10))),
        "posedirs": rng.normal(0, 1e-3, (mano.N_VERTS, 3, 135)), "hands_components": q,
        "hands_mean": rng.normal(0, 0.05, 45), "f": np.zeros((1, 3), dtype=np.uint32), "bs_style": "lbs",
    }  # fmt: skip


def _left(arrays: dict) -> dict:
    """The mirrored (left) model: x -> -x on the template (blend shapes kept, as MANO_LEFT mirrors MANO_RIGHT)."""
    out = dict(arrays)
    out["v_template"] = arrays["v_template"] * np.array([-1.0, 1.0, 1.0])
    return out


def write_model(path: Path, arrays: dict, protocol: int = 2) -> Path:
    """Pickle ``arrays`` as a MANO file (``Ch`` objects under the module name ``chumpy.ch``)."""
    pkg, fake = types.ModuleType("chumpy"), types.ModuleType("chumpy.ch")
    fake.Ch, pkg.ch = Ch, fake
    with swapped_modules({"chumpy": pkg, "chumpy.ch": fake}):
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(pickle.dumps(arrays, protocol=protocol))
    return path


@pytest.fixture(scope="module")
def mano_dir(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("mano")
    arrays = _model_arrays()
    write_model(d / "MANO_RIGHT.pkl", arrays)
    write_model(d / "MANO_LEFT.pkl", _left(arrays), protocol=1)  # protocol 1: copyreg._reconstructor
    return d


# ---- the MANO forward pass ----------------------------------------------------------------------------


def test_mano_pickle_rest_pose_and_rigid_motion(mano_dir: Path) -> None:
    m = mano.load_mano(mano_dir / "MANO_RIGHT.pkl")
    arrays = _model_arrays()
    np.testing.assert_allclose(m.shapedirs, arrays["shapedirs"].x)  # the chumpy stand-in yields the array
    np.testing.assert_allclose(m.j_regressor, arrays["J_regressor"].toarray())
    assert m.parents.tolist() == PARENTS
    zero = np.zeros((1, 16, 3))
    joints, verts = mano.forward(m, zero, vertex_ids=None)
    np.testing.assert_allclose(joints[0], m.j_regressor @ m.v_template, atol=1e-12)  # regressed template joints
    np.testing.assert_allclose(joints[0], REST, atol=1e-12)
    np.testing.assert_allclose(verts[0], m.v_template, atol=1e-12)
    kp = mano.keypoints(m, np.zeros((1, 3)), np.zeros((1, 45)), np.zeros((1, 3)), flat_hand_mean=True)
    np.testing.assert_allclose(kp[0], np.concatenate([REST, TIPS])[list(mano.MANO_TO_MEDIAPIPE)], atol=1e-12)
    # a global rotation about the wrist and a translation move every keypoint rigidly (any finger pose)
    rng = np.random.default_rng(1)
    pose = rng.normal(0, 0.3, (1, 45))
    aa, t = np.array([[0.3, -1.2, 0.5]]), np.array([[0.1, -0.2, 0.9]])
    base = mano.keypoints(m, np.zeros((1, 3)), pose, np.zeros((1, 3)))
    moved = mano.keypoints(m, aa, pose, t)
    R = mano.rodrigues(aa[0])
    np.testing.assert_allclose(moved[0], (base[0] - REST[0]) @ R.T + REST[0] + t[0], atol=1e-12)
    # shape: betas move the template by shapedirs . betas
    b = rng.normal(size=10)
    _, v_b = mano.forward(m, zero, betas=b, vertex_ids=None)
    np.testing.assert_allclose(v_b[0], m.v_template + m.shapedirs @ b, atol=1e-12)
    # PCA pose with hands_mean == the same 45 numbers given directly
    c = rng.normal(size=(1, 12))
    np.testing.assert_allclose(
        mano.full_pose(m, aa, c), mano.full_pose(m, aa, c @ m.hands_components[:12] + m.hands_mean, True)
    )


def test_bending_one_joint_turns_its_finger_about_it(mano_dir: Path) -> None:
    """The kinematic chain and skinning against a direct construction: index MCP (MANO joint 1) bent by R
    turns joints 2, 3 and the index tip about joint 1; every other keypoint stays."""
    m = mano.load_mano(mano_dir / "MANO_RIGHT.pkl")
    pose = np.zeros((1, 16, 3))
    pose[0, 1] = [0.0, 0.0, 1.1]
    R = mano.rodrigues(pose[0, 1])
    joints, tips = mano.forward(m, pose)
    feat = (mano.rodrigues(pose[0, 1:]) - np.eye(3)).reshape(-1)
    np.testing.assert_allclose(joints[0, 2:4], REST[1] + (REST[2:4] - REST[1]) @ R.T, atol=1e-12)
    np.testing.assert_allclose(joints[0, [0, 1, *range(4, 16)]], REST[[0, 1, *range(4, 16)]], atol=1e-12)
    tip = TIPS[1] + m.posedirs[mano.TIP_VERTS[1]] @ feat  # index tip with its pose blend shape
    np.testing.assert_allclose(tips[0, 1], REST[1] + R @ (tip - REST[1]), atol=1e-12)


@pytest.mark.parametrize("fmt", ["csc", "csr", "coo"])
def test_sparse_stand_ins(tmp_path: Path, fmt: str) -> None:
    a = np.zeros((4, 6))
    a[[0, 1, 3, 3], [5, 0, 2, 4]] = [1.0, 2.0, 3.0, 4.0]
    f = tmp_path / "m.pkl"
    for protocol in (1, 2, 4):
        f.write_bytes(pickle.dumps({"J_regressor": getattr(sp, f"{fmt}_matrix")(a)}, protocol=protocol))
        with open(f, "rb") as fh:
            np.testing.assert_array_equal(mano.safe_load_pickle(fh, f)["J_regressor"], a)


def test_rodrigues_matches_scipy() -> None:
    from scipy.spatial.transform import Rotation

    aa = np.random.default_rng(2).normal(size=(20, 3))
    np.testing.assert_allclose(mano.rodrigues(aa), Rotation.from_rotvec(aa).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(mano.rodrigues(np.zeros(3)), np.eye(3))


def test_unpickler_refuses_other_classes(tmp_path: Path, mano_dir: Path) -> None:
    import os

    bad = tmp_path / "MANO_RIGHT.pkl"
    bad.write_bytes(pickle.dumps({"v_template": os.system}))  # names posix.system: never called
    with pytest.raises(InputError, match=r"MANO_RIGHT\.pkl.*refusing to load the class posix\.system"):
        mano.load_mano(bad)
    arrays = _model_arrays()
    del arrays["weights"]
    write_model(tmp_path / "m" / "MANO_RIGHT.pkl", arrays)
    with pytest.raises(InputError, match=r"field 'weights'.*missing"):
        mano.load_mano(tmp_path / "m" / "MANO_RIGHT.pkl")
    with pytest.raises(InputError, match=r"option '--mano-dir'.*MANO_LEFT\.pkl.*no such file"):
        mano.find_model(tmp_path / "m", "left")
    assert mano.find_model(mano_dir, "right") == mano_dir / "MANO_RIGHT.pkl"


# ---- GRAB ---------------------------------------------------------------------------------------------

N_GRAB, TABLE, BOX = 61, 0.80, 0.06
R_OFF, L_OFF = np.array([-0.05, -0.25, 0.05]), np.array([0.05, -0.25, 0.05])  # hands from the object


def _grab_tree(root: Path, mano_dir: Path, drop: str | None = None) -> Path:
    """A GRAB layout under ``root``: grab/s1/cube_lift.npz (120 fps), the subject's hand template and the
    object mesh under tools/. The object turns 90 deg about z (GRAB's convention) and moves along x."""
    k = np.arange(N_GRAB)[:, None]
    vt = mano.load_mano(mano_dir / "MANO_RIGHT.pkl").v_template * 1.05  # the subject's own (larger) hand
    vt_rel = "tools/subject_meshes/male/s1_rhand.ply"
    (root / vt_rel).parent.mkdir(parents=True)
    trimesh.Trimesh(vt, np.array([[0, 1, 2], [3, 4, 5]]), process=False).export(root / vt_rel)
    mesh_rel = "tools/object_meshes/contact_meshes/cube.ply"
    (root / mesh_rel).parent.mkdir(parents=True)
    trimesh.creation.box([BOX] * 3).export(root / mesh_rel)
    obj_pos = np.array([0.3, 0.2, TABLE + BOX / 2]) + k * np.array([0.001, 0, 0])
    params = {"global_orient": np.tile([0, 0, np.pi / 2], (N_GRAB, 1)), "transl": obj_pos}
    rhand = {
        "global_orient": np.zeros((N_GRAB, 3)), "hand_pose": np.zeros((N_GRAB, 24)),
        "transl": obj_pos + R_OFF, "fullpose": np.zeros((N_GRAB, 45)),
    }  # fmt: skip
    if drop:
        del rhand[drop]
    seq = root / "grab" / "s1" / "cube_lift.npz"
    seq.parent.mkdir(parents=True)
    np.savez(
        seq, framerate=np.array(120.0), obj_name=np.array("cube"), n_comps=np.array(24), gender=np.array("male"),
        rhand={"params": rhand, "vtemp": vt_rel},
        lhand={"params": {**rhand, "transl": obj_pos + L_OFF}, "vtemp": ""},
        object={"params": params, "object_mesh": mesh_rel}, table={"params": {}, "table_mesh": ""},
    )  # fmt: skip
    return seq


def test_grab_to_clip(tmp_path: Path, mano_dir: Path) -> None:
    seq = _grab_tree(tmp_path / "GRAB", mano_dir)
    out = convert_grab(seq, mano_dir, tmp_path / "clips" / "cube.npz", opts=RawOptions(fps=20.0, left=True))
    d = load_demo(out)  # valid, mesh and all
    assert d.fps == 20.0 and d.n_frames == 11 and d.object_name == "cube"
    assert d.object_mesh_path == (tmp_path / "clips" / "meshes" / "cube.obj").resolve()
    # clip frame k = source frame 6 k; z up, metres: the table top under the box
    src = 6 * np.arange(11)[:, None]
    pos = np.array([0.3, 0.2, TABLE + BOX / 2]) + src * np.array([0.001, 0, 0])
    np.testing.assert_allclose(d.object_pos, pos, atol=1e-6)
    assert d.support_height == pytest.approx(TABLE, abs=1e-6)
    # GRAB's object model is v @ R + t: +90 deg about z in the file is -90 deg in the world
    np.testing.assert_allclose(
        np_quat_to_mat(d.object_quat[0]), mano.rodrigues(np.array([0, 0, -np.pi / 2])), atol=1e-6
    )
    # the subject's template, flat hand (PCA zeros, flat_hand_mean): keypoints = regressed joints + transl
    m = mano.load_mano(mano_dir / "MANO_RIGHT.pkl")
    vt = m.v_template * 1.05
    rest = np.concatenate([m.j_regressor @ vt, vt[list(mano.TIP_VERTS)]])[list(mano.MANO_TO_MEDIAPIPE)]
    np.testing.assert_allclose(d.right_joints, rest[None] + (pos + R_OFF)[:, None], atol=1e-6)
    with np.load(out, allow_pickle=False) as z:
        left = z["left_joints"]
    assert left.shape == (11, 21, 3) and left[:, :, 0].mean() > d.right_joints[:, :, 0].mean()


def test_grab_cli_and_bad_inputs(tmp_path: Path, mano_dir: Path) -> None:
    seq = _grab_tree(tmp_path / "GRAB", mano_dir)
    args = ["convert", "grab", str(seq), "--mano-dir", str(mano_dir), "--out", str(tmp_path / "o" / "c.npz")]
    r = CliRunner().invoke(main, [*args, "--fps", "30", "--start", "12", "--frames", "5"])
    assert r.exit_code == 0, r.output
    d = load_demo(tmp_path / "o" / "c.npz")
    assert d.n_frames == 5 and d.object_pos[0, 0] == pytest.approx(0.312)
    r = CliRunner().invoke(main, [*args[:3], "--mano-dir", str(tmp_path / "nowhere"), *args[5:]])
    assert r.exit_code == 2 and "MANO_RIGHT.pkl" in r.output and "--mano-dir" in r.output
    assert len(r.output.strip().splitlines()) == 1
    bad = _grab_tree(tmp_path / "GRAB2", mano_dir, drop="hand_pose")
    r = CliRunner().invoke(main, ["convert", "grab", str(bad), *args[3:]])
    assert r.exit_code == 2 and "cube_lift.npz" in r.output and "rhand.params.hand_pose" in r.output
    assert len(r.output.strip().splitlines()) == 1
    evil = tmp_path / "evil"
    evil.mkdir()
    (evil / "MANO_RIGHT.pkl").write_bytes(pickle.dumps({"v_template": sp.random}))
    r = CliRunner().invoke(main, [*args[:3], "--mano-dir", str(evil), *args[5:]])
    assert r.exit_code == 2 and "MANO_RIGHT.pkl" in r.output and "refusing" in r.output and "random" in r.output
    r = CliRunner().invoke(main, [*args, "--start", "70"])
    assert r.exit_code == 2 and "--start" in r.output


def test_grab_with_a_bad_mesh_leaves_the_mesh_already_there(tmp_path: Path, mano_dir: Path) -> None:
    """A conversion refused for its object mesh leaves meshes/<object>.obj beside OUT as it was (another
    clip's of the same object, or the user's own): the mesh is checked before it replaces anything."""
    seq = _grab_tree(tmp_path / "GRAB", mano_dir)
    ply = tmp_path / "GRAB" / "tools" / "object_meshes" / "contact_meshes" / "cube.ply"
    m = trimesh.load(ply, process=False, force="mesh")
    m.update_faces(np.arange(len(m.faces)) < 6)  # three sides of the box: fill_holes cannot close it
    m.export(ply)
    mine = tmp_path / "o" / "meshes" / "cube.obj"
    mine.parent.mkdir(parents=True)
    mine.write_text("# mine\n")
    args = ["convert", "grab", str(seq), "--mano-dir", str(mano_dir), "--out", str(tmp_path / "o" / "c.npz")]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 2 and "cube.ply" in r.output and "watertight" in r.output, r.output
    assert mine.read_text() == "# mine\n" and [p.name for p in mine.parent.iterdir()] == ["cube.obj"]


# ---- ARCTIC -------------------------------------------------------------------------------------------

N_ARCTIC, STAND, ANGLE = 31, 0.95, 0.2


def _arctic_tree(root: Path, parts_json: bool = False) -> Path:
    """ARCTIC raw layout under ``root``: raw_seqs/s01/box_grab_01.{mano,object}.npy (30 fps) and the box
    template (mm) in meta/object_vtemplates/box/ (top.obj + bottom.obj, or mesh.obj + parts.json)."""
    k = np.arange(N_ARCTIC)[:, None]
    d = root / "meta" / "object_vtemplates" / "box"
    d.mkdir(parents=True)
    bottom = trimesh.creation.box([100, 100, 40], trimesh.transformations.translation_matrix([0, 0, 20]))
    top = trimesh.creation.box(
        [100, 60, 14], trimesh.transformations.translation_matrix([0, 20, 43])
    )  # 4 mm into the base
    if parts_json:
        trimesh.util.concatenate([bottom, top]).export(d / "mesh.obj")
        (d / "parts.json").write_text(json.dumps([0] * len(bottom.vertices) + [1] * len(top.vertices)))
    else:
        bottom.export(d / "bottom.obj")
        top.export(d / "top.obj")
    trans_mm = np.array([300.0, 100.0, STAND * 1000]) + k * np.array([2.0, 0, 0])
    obj = np.concatenate([np.full((N_ARCTIC, 1), ANGLE), np.tile([0, 0, 0.4], (N_ARCTIC, 1)), trans_mm], axis=1)
    hand = {"rot": np.zeros((N_ARCTIC, 3)), "pose": np.zeros((N_ARCTIC, 45)), "shape": np.zeros((N_ARCTIC, 10)),
            "fitting_err": np.zeros(N_ARCTIC)}  # fmt: skip
    hands = {"right": {**hand, "trans": trans_mm / 1000 + [0.08, -0.1, 0.02]},
             "left": {**hand, "trans": trans_mm / 1000 + [-0.08, -0.1, 0.02]}}  # fmt: skip
    seq = root / "raw_seqs" / "s01" / "box_grab_01"
    seq.parent.mkdir(parents=True)
    np.save(seq.with_name("box_grab_01.object.npy"), obj)
    np.save(seq.with_name("box_grab_01.mano.npy"), hands)
    return seq.with_name("box_grab_01.mano.npy")


@pytest.mark.parametrize("parts_json", [False, True])
def test_arctic_to_two_hand_clip(tmp_path: Path, mano_dir: Path, parts_json: bool) -> None:
    seq = _arctic_tree(tmp_path / "arctic_data" / "data", parts_json)
    out = convert_arctic(seq, mano_dir, tmp_path / "clips" / "box.npz", opts=RawOptions(fps=20.0))
    d = load_demo(out)
    assert d.n_frames == 21 and d.fps == 20.0  # 30 -> 20 fps: source frames 0, 1.5, 3, ..., 30
    s = 1.5 * np.arange(21)[:, None]
    pos = (np.array([300.0, 100.0, STAND * 1000]) + s * np.array([2.0, 0, 0])) / 1000  # mm -> m, interpolated
    np.testing.assert_allclose(d.object_pos, pos, atol=1e-6)
    np.testing.assert_allclose(np_quat_to_mat(d.object_quat[3]), mano.rodrigues(np.array([0, 0, 0.4])), atol=1e-6)
    assert d.support_height == pytest.approx(STAND, abs=1e-6)
    assert d.object_mesh_path.name == "box_hinge0200mrad.obj"
    v = np.asarray(trimesh.load(d.object_mesh_path, process=False, force="mesh").vertices)
    lid_corner = mano.rodrigues(np.array([0, 0, -ANGLE])) @ np.array([0.05, 0.05, 0.05])  # ARCTIC: Rz(-angle)
    assert np.linalg.norm(v - lid_corner, axis=1).min() < 1e-6
    mesh = trimesh.load(d.object_mesh_path, force="mesh")
    parts_volume = (100 * 100 * 40 + 100 * 60 * 14) * 1e-9  # m^3, the overlap counted twice
    assert mesh.is_watertight and len(mesh.split(only_watertight=False)) == 1  # one body: the parts' union
    assert 0.99 * parts_volume - 100 * 60 * 4 * 1e-9 < mesh.volume < parts_volume - 1e-7  # the overlap once
    m = mano.load_mano(mano_dir / "MANO_RIGHT.pkl")
    pose = mano.full_pose(m, np.zeros((1, 3)), np.zeros((1, 45)))  # pose 0 = MANO's mean hand (flat_hand_mean off)
    j, tips = mano.forward(m, pose)
    rest = np.concatenate([j, tips], axis=1)[0, list(mano.MANO_TO_MEDIAPIPE)]
    np.testing.assert_allclose(d.right_joints, rest[None] + (pos + np.array([0.08, -0.1, 0.02]))[:, None], atol=1e-6)
    with np.load(out, allow_pickle=False) as z:
        left = z["left_joints"]
    assert left.shape == (21, 21, 3) and left.dtype == np.float32
    assert left[:, 0, 0].mean() < d.right_joints[:, 0, 0].mean()  # true positions, not mirrored


def test_arctic_bad_inputs(tmp_path: Path, mano_dir: Path) -> None:
    seq = _arctic_tree(tmp_path / "a")
    hands = np.load(seq, allow_pickle=True).item()
    del hands["left"]["shape"]
    np.save(seq, hands)
    args = ["convert", "arctic", str(seq), "--mano-dir", str(mano_dir), "--out", str(tmp_path / "o.npz")]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 2 and "box_grab_01.mano.npy" in r.output and "left.shape" in r.output
    assert len(r.output.strip().splitlines()) == 1
    r = CliRunner().invoke(main, ["convert", "arctic", str(tmp_path / "a" / "raw_seqs" / "s01" / "nope"), *args[3:]])
    assert r.exit_code == 2 and "nope.mano.npy" in r.output
    np.save(seq, np.zeros((3, 7)))  # an array where the dict of hands belongs
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 2 and "box_grab_01.mano.npy" in r.output and "'right'" in r.output


def test_arctic_hinge_warning_wrong_left_model_and_open_mesh(tmp_path: Path, mano_dir: Path) -> None:
    seq = _arctic_tree(tmp_path / "a")
    obj = np.load(seq.with_name("box_grab_01.object.npy"))
    obj[:, 0] = np.linspace(0, 0.5, len(obj))  # the lid opens during the clip
    np.save(seq.with_name("box_grab_01.object.npy"), obj)
    args = ["convert", "arctic", str(seq), "--out", str(tmp_path / "o" / "b.npz")]
    r = CliRunner().invoke(main, [*args, "--mano-dir", str(mano_dir)])
    assert r.exit_code == 0 and "warning: box_grab_01: the hinge moves 0.25 rad" in r.output
    assert (tmp_path / "o" / "meshes" / "box_hinge0250mrad.obj").is_file()
    # a right-hand model given as MANO_LEFT.pkl: the left keypoints are not a left hand
    wrong = tmp_path / "wrong"
    write_model(wrong / "MANO_RIGHT.pkl", _model_arrays())
    write_model(wrong / "MANO_LEFT.pkl", _model_arrays())
    r = CliRunner().invoke(main, [*args[:3], "--out", str(tmp_path / "w" / "b.npz"), "--mano-dir", str(wrong)])
    assert r.exit_code == 2 and "field 'left_joints'" in r.output and "mirrored" in r.output, r.output
    assert not (tmp_path / "w" / "b.npz").exists()
    # an open object mesh is refused at conversion, naming the template folder
    d = tmp_path / "a" / "meta" / "object_vtemplates" / "box"
    top = trimesh.load(d / "top.obj", process=False, force="mesh")
    top.update_faces(np.arange(len(top.faces)) < 6)  # half the box: three sides (fill_holes cannot close it)
    top.export(d / "top.obj")
    r = CliRunner().invoke(main, [*args[:3], "--out", str(tmp_path / "x" / "b.npz"), "--mano-dir", str(mano_dir)])
    assert r.exit_code == 2 and "object_vtemplates/box" in r.output and "watertight" in r.output, r.output
