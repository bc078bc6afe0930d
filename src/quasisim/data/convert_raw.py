"""GRAB and ARCTIC sequences, as released, -> ``quasisim-demo-v1`` clips (``quasisim convert grab|arctic``).

The hand keypoints are computed from the datasets' MANO fits with the user's MANO model
(:mod:`quasisim.data.mano`): 16 MANO joints + 5 fingertip vertices in MediaPipe order, metres. Both datasets'
world frames are z up (GRAB: the mocap frame, tables 0.75-1.2 m high, its viewer's camera at z = 1.5 m; ARCTIC:
likewise), so no axis change is needed. Clips are resampled from the source rate (GRAB: the file's
``framerate``, 120; ARCTIC: 30, not stored in the files) to ``--fps``: clip frame ``k`` is source frame
``start + k * src_fps / fps``, interpolated linearly (keypoints, positions) and by slerp (object rotation)
between the two neighbouring source frames (plain decimation when the ratio is an integer). The table height
is the object's lowest point at clip frame 0 (the object starts resting on it).

GRAB (``<root>/grab/s1/apple_lift.npz``, Taheri et al. 2020): a dict per body part; the right hand is
``rhand.params`` (``global_orient``, ``hand_pose`` = PCA coefficients, ``transl``) posed with MANO with the
subject's own template ``rhand.vtemp`` (a mesh under ``<root>/tools/subject_meshes``), ``flat_hand_mean``
and the first ``n`` PCA components, as GRAB's own code builds it. The object pose is ``object.params``
(``global_orient`` axis-angle, ``transl``) and GRAB's object model computes ``v @ R + t``, i.e. the world
rotation is ``R^T``. The mesh is ``object.object_mesh`` (relative to ``<root>``).

ARCTIC (``<root>/raw_seqs/s01/box_grab_01.{mano,object}.npy``, Fan et al. 2023): ``mano.npy`` holds
``right`` / ``left`` dicts of ``rot`` (T, 3), ``pose`` (T, 45 axis-angle, relative to MANO's mean hand),
``trans`` (T, 3, m) and ``shape`` (T, 10); ``object.npy`` is (T, 7): articulation angle (rad), axis-angle
rotation, translation (mm). Object templates (mm) are in ``<root>/meta/object_vtemplates/<object>/``. Rigid
route: the top part is turned about the hinge (ARCTIC's rule: axis-angle ``(0, 0, -1) * angle`` in the object
frame) by the median angle over the clip and joined to the base part into one mesh; the object frame is the
base part's frame.
"""

from __future__ import annotations

import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from quasisim.data import mano
from quasisim.data.demo import Demo, save_demo
from quasisim.errors import InputError, shaped_array
from quasisim.files import atomic_path

ARCTIC_FPS = 30.0  # ARCTIC's ground truth is per video frame (30 fps); the files do not state it
HINGE_WARN = 0.1  # rad; the hinge moving more than this within a clip is reported (rigid route)


@dataclass(frozen=True)
class RawOptions:
    """``fps``: clip frame rate (None: the source rate); ``start``: source frame of clip frame 0;
    ``frames``: clip length (None: to the end of the sequence); ``name``: clip name (None: OUT's stem);
    ``left``: also write the left hand as ``left_joints`` (GRAB; ARCTIC always does); ``source_fps``:
    the source rate where the file does not state one (ARCTIC)."""

    fps: float | None = 20.0
    start: int = 0
    frames: int | None = None
    name: str | None = None
    left: bool = False
    source_fps: float = ARCTIC_FPS


# ---- resampling ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Timeline:
    """Clip frame ``k`` at fractional source frame ``s[k]`` = ``lo[k] + a[k]`` (``hi = lo + 1`` or ``lo``)."""

    s: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    a: np.ndarray
    step: float

    @property
    def used(self) -> np.ndarray:
        """The source frames the clip needs (sorted)."""
        return np.unique(np.concatenate([self.lo, self.hi]))

    def lerp(self, x: np.ndarray, used: np.ndarray) -> np.ndarray:
        """Values ``x`` at the ``used`` source frames -> values at the clip frames (linear)."""
        i0, i1 = np.searchsorted(used, self.lo), np.searchsorted(used, self.hi)
        a = self.a.reshape(-1, *([1] * (x.ndim - 1)))
        return (1 - a) * x[i0] + a * x[i1]

    def slerp(self, R: np.ndarray, used: np.ndarray) -> np.ndarray:
        """Rotation matrices at the ``used`` frames -> at the clip frames (slerp)."""
        from scipy.spatial.transform import Rotation

        r0 = Rotation.from_matrix(R[np.searchsorted(used, self.lo)])
        r1 = Rotation.from_matrix(R[np.searchsorted(used, self.hi)])
        return (r0 * Rotation.from_rotvec((r0.inv() * r1).as_rotvec() * self.a[:, None])).as_matrix()


def timeline(n_src: int, src_fps: float, opts: RawOptions, path: Path) -> Timeline:
    """The clip's frames in a source sequence of ``n_src`` frames at ``src_fps``."""
    fps = opts.fps or src_fps
    if not (fps > 0 and src_fps > 0):
        raise InputError(path, "--fps", "a positive frame rate", f"{fps:g} (source {src_fps:g})")
    if not 0 <= opts.start < n_src - 1:
        raise InputError(path, "--start", f"a source frame in [0, {n_src - 2}]", str(opts.start))
    step = src_fps / fps
    n_max = math.floor((n_src - 1 - opts.start) / step + 1e-9) + 1
    n = n_max if opts.frames is None else min(opts.frames, n_max)
    if n < 2:
        raise InputError(path, "--frames", f"at least 2 clip frames ({n_max} fit after --start at {fps:g} fps)", str(n))
    s = opts.start + step * np.arange(n)
    lo = np.minimum(np.floor(s + 1e-9).astype(np.int64), n_src - 1)
    a = np.where(s - lo < 1e-9, 0.0, s - lo)
    hi = np.where(a > 0, np.minimum(lo + 1, n_src - 1), lo)
    return Timeline(s=s, lo=lo, hi=hi, a=a, step=step)


# ---- shared pieces ------------------------------------------------------------------------------------


def _array(d: dict[str, Any], path: Path, field: str, shape: tuple[int | None, ...]) -> np.ndarray:
    """``d[last part of field]`` as float64 with ``shape`` (None: any), else :class:`InputError`."""
    key = field.split(".")[-1]
    if not isinstance(d, dict) or key not in d:
        keys = ", ".join(sorted(d)) if isinstance(d, dict) else type(d).__name__
        raise InputError(path, field, "an entry of this name", f"missing (keys: {keys})")
    a = shaped_array(d[key], path, field, shape, "T")
    if not np.isfinite(a).all():
        raise InputError(path, field, "finite numbers", "NaN or inf")
    return a


def _frames(arrays: dict[str, np.ndarray], path: Path) -> int:
    """The common frame count of per-frame ``arrays`` (field -> array)."""
    counts = {k: len(v) for k, v in arrays.items()}
    n = min(counts.values())
    for k, c in counts.items():
        if c != n:
            raise InputError(path, k, f"{n} frames (as {min(counts, key=counts.get)})", str(c))
    return n


def _load_mesh(path: Path, field: str, scale: float = 1.0) -> Any:
    """A mesh file as trimesh (vertex order kept), scaled by ``scale``."""
    import trimesh

    if not path.is_file():
        raise InputError(path, field, "an existing mesh file", "no such file")
    try:
        m = trimesh.load(path, process=False, force="mesh")
    except Exception as e:
        raise InputError(path, field, "a mesh file trimesh can read", f"{type(e).__name__}: {str(e)[:80]}") from None
    if scale != 1.0:
        m.apply_scale(scale)
    return m


def _write_mesh(m: Any, out: Path, stem: str, source: Path) -> Path:
    """``meshes/<stem>.obj`` beside ``out``, checked as the demo loader will check it (closed after repair,
    plausible size) before it replaces the file there (another clip's of the object, or the user's); an
    :class:`InputError` names the ``source`` mesh and leaves that file as it was."""
    from quasisim.assets.object import load_object  # heavy (JAX): only when converting

    mesh_path = out.parent / "meshes" / f"{stem}.obj"
    with atomic_path(mesh_path) as tmp:
        m.export(tmp, file_type="obj")
        try:
            load_object(tmp)
        except InputError as e:
            raise InputError(source, "mesh", e.expected, e.got) from None
    return mesh_path


def save_clip(demo: Demo, out: Path, left: np.ndarray | None) -> Path:
    """``save_demo`` of ``demo`` with ``left_joints`` (T, 21, 3) when given (validated as a left hand there)."""
    from dataclasses import replace

    return save_demo(demo if left is None else replace(demo, left_joints=np.asarray(left, dtype=np.float32)), out)


def _support(vertices: np.ndarray, R0: np.ndarray, p0: np.ndarray) -> float:
    """z of the mesh's lowest point at the pose ``R0``, ``p0``."""
    return float((vertices @ R0.T + p0)[:, 2].min())


def _demo(
    name: str, fps: float, right: np.ndarray, obj_name: str, mesh_path: Path, R: np.ndarray, pos: np.ndarray,
    vertices: np.ndarray, source: str,
) -> Demo:  # fmt: skip
    from quasisim.rotations import np_mat_to_quat, sign_continuous

    return Demo(
        name=name, fps=float(fps), right_joints=right, object_name=obj_name, object_mesh_path=mesh_path,
        object_pos=pos, object_quat=sign_continuous(np_mat_to_quat(R)),
        support_height=_support(vertices, R[0], pos[0]), source=source,
    )  # fmt: skip


# ---- GRAB ---------------------------------------------------------------------------------------------


def _grab_part(seq: Path, key: str) -> dict[str, Any]:
    part = mano.load_npz_member(seq, key)
    if not isinstance(part, dict) or not isinstance(part.get("params"), dict):
        got = f"keys {sorted(part)}" if isinstance(part, dict) else type(part).__name__
        raise InputError(seq, f"{key}.params", "a dict of per-frame parameters (GRAB layout)", got)
    return part


def _grab_hand(seq: Path, part: dict[str, Any], key: str) -> dict[str, np.ndarray]:
    """One GRAB hand's per-frame MANO parameters, checked."""
    p = part["params"]
    return {f"{key}.params.{k}": _array(p, seq, f"{key}.params.{k}", (None, w))
            for k, w in (("global_orient", 3), ("hand_pose", None), ("transl", 3))}  # fmt: skip


def _grab_keypoints(
    seq: Path, root: Path, part: dict[str, Any], key: str, model: mano.ManoModel, used: np.ndarray
) -> np.ndarray:
    """(len(used), 21, 3) keypoints of one GRAB hand at the source frames ``used``: MANO with the subject's
    template ``vtemp``, ``flat_hand_mean`` and PCA pose (GRAB's ``smplx.create(..., num_pca_comps=n)``)."""
    go, hp, tr = _grab_hand(seq, part, key).values()
    if not 1 <= hp.shape[1] <= len(model.hands_components):
        n_max = len(model.hands_components)
        raise InputError(seq, f"{key}.params.hand_pose", f"1 to {n_max} PCA coefficients", str(hp.shape[1]))
    vtemp = None
    if part.get("vtemp"):
        vt_file = root / str(part["vtemp"])
        vtemp = np.asarray(_load_mesh(vt_file, f"{key}.vtemp").vertices, dtype=np.float64)
        if vtemp.shape != model.v_template.shape:
            raise InputError(vt_file, f"{key}.vtemp", f"{len(model.v_template)} MANO vertices", str(len(vtemp)))
    return mano.keypoints(model, go[used], hp[used], tr[used], flat_hand_mean=True, v_template=vtemp)


def convert_grab(seq: str | Path, mano_dir: str | Path, out: str | Path, grab_root: str | Path | None = None,
                 opts: RawOptions = RawOptions()) -> Path:  # fmt: skip
    """A GRAB sequence ``.npz`` -> ``out`` (demo npz) and ``meshes/<object>.obj`` beside it; returns ``out``.
    ``grab_root`` is the folder holding ``grab/`` and ``tools/`` (default: three levels above ``seq``)."""
    seq, out = Path(seq), Path(out)
    if not seq.is_file():
        raise InputError(seq, None, "a GRAB sequence file (grab/<subject>/<object>_<intent>.npz)", "no such file")
    root = Path(grab_root) if grab_root is not None else seq.resolve().parents[2]
    parts = {k: _grab_part(seq, k) for k in ("rhand", "object", *(("lhand",) if opts.left else ()))}
    src_fps = float(np.asarray(mano.load_npz_member(seq, "framerate"), dtype=np.float64).reshape(-1)[0])
    rot = _array(parts["object"]["params"], seq, "object.params.global_orient", (None, 3))
    pos = _array(parts["object"]["params"], seq, "object.params.transl", (None, 3))
    hands = {k: v for key in parts if key != "object" for k, v in _grab_hand(seq, parts[key], key).items()}
    n = _frames({"object.params.global_orient": rot, "object.params.transl": pos, **hands}, seq)
    tl = timeline(n, src_fps, opts, seq)
    used = tl.used
    kp = {}
    for key, side in (("rhand", "right"), ("lhand", "left")):
        if key in parts:
            model = mano.load_mano(mano.find_model(mano_dir, side))
            kp[key] = tl.lerp(_grab_keypoints(seq, root, parts[key], key, model, used), used)
    R = tl.slerp(np.swapaxes(mano.rodrigues(rot[used]), -1, -2), used)  # GRAB: v @ R + t, i.e. R^T v + t
    if "object_mesh" in parts["object"]:
        rel = str(parts["object"]["object_mesh"])
    else:
        rel = f"tools/object_meshes/contact_meshes/{mano.load_npz_member(seq, 'obj_name')}.ply"
    m = _load_mesh(root / rel, "object.object_mesh")
    obj_name = Path(rel).stem
    mesh_path = _write_mesh(m, out, obj_name, root / rel)
    demo = _demo(
        opts.name or out.stem, opts.fps or src_fps, kp["rhand"], obj_name, mesh_path, R, tl.lerp(pos[used], used), np.asarray(m.vertices), f"GRAB {seq.parent.name}/{seq.name} source frames "
        f"{tl.s[0]:g}..{tl.s[-1]:g} step {tl.step:g} at {src_fps:g} fps (quasisim convert grab)",
    )  # fmt: skip
    return save_clip(demo, out, kp.get("lhand"))


# ---- ARCTIC -------------------------------------------------------------------------------------------


def _arctic_base(seq: Path) -> Path:
    """``.../s01/box_grab_01`` from a ``.mano.npy`` / ``.object.npy`` path or the base itself."""
    name = seq.name
    for suffix in (".mano.npy", ".object.npy", ".npy"):
        if name.endswith(suffix):
            return seq.with_name(name.removesuffix(suffix))
    return seq


def _arctic_hand(path: Path, hands: Any, side: str) -> dict[str, np.ndarray]:
    """One ARCTIC hand's per-frame MANO parameters (``rot``, ``pose``, ``trans``, ``shape``), checked."""
    if not isinstance(hands, dict) or not isinstance(hands.get(side), dict):
        got = f"keys {sorted(hands)}" if isinstance(hands, dict) else type(hands).__name__
        raise InputError(path, side, "a dict per hand ('right', 'left') of MANO parameters (ARCTIC layout)", got)
    return {f"{side}.{k}": _array(hands[side], path, f"{side}.{k}", (None, w))
            for k, w in (("rot", 3), ("pose", 45), ("trans", 3), ("shape", mano.N_BETAS))}  # fmt: skip


def _arctic_keypoints(params: dict[str, np.ndarray], model: mano.ManoModel, used: np.ndarray) -> np.ndarray:
    """(len(used), 21, 3) keypoints: MANO with 45 axis-angle numbers relative to the mean hand (ARCTIC's
    ``MANO(use_pca=False, flat_hand_mean=False)``) and per-frame shape."""
    rot, pose, trans, shape = (a[used] for a in params.values())
    return mano.keypoints(model, rot, pose, trans, betas=shape, flat_hand_mean=False)


def _union(bottom: Any, top: Any, where: Path) -> Any:
    """The boolean union of the two closed parts (trimesh with the manifold3d engine), so that where they
    overlap the volume, mass and inertia count once."""
    import trimesh

    want = "two closed (watertight) parts whose union is one closed mesh"
    for name, part in (("bottom", bottom), ("top", top)):
        if not part.is_watertight:
            raise InputError(where, f"{name} part", want, "an open mesh (not watertight)")
    try:
        u = trimesh.boolean.union([bottom, top], engine="manifold")
    except (ValueError, RuntimeError) as e:
        raise InputError(where, "bottom and top parts", want, str(e)) from e
    if not u.is_watertight or len(u.faces) == 0:
        raise InputError(where, "bottom and top parts", want, "a union that is not watertight")
    return u


def _arctic_mesh(root: Path, obj_name: str, angle: float) -> Any:
    """The object's two parts (mm -> m) as one rigid mesh (their union), the top turned by ``angle`` about the hinge:
    ``top.obj`` + ``bottom.obj`` where present, else ``mesh.obj`` split by ``parts.json`` (1: top)."""

    d = root / "meta" / "object_vtemplates" / obj_name
    hinge = mano.rodrigues(np.array([0.0, 0.0, -angle]))
    if (d / "top.obj").is_file() and (d / "bottom.obj").is_file():
        top, bottom = _load_mesh(d / "top.obj", "top.obj", 1e-3), _load_mesh(d / "bottom.obj", "bottom.obj", 1e-3)
        top.vertices = np.asarray(top.vertices) @ hinge.T
        return _union(bottom, top, d)
    m = _load_mesh(d / "mesh.obj", "mesh.obj", 1e-3)
    parts_file = d / "parts.json"
    if not parts_file.is_file():
        raise InputError(parts_file, "parts", "ARCTIC's per-vertex part labels (0 bottom, 1 top)", "no such file")
    parts = np.asarray(json.loads(parts_file.read_text()), dtype=bool).reshape(-1)
    if len(parts) != len(m.vertices):
        raise InputError(parts_file, "parts", f"{len(m.vertices)} labels (one per vertex of mesh.obj)", str(len(parts)))
    v = np.asarray(m.vertices).copy()
    v[parts] = v[parts] @ hinge.T
    m.vertices = v
    on_top = parts[np.asarray(m.faces)].all(axis=1)
    bottom, top = m.submesh([np.flatnonzero(~on_top)], append=True), m.submesh([np.flatnonzero(on_top)], append=True)
    return _union(bottom, top, d)


def convert_arctic(seq: str | Path, mano_dir: str | Path, out: str | Path, arctic_root: str | Path | None = None,
                   opts: RawOptions = RawOptions()) -> Path:  # fmt: skip
    """An ARCTIC raw sequence (``raw_seqs/<subject>/<seq>.mano.npy`` and ``.object.npy``) -> ``out`` with
    ``right_joints`` and ``left_joints``, and the rigid mesh in ``meshes/``. ``arctic_root`` holds
    ``raw_seqs/`` and ``meta/`` (default: three levels above ``seq``)."""
    base, out = _arctic_base(Path(seq)), Path(out)
    mano_file, obj_file = base.with_name(base.name + ".mano.npy"), base.with_name(base.name + ".object.npy")
    for f in (mano_file, obj_file):
        if not f.is_file():
            raise InputError(
                f, None, "an ARCTIC raw sequence file (raw_seqs/<subject>/<seq>.{mano,object}.npy)", "no such file"
            )
    root = Path(arctic_root) if arctic_root is not None else base.resolve().parents[2]
    with open(mano_file, "rb") as f:
        hands = mano.load_npy(f, mano_file)
    with open(obj_file, "rb") as f:
        obj = np.asarray(mano.load_npy(f, obj_file), dtype=np.float64)
    if obj.ndim != 2 or obj.shape[1] != 7 or not np.isfinite(obj).all():
        raise InputError(
            obj_file, "object", "finite (T, 7) [angle, axis-angle (3), translation (3, mm)]", str(obj.shape)
        )
    params = {side: _arctic_hand(mano_file, hands, side) for side in ("right", "left")}
    _frames({**params["right"], **params["left"]}, mano_file)
    if len(obj) != len(params["right"]["right.rot"]):
        raise InputError(
            obj_file, "object", f"{len(params['right']['right.rot'])} frames (as {mano_file.name})", str(len(obj))
        )
    tl = timeline(len(obj), opts.source_fps, opts, obj_file)
    used = tl.used
    kp = {}
    for side in ("right", "left"):
        model = mano.load_mano(mano.find_model(mano_dir, side))
        kp[side] = tl.lerp(_arctic_keypoints(params[side], model, used), used)
    arti = tl.lerp(obj[used, 0], used)
    angle = round(float(np.median(arti)), 3)
    dev = float(np.abs(arti - angle).max())
    if dev > HINGE_WARN:
        msg = f"the hinge moves {dev:.2f} rad from the baked {angle:.3f} rad (rigid route; pick --start/--frames)"
        print(f"warning: {base.name}: {msg}", file=sys.stderr)
    obj_name = base.name.split("_")[0]
    m = _arctic_mesh(root, obj_name, angle)
    mesh_dir = root / "meta" / "object_vtemplates" / obj_name
    mesh_path = _write_mesh(m, out, f"{obj_name}_hinge{round(angle * 1000):04d}mrad", mesh_dir)
    R = tl.slerp(mano.rodrigues(obj[used, 1:4]), used)
    demo = _demo(
        opts.name or out.stem, opts.fps or opts.source_fps, kp["right"], obj_name, mesh_path, R,
        tl.lerp(obj[used, 4:7] * 1e-3, used), np.asarray(m.vertices),
        f"ARCTIC {base.parent.name}/{base.name} source frames {tl.s[0]:g}..{tl.s[-1]:g} step {tl.step:g} at "
        f"{opts.source_fps:g} fps, hinge baked at {angle:.3f} rad (quasisim convert arctic)",
    )  # fmt: skip
    return save_clip(demo, out, kp["left"])
