"""The OakInk2 converter (``quasisim.data.convert_oakink2``) on small synthetic files in OakInk2's released
layout (anno_preview/<scene>++<seq>.pkl with raw_mano as pickled torch tensors and obj_transf keyed by mocap
frame id, program/program_info/<seq>.json segments, object_raw/align_ds/<obj_id>/*.obj, obj_desc.json) and a
synthetic MANO model pair; neither OakInk2, MANO nor torch is needed (the tensors are pickled byte for byte as
torch pickles them, see test_convert_taco.py).

The synthetic sequence: 240 mocap frames (ids 100..339, 120 Hz, y up, metres). A cup (box) rests, then moves
and turns from frame 180; the right hand comes down onto its top face and, from frame 170 on, rests with its
four finger tips on that face (the hand moves with the cup). A plate (box) is held the same way by the left
hand (touching from frame 230, moving from 260). Segments: 0 right hand / cup, 1 both hands, 2 left hand /
plate."""

from __future__ import annotations

import json
import pickle
import re
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from quasisim.data import mano
from quasisim.data.convert import UP_AXES
from quasisim.data.convert_oakink2 import OakInk2Options, convert_oakink2, read_anno
from quasisim.data.demo import load_demo
from quasisim.errors import InputError, QuasisimError
from quasisim.rotations import np_mat_to_quat, np_quat_to_mat
from test_convert_raw import REST, TIPS, _left, _model_arrays, write_model
from test_convert_taco import Tensor, dump_torch

TOKEN = "scene_01__A001++seq__0b3d183d6b2e90eefd66__2023-04-27-20-38-16"
IDS = np.arange(100, 340)  # mocap frame ids (not from 0: looked up by id, not by position)
CUP, PLATE = "O02@0038@00001", "C12001"
BOX = {CUP: (0.08, 0.08, 0.06), PLATE: (0.10, 0.09, 0.03)}  # m
OFFSET = {CUP: (0.0, 0.0, 0.0), PLATE: (0.01, 0.005, 0.0)}  # the plate off its frame's origin: not mirror-symmetric
WRIST = np.array([0.09, 0.006, 0.005])  # the rest wrist away from the origin, as in the real MANO
ORDER = list(mano.MANO_TO_MEDIAPIPE)
FINGER_TIPS = [8, 12, 16, 20]  # MediaPipe: index, middle, ring, little tips (z = 0 in the rest hand)
TABLE = 0.8
W = UP_AXES["y"]  # OakInk2's y up -> z up


def _segments() -> dict:
    return {
        "(None, (130, 250))": {
            "primitive": "pick_up", "obj_list": [CUP], "interaction_mode": "rh_main", "primitive_lh": None,
            "primitive_rh": "pick_up", "obj_list_lh": None, "obj_list_rh": [CUP],
        },
        "((140, 300), (160, 320))": {
            "primitive": "pour", "obj_list": [CUP, PLATE], "interaction_mode": "bh_main", "primitive_lh": "hold",
            "primitive_rh": "pour", "obj_list_lh": [PLATE], "obj_list_rh": [CUP],
        },
        "((200, 330), None)": {
            "primitive": "place_onto", "obj_list": [PLATE], "interaction_mode": "lh_main",
            "primitive_lh": "place_onto", "primitive_rh": None, "obj_list_lh": [PLATE], "obj_list_rh": None,
        },
    }  # fmt: skip


# ---- the synthetic motion -----------------------------------------------------------------------


@pytest.fixture(scope="module")
def mano_dir(tmp_path_factory) -> Path:
    """MANO_RIGHT / MANO_LEFT (mirrored) with the rest wrist at +-WRIST (OakInk2 centres the hand there)."""
    arrays = _model_arrays()
    arrays["v_template"] = arrays["v_template"] + WRIST
    d = tmp_path_factory.mktemp("mano")
    write_model(d / "MANO_RIGHT.pkl", arrays)
    write_model(d / "MANO_LEFT.pkl", _left(arrays))
    return d


def _mesh(obj: str) -> trimesh.Trimesh:
    """The object's mesh in its own frame (metres)."""
    return trimesh.creation.box(BOX[obj], transform=trimesh.transformations.translation_matrix(OFFSET[obj]))


def _object(obj: str, ids: np.ndarray = IDS) -> tuple[np.ndarray, np.ndarray]:
    """World rotations (n, 3, 3) and positions (n, 3) of an object: at rest, then moving and turning."""
    if obj == CUP:
        start, aa0, omega, p0, vel = 180, [0.3, 0.5, 0.2], [0.0, 0.004, 0.0], [0.1, 0.03, 0.2], [5e-4, 1e-3, 0.0]
    else:
        start, aa0, omega, p0, vel = 260, [-0.2, 1.0, 0.1], [0.003, 0.0, 0.0], [-0.25, 0.015, 0.25], [-4e-4, 8e-4, 0]
    k = np.clip(np.asarray(ids, float) - start, 0, None)[:, None]
    return mano.rodrigues(np.asarray(aa0) + k * omega), np.asarray(p0) + k * np.asarray(vel)


def _hand(side: str, ids: np.ndarray = IDS) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(rotation (n, 3, 3), tsl (n, 3), keypoints (n, 21, 3), gap (n,)) of a flat hand lying on its object's
    top face: the four finger tips ``gap`` above the face, 0 (contact) from the touch frame, 5 cm 70 frames
    before."""
    obj, touch, mirror = (CUP, 170, 1.0) if side == "right" else (PLATE, 230, -1.0)
    R, p = _object(obj, ids)
    rest = np.concatenate([REST, TIPS])[ORDER] * [mirror, 1.0, 1.0]  # relative to the wrist
    gap = 0.05 * np.clip((touch - np.asarray(ids, float)) / 70.0, 0, 1)
    rel = np.array([0.005 * mirror, -0.17, BOX[obj][2] / 2])[None] + gap[:, None] * [0.0, 0.0, 1.0]  # object frame
    tsl = np.einsum("tij,tj->ti", R, rel) + p
    kp = np.einsum("tij,kj->tki", R, rest) + tsl[:, None]
    return R, tsl, kp, gap


def _oakink2_tree(root: Path, torch: bool = True, fingers: np.ndarray | None = None, betas: np.ndarray | None = None,
                  segments: dict | None = None) -> Path:  # fmt: skip
    """OakInk2's layout under ``root``; returns the annotation pickle. ``fingers``: (n, 15, 4) quaternions of
    the right hand's finger joints (default identity); ``betas``: (n, 10) its shape (default zeros)."""
    n = len(IDS)
    raw_mano, raw_smplx = {}, {}
    rot = {side: _hand(side) for side in ("right", "left")}
    for t, f in enumerate(IDS):
        frame = {}
        for side, p in (("right", "rh"), ("left", "lh")):
            R, tsl, _, _ = rot[side]
            q = np.tile([1.0, 0.0, 0.0, 0.0], (16, 1))
            q[0] = np_mat_to_quat(R[t])
            if side == "right" and fingers is not None:
                q[1:] = fingers[t]
            b = betas[t] if side == "right" and betas is not None else np.zeros(10)
            arrays = {"pose_coeffs": q.reshape(1, 16, 4), "tsl": tsl[t].reshape(1, 3), "betas": b.reshape(1, 10)}
            for k, a in arrays.items():
                a = a.astype(np.float32)
                frame[f"{p}__{k}"] = Tensor(a.reshape(-1), 0, a.shape, tuple(np.array(a.strides) // 4)) if torch else a
        raw_mano[int(f)] = frame
        raw_smplx[int(f)] = {
            "world_tsl": Tensor(np.zeros(3, np.float32), 0, (1, 3), (3, 1)) if torch else np.zeros((1, 3))
        }
    obj_transf = {}
    for obj in (CUP, PLATE):
        R, p = _object(obj)
        mats = np.tile(np.eye(4), (n, 1, 1))
        mats[:, :3, :3], mats[:, :3, 3] = R, p
        obj_transf[obj] = {int(f): mats[t] for t, f in enumerate(IDS)}
    anno = {
        "cam_def": {"012345": "allocentric_top"}, "cam_selection": ["allocentric_top"],
        "frame_id_list": [int(f) for f in IDS[::4]], "cam_intr": {}, "cam_extr": {},
        "mocap_frame_id_list": [int(f) for f in IDS], "obj_list": [CUP, PLATE], "obj_transf": obj_transf,
        "raw_smplx": raw_smplx, "raw_mano": raw_mano,
    }  # fmt: skip
    anno_file = root / "anno_preview" / f"{TOKEN}.pkl"
    dump_torch(anno_file, anno)
    prog = root / "program" / "program_info" / f"{TOKEN}.json"
    prog.parent.mkdir(parents=True)
    prog.write_text(json.dumps(_segments() if segments is None else segments, indent=4))
    desc = root / "program" / "desc_info" / f"{TOKEN}.json"
    desc.parent.mkdir(parents=True)
    desc.write_text(json.dumps({k: {"seg_desc": f"segment {i}"} for i, k in enumerate(_segments())}))
    align = root / "object_raw" / "align_ds"
    for obj in (CUP, PLATE):
        (align / obj).mkdir(parents=True)
        _mesh(obj).export(align / obj / f"{obj}.obj")  # metres, as released
    names = {CUP: {"obj_id": CUP, "obj_name": "cup"}, PLATE: {"obj_id": PLATE, "obj_name": "plate"}}
    (root / "object_raw" / "obj_desc.json").write_text(json.dumps(names))
    return anno_file


@pytest.fixture(scope="module")
def tree(tmp_path_factory) -> Path:
    return _oakink2_tree(tmp_path_factory.mktemp("OakInk2"))


def _lift(obj: str, R0: np.ndarray, p0: np.ndarray, mirror: bool = False) -> float:
    """The z shift that puts the object's lowest point at TABLE (after the y -> z turn)."""
    v = _mesh(obj).vertices
    M = np.diag([-1.0, 1.0, 1.0]) if mirror else np.eye(3)
    return TABLE - float(((v @ R0.T + p0) @ (M @ W).T)[:, 2].min())


def _gaps(d, tips: np.ndarray) -> np.ndarray:
    """(T, k) distances (m) from the world points ``tips`` (T, k, 3) to the demo's object surface."""
    mesh = trimesh.load(d.object_mesh_path, process=False, force="mesh")
    R = np_quat_to_mat(d.object_quat)
    local = np.einsum("tji,tkj->tki", R, tips - d.object_pos[:, None])  # R^T (x - p)
    _, dist, _ = trimesh.proximity.closest_point(mesh, local.reshape(-1, 3))
    return dist.reshape(tips.shape[:2])


# ---- conversions --------------------------------------------------------------------------------


def test_one_hand_segment(tree: Path, mano_dir: Path) -> None:
    """Segment 0 (right hand, the cup): 120 -> 20 fps is every 6th mocap frame; metres kept, y up turned to z
    up and lifted; the keypoints as manotorch's quaternion MANO with the wrist at tsl; the finger tips on the
    cup's surface on the contact frames."""
    out = convert_oakink2(tree, mano_dir, tree.parent / "clips" / "pick.npz")
    d = load_demo(out)  # valid, mesh and all
    ids = 130 + 6 * np.arange(20)  # [130, 250) at every 6th frame
    assert d.fps == 20.0 and d.n_frames == 20 and d.left_joints is None
    assert d.object_name == "cup_O02_0038_00001" and d.object_mesh_path.name == "cup_O02_0038_00001.obj"
    R, p = _object(CUP, ids)
    lift = np.array([0, 0, _lift(CUP, R[0], p[0])])
    np.testing.assert_allclose(d.object_pos, p @ W.T + lift, atol=1e-6)
    np.testing.assert_allclose(np_quat_to_mat(d.object_quat), W @ R, atol=1e-6)
    assert d.support_height == pytest.approx(TABLE, abs=1e-6)
    v = np.asarray(trimesh.load(d.object_mesh_path, process=False, force="mesh").vertices)
    np.testing.assert_allclose(np.ptp(v, axis=0), BOX[CUP], atol=1e-9)  # metres, not rescaled
    _, _, kp, gap = _hand("right", ids)
    np.testing.assert_allclose(d.right_joints, kp @ W.T + lift, atol=1e-5)
    # contact: the four finger tips lie on the cup's surface when the synthetic data says so (gap 0), and
    # the synthetic gap above it before
    gaps = _gaps(d, d.right_joints[:, FINGER_TIPS])
    contact = gap == 0
    assert contact.sum() >= 10 and gap.max() > 0.02
    assert gaps[contact].max() < 2e-3, gaps[contact].max()
    np.testing.assert_allclose(gaps, np.repeat(gap[:, None], 4, axis=1), atol=1e-3)
    assert (
        f"OakInk2 {TOKEN} segment 0 (pick_up:00) 'segment 0' object {CUP} hands right mocap frames 130..244" in d.source
    )


def test_two_hand_segment_and_resampling(tree: Path, mano_dir: Path, capsys) -> None:
    """Segment 1 (both intervals): right and left hands over the enclosing range [140, 320); 120 -> 50 fps
    interpolates between mocap frames (step 2.4); the cup is the main object (a note names the other)."""
    d = load_demo(
        convert_oakink2(tree, mano_dir, tree.parent / "b" / "pour.npz", opts=OakInk2Options(segment=1, fps=50.0))
    )
    assert "involves objects O02@0038@00001, C12001; using O02@0038@00001" in capsys.readouterr().err
    s = 140 + 2.4 * np.arange(75)  # (320 - 1 - 140) / 2.4 + 1 = 75.6 -> 75 clip frames
    assert d.n_frames == 75 and d.fps == 50.0 and d.left_joints is not None
    R, p = _object(CUP, IDS)
    lift = np.array([0, 0, _lift(CUP, R[40], p[40])])  # mocap frame 140

    def at(x: np.ndarray) -> np.ndarray:  # values at the mocap frames IDS -> at the fractional frames s
        flat = x.reshape(len(IDS), -1)
        return np.stack([np.interp(s, IDS, c) for c in flat.T], axis=1).reshape(len(s), *x.shape[1:])

    np.testing.assert_allclose(d.object_pos, at(p) @ W.T + lift, atol=1e-6)
    for side, joints in (("right", d.right_joints), ("left", d.left_joints)):
        np.testing.assert_allclose(joints, at(_hand(side)[2]) @ W.T + lift, atol=1e-5)
    # slerp between neighbouring frames: on a frame, the frame's rotation
    on = np.flatnonzero(np.abs(s - np.round(s)) < 1e-9)
    np.testing.assert_allclose(np_quat_to_mat(d.object_quat[on]), W @ R[np.round(s[on]).astype(int) - 100], atol=1e-6)
    contact = np.interp(s, IDS, _hand("right")[3]) == 0
    assert contact.sum() > 30 and _gaps(d, d.right_joints[:, FINGER_TIPS])[contact].max() < 2e-3


def test_left_hand_alone_is_mirrored(tree: Path, mano_dir: Path, capsys) -> None:
    """Segment 2 (left hand only, by its name): written mirrored as a right-hand clip, mesh mirrored too; the
    mirrored finger tips still lie on the mirrored plate's surface."""
    d = load_demo(convert_oakink2(tree, mano_dir, tree.parent / "c" / "place.npz",
                                  opts=OakInk2Options(segment="place_onto:00", fps=0)))  # fmt: skip
    assert "the left hand alone is written mirrored" in capsys.readouterr().err
    ids = np.arange(200, 330)
    assert d.fps == 120.0 and d.n_frames == 130 and d.left_joints is None
    assert d.object_name == "plate_C12001_mirrored"
    R, p = _object(PLATE, ids)
    M = np.diag([-1.0, 1.0, 1.0])
    lift = np.array([0, 0, _lift(PLATE, R[0], p[0], mirror=True)])
    np.testing.assert_allclose(d.object_pos, p @ (M @ W).T + lift, atol=1e-6)
    _, _, kp, gap = _hand("left", ids)
    contact = gap == 0
    np.testing.assert_allclose(d.right_joints, kp @ (M @ W).T + lift, atol=1e-5)
    mesh = trimesh.load(d.object_mesh_path, process=False, force="mesh")
    assert mesh.is_watertight and mesh.volume > 0  # the faces' winding flipped with the mirror
    # the posed mesh is the mirror image of the posed plate (the plate is not mirror-symmetric)
    world = np.asarray(mesh.vertices) @ np_quat_to_mat(d.object_quat[0]).T + d.object_pos[0]
    want = (_mesh(PLATE).vertices @ R[0].T + p[0]) @ (M @ W).T + lift
    np.testing.assert_allclose(np.sort(world, axis=0), np.sort(want, axis=0), atol=1e-6)
    assert _gaps(d, d.right_joints[:, FINGER_TIPS])[contact].max() < 2e-3
    assert "hands left mirrored" in d.source


def test_keypoints_follow_mano_with_quaternions(tmp_path: Path, mano_dir: Path) -> None:
    """Finger quaternions (not normalised, as pytorch3d's conversion accepts) and per-frame shapes, numpy
    values: the keypoints are the repository's MANO pass on their rotations, wrist at tsl; --range, --frames,
    --hands, --object, --up z, --table-height."""
    rng = np.random.default_rng(5)
    aa = rng.normal(0, 0.2, (len(IDS), 15, 3))
    fingers = np.concatenate([np.cos(np.linalg.norm(aa, axis=-1, keepdims=True) / 2),
                              np.sin(np.linalg.norm(aa, axis=-1, keepdims=True) / 2) * aa
                              / np.linalg.norm(aa, axis=-1, keepdims=True)], axis=-1) * 1.7  # fmt: skip
    betas = rng.normal(0, 1.0, (len(IDS), 10))
    anno = _oakink2_tree(tmp_path / "OakInk2", torch=False, fingers=fingers, betas=betas)
    R, tsl, _, _ = _hand("right")
    m = mano.load_mano(mano_dir / "MANO_RIGHT.pkl")
    go = Rotation.from_matrix(R).as_rotvec()
    kp = mano.keypoints(m, go, aa.reshape(len(IDS), 45), np.zeros((len(IDS), 3)), betas=betas, flat_hand_mean=True)
    want = kp - kp[:, :1] + tsl[:, None]
    assert np.linalg.norm(kp[:, 0], axis=1).min() > 0.08  # the wrist is not at the origin: the centring matters
    opts = OakInk2Options(frame_range=(150, 200), frames=8, fps=30.0, hands="right", object_id=PLATE, up="z",
                          table_height=1.0, name="clip")  # fmt: skip
    d = load_demo(convert_oakink2(anno, mano_dir, tmp_path / "o" / "c.npz", opts=opts))
    src = 150 + 4 * np.arange(8) - 100
    assert d.n_frames == 8 and d.name == "clip" and d.object_name == "plate_C12001"
    Rp, pp = _object(PLATE)
    lift = np.array([0, 0, 1.0 - float((_mesh(PLATE).vertices @ Rp[50].T + pp[50])[:, 2].min())])
    np.testing.assert_allclose(d.right_joints, want[src] + lift, atol=1e-5)
    np.testing.assert_allclose(d.object_pos, pp[src] + lift, atol=1e-6)
    assert d.support_height == pytest.approx(1.0)


# ---- bad input ----------------------------------------------------------------------------------


def _rewrite(anno_file: Path, edit) -> None:
    data = read_anno(anno_file)
    edit(data)
    anno_file.write_bytes(pickle.dumps(data))


def test_oakink2_bad_inputs(tmp_path: Path, mano_dir: Path, capsys) -> None:
    def fails(anno: Path, match: str, **kw) -> None:
        with pytest.raises(InputError, match=match):
            convert_oakink2(anno, kw.pop("mano", mano_dir), tmp_path / "o" / "c.npz", opts=OakInk2Options(**kw))

    def tree(name: str, **kw) -> Path:
        return _oakink2_tree(tmp_path / name, torch=False, **kw)

    anno = tree("ok")
    root = anno.parents[1]
    fails(anno, r"option '--mano-dir'.*MANO_RIGHT\.pkl.*no such file", mano=tmp_path / "nowhere")
    with pytest.raises(InputError, match=r"nope.*an OakInk2 annotation file"):
        convert_oakink2(tmp_path / "nope", mano_dir, tmp_path / "o" / "c.npz")
    with pytest.raises(InputError, match=r"anno_preview/scene_01__A001\+\+seq__x\.pkl: expected OakInk2's annotation "
                       r"pickle.*no such file"):  # fmt: skip
        convert_oakink2("scene_01__A001/seq__x", mano_dir, tmp_path / "o" / "c.npz", oakink2_root=root)
    # unknown segments list the valid ones
    fails(anno, r"program_info/.*\.json: option '--segment': expected a segment index or name: 0 pick_up:00 "
          r"\(rh 130-250\); 1 pour:00 \(rh\+lh 140-320\); 2 place_onto:00 \(lh 200-330\), got 3", segment=3)  # fmt: skip
    fails(anno, r"'--segment'.*0 pick_up:00.*got 'pour:01'", segment="pour:01")
    with pytest.raises(QuasisimError, match="either --segment or --range"):
        convert_oakink2(anno, mano_dir, tmp_path / "o" / "c.npz", opts=OakInk2Options(segment=1, frame_range=(1, 9)))
    fails(anno, r"option '--object': expected an object with poses in obj_transf: O02@0038@00001, C12001, got X9",
          object_id="X9")  # fmt: skip
    # the program file: missing, a malformed key
    prog = root / "program" / "program_info" / f"{TOKEN}.json"
    prog.rename(prog.with_suffix(".bak"))
    fails(anno, r"program_info/.*\.json: expected OakInk2's primitive-task segments.*no such file")
    prog.write_text(json.dumps({"((5, 3), None)": {"primitive": "x"}}))
    fails(anno, r"field '\(\(5, 3\), None\)': expected a key '\(lh_interval, rh_interval\)'")
    prog.with_suffix(".bak").rename(prog)
    # annotation fields: missing, wrong shape, a missing frame, a zero quaternion, a non-rigid pose
    _rewrite(anno, lambda a: a.pop("raw_mano"))
    fails(
        anno, rf"{re.escape(TOKEN)}\.pkl: field 'raw_mano': expected an entry of this name, got missing \(keys: cam_def"
    )
    anno = tree("shape")
    _rewrite(anno, lambda a: a["raw_mano"][136].update(rh__pose_coeffs=np.zeros((1, 16, 3))))
    fails(anno, r"field 'raw_mano\[136\]\.rh__pose_coeffs': expected an array of shape \(1, 16, 4\), got \(1, 16, 3\)")
    _rewrite(anno, lambda a: a["raw_mano"][136].pop("rh__pose_coeffs"))
    fails(anno, r"field 'raw_mano\[136\]\.rh__pose_coeffs': expected an entry of this name, got missing \(keys: lh__")
    _rewrite(anno, lambda a: a["raw_mano"][136].update(rh__pose_coeffs=np.zeros((1, 16, 4))))
    fails(anno, r"field 'raw_mano\[136\]\.rh__pose_coeffs': expected quaternions w, x, y, z \(non-zero\)")
    _rewrite(anno, lambda a: a["raw_mano"].pop(136))
    fails(anno, r"field 'raw_mano\[136\]': expected an entry for mocap frame 136, got none \(frames 100\.\.339\)")
    anno = tree("pose")
    bad = np.eye(4)
    bad[:3, :3] *= 2.0
    _rewrite(anno, lambda a: a["obj_transf"][CUP].update({136: bad}))
    fails(anno, r"field 'obj_transf\[O02@0038@00001\]\[136\]': expected 4x4 rigid transforms")
    _rewrite(anno, lambda a: a["obj_transf"][CUP].update({136: np.eye(3)}))
    fails(anno, r"field 'obj_transf\[O02@0038@00001\]\[136\]': expected an array of shape \(4, 4\), got \(3, 3\)")
    _rewrite(anno, lambda a: a["obj_transf"][CUP].pop(136))
    fails(anno, r"field 'obj_transf\[O02@0038@00001\]\[136\]': expected an entry for mocap frame 136")
    # the mesh: missing, two candidates
    anno = tree("mesh")
    folder = anno.parents[1] / "object_raw" / "align_ds" / CUP
    (folder / f"{CUP}.obj").rename(folder.parent / "x.obj")
    fails(anno, r"align_ds/O02@0038@00001: option '--object-dir': expected one mesh file \(\.obj or \.ply\), got none")
    trimesh.creation.box(BOX[CUP]).export(folder / "a.obj")
    trimesh.creation.box(BOX[CUP]).export(folder / "b.ply")
    fails(anno, r"option '--object-dir': expected one mesh file \(\.obj or \.ply\), got a\.obj, b\.ply")
    with pytest.raises(InputError, match=r"nowhere/O02@0038@00001: option '--object-dir': expected the object's mesh"):
        convert_oakink2(anno, mano_dir, tmp_path / "o" / "c.npz", object_dir=tmp_path / "nowhere")
    # a range too short for two clip frames
    fails(anno, r"option '--frames': expected at least 2 clip frames", frame_range=(150, 153))
    assert not (tmp_path / "o").exists()  # nothing written by any failure


def test_convert_oakink2_command(tree: Path, mano_dir: Path) -> None:
    from click.testing import CliRunner

    from quasisim.cli import main

    out = tree.parent / "cli" / "pour.npz"
    args = ["convert", "oakink2", str(tree), "--mano-dir", str(mano_dir), "--out", str(out), "--segment", "1"]
    r = CliRunner().invoke(main, [*args, "--frames", "30"])
    assert r.exit_code == 0, r.output
    d = load_demo(out)
    assert d.n_frames == 30 and d.left_joints is not None and r.stdout.strip().endswith("pour.npz")
    r = CliRunner().invoke(main, ["convert", "oakink2", str(tree), "--list-segments"])
    assert r.exit_code == 0, r.output
    assert r.stdout.splitlines()[1].startswith("1 pour:00 (rh+lh 140-320) bh_main objects: O02@0038@00001, C12001")
    r = CliRunner().invoke(main, [*args[:-1], "9"])
    assert r.exit_code == 2 and "error:" in r.output and "2 place_onto:00 (lh 200-330)" in r.output
    r = CliRunner().invoke(main, [*args[:-2], "--range", "150-200"])
    assert r.exit_code == 2 and "BEGIN:END" in r.output
    r = CliRunner().invoke(main, [*args[:-2], "--range", "150:200"])
    assert r.exit_code == 0, r.output
