"""OakInk2 sequences, as released, -> ``quasisim-demo-v1`` clips (``quasisim convert oakink2``).

OakInk2 (Zhan et al., CVPR 2024, https://oakink.net/v2; toolkit: https://github.com/oakink/OakInk2, the same
package in https://github.com/oakink/OakInk2-PreviewTool): bimanual manipulation in complex tasks, each
sequence split into **primitive-task segments** with a frame interval per hand. A clip here is one segment
(or a frame range), one object, one or both hands.

Layout (the OakInk2 README, "Setup dataset files" and "Dataset Format"; the files as the toolkit's
``oakink2_toolkit/dataset.py`` reads them)::

    <root>/anno_preview/<scene>++<seq>.pkl          the annotation pickle (``anno/`` in the README's format list)
    <root>/program/program_info/<scene>++<seq>.json  the segments
    <root>/program/desc_info/<scene>++<seq>.json     their text descriptions (optional)
    <root>/object_repair/align_ds/<obj_id>/*.obj|ply one mesh per object (or object_raw/, object_preview/)
    <root>/object_raw/obj_desc.json                  {obj_id: {"obj_id", "obj_name"}} (optional)

The sequence key ``scene_0x__y00z/<seq>`` names the files with ``/`` replaced by ``++``.

Read from the annotation pickle (a dict; README "Dataset Format", ``OakInk2__Dataset.instantiate_complex_task``):

* ``mocap_frame_id_list`` (list of int): the mocap frame ids; ``raw_mano`` and ``obj_transf`` are dicts keyed
  by them (``_collect_mano`` / ``_collect_obj_transf`` look each frame id up).
* ``raw_mano`` (dict frame id -> dict): ``rh__pose_coeffs`` / ``lh__pose_coeffs`` (1, 16, 4) **quaternions
  w, x, y, z** (README: "are quaternions in [w,x,y,z] format"), the global orientation then MANO's 15 finger
  joints; ``rh__tsl`` / ``lh__tsl`` (1, 3); ``rh__betas`` / ``lh__betas`` (1, 10). The values are pickled torch
  tensors, read without torch as for TACO (:class:`quasisim.data.convert_taco.TorchTensorUnpickler`).
* ``obj_list`` (list of object ids) and ``obj_transf`` (dict obj_id -> dict frame id -> (4, 4)): the object
  pose, ``x_world = R x + t`` (the preview tool renders ``cam_extr @ obj_transf[obj_id][frame]`` applied to
  the mesh as loaded).
* ``raw_smplx``, the camera fields and ``frame_id_list`` (the 30 fps image frames) are not used.

Conventions (what the toolkit and its users told us):

* **Hand**: the toolkit poses each hand with manotorch's ``ManoLayer(rot_mode="quat", side=..., center_idx=0,
  use_pca=False, flat_hand_mean=True)`` and adds ``tsl`` to its joints and vertices
  (``oakink2_preview/launch/viz/seg_3d.py`` in OakInk2-PreviewTool; ``dev_fn/dataset/mano_adapter.py`` in
  kelvin34501/OakInk2-SimEnv-IsaacGym does the same). manotorch's quaternion mode turns the 16 quaternions
  into rotation matrices (normalised) with no mean hand added, and ``center_idx=0`` moves the posed **wrist
  joint to the origin**, so the wrist lies at ``tsl``. Keypoints here: the repository's MANO pass
  (:mod:`quasisim.data.mano`, the TACO converter's route) on the quaternions as axis-angle, ``flat_hand_mean``,
  the per-frame ``betas``, then shifted so the wrist is at ``tsl``; the left hand with ``MANO_LEFT.pkl``.
  (manotorch's own tips are vertices 745, 317, 444, 556, 673; here smplx's, as for every other clip.)
* **Units**: metres for ``tsl``, ``obj_transf`` and the meshes: the preview tool draws the meshes as loaded,
  posed by ``obj_transf``, beside the MANO hands (metres) without any scale (``seg_3d.py``,
  ``util/vis_pyrender_util.py``, whose fallback object is a 4 x 6 x 8 cm box given as 0.04, 0.06, 0.08).
* **Rate**: 120 Hz mocap (``oakink2_toolkit/meta.py``: ``FPS_MOCAP = 120``, ``FPS_VIDEO = 30``; OakInk2-TaMF
  slices segments from ``FPS_MOCAP``; ManipTrans's OakInk2 loader: "OakInk2 120Hz").
* **World**: **y up** (not stated by OakInk2; inferred: ManipTrans (jeffyu880/ManipTrans and forks) maps the
  OakInk2 world into its z-up simulator with ``Rz(-90 deg) Rx(90 deg)`` and the world origin at the table's
  surface, and OakInk2-SimEnv-IsaacGym declares ``FrameConvention.Y_UP`` with its table top at y = 0). ``up``
  turns another axis to +z. The clip is then moved up so that the object's lowest point at clip frame 0 is at
  ``table_height`` (the world's origin is not needed; ``support_height`` is that height).
* **Segments** (``program_info/<seq>.json``; README, toolkit ``program.py``): a dict whose keys are
  ``str((lh_interval, rh_interval))``, each interval ``None`` (that hand not in the segment) or
  ``(begin, end)`` in mocap frame ids, and whose values hold ``primitive``, ``obj_list``,
  ``interaction_mode`` (``lh_main``, ``rh_main``, ``bh_main``), ``obj_list_lh``, ``obj_list_rh``. Segment
  ``i`` is the ``i``-th key in file order (the toolkit's ``exec_path`` order, ManipTrans's ``@stage``) and is
  also named as the toolkit names it, ``<primitive>:<nn>`` (``pour:00``, the n-th of that primitive). Its
  frames are the toolkit's ``frame_range``: from the earliest begin to the latest end of its hands' intervals,
  ``range(begin, end)`` (end excluded).

Choices: ``hands`` defaults to the segment's hands (those with an interval; a range's: those of the
segments it overlaps, else the right hand); a hand is read from ``raw_mano`` over the whole clip (the mocap
covers both hands at every frame). A clip of the left hand alone is written **mirrored** (x -> -x after the
up turn, the mesh mirrored too) as a right-hand clip, since a demo's ``right_joints`` is required. The object
defaults to the first object of the segment's main hand (``interaction_mode``), one with poses; ``object_id``
overrides it. Clip frame ``k`` is mocap frame ``begin + k * 120 / fps`` (:func:`quasisim.data.convert_raw.timeline`),
at most ``frames`` clip frames.
"""

from __future__ import annotations

import ast
import json
import re
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from quasisim.data import mano
from quasisim.data.convert import UP_AXES, rigid_transforms
from quasisim.data.convert_raw import RawOptions, _demo, _load_mesh, _support, _write_mesh, save_clip, timeline
from quasisim.errors import InputError, QuasisimError, choice_error

OAKINK2_FPS = 120.0  # mocap rate (oakink2_toolkit/meta.py FPS_MOCAP)
TABLE_HEIGHT = 0.8  # m: the object's lowest point at clip frame 0 is put there
ANNO_DIRS = ("anno_preview", "anno")  # the README's download layout, its format list
OBJECT_DIRS = ("object_repair", "object_raw", "object_preview")  # the toolkit's obj_offset choices, oldest last
HANDS = ("right", "left", "both")
PREFIX = {"right": "rh", "left": "lh"}
MIRROR = np.diag([-1.0, 1.0, 1.0])


@dataclass(frozen=True)
class OakInk2Options:
    """``segment``: a segment's index or toolkit name (None: 0, unless ``frame_range``); ``frame_range``:
    mocap frame ids ``(begin, end)``, end excluded, instead of a segment; ``hands``: ``right``, ``left`` or
    ``both`` (None: the segment's); ``object_id``: the object (None: the segment's main one); ``fps``: clip
    rate (None: 120); ``frames``: at most this many clip frames; ``name``: clip name (None: OUT's stem);
    ``source_fps``: OakInk2's rate; ``up``: the world's up axis; ``table_height``: z of the object's lowest
    point at clip frame 0 (m)."""

    segment: int | str | None = None
    frame_range: tuple[int, int] | None = None
    hands: str | None = None
    object_id: str | None = None
    fps: float | None = 20.0
    frames: int | None = None
    name: str | None = None
    source_fps: float = OAKINK2_FPS
    up: str = "y"
    table_height: float = TABLE_HEIGHT


# ---- the files of one sequence --------------------------------------------------------------------


@dataclass(frozen=True)
class OakInk2Sequence:
    """One sequence: ``root`` (holding ``anno_preview/``, ``program/``, ``object_*/``), its file token
    ``<scene>++<seq>`` and its annotation pickle."""

    root: Path
    token: str
    anno: Path

    @property
    def program(self) -> Path:
        return self.root / "program" / "program_info" / f"{self.token}.json"

    @property
    def desc(self) -> Path:
        return self.root / "program" / "desc_info" / f"{self.token}.json"


def find_sequence(seq: str | Path, oakink2_root: str | Path | None = None) -> OakInk2Sequence:
    """``seq``: the annotation pickle (``<root>/anno_preview/<scene>++<seq>.pkl``; root: two levels above it
    unless given), or, with ``oakink2_root``, the sequence key ``scene_0x__y00z/<seq>`` (or its token)."""
    p = Path(seq)
    if p.is_file():
        root = Path(oakink2_root) if oakink2_root is not None else p.resolve().parents[1]
        return OakInk2Sequence(root, p.stem, p)
    if oakink2_root is not None:
        root = Path(oakink2_root)
        token = str(seq).strip("/").replace("/", "++").removesuffix(".pkl")
        for d in ANNO_DIRS:
            if (root / d / f"{token}.pkl").is_file():
                return OakInk2Sequence(root, token, root / d / f"{token}.pkl")
        anno = root / ANNO_DIRS[0] / f"{token}.pkl"
        raise InputError(anno, None, "OakInk2's annotation pickle of the sequence (anno_preview/<scene>++<seq>.pkl)",
                         "no such file")  # fmt: skip
    raise InputError(
        p, None, "an OakInk2 annotation file (<root>/anno_preview/<scene>++<seq>.pkl), or a sequence key "
        "scene_0x__y00z/<seq> with --oakink2-root", "no such file",
    )  # fmt: skip


# ---- segments -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Segment:
    """One primitive-task segment of ``program_info``: its index (file order), the toolkit's name, each hand's
    interval (mocap frame ids, end excluded; None: that hand is not in it) and its annotations."""

    index: int
    name: str
    lh: tuple[int, int] | None
    rh: tuple[int, int] | None
    primitive: str
    interaction_mode: str
    obj_list: tuple[str, ...]
    obj_list_lh: tuple[str, ...]
    obj_list_rh: tuple[str, ...]
    desc: str = ""

    @property
    def frame_range(self) -> tuple[int, int]:
        """The toolkit's ``frame_range``: the hands' intervals enclosed."""
        iv = [i for i in (self.lh, self.rh) if i is not None]
        return min(i[0] for i in iv), max(i[1] for i in iv)

    @property
    def hands(self) -> tuple[str, ...]:
        return tuple(s for s, iv in (("right", self.rh), ("left", self.lh)) if iv is not None)

    def objects(self) -> list[str]:
        """Its objects, the main hand's first (``interaction_mode``), no repeats."""
        main = {"rh_main": self.obj_list_rh, "lh_main": self.obj_list_lh}.get(self.interaction_mode, self.obj_list)
        return list(dict.fromkeys([*main, *self.obj_list, *self.obj_list_rh, *self.obj_list_lh]))

    def describe(self) -> str:
        b, e = self.frame_range
        hands = "+".join(PREFIX[h] for h in self.hands)
        return f"{self.index} {self.name} ({hands} {b}-{e})"


def _interval(x: Any) -> tuple[int, int] | None:
    if x is None:
        return None
    ok = isinstance(x, tuple | list) and len(x) == 2 and all(isinstance(v, int) and not isinstance(v, bool) for v in x)
    if not ok or not 0 <= x[0] < x[1]:
        raise ValueError
    return int(x[0]), int(x[1])


def _names(d: dict[str, Any], key: str, path: Path, where: str) -> tuple[str, ...]:
    v = d.get(key)
    if v is None:
        return ()
    if not isinstance(v, list | tuple) or not all(isinstance(s, str) for s in v):
        raise InputError(path, f"{where}.{key}", "a list of object ids or null", type(v).__name__)
    return tuple(v)


def _load_json(path: Path, want: str) -> Any:
    if not path.is_file():
        raise InputError(path, None, want, "no such file")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as e:
        raise InputError(path, None, f"{want} (JSON)", f"{type(e).__name__}: {str(e)[:80]}") from None


def read_segments(s: OakInk2Sequence) -> list[Segment]:
    """The sequence's segments from ``program_info`` (and their texts from ``desc_info`` when present)."""
    want = "OakInk2's primitive-task segments {'(lh_interval, rh_interval)': {...}} (program/program_info/<seq>.json)"
    info = _load_json(s.program, want)
    if not isinstance(info, dict) or not info:
        raise InputError(
            s.program, None, want, f"{type(info).__name__} of {len(info) if isinstance(info, dict | list) else 0}"
        )
    desc: dict[str, Any] = {}
    if s.desc.is_file():
        raw = _load_json(s.desc, "the segments' descriptions")
        if isinstance(raw, dict):
            for k, v in raw.items():
                try:
                    desc[str(ast.literal_eval(k))] = v.get("seg_desc", "") if isinstance(v, dict) else ""
                except (ValueError, SyntaxError):
                    continue
    out, counter = [], {}
    for i, (key, v) in enumerate(info.items()):
        try:
            pair = ast.literal_eval(key)
            if not isinstance(pair, tuple) or len(pair) != 2:
                raise ValueError
            lh, rh = _interval(pair[0]), _interval(pair[1])
            if lh is None and rh is None:
                raise ValueError
        except (ValueError, SyntaxError):
            raise InputError(s.program, key, "a key '(lh_interval, rh_interval)', each None or (begin, end) mocap "
                             "frame ids with begin < end, not both None", "this key") from None  # fmt: skip
        if not isinstance(v, dict):
            raise InputError(s.program, key, "a dict with 'primitive', 'obj_list', 'interaction_mode', ...",
                             type(v).__name__)  # fmt: skip
        prim = str(v.get("primitive", "?(unk)"))
        n = counter.get(prim, 0)
        counter[prim] = n + 1
        text = " ".join(str(desc.get(str(pair), "")).split())
        out.append(Segment(
            index=i, name=f"{prim}:{n:02d}", lh=lh, rh=rh, primitive=prim,
            interaction_mode=str(v.get("interaction_mode", "")), obj_list=_names(v, "obj_list", s.program, key),
            obj_list_lh=_names(v, "obj_list_lh", s.program, key), obj_list_rh=_names(v, "obj_list_rh", s.program, key),
            desc=text,
        ))  # fmt: skip
    return out


def choose_segment(segments: list[Segment], which: int | str, path: Path) -> Segment:
    """Segment ``which`` (index or toolkit name); :class:`InputError` listing the valid ones."""
    for seg in segments:
        if which == seg.index or (isinstance(which, str) and which in (seg.name, str(seg.index))):
            return seg
    valid = "; ".join(seg.describe() for seg in segments)
    raise InputError(path, "--segment", f"a segment index or name: {valid}", repr(which))


# ---- the annotation pickle ----------------------------------------------------------------------


def read_anno(path: Path) -> dict[str, Any]:
    """The annotation pickle (torch tensors read without torch), its used fields checked to be there."""
    from quasisim.data.convert_taco import load_pickle

    want = "OakInk2's annotation pickle (a dict with mocap_frame_id_list, obj_list, obj_transf, raw_mano)"
    if not path.is_file():
        raise InputError(path, None, want, "no such file")
    data = load_pickle(path)
    if not isinstance(data, dict):
        raise InputError(path, None, want, type(data).__name__)
    for key, kind in (("mocap_frame_id_list", list | tuple), ("obj_list", list | tuple), ("obj_transf", dict),
                      ("raw_mano", dict)):  # fmt: skip
        if key not in data:
            raise InputError(path, key, "an entry of this name", f"missing (keys: {', '.join(sorted(map(str, data)))})")
        if not isinstance(data[key], kind):
            raise InputError(path, key, "a list" if kind is not dict else "a dict keyed by frame/object id",
                             type(data[key]).__name__)  # fmt: skip
    return data


def _frame(d: dict[Any, Any], f: int, path: Path, field: str) -> Any:
    """``d[f]`` (frame id keys as ints, or their strings)."""
    if f in d:
        return d[f]
    if str(f) in d:
        return d[str(f)]
    ids = [k for k in d if isinstance(k, int)]
    have = f"{min(ids)}..{max(ids)}" if ids else f"{len(d)} entries"
    raise InputError(path, field, f"an entry for mocap frame {f}", f"none (frames {have})")


def _param(entry: Any, path: Path, field: str, shape: tuple[int, ...]) -> np.ndarray:
    """One per-frame tensor of ``raw_mano``: released as ``(1, *shape)``; ``shape`` is accepted too."""
    key = field.split(".")[-1]
    if not isinstance(entry, dict) or key not in entry:
        keys = ", ".join(sorted(map(str, entry))) if isinstance(entry, dict) else type(entry).__name__
        raise InputError(path, field, "an entry of this name", f"missing (keys: {keys})")
    want = f"an array of shape {(1, *shape)}"
    try:
        a = np.asarray(entry[key], dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(path, field, want, type(entry[key]).__name__) from None
    if a.shape not in ((1, *shape), shape):
        raise InputError(path, field, want, str(a.shape))
    if not np.isfinite(a).all():
        raise InputError(path, field, "finite numbers", "NaN or inf")
    return a.reshape(shape)


def hand_params(anno: dict[str, Any], path: Path, side: str, ids: np.ndarray) -> tuple[np.ndarray, ...]:
    """Quaternions (n, 16, 4) w x y z (normalised), ``tsl`` (n, 3) and ``betas`` (n, 10) of one hand at the
    mocap frames ``ids``."""
    p = PREFIX[side]
    quat, tsl, betas = np.empty((len(ids), 16, 4)), np.empty((len(ids), 3)), np.empty((len(ids), mano.N_BETAS))
    for t, f in enumerate(ids):
        entry = _frame(anno["raw_mano"], int(f), path, f"raw_mano[{f}]")
        quat[t] = _param(entry, path, f"raw_mano[{f}].{p}__pose_coeffs", (16, 4))
        tsl[t] = _param(entry, path, f"raw_mano[{f}].{p}__tsl", (3,))
        betas[t] = _param(entry, path, f"raw_mano[{f}].{p}__betas", (mano.N_BETAS,))
    norm = np.linalg.norm(quat, axis=-1)
    if (norm < 1e-6).any():
        t, j = np.argwhere(norm < 1e-6)[0]
        raise InputError(path, f"raw_mano[{ids[t]}].{p}__pose_coeffs", "quaternions w, x, y, z (non-zero)",
                         f"a zero quaternion at joint {j}")  # fmt: skip
    return quat / norm[..., None], tsl, betas


def hand_keypoints(model: mano.ManoModel, quat: np.ndarray, tsl: np.ndarray, betas: np.ndarray) -> np.ndarray:
    """(n, 21, 3) keypoints as manotorch's ``ManoLayer(rot_mode="quat", center_idx=0, flat_hand_mean=True)`` +
    ``tsl`` poses the hand: the 16 rotations of the w-x-y-z quaternions, no mean hand, the wrist at ``tsl``."""
    from scipy.spatial.transform import Rotation

    n = len(quat)
    aa = Rotation.from_quat(quat.reshape(-1, 4)[:, [1, 2, 3, 0]]).as_rotvec().reshape(n, 16, 3)  # scipy: x y z w
    kp = mano.keypoints(model, aa[:, 0], aa[:, 1:].reshape(n, 45), np.zeros((n, 3)), betas=betas, flat_hand_mean=True)
    return kp - kp[:, :1] + tsl[:, None]


def object_poses(anno: dict[str, Any], path: Path, obj_id: str, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions (n, 3) and rotations (n, 3, 3) of ``obj_transf[obj_id]`` at the mocap frames ``ids``."""
    poses = anno["obj_transf"].get(obj_id)
    if not isinstance(poses, dict):
        got = "missing" if poses is None else type(poses).__name__
        raise InputError(path, f"obj_transf[{obj_id}]", "a dict of 4x4 poses keyed by mocap frame id", got)
    mats = np.empty((len(ids), 4, 4))
    for t, f in enumerate(ids):
        field = f"obj_transf[{obj_id}][{f}]"
        m = _frame(poses, int(f), path, field)
        try:
            a = np.asarray(m, dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError(path, field, "a 4x4 pose", type(m).__name__) from None
        if a.shape != (4, 4):
            raise InputError(path, field, "an array of shape (4, 4)", str(a.shape))
        if not np.isfinite(a).all():
            raise InputError(path, field, "finite numbers", "NaN or inf")
        mats[t] = a
    try:
        return rigid_transforms(mats, path, f"obj_transf[{obj_id}]")
    except InputError:
        for t, f in enumerate(ids):  # name the mocap frame
            rigid_transforms(mats[t : t + 1], path, f"obj_transf[{obj_id}][{f}]")
        raise


# ---- the object mesh ----------------------------------------------------------------------------


def find_mesh(root: Path, object_dir: str | Path | None, obj_id: str) -> tuple[Path, str | None]:
    """The mesh ``<align_ds>/<obj_id>/*.obj|ply`` (exactly one, as the toolkit's ``load_obj``) and the object's
    name from ``obj_desc.json`` beside ``align_ds`` (None when absent)."""
    if object_dir is not None:
        align = Path(object_dir)
    else:
        found = [root / d / "align_ds" for d in OBJECT_DIRS if (root / d / "align_ds" / obj_id).is_dir()]
        align = found[0] if found else root / OBJECT_DIRS[0] / "align_ds"
    folder = align / obj_id
    if not folder.is_dir():
        raise InputError(folder, "--object-dir", "the object's mesh folder align_ds/<obj_id>/ (object_repair/, "
                         "object_raw/ or object_preview/)", "no such folder")  # fmt: skip
    meshes = sorted(p for p in folder.iterdir() if p.suffix in (".obj", ".ply") and p.is_file())
    if len(meshes) != 1:
        raise InputError(folder, "--object-dir", "one mesh file (.obj or .ply)",
                         ", ".join(p.name for p in meshes) or "none")  # fmt: skip
    name = None
    desc = align.parent / "obj_desc.json"
    if desc.is_file():
        try:
            entry = json.loads(desc.read_text(encoding="utf-8")).get(obj_id)
            name = str(entry["obj_name"]) if isinstance(entry, dict) and entry.get("obj_name") else None
        except (ValueError, UnicodeDecodeError, AttributeError):
            name = None
    return meshes[0], name


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_-]+", "_", text.strip()).strip("_") or "object"


# ---- the conversion -----------------------------------------------------------------------------


def _range_and_segment(
    segments: list[Segment], opts: OakInk2Options, s: OakInk2Sequence
) -> tuple[Segment | None, int, int]:
    if opts.frame_range is not None:
        if opts.segment is not None:
            raise QuasisimError("give either --segment or --range, not both")
        b, e = opts.frame_range
        if not 0 <= b < e:
            raise InputError(s.anno, "--range", "mocap frame ids BEGIN:END with 0 <= BEGIN < END", f"{b}:{e}")
        overlap = [(min(e, g.frame_range[1]) - max(b, g.frame_range[0]), g) for g in segments]
        best = max(overlap, key=lambda x: x[0], default=(0, None))
        return (best[1] if best[0] > 0 else None), b, e
    seg = choose_segment(segments, 0 if opts.segment is None else opts.segment, s.program)
    return (seg, *seg.frame_range)


def convert_oakink2(
    seq: str | Path, mano_dir: str | Path, out: str | Path, oakink2_root: str | Path | None = None,
    object_dir: str | Path | None = None, opts: OakInk2Options = OakInk2Options(),
) -> Path:  # fmt: skip
    """An OakInk2 sequence (its annotation pickle, or its key with ``oakink2_root``) -> ``out`` (demo npz) and
    the object's mesh in ``meshes/`` beside it; returns ``out``. ``object_dir``: the ``align_ds`` folder of
    the meshes (default: ``<root>/object_repair/align_ds``, else ``object_raw``, ``object_preview``). The module
    docstring has the layout, the conventions and the choices."""
    from quasisim.data.demo import validate_arrays

    if opts.up not in UP_AXES:
        raise choice_error("up axis", opts.up, tuple(UP_AXES))
    if opts.hands is not None and opts.hands not in HANDS:
        raise choice_error("hands", opts.hands, HANDS)
    out = Path(out)
    s = find_sequence(seq, oakink2_root)
    segments = read_segments(s)
    seg, begin, end = _range_and_segment(segments, opts, s)
    anno = read_anno(s.anno)

    # hands
    if opts.hands is not None:
        sides = ("right", "left") if opts.hands == "both" else (opts.hands,)
    elif opts.frame_range is None:
        sides = seg.hands
    else:
        over = [g for g in segments if min(end, g.frame_range[1]) > max(begin, g.frame_range[0])]
        sides = tuple(h for h in ("right", "left") if any(h in g.hands for g in over)) or ("right",)
    where = f"{s.token}" + (f" segment {seg.index} ({seg.name})" if seg is not None else f" frames {begin}-{end}")
    if seg is not None and opts.frame_range is None:
        for h in sides:
            if h not in seg.hands:
                print(f"warning: {where}: the {h} hand has no interval in this segment (it is read from raw_mano "
                      "anyway)", file=sys.stderr)  # fmt: skip

    # the object
    scene_objs = [str(o) for o in anno["obj_list"]]
    if opts.object_id is not None:
        obj_id = opts.object_id
        if obj_id not in anno["obj_transf"]:
            raise InputError(s.anno, "--object", f"an object with poses in obj_transf: {', '.join(scene_objs)}", obj_id)
    else:
        cands = seg.objects() if seg is not None else []
        posed = [o for o in cands if o in anno["obj_transf"]]
        if not posed:
            got = ", ".join(cands) or "none"
            raise InputError(s.program if seg else s.anno, "--object", f"a segment object with poses in obj_transf "
                             f"(or --object: {', '.join(scene_objs)})", got)  # fmt: skip
        obj_id = posed[0]
        if len(posed) > 1:
            print(f"note: {where} involves objects {', '.join(posed)}; using {obj_id} (--object to choose)",
                  file=sys.stderr)  # fmt: skip

    # frames
    tl = timeline(end - begin, opts.source_fps, RawOptions(fps=opts.fps, start=0, frames=opts.frames), s.anno)
    used = tl.used
    ids = begin + used
    pos, rot = object_poses(anno, s.anno, obj_id, ids)
    kp = {}
    for side in sides:
        model = mano.load_mano(mano.find_model(mano_dir, side))
        kp[side] = hand_keypoints(model, *hand_params(anno, s.anno, side, ids))

    mesh_file, obj_label = find_mesh(s.root, object_dir, obj_id)
    m = _load_mesh(mesh_file, "--object-dir")  # metres, as released
    mirrored = sides == ("left",)
    W = (MIRROR if mirrored else np.eye(3)) @ UP_AXES[opts.up]
    if mirrored:  # a left hand alone: the mirror image, a right-hand clip
        m.apply_transform(np.diag([-1.0, 1.0, 1.0, 1.0]))  # trimesh flips the faces' winding too
        print(f"note: {where}: the left hand alone is written mirrored (x -> -x) as the clip's right hand",
              file=sys.stderr)  # fmt: skip
    M = MIRROR if mirrored else np.eye(3)
    R = tl.slerp(W @ rot @ M, used)  # mesh vertices M v: W (R v + p) = (W R M)(M v) + W p
    p = tl.lerp(pos, used) @ W.T
    v = np.asarray(m.vertices)
    lift = np.array([0.0, 0.0, opts.table_height - _support(v, R[0], p[0])])
    hands = {side: tl.lerp(k, used) @ W.T + lift for side, k in kp.items()}
    right = hands["left" if mirrored else "right"]
    left = hands.get("left") if not mirrored else None

    obj_name = _slug(f"{obj_label}_{obj_id}" if obj_label else obj_id) + ("_mirrored" if mirrored else "")
    text = f" '{seg.desc}'" if seg is not None and seg.desc else ""
    demo = _demo(
        opts.name or out.stem, opts.fps or opts.source_fps, right, obj_name, out.parent / "meshes" / f"{obj_name}.obj",
        R, p + lift, v, f"OakInk2 {where}{text} object {obj_id} hands {'+'.join(sides)}"
        f"{' mirrored' if mirrored else ''} mocap frames {begin + tl.s[0]:g}..{begin + tl.s[-1]:g} step {tl.step:g} "
        f"at {opts.source_fps:g} fps, up {opts.up}, lifted {lift[2]:+.3f} m (quasisim convert oakink2)",
    )  # fmt: skip
    if left is not None:
        demo = replace(demo, left_joints=left)
    try:
        validate_arrays(demo, out)  # before the mesh is written
    except InputError as e:
        raise InputError(s.anno, e.field, e.expected, e.got) from None
    _write_mesh(m, out, obj_name, mesh_file)
    return save_clip(demo, out, None)
