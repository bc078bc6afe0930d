"""The TACO converter (``quasisim.data.convert_taco``) on small synthetic files in TACO's released layout
(Hand_Poses/<triplet>/<sequence>/right_hand*.pkl with pickled torch tensors, Object_Poses/.../tool_<id>.npy,
Object_Models/<id>_cm.obj) and a synthetic MANO model; neither TACO, MANO nor torch is needed: the torch
tensors are pickled here byte for byte as torch pickles them (torch/_tensor.py, torch/storage.py,
torch/serialization.py: ``_rebuild_tensor_v2`` over a storage saved by ``torch.save`` in the legacy format)."""

from __future__ import annotations

import contextlib
import io
import pickle
import re
import types
from collections import OrderedDict
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import trimesh

from helpers import swapped_modules
from quasisim.data import mano
from quasisim.data.convert_taco import TacoOptions, convert_taco, load_pickle
from quasisim.data.demo import load_demo
from quasisim.errors import InputError
from quasisim.rotations import np_quat_to_mat
from test_convert_raw import REST, TIPS, _model_arrays, write_model

TRIPLET, SEQ, TOOL = "(stir, spoon, bowl)", "20231105_019", "035"
N, ONSET, TABLE, BOX = 120, 60, 0.70, 0.06  # frames (30 fps), the tool's first moving frame, m, m
WRIST = np.array([0.09, 0.006, 0.005])  # the rest wrist joint away from the origin, as in the real MANO
GO = np.array([0.1, -0.2, 0.3])  # global orientation (axis-angle)
ORDER = list(mano.MANO_TO_MEDIAPIPE)

# ---- torch's pickles, without torch ---------------------------------------------------------------


def _stub(module: str, name: str, obj: object) -> object:
    obj.__module__, obj.__qualname__, obj.__name__ = module, name, name
    return obj


class _Torch:
    """Stand-ins for the torch names a pickled tensor refers to (pickle looks them up by module and name)."""

    FloatStorage = _stub("torch", "FloatStorage", type("FloatStorage", (), {}))
    DoubleStorage = _stub("torch", "DoubleStorage", type("DoubleStorage", (), {}))
    device = _stub("torch", "device", type("device", (), {}))
    _load_from_bytes = _stub("torch.storage", "_load_from_bytes", lambda b: None)
    _rebuild_tensor_v2 = _stub("torch._utils", "_rebuild_tensor_v2", lambda *a: None)


@contextlib.contextmanager
def _torch_modules() -> Iterator[None]:
    mods = {name: types.ModuleType(name) for name in ("torch", "torch.storage", "torch._utils")}
    mods["torch"].FloatStorage, mods["torch"].DoubleStorage = _Torch.FloatStorage, _Torch.DoubleStorage
    mods["torch"].device = _Torch.device
    mods["torch.storage"]._load_from_bytes = _Torch._load_from_bytes
    mods["torch._utils"]._rebuild_tensor_v2 = _Torch._rebuild_tensor_v2
    with swapped_modules(mods):
        yield


def _legacy_save(data: np.ndarray, location: str = "cuda:0") -> bytes:
    """``torch.save(storage, f, _use_new_zipfile_serialization=False)`` of a 1-D float storage: magic number,
    protocol, system info, the persistent id, the storage keys, then int64 numel and the raw data."""
    kind = {np.float32: _Torch.FloatStorage, np.float64: _Torch.DoubleStorage}[data.dtype.type]
    f = io.BytesIO()
    info = {"protocol_version": 1001, "little_endian": True, "type_sizes": {"short": 2, "int": 4, "long": 8}}
    for x in (0x1950A86A20F9469CFC6C, 1001, info):
        pickle.dump(x, f, protocol=2)
    marker = object()

    class Legacy(pickle.Pickler):
        def persistent_id(self, obj: object) -> object:
            return ("storage", kind, "94370384", location, len(data), None) if obj is marker else None

    Legacy(f, protocol=2).dump(marker)
    pickle.dump(["94370384"], f, protocol=2)
    f.write(np.int64(len(data)).tobytes() + data.astype(data.dtype.newbyteorder("<")).tobytes())
    return f.getvalue()


class Storage:
    """Pickles like torch's TypedStorage: ``(torch.storage._load_from_bytes, (legacy torch.save bytes,))``,
    saved from a GPU (location ``cuda:0``)."""

    def __init__(self, data: np.ndarray) -> None:
        self.data = data

    def __reduce__(self) -> tuple:
        return _Torch._load_from_bytes, (_legacy_save(self.data),)


class Truncated(Storage):
    """A storage whose data ends 4 numbers early."""

    def __reduce__(self) -> tuple:
        return _Torch._load_from_bytes, (_legacy_save(self.data)[:-16],)


class Tensor:
    """Pickles like a torch tensor: ``_rebuild_tensor_v2(storage, offset, size, stride, requires_grad,
    OrderedDict())``, the whole storage with each view (TACO's frames are rows of one (T, 48) buffer)."""

    def __init__(self, buffer: np.ndarray, offset: int, size: tuple, stride: tuple, kind: type = Storage) -> None:
        self.args = (kind(buffer), offset, size, stride, True, OrderedDict())

    def __reduce_ex__(self, protocol: int) -> tuple:
        return _Torch._rebuild_tensor_v2, self.args


def _rows(a: np.ndarray) -> list[Tensor]:
    """Each row of ``a`` (T, n) as a tensor viewing the flat storage of all of ``a``."""
    flat = np.ascontiguousarray(a).reshape(-1)
    return [Tensor(flat, t * a.shape[1], (a.shape[1],), (1,)) for t in range(len(a))]


def dump_torch(path: Path, obj: object) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with _torch_modules():
        path.write_bytes(pickle.dumps(obj, protocol=4))


def test_torch_tensors_are_read_without_torch(tmp_path: Path) -> None:
    a = np.arange(24, dtype=np.float32).reshape(4, 6) / 7
    b = np.linspace(0, 1, 12)  # float64
    f = tmp_path / "t.pkl"
    dump_torch(f, {"rows": _rows(a), "col": Tensor(a.reshape(-1), 2, (4,), (6,)), "b": Tensor(b, 1, (2, 3), (1, 2))})
    got = load_pickle(f)
    for t in range(4):
        np.testing.assert_array_equal(got["rows"][t], a[t])
    np.testing.assert_array_equal(got["col"], a[:, 2])
    np.testing.assert_array_equal(got["b"], np.lib.stride_tricks.as_strided(b[1:], (2, 3), (8, 16)))
    assert got["b"].dtype == np.float64 and got["rows"][0].dtype == np.float32
    # a view past its storage, a truncated storage and any other torch class are refused, naming the file
    dump_torch(f, {"x": Tensor(a.reshape(-1), 20, (6,), (1,))})
    with pytest.raises(InputError, match=r"t\.pkl.*numpy arrays or torch tensors.*beyond its storage"):
        load_pickle(f)
    dump_torch(f, {"x": Tensor(a.reshape(-1), 0, (6,), (1,), Truncated)})
    with pytest.raises(InputError, match=r"t\.pkl.*truncated torch storage"):
        load_pickle(f)
    dump_torch(f, {"d": _Torch.device})
    with pytest.raises(InputError, match=r"t\.pkl.*refusing to load the class torch\.device"):
        load_pickle(f)


# ---- a TACO sequence ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def mano_dir(tmp_path_factory) -> Path:
    """The synthetic MANO model with its rest wrist at :data:`WRIST` (TACO centres the hand there)."""
    arrays = _model_arrays()
    arrays["v_template"] = arrays["v_template"] + WRIST
    d = tmp_path_factory.mktemp("mano")
    write_model(d / "MANO_RIGHT.pkl", arrays)
    return d


def _tool_poses() -> np.ndarray:
    """(N, 4, 4): the box rests (turned 0.4 rad about z) until frame ONSET, then slides along x, rises and
    turns."""
    k = np.clip(np.arange(N) - (ONSET - 1), 0, None)
    mats = np.tile(np.eye(4), (N, 1, 1))
    mats[:, :3, :3] = mano.rodrigues(np.stack([np.zeros(N), np.zeros(N), 0.4 + 0.01 * k], axis=1))
    mats[:, :3, 3] = np.array([0.3, 0.2, TABLE + BOX / 2]) + k[:, None] * np.array([0.01, 0.0, 0.005])
    return mats


def _hand(mats: np.ndarray, away: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """hand_pose (N, 48) (GO, flat fingers) and hand_trans (N, 3): the index tip 5 mm off the box's -y face
    (plus ``away`` along -y) from the onset on, reaching there from 12 cm away before it."""
    index_tip = mano.rodrigues(GO) @ TIPS[1]  # the wrist (REST[0] = 0) at hand_trans
    target = mats[:, :3, 3] + np.einsum("tij,j->ti", mats[:, :3, :3], [0.0, -BOX / 2 - 0.005 - away, 0.0])
    target[:ONSET] = target[ONSET] + np.outer(ONSET - np.arange(ONSET), [0.0, -0.002, 0.0])
    return np.tile(np.concatenate([GO, np.zeros(45)]), (N, 1)), target - index_tip


def _taco_tree(
    root: Path, pose: np.ndarray | None = None, trans: np.ndarray | None = None, beta: np.ndarray | None = None,
    torch: bool = True, mats: np.ndarray | None = None,
) -> Path:  # fmt: skip
    """TACO's layout under ``root``: the hand files (torch tensors, or numpy arrays), the tool's and the
    target's poses and the tool mesh (cm). Frame keys '00001'... are written in shuffled order."""
    mats = _tool_poses() if mats is None else mats
    if pose is None:
        pose, trans = _hand(mats)
    beta = np.zeros(10, dtype=np.float32) if beta is None else beta
    hands = root / "Hand_Poses" / TRIPLET / SEQ
    p, t = (_rows(pose.astype(np.float32)), _rows(trans.astype(np.float32))) if torch else (pose, trans)
    frames = {f"{i + 1:05d}": {"hand_pose": p[i], "hand_trans": t[i]} for i in np.random.default_rng(0).permutation(N)}
    shape = {"hand_shape": Tensor(beta.reshape(-1), 0, (1, 10), (10, 1)) if torch else beta.reshape(1, 10)}
    dump_torch(hands / "right_hand.pkl", frames)
    dump_torch(hands / "right_hand_shape.pkl", shape)
    objects = root / "Object_Poses" / TRIPLET / SEQ
    objects.mkdir(parents=True)
    np.save(objects / f"tool_{TOOL}.npy", mats)
    np.save(objects / "target_022.npy", np.tile(np.eye(4), (len(mats), 1, 1)))
    (root / "Object_Models").mkdir()
    trimesh.creation.box([BOX * 100] * 3).export(root / "Object_Models" / f"{TOOL}_cm.obj")  # centimetres
    return hands


def test_taco_to_clip(tmp_path: Path, mano_dir: Path) -> None:
    seq = _taco_tree(tmp_path / "TACO")
    out = convert_taco(seq, mano_dir, tmp_path / "clips" / "spoon.npz")
    d = load_demo(out)  # valid, mesh and all
    # the automatic segment: 1.5 s (45 frames) before the onset, at 30 fps, to the end (< 150 frames)
    start = ONSET - 45
    assert d.fps == 30.0 and d.n_frames == N - start
    assert d.object_name == "spoon_035" and d.object_mesh_path.name == "spoon_035.obj"
    mats = _tool_poses()[start:]
    np.testing.assert_allclose(d.object_pos, mats[:, :3, 3], atol=1e-6)  # metres, as in the file
    np.testing.assert_allclose(np_quat_to_mat(d.object_quat), mats[:, :3, :3], atol=1e-6)
    v = np.asarray(trimesh.load(d.object_mesh_path, process=False, force="mesh").vertices)
    np.testing.assert_allclose(np.ptp(v, axis=0), [BOX] * 3, atol=1e-9)  # cm -> m
    assert d.support_height == pytest.approx(TABLE, abs=1e-6)  # the box rests on the table at clip frame 0
    # MANO with flat_hand_mean (hands_mean not added), the wrist at hand_trans, turned by GO about it
    _, trans = _hand(_tool_poses())
    rest = np.concatenate([REST, TIPS])[ORDER]
    np.testing.assert_allclose(d.right_joints, rest @ mano.rodrigues(GO).T + trans[start:, None], atol=1e-6)
    assert "TACO (stir, spoon, bowl)/20231105_019 tool 035 source frames 15..119" in d.source


def test_keypoints_follow_mano_and_options(tmp_path: Path, mano_dir: Path, capsys) -> None:
    """Numpy values (not tensors), a finger pose and a hand shape: the keypoints are the repository's MANO
    forward pass on them, wrist moved to hand_trans; --fps, --start, --frames and --up."""
    rng = np.random.default_rng(3)
    pose, trans = _hand(_tool_poses())
    pose[:, 3:] = rng.normal(0, 0.15, 45) + np.linspace(0, 0.2, N)[:, None]  # fingers closing over time
    beta = rng.normal(0, 1.0, 10)
    seq = _taco_tree(tmp_path / "TACO", pose, trans, beta, torch=False)
    m = mano.load_mano(mano_dir / "MANO_RIGHT.pkl")
    kp = mano.keypoints(m, pose[:, :3], pose[:, 3:], np.zeros((N, 3)), betas=beta, flat_hand_mean=True)
    want = kp - kp[:, :1] + trans[:, None]
    assert np.linalg.norm(kp[:, 0], axis=1).min() > 0.08  # the wrist is not at the origin: the centring matters
    opts = TacoOptions(fps=15.0, start=10, frames=20, name="clip")
    d = load_demo(convert_taco(seq, mano_dir, tmp_path / "a" / "c.npz", opts=opts))
    src = 10 + 2 * np.arange(20)  # 30 -> 15 fps: every other source frame
    assert d.n_frames == 20 and d.fps == 15.0 and d.name == "clip"
    np.testing.assert_allclose(d.right_joints, want[src], atol=1e-5)
    np.testing.assert_allclose(d.object_pos, _tool_poses()[src, :3, 3], atol=1e-6)
    assert capsys.readouterr().err == ""
    # y up: the clip is turned so that y becomes z; a --start after the onset is warned about
    opts = TacoOptions(start=70, frames=10, up="y")
    d = load_demo(convert_taco(seq, mano_dir, tmp_path / "b" / "c.npz", tmp_path / "TACO", opts=opts))
    up = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    np.testing.assert_allclose(d.object_pos, _tool_poses()[70:80, :3, 3] @ up.T, atol=1e-6)
    np.testing.assert_allclose(d.right_joints, want[70:80] @ up.T, atol=1e-5)
    assert "--start 70 is at or after the tool's motion onset (source frame 60)" in capsys.readouterr().err


def test_taco_bad_inputs(tmp_path: Path, mano_dir: Path, capsys) -> None:
    def fails(root: Path, match: str, **kw) -> None:
        with pytest.raises(InputError, match=match):
            convert_taco(root / "Hand_Poses" / TRIPLET / SEQ, kw.pop("mano", mano_dir), tmp_path / "o" / "c.npz", **kw)

    def tree(name: str, **kw) -> Path:
        _taco_tree(tmp_path / name, **kw)
        return tmp_path / name

    root = tree("ok")
    hands, objects = root / "Hand_Poses" / TRIPLET / SEQ, root / "Object_Poses" / TRIPLET / SEQ
    fails(root, r"option '--mano-dir'.*MANO_RIGHT\.pkl.*no such file", mano=tmp_path / "nowhere")
    with pytest.raises(InputError, match=r"nope.*a TACO sequence folder"):
        convert_taco(tmp_path / "nope", mano_dir, tmp_path / "o" / "c.npz")
    # a hand frame of the wrong width, named by its key
    frames = load_pickle(hands / "right_hand.pkl")
    frames["00003"]["hand_pose"] = frames["00003"]["hand_pose"][:47]
    (hands / "right_hand.pkl").write_bytes(pickle.dumps(frames))
    fails(root, r"right_hand\.pkl: field '00003\.hand_pose': expected an array of shape \(48\), got \(47,\)")
    del frames["00003"]["hand_pose"]
    (hands / "right_hand.pkl").write_bytes(pickle.dumps(frames))
    fails(root, r"right_hand\.pkl: field '00003\.hand_pose': expected an entry of this name, got missing")
    (hands / "right_hand.pkl").write_bytes(pickle.dumps([1, 2, 3]))
    fails(root, r"right_hand\.pkl: expected TACO's right-hand MANO parameters.*got list")
    (hands / "right_hand.pkl").unlink()
    fails(root, r"right_hand\.pkl: expected TACO's right-hand MANO parameters.*no such file")
    # tool poses: shape, rigidity, frame count; one tool file; the mesh
    root = tree("pose")
    objects = root / "Object_Poses" / TRIPLET / SEQ
    np.save(objects / f"tool_{TOOL}.npy", _tool_poses()[:, :3])
    fails(root, r"tool_035\.npy: field 'pose': expected an array of shape \(T, 4, 4\), got \(120, 3, 4\)")
    bad = _tool_poses()
    bad[7, :3, :3] *= 2.0
    np.save(objects / f"tool_{TOOL}.npy", bad)
    fails(root, r"tool_035\.npy: field 'pose': expected 4x4 rigid transforms.*at frame 7")
    np.save(objects / f"tool_{TOOL}.npy", _tool_poses()[:100])
    fails(root, r"tool_035\.npy: field 'pose': expected 120 frames \(as right_hand\.pkl\), got 100")
    np.save(objects / "tool_036.npy", _tool_poses())
    fails(root, r"Object_Poses/\(stir, spoon, bowl\)/20231105_019: expected one tool pose file.*tool_035.npy, tool_036")
    (objects / "tool_036.npy").unlink()
    (objects / f"tool_{TOOL}.npy").unlink()
    fails(root, r"expected one tool pose file tool_<id>\.npy, got none")
    root = tree("mesh")
    (root / "Object_Models" / f"{TOOL}_cm.obj").unlink()
    fails(root, r"Object_Models/035_cm\.obj: option '--object-models': expected an existing mesh file")
    # a tool that never moves: no automatic segment (a given --start converts it)
    still = np.tile(_tool_poses()[0], (N, 1, 1))
    root = tree("still", mats=still)
    fails(root, r"tool_035\.npy: field 'pose': expected a tool that moves .*give --start.*at rest over all 120")
    out = convert_taco(
        root / "Hand_Poses" / TRIPLET / SEQ, mano_dir, tmp_path / "s" / "c.npz", opts=TacoOptions(start=0)
    )
    assert load_demo(out).n_frames == 120
    # no shape file: MANO's mean shape, as TACO's loader, with a warning
    capsys.readouterr()
    (root / "Hand_Poses" / TRIPLET / SEQ / "right_hand_shape.pkl").unlink()
    convert_taco(root / "Object_Poses" / TRIPLET / SEQ, mano_dir, tmp_path / "s2" / "c.npz", opts=TacoOptions(start=0))
    assert "right_hand_shape.pkl: no such file; using MANO's mean hand shape" in capsys.readouterr().err


def test_tool_not_in_the_right_hand_is_warned_about(tmp_path: Path, mano_dir: Path, capsys) -> None:
    pose, trans = _hand(_tool_poses(), away=0.1)  # the right hand 10 cm from the tool as it starts moving
    seq = _taco_tree(tmp_path / "TACO", pose, trans)
    convert_taco(seq, mano_dir, tmp_path / "c.npz", opts=TacoOptions(frames=30))
    err = capsys.readouterr().err
    gap = re.search(
        r"the right hand's closest fingertip is ([\d.]+) cm from the tool when it starts moving \(source frame 60\)",
        err,
    )
    assert gap and 8.0 < float(gap[1]) < 11.0, err


def test_convert_taco_command(tmp_path: Path, mano_dir: Path) -> None:
    from click.testing import CliRunner

    from quasisim.cli import main

    seq = _taco_tree(tmp_path / "TACO")
    out = tmp_path / "clips" / "spoon.npz"
    args = ["convert", "taco", str(seq), "--mano-dir", str(mano_dir), "--out", str(out), "--frames", "40"]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0, r.output
    assert load_demo(out).n_frames == 40 and r.output.strip().endswith("spoon.npz")
    r = CliRunner().invoke(main, [*args[:-4], "--out", str(tmp_path / "o.npz"), "--start", "500"])
    assert r.exit_code == 2 and "error" in r.output.lower()
