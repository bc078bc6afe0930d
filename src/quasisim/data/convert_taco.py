"""TACO sequences, as released, -> ``quasisim-demo-v1`` clips (``quasisim convert taco``).

TACO (Liu et al., CVPR 2024, https://taco2024.github.io, https://github.com/leolyliu/TACO-Instructions):
bimanual tool use, ``(action, tool, target)`` triplets, 30 fps. The paper this project follows takes, per
sequence, the **right hand and its tool** (the tool object of the triplet; "one sequence for each
right-hand tool object") and "the first approach-action clip with the maximal length set to 150 frames".

Layout (TACO-Instructions README, "Data Organization"; the file contents as its ``dataset_utils`` read
them)::

    <root>/Hand_Poses/<triplet>/<sequence>/right_hand.pkl        {frame: {"hand_pose": (48,), "hand_trans": (3,)}}
                                           right_hand_shape.pkl  {"hand_shape": (10,)}
    <root>/Object_Poses/<triplet>/<sequence>/tool_<id>.npy       (T, 4, 4) tool poses
                                             target_<id>.npy     (T, 4, 4) target poses (not used)
    <root>/Object_Models/<id>_cm.obj                             meshes in centimetres

e.g. ``Hand_Poses/(stir, spoon, bowl)/20231105_019``. The object models folder is ``Object_Models`` in the
README and ``object_models_released`` in TACO's own scripts; either is found under ``<root>``, or pass it.

Conventions (from TACO's ``dataset_utils/visualization.py`` and ``hand_pose_loader.py``):

* **Hand**: ``right_hand.pkl`` is a pickled dict, one entry per frame in the order of its sorted keys
  (``"00001"``, ``"00002"``, ...), each ``hand_pose`` = 3 global-orientation + 45 finger axis-angle numbers
  (no PCA) and ``hand_trans`` (m). The values are pickled **torch tensors** (read here without torch,
  see :class:`TorchTensorUnpickler`; numpy arrays are accepted too). TACO poses the hand with manopth's
  ``ManoLayer(use_pca=False, center_idx=0)`` and its default ``flat_hand_mean=True`` (the 45 numbers are
  the finger pose itself, not offsets from MANO's mean hand), the shape ``hand_shape`` (zeros when
  ``right_hand_shape.pkl`` is missing, as TACO's ``read_hand_shape``), and ``center_idx=0``: the posed hand
  is moved so that its **wrist joint is at** ``hand_trans``. Keypoints here: the repository's MANO forward
  pass (:mod:`quasisim.data.mano`: 16 joints + smplx's 5 fingertip vertices, MediaPipe order), shifted the
  same way. (manopth's own tips are vertices 745, 317, 444, 556, 673; the GRAB and ARCTIC clips use
  smplx's, and so does this converter, so that every clip has the same keypoints.)
* **Tool**: ``tool_<id>.npy`` maps the mesh's points into the world, ``x_world = R x + t`` with ``t`` in
  metres; the mesh ``<id>_cm.obj`` is in centimetres (TACO's script scales it by 0.01), converted here to
  metres. The target object is not used (a clip has one object).
* **World**: metres, **z up** (not stated by TACO; inferred from its visualization script: the fixed
  camera's ``CAMERA_TO_WORLD``, an OpenCV camera (``pyt3d_wrapper.py`` negates the focal lengths for
  PyTorch3D), has its image-down axis along world -z and stands 1.09 m above the origin looking 17 deg
  down at a workspace about 0.66 m high; its orbit cameras use ``up=(0, 0, 1)``). ``up`` turns another
  axis to +z.
* **Rate**: 30 fps (TACO's videos and annotations; not in the pose files), ``source_fps``.

Segment ("the first approach-and-act segment, up to 150 frames"): clip frame ``k`` is source frame
``start + k * source_fps / fps`` (as GRAB/ARCTIC, :func:`quasisim.data.convert_raw.timeline`), at most
``frames`` (150) clip frames, at the source rate unless ``fps`` is given. ``start`` (source frame) is
automatic unless given: the tool's **motion onset** ``n`` is the first frame at which it is 5 mm or 5 deg
away from its pose at frame 0 (the rule of the bundled GRAB clips), and the clip starts
``APPROACH_S`` = 1.5 s before it, ``start = max(0, n - round(1.5 * source_fps))``: the end of the reach,
the grasp and lift, and the tool's use, for at most 5 s at 30 fps. The tool then rests on the table at clip
frame 0 (``support_height`` is its lowest point there). A tool that never moves is refused in automatic
mode (give ``start``). Warnings (stderr; the clip is written): the right hand's closest fingertip is more
than 3 cm from the tool's surface at the onset (the tool is then probably in the left hand; the paper uses
right-hand tools), and a given ``start`` at or after the onset (the tool may not rest there).
"""

from __future__ import annotations

import io
import math
import pickle
import sys
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from quasisim.data import mano
from quasisim.data.convert import UP_AXES, rigid_transforms
from quasisim.data.convert_raw import RawOptions, _array, _demo, _load_mesh, _write_mesh, save_clip, timeline
from quasisim.errors import InputError, choice_error, shaped_array

TACO_FPS = 30.0  # TACO's rate (videos and annotations); the pose files do not state it
MAX_FRAMES = 150  # the paper's maximal clip length
ONSET_M, ONSET_DEG = 0.005, 5.0  # the tool's motion onset: this far from its pose at frame 0
APPROACH_S = 1.5  # s of the approach kept before the onset (the bundled GRAB clips' onset lands at 1.5 s)
HOLD_WARN_M = 0.03  # the right hand's closest fingertip this far from the tool at the onset: a warning
MODEL_DIRS = ("Object_Models", "object_models_released")  # README's name, TACO's scripts' name
FINGERTIPS = (4, 8, 12, 16, 20)  # MediaPipe order


@dataclass(frozen=True)
class TacoOptions:
    """``fps``: clip rate (None: the source rate, 30); ``start``: source frame of clip frame 0 (None:
    automatic, see the module docstring); ``frames``: at most this many clip frames (None: to the end);
    ``name``: clip name (None: OUT's stem); ``source_fps``: TACO's rate; ``up``: the world's up axis
    (``z``, ``y``, ``-y``, ``x``, ``-x``, ``-z``; turned to +z)."""

    fps: float | None = None
    start: int | None = None
    frames: int | None = MAX_FRAMES
    name: str | None = None
    source_fps: float = TACO_FPS
    up: str = "z"


# ---- pickled torch tensors, without torch ---------------------------------------------------------

_TORCH_MAGIC = 0x1950A86A20F9469CFC6C  # torch.serialization.MAGIC_NUMBER (the legacy format)
_STORAGES = {  # torch storage class -> numpy dtype (little endian)
    "FloatStorage": "<f4", "DoubleStorage": "<f8", "HalfStorage": "<f2", "BFloat16Storage": "<u2",
    "LongStorage": "<i8", "IntStorage": "<i4", "ShortStorage": "<i2", "CharStorage": "i1", "ByteStorage": "u1",
    "BoolStorage": "?",
}  # fmt: skip


class _StorageType(str):
    """The name of a torch storage class, standing in for the class inside a storage's header."""


class _HeaderUnpickler(pickle.Unpickler):
    """The plain pickles of a legacy ``torch.save`` header: numbers, strings, containers; storage classes
    become their names (:class:`_StorageType`), a persistent id is returned as it is; nothing else."""

    def find_class(self, module: str, name: str) -> Any:
        if module == "torch" and name in _STORAGES:
            return _StorageType(name)
        raise pickle.UnpicklingError(f"refusing to load the class {module}.{name} in a torch storage")

    def persistent_load(self, pid: Any) -> Any:
        return pid


def _load_storage(b: bytes) -> np.ndarray:
    """A torch storage as ``torch.storage._load_from_bytes`` gets it (``torch.save`` in the legacy format, as
    a storage's ``__reduce__`` writes it: magic number, protocol, system info, the storage's persistent id
    ``('storage', <Type>Storage, key, location, numel, view)``, the list of keys, then ``int64 numel`` and
    the raw little-endian data) as a 1-D numpy array; wherever it was saved from (``cuda:0`` or ``cpu``)."""
    f = io.BytesIO(b)
    try:
        magic, _, info, pid, keys = (_HeaderUnpickler(f).load() for _ in range(5))
    except (EOFError, ValueError, TypeError) as e:
        raise pickle.UnpicklingError(f"an unreadable torch storage ({type(e).__name__})") from None
    if magic != _TORCH_MAGIC:
        raise pickle.UnpicklingError("a torch storage not in torch.save's legacy format")
    if not isinstance(info, dict) or not info.get("little_endian", False):
        raise pickle.UnpicklingError("a big-endian torch storage")
    ok = isinstance(pid, tuple) and len(pid) >= 5 and pid[0] == "storage" and isinstance(pid[1], _StorageType)
    if not ok or keys != [pid[2]] or (len(pid) > 5 and pid[5] is not None):
        raise pickle.UnpicklingError(f"a torch storage of an unexpected layout ({str(pid)[:60]})")
    dtype = np.dtype(_STORAGES[pid[1]])
    head = f.read(8)
    n = int(np.frombuffer(head, "<i8")[0]) if len(head) == 8 else -1
    data = f.read(max(n, 0) * dtype.itemsize)
    if n != pid[4] or len(data) != n * dtype.itemsize:
        raise pickle.UnpicklingError(f"a truncated torch storage ({len(data)} bytes for {pid[4]} numbers)")
    a = np.frombuffer(data, dtype)
    if pid[1] == "BFloat16Storage":  # the upper half of a float32
        return (a.astype(np.uint32) << 16).view(np.float32)
    return a.astype(dtype.newbyteorder("="))


def _rebuild_tensor(storage: Any, offset: Any, size: Any, stride: Any, *_: Any) -> np.ndarray:
    """``torch._utils._rebuild_tensor_v2`` in numpy: the view ``size``/``stride`` (in elements) of a storage
    from ``offset``, copied; every index is checked to lie inside the storage."""
    if not isinstance(storage, np.ndarray):
        raise pickle.UnpicklingError(f"a tensor without a torch storage ({type(storage).__name__})")
    try:
        offset, size, stride = int(offset), tuple(int(s) for s in size), tuple(int(s) for s in stride)
    except (TypeError, ValueError):
        raise pickle.UnpicklingError("a tensor with a malformed size or stride") from None
    if len(size) != len(stride) or offset < 0 or min(size, default=0) < 0 or min(stride, default=0) < 0:
        raise pickle.UnpicklingError(f"a tensor with a malformed view (size {size}, stride {stride})")
    if 0 in size:
        return np.zeros(size, dtype=storage.dtype)
    last = offset + sum((n - 1) * s for n, s in zip(size, stride, strict=True))
    if last >= len(storage):
        raise pickle.UnpicklingError(f"a tensor view beyond its storage ({last} >= {len(storage)})")
    strides = tuple(s * storage.itemsize for s in stride)
    return np.lib.stride_tricks.as_strided(storage[offset:], shape=size, strides=strides).copy()


def _rebuild_parameter(data: Any, *_: Any) -> Any:
    """``torch._utils._rebuild_parameter(_with_state)``: the parameter's data."""
    return data


class TorchTensorUnpickler(mano.SafeUnpickler):
    """:class:`quasisim.data.mano.SafeUnpickler` that also reads torch tensors pickled with ``pickle.dump``
    (as TACO's hand files hold them), as numpy arrays, without importing torch: a tensor pickles as
    ``torch._utils._rebuild_tensor_v2(storage, offset, size, stride, requires_grad, hooks)`` with its
    storage as ``torch.storage._load_from_bytes(<legacy torch.save bytes>)``; both are replaced by numpy
    readers (:func:`_load_storage`, :func:`_rebuild_tensor`) and ``hooks`` is an empty
    ``collections.OrderedDict``. Any other torch class is refused, as any other class is."""

    ALLOWED = "numpy arrays or torch tensors"

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) == ("torch.storage", "_load_from_bytes"):
            return _load_storage
        if module == "torch._utils" and name in ("_rebuild_tensor", "_rebuild_tensor_v2"):
            return _rebuild_tensor
        if module == "torch._utils" and name in ("_rebuild_parameter", "_rebuild_parameter_with_state"):
            return _rebuild_parameter
        if (module, name) == ("collections", "OrderedDict"):
            return OrderedDict
        return super().find_class(module, name)


def load_pickle(path: Path) -> Any:
    """A TACO pickle (:class:`TorchTensorUnpickler`); :class:`InputError` naming ``path`` on any failure."""
    with open(path, "rb") as f:
        return mano.safe_load_pickle(f, path, TorchTensorUnpickler)


# ---- the files of one sequence --------------------------------------------------------------------


@dataclass(frozen=True)
class TacoSequence:
    """One sequence's files: ``root``/Hand_Poses/``triplet``/``name`` and ``root``/Object_Poses/..."""

    root: Path
    triplet: str
    name: str

    @property
    def hands(self) -> Path:
        return self.root / "Hand_Poses" / self.triplet / self.name

    @property
    def objects(self) -> Path:
        return self.root / "Object_Poses" / self.triplet / self.name

    @property
    def tool_word(self) -> str:
        """The triplet's tool, ``(action, tool, target)``; ``tool`` when the name is not such a triplet."""
        parts = [p.strip() for p in self.triplet.strip().removeprefix("(").removesuffix(")").split(",")]
        word = "_".join(parts[1].split()) if len(parts) == 3 else ""
        return word if word and word.replace("_", "").replace("-", "").isalnum() else "tool"


def find_sequence(seq: str | Path, taco_root: str | Path | None = None) -> TacoSequence:
    """``seq``: a sequence folder (``Hand_Poses/<triplet>/<sequence>`` or ``Object_Poses/...``, or a file in
    one), or, with ``taco_root``, ``<triplet>/<sequence>`` relative to it. ``taco_root`` defaults to three
    levels above the folder."""
    p = Path(seq)
    if p.is_file():
        p = p.parent
    if p.is_dir():
        root = Path(taco_root) if taco_root is not None else p.resolve().parents[2]
        return TacoSequence(root, p.resolve().parent.name, p.resolve().name)
    if taco_root is not None and len(p.parts) >= 2:
        return TacoSequence(Path(taco_root), p.parts[-2], p.parts[-1])
    raise InputError(
        p, None, "a TACO sequence folder (Hand_Poses/<triplet>/<sequence>, e.g. 'Hand_Poses/(stir, spoon, bowl)/"
        "20231105_019'), or <triplet>/<sequence> with --taco-root", "no such folder",
    )  # fmt: skip


def read_hand(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``right_hand.pkl`` -> ``hand_pose`` (T, 48) and ``hand_trans`` (T, 3, m), frames in sorted key order."""
    want = "TACO's right-hand MANO parameters: a dict {frame: {'hand_pose': (48,), 'hand_trans': (3,)}}"
    if not path.is_file():
        raise InputError(path, None, want, "no such file")
    data = load_pickle(path)
    if not isinstance(data, dict) or len(data) < 2:
        raise InputError(path, None, f"{want} of at least 2 frames", f"{type(data).__name__} of {_len(data)}")
    try:
        keys = sorted(data)
    except TypeError:
        raise InputError(path, None, "frame keys of one kind ('00001', '00002', ...)", str(list(data)[:4])) from None
    pose, trans = np.empty((len(keys), 48)), np.empty((len(keys), 3))
    for t, k in enumerate(keys):
        frame = data[k]
        if not isinstance(frame, dict):
            raise InputError(path, str(k), "a dict with 'hand_pose' (48,) and 'hand_trans' (3,)", type(frame).__name__)
        pose[t] = _array(frame, path, f"{k}.hand_pose", (48,))
        trans[t] = _array(frame, path, f"{k}.hand_trans", (3,))
    return pose, trans


def _len(x: Any) -> str:
    return f"{len(x)} entries" if isinstance(x, dict | list | tuple) else "no frames"


def read_shape(path: Path) -> np.ndarray:
    """``right_hand_shape.pkl`` -> the 10 MANO shape coefficients; zeros (with a warning) when the file is
    missing, as TACO's own ``read_hand_shape``."""
    if not path.is_file():
        print(f"warning: {path}: no such file; using MANO's mean hand shape (TACO's rule)", file=sys.stderr)
        return np.zeros(mano.N_BETAS)
    data = load_pickle(path)
    if not isinstance(data, dict) or "hand_shape" not in data:
        got = f"keys {sorted(map(str, data))}" if isinstance(data, dict) else type(data).__name__
        raise InputError(path, "hand_shape", "a dict with 'hand_shape' (10 MANO shape coefficients)", got)
    want = f"{mano.N_BETAS} finite MANO shape coefficients, e.g. (10,) or (1, 10)"
    try:
        beta = np.asarray(data["hand_shape"], dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(path, "hand_shape", want, type(data["hand_shape"]).__name__) from None
    if beta.size != mano.N_BETAS or not np.isfinite(beta).all():
        raise InputError(path, "hand_shape", want, f"shape {beta.shape}" if beta.size != mano.N_BETAS else "NaN or inf")
    return beta.reshape(mano.N_BETAS)


def read_tool(objects: Path) -> tuple[str, Path, np.ndarray, np.ndarray]:
    """The tool's id, pose file, positions (T, 3, m) and rotations (T, 3, 3) from ``tool_<id>.npy``."""
    if not objects.is_dir():
        want = "TACO's object poses folder (Object_Poses/<triplet>/<sequence>/tool_<id>.npy)"
        raise InputError(objects, None, want, "no such folder")
    tools = sorted(objects.glob("tool_*.npy"))
    if len(tools) != 1:
        got = "none" if not tools else ", ".join(t.name for t in tools)
        raise InputError(objects, None, "one tool pose file tool_<id>.npy", got)
    path = tools[0]
    with open(path, "rb") as f:
        mats = shaped_array(mano.load_npy(f, path), path, "pose", (None, 4, 4))
    if len(mats) < 2:
        raise InputError(path, "pose", "at least 2 frames of 4x4 poses", str(len(mats)))
    if not np.isfinite(mats).all():
        t = int(np.argwhere(~np.isfinite(mats))[0][0])
        raise InputError(path, "pose", "finite numbers", f"NaN or inf at frame {t}")
    pos, rot = rigid_transforms(mats, path)
    return path.stem.removeprefix("tool_"), path, pos, rot


def find_models(root: Path, object_models: str | Path | None) -> Path:
    """The folder of ``<id>_cm.obj``: ``object_models``, else ``<root>/Object_Models`` or
    ``<root>/object_models_released``."""
    if object_models is not None:
        return Path(object_models)
    for name in MODEL_DIRS:
        if (root / name).is_dir():
            return root / name
    return root / MODEL_DIRS[0]  # the missing mesh is reported there


# ---- the segment --------------------------------------------------------------------------------


def motion_onset(pos: np.ndarray, rot: np.ndarray) -> int | None:
    """The first frame at which the tool is :data:`ONSET_M` or :data:`ONSET_DEG` away from its pose at frame
    0 (None: never)."""
    cos = (np.einsum("ij,tij->t", rot[0], rot) - 1.0) / 2.0  # trace(R0^T R) = 1 + 2 cos(angle)
    moved = (np.linalg.norm(pos - pos[0], axis=1) >= ONSET_M) | (cos <= math.cos(math.radians(ONSET_DEG)))
    return int(np.argmax(moved)) if moved.any() else None


def segment_start(onset: int | None, opts: TacoOptions, tool_file: Path, n: int) -> int:
    """``opts.start``, or :data:`APPROACH_S` before the tool's motion onset (from frame 0 at the earliest)."""
    if opts.start is not None:
        return opts.start
    if onset is None:
        raise InputError(
            tool_file, "pose", f"a tool that moves ({ONSET_M * 1000:g} mm or {ONSET_DEG:g} deg from its first pose) "
            "for the automatic approach-and-act segment (or give --start)", f"a tool at rest over all {n} frames",
        )  # fmt: skip
    return max(0, onset - round(APPROACH_S * opts.source_fps))


def _hand_gap(mesh: Any, tips: np.ndarray, pos: np.ndarray, rot: np.ndarray) -> float:
    """The closest fingertip's distance (m) to the mesh surface, the mesh at pose ``rot``, ``pos``."""
    import trimesh

    _, dist, _ = trimesh.proximity.closest_point(mesh, (tips - pos) @ rot)  # world -> object frame: R^T (x - t)
    return float(np.min(dist))


# ---- the conversion -----------------------------------------------------------------------------


def convert_taco(
    seq: str | Path, mano_dir: str | Path, out: str | Path, taco_root: str | Path | None = None,
    object_models: str | Path | None = None, opts: TacoOptions = TacoOptions(),
) -> Path:  # fmt: skip
    """A TACO sequence -> ``out`` (demo npz: the right hand, the tool) and ``meshes/<tool>_<id>.obj`` beside
    it; returns ``out``. ``seq``: the sequence folder under ``Hand_Poses/`` or ``Object_Poses/`` (see
    :func:`find_sequence`); ``taco_root``: the folder holding ``Hand_Poses/`` and ``Object_Poses/``
    (default: three levels above ``seq``); ``object_models``: the folder of ``<id>_cm.obj`` (default:
    ``<root>/Object_Models`` or ``<root>/object_models_released``). The module docstring has the layout,
    the conventions and the segment rule."""
    from quasisim.data.demo import validate_arrays

    if opts.up not in UP_AXES:
        raise choice_error("up axis", opts.up, tuple(UP_AXES))
    out = Path(out)
    s = find_sequence(seq, taco_root)
    tool_id, tool_file, pos, rot = read_tool(s.objects)
    hand_file = s.hands / "right_hand.pkl"
    pose, trans = read_hand(hand_file)
    beta = read_shape(s.hands / "right_hand_shape.pkl")
    if len(pose) != len(pos):
        raise InputError(tool_file, "pose", f"{len(pose)} frames (as {hand_file.name})", str(len(pos)))
    mesh_file = find_models(s.root, object_models) / f"{tool_id}_cm.obj"
    m = _load_mesh(mesh_file, "--object-models", 0.01)  # centimetres -> metres

    model = mano.load_mano(mano.find_model(mano_dir, "right"))
    kp = mano.keypoints(model, pose[:, :3], pose[:, 3:], np.zeros_like(trans), betas=beta, flat_hand_mean=True)
    kp = kp - kp[:, :1] + trans[:, None]  # manopth's center_idx=0: the wrist at hand_trans

    onset = motion_onset(pos, rot)
    start = segment_start(onset, opts, tool_file, len(pos))
    where = f"{s.triplet}/{s.name}"
    if onset is not None:
        gap = _hand_gap(m, kp[onset, list(FINGERTIPS)], pos[onset], rot[onset])
        if gap > HOLD_WARN_M:
            print(f"warning: {where}: the right hand's closest fingertip is {gap * 100:.1f} cm from the tool when it "
                  f"starts moving (source frame {onset}): the tool may be in the left hand (the paper uses "
                  "right-hand tools)", file=sys.stderr)  # fmt: skip
        if opts.start is not None and start >= onset:
            print(f"warning: {where}: --start {start} is at or after the tool's motion onset (source frame {onset}): "
                  "it may not rest on the table at clip frame 0", file=sys.stderr)  # fmt: skip

    tl = timeline(len(pos), opts.source_fps, RawOptions(fps=opts.fps, start=start, frames=opts.frames), tool_file)
    used = tl.used
    up = UP_AXES[opts.up]
    obj_name = f"{s.tool_word}_{tool_id}"
    demo = _demo(
        opts.name or out.stem, opts.fps or opts.source_fps, tl.lerp(kp[used], used) @ up.T, obj_name,
        out.parent / "meshes" / f"{obj_name}.obj", up @ tl.slerp(rot[used], used), tl.lerp(pos[used], used) @ up.T,
        np.asarray(m.vertices), f"TACO {where} tool {tool_id} source frames {tl.s[0]:g}..{tl.s[-1]:g} step "
        f"{tl.step:g} at {opts.source_fps:g} fps, up {opts.up} (quasisim convert taco)",
    )  # fmt: skip
    try:
        validate_arrays(demo, out)  # before the mesh is written
    except InputError as e:
        source = {"right_joints": hand_file, "object_pos": tool_file, "object_quat": tool_file}
        raise InputError(source.get(e.field or "", tool_file), e.field, e.expected, e.got) from None
    _write_mesh(m, out, obj_name, mesh_file)
    return save_clip(demo, out, None)
