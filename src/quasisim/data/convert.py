"""Bring your own data in: 21 hand landmarks per frame (MediaPipe order) plus the object's pose per frame
and its mesh -> a ``quasisim-demo-v1`` clip (see ``docs/demo_format.md``).

Inputs (one row per frame, the same number of frames in both files):

* landmarks: ``.npz`` (an array (T, 21, 3) or (T, 63), under ``--key`` or the only such array; optional
  ``fps``), ``.csv`` (63 numbers per row ``x0, y0, z0, ..., z20``, or 64 with a leading frame number or
  time stamp; header lines are skipped) or ``.json`` (a list of frames, each 21 ``[x, y, z]`` or 21
  ``{"x": .., "y": .., "z": ..}``; or an object with that list under ``"frames"`` or ``"landmarks"`` and
  an optional ``"fps"``);
* object poses: ``.npz`` with ``object_pos`` (T, 3) and ``object_quat`` (T, 4), or one array (T, 7) or
  (T, 4, 4); ``.csv`` rows of 7 numbers ``x, y, z`` + quaternion (or 8 with a leading frame column), or 16
  (a row-major 4x4 pose); ``.json`` a list of such rows or of ``{"pos": [..], "quat": [..]}``;
* a mesh any of trimesh's formats read (``.obj``, ``.stl``, ``.ply``, ...), in the object's frame.

Options: the length unit of all three (``m``, ``cm``, ``mm``), the world's up axis (``z``, ``y``, ``-y``,
``x``, ``-x``, ``-z``; the clip is turned so that it is +z), the quaternion order (``wxyz`` or ``xyzw``),
the frame rate, the table height (default: the mesh's lowest point in the first frame, i.e. the object
starts resting on the table).
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from quasisim.data.demo import N_KEYPOINTS, Demo, save_demo, validate_arrays
from quasisim.errors import InputError, QuasisimError, choice_error
from quasisim.files import atomic_path, check_out_dir, npz_array, npz_member, npz_number, open_npz, refuse_overwrite
from quasisim.rotations import np_mat_to_quat, np_quat_to_mat, sign_continuous

UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}
# rotations taking each up axis to +z (proper rotations, det +1)
UP_AXES = {
    "z": np.eye(3),
    "-z": np.diag([1.0, -1.0, -1.0]),
    "y": np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]),
    "-y": np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]),
    "x": np.array([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]]),
    "-x": np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]]),
}
QUAT_ORDERS = ("wxyz", "xyzw")
HAND_SIZE = (0.04, 0.15)  # m, plausible wrist-to-middle-knuckle distances (the units check)


@dataclass(frozen=True)
class ConvertOptions:
    """How to read the inputs: length ``units``, ``up`` axis, ``quat_order``, ``fps`` (None: from the
    landmark file), ``support_height`` in m after conversion (None: the object's lowest point at frame 0),
    the landmark array's npz ``key`` (None: the only (T, 21, 3) or (T, 63) array), clip ``name``."""

    units: str = "m"
    up: str = "z"
    quat_order: str = "wxyz"
    fps: float | None = None
    support_height: float | None = None
    key: str | None = None
    name: str | None = None

    def check(self) -> None:
        for kind, value, options in (
            ("unit", self.units, UNITS), ("up axis", self.up, UP_AXES), ("quaternion order", self.quat_order, QUAT_ORDERS),
        ):  # fmt: skip
            if value not in options:
                raise choice_error(kind, value, tuple(options))
        n = self.name
        if n is not None and (not n.strip() or n != Path(n).name or n in (".", "..") or not n.isprintable()):
            raise QuasisimError(f"--name expects a clip name without folders (e.g. mug_lift), got {n!r}")


# ---- reading rows of numbers ----------------------------------------------------------------------


def _csv_rows(path: Path) -> np.ndarray:
    rows = []
    with open(path, newline="", encoding="utf-8") as f:
        try:
            for i, row in enumerate(csv.reader(f)):
                cells = [c.strip() for c in row if c.strip()]
                try:
                    rows.append([float(c) for c in cells])
                except ValueError:
                    if rows:  # only leading lines may be headers
                        raise InputError(
                            path, f"line {i + 1}", "numbers separated by commas", ",".join(cells)[:60]
                        ) from None
        except (UnicodeDecodeError, csv.Error) as e:
            raise InputError(path, None, "a UTF-8 text CSV file", " ".join(str(e).split())[:80]) from None
    if not rows or len({len(r) for r in rows}) != 1:
        raise InputError(
            path,
            None,
            "rows of equally many numbers, one row per frame",
            f"{len(rows)} rows of lengths {sorted({len(r) for r in rows})}",
        )
    return np.array(rows)


def _json_frames(obj: Any, path: Path) -> tuple[Any, float | None]:
    if isinstance(obj, dict):
        fps = obj.get("fps")
        if fps is not None and (isinstance(fps, bool) or not isinstance(fps, int | float)):
            raise InputError(path, "fps", "a number", repr(fps)[:40])
        for k in ("frames", "landmarks", "poses"):
            if k in obj:
                return obj[k], None if fps is None else float(fps)
    return obj, None


def _json_row(frame: Any) -> list[float]:
    """One frame of a JSON file as a flat list of numbers (landmark dicts, pose dicts and nested lists)."""
    if isinstance(frame, dict):
        if "pos" in frame:
            return [*frame["pos"], *frame["quat"]]
        return [float(frame[k]) for k in ("x", "y", "z")]
    if isinstance(frame, list):
        return [v for item in frame for v in (_json_row(item) if isinstance(item, list | dict) else [float(item)])]
    raise TypeError(f"unexpected {type(frame).__name__}")


def read_rows(path: Path, widths: tuple[int, ...], key: str | None = None) -> tuple[np.ndarray, float | None]:
    """(T, w) numbers of a per-frame file for one of the allowed row ``widths`` (a leading frame-number or
    time column is dropped), and the frame rate when the file states one."""
    suffix = path.suffix.lower()
    if not path.is_file():
        raise InputError(path, None, "an existing .npz, .csv or .json file", "no such file")
    fps = None
    if suffix == ".npz":
        arr, fps = _npz_array(path, widths, key)
    elif suffix == ".csv":
        arr = _csv_rows(path)
    elif suffix == ".json":
        try:
            frames, fps = _json_frames(json.loads(path.read_text(encoding="utf-8")), path)
            arr = np.array([_json_row(f) for f in frames], dtype=float)
        except InputError:
            raise
        except (ValueError, KeyError, TypeError) as e:
            raise InputError(
                path, None, "a JSON list of frames (see `quasisim convert landmarks --help`)", str(e)[:80]
            ) from None
    else:
        raise InputError(path, None, "a file ending in .npz, .csv or .json", f"'{suffix}'")
    if arr.ndim == 0 or len(arr) == 0:
        raise InputError(path, key, "one row of numbers per frame", "no frames")
    arr = arr.reshape(len(arr), -1)
    want = " or ".join(str(w) for w in widths)
    if arr.shape[1] - 1 in widths and arr.shape[1] not in widths:
        if len(arr) > 1 and not (np.diff(arr[:, 0]) > 0).all():  # e.g. a trailing column, not a leading one
            raise InputError(
                path, key, f"{want} numbers per frame, or one more in a leading, increasing frame number or time "
                "column", f"{arr.shape[1]} numbers whose first column does not increase",
            )  # fmt: skip
        arr = arr[:, 1:]  # frame number or time stamp
    if arr.shape[1] not in widths:
        raise InputError(path, key, f"{want} numbers per frame", f"{arr.shape[1]}")
    if not np.isfinite(arr).all():
        raise InputError(
            path, key, "finite numbers", f"NaN or inf at frame {int(np.argwhere(~np.isfinite(arr))[0][0])}"
        )
    return arr, fps


def _npz_array(path: Path, widths: tuple[int, ...], key: str | None) -> tuple[np.ndarray, float | None]:
    with open_npz(path, "numeric", "npz file") as z:
        fps = npz_number(z, "fps", path) if "fps" in z.files else None
        if key is None:
            arrays = {k: npz_member(z, k, path) for k in z.files}
            fits = [k for k, a in arrays.items() if a.ndim >= 2 and int(np.prod(a.shape[1:])) in widths]
            if len(fits) != 1:
                raise InputError(
                    path,
                    None,
                    f"one array of {' or '.join(map(str, widths))} numbers per frame (or pass --key)",
                    f"arrays {z.files}",
                )
            key = fits[0]
        if key not in z.files:
            raise InputError(path, key, "an array under this key", f"keys {z.files}")
        a = npz_member(z, key, path)
        if a.dtype.kind not in "fiu":
            raise InputError(path, key, "a numeric array", f"dtype {a.dtype}")
        return np.asarray(a, dtype=float), fps


# ---- the conversion -------------------------------------------------------------------------------


def read_landmarks(path: Path, opts: ConvertOptions) -> tuple[np.ndarray, float | None]:
    """(T, 21, 3) landmarks in m, z up; and the file's frame rate, if it has one."""
    rows, fps = read_rows(path, (N_KEYPOINTS * 3,), opts.key)
    pts = rows.reshape(-1, N_KEYPOINTS, 3) * UNITS[opts.units] @ UP_AXES[opts.up].T
    size = float(np.median(np.linalg.norm(pts[:, 9] - pts[:, 0], axis=-1)))
    if not HAND_SIZE[0] <= size <= HAND_SIZE[1]:
        raise InputError(
            path, "landmarks", f"a hand {HAND_SIZE[0] * 100:g}-{HAND_SIZE[1] * 100:g} cm from wrist (0) to middle knuckle (9) "
            f"in --units {opts.units} (check the units and the MediaPipe keypoint order)", f"{size * 100:.3g} cm",
        )  # fmt: skip
    return pts, fps


def rigid_transforms(mats: np.ndarray, path: Path, field: str = "pose") -> tuple[np.ndarray, np.ndarray]:
    """Translations (T, 3) and rotations (T, 3, 3) of 4x4 poses (T, 4, 4), checked to be rigid transforms."""
    pos, rot = mats[:, :3, 3], mats[:, :3, :3]
    not_rotation = np.abs(rot @ rot.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2))
    not_last_row = np.abs(mats[:, 3] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=1)
    bad = (not_rotation > 0.01) | (not_last_row > 0.01) | (np.linalg.det(rot) < 0)
    if bad.any():
        t = int(np.argmax(bad))
        raise InputError(
            path, field, "4x4 rigid transforms (a rotation, det +1, then a translation; last row 0 0 0 1)",
            f"{mats[t].round(3).tolist()} at frame {t}",
        )  # fmt: skip
    return pos, rot


def read_poses(path: Path, opts: ConvertOptions) -> tuple[np.ndarray, np.ndarray]:
    """Object positions (T, 3) in m and unit quaternions (T, 4) w x y z, z up."""
    if path.suffix.lower() == ".npz":
        with open_npz(path, "numeric", "npz file") as z:
            if {"object_pos", "object_quat"} <= set(z.files):
                pq = npz_array(z, "object_pos", path, ("T", 3)), npz_array(z, "object_quat", path, ("T", 4))
                if len(pq[0]) != len(pq[1]):
                    raise InputError(path, "object_quat", f"{len(pq[0])} frames (as object_pos)", f"{len(pq[1])}")
                rows = np.concatenate(pq, axis=1)
            else:
                rows = read_rows(path, (7, 16))[0]
    else:
        rows = read_rows(path, (7, 16))[0]
    if rows.shape[1] == 16:
        pos, rot = rigid_transforms(rows.reshape(-1, 4, 4), path)
    else:
        q = rows[:, 3:7] if opts.quat_order == "wxyz" else rows[:, [6, 3, 4, 5]]
        norm = np.linalg.norm(q, axis=1)
        if np.any(np.abs(norm - 1.0) > 0.01):
            t = int(np.argmax(np.abs(norm - 1.0)))
            raise InputError(
                path, "quaternion", f"unit quaternions in {opts.quat_order} order", f"|q| = {norm[t]:.3g} at frame {t}"
            )
        pos, rot = rows[:, :3], np_quat_to_mat(q / norm[:, None])
    up = UP_AXES[opts.up]
    return pos * UNITS[opts.units] @ up.T, sign_continuous(np_mat_to_quat(up @ rot))


def convert_landmarks(
    landmarks: str | Path, poses: str | Path, mesh: str | Path, out: str | Path, opts: ConvertOptions,
    overwrite: bool = False,
) -> Path:  # fmt: skip
    """Write ``out`` (a ``quasisim-demo-v1`` npz) and ``meshes/<name>.obj`` beside it; returns ``out``.

    Every check (inputs, options, the clip they make, its mesh) runs before anything is written; an existing
    ``out`` or mesh is replaced only with ``overwrite``.
    """
    import tempfile

    import trimesh

    from quasisim.assets.object import load_object
    from quasisim.data.demo import _check_resting

    opts.check()
    landmarks, poses, mesh, out = Path(landmarks), Path(poses), Path(mesh), Path(out)
    if out.suffix != ".npz" or out.is_dir():
        raise InputError(out, "--out", "the .npz file of the clip to write", "a folder" if out.is_dir() else out.name)
    check_out_dir(out.parent)
    joints, file_fps = read_landmarks(landmarks, opts)
    pos, quat = read_poses(poses, opts)
    if len(pos) != len(joints):
        raise InputError(poses, None, f"{len(joints)} frames (as {landmarks.name})", f"{len(pos)}")
    fps = opts.fps if opts.fps is not None else file_fps
    if fps is None:
        raise InputError(landmarks, "fps", "a frame rate in the file or --fps", "none")
    try:
        m = trimesh.load(mesh, force="mesh")
    except Exception as e:  # trimesh raises many kinds (unknown format, damaged file, ...)
        got = " ".join(f"{type(e).__name__}: {e}".split())[:120]
        raise InputError(mesh, None, "a mesh file trimesh can read (.obj, .stl, .ply, ...)", got) from None
    if not isinstance(m, trimesh.Trimesh) or len(m.faces) == 0:
        raise InputError(mesh, None, "a triangle mesh with at least one face", "no triangles")
    m.apply_scale(UNITS[opts.units])  # the object frame keeps its axes: only the world is turned
    name = opts.name or out.stem
    mesh_path = out.parent / "meshes" / f"{name}.obj"
    with tempfile.TemporaryDirectory() as tmp:  # the mesh checked as a demo's mesh is, before anything is written
        m.export(Path(tmp) / mesh_path.name, file_type="obj")
        try:
            vertices = load_object(Path(tmp) / mesh_path.name).vertices
        except InputError as e:
            raise InputError(mesh, e.field, f"{e.expected} (after --units {opts.units})", e.got) from None
    support = opts.support_height
    if support is None:
        support = float((np.asarray(m.vertices) @ np_quat_to_mat(quat[0]).T + pos[0])[:, 2].min())
    demo = Demo(
        name=name, fps=float(fps), right_joints=joints, object_name=mesh.stem, object_mesh_path=mesh_path,
        object_pos=pos, object_quat=quat, support_height=float(support),
        source=f"quasisim convert landmarks {landmarks.name} {poses.name} {mesh.name} ({opts.units}, up {opts.up})",
    )  # fmt: skip
    try:
        validate_arrays(demo, out)
        _check_resting(demo, vertices, out)
    except InputError as e:  # name the input the bad values come from
        raise _named(e, landmarks, poses, opts) from None
    refuse_overwrite(out.parent, (out.name, f"meshes/{mesh_path.name}"), overwrite)
    with atomic_path(mesh_path) as tmp_mesh:
        m.export(tmp_mesh, file_type="obj")
    return save_demo(demo, out)


def _named(e: InputError, landmarks: Path, poses: Path, opts: ConvertOptions) -> InputError:
    """An error of the converted clip's field ``e.field`` as one of the input (file or option) it comes from."""
    if e.field == "fps" and opts.fps is not None:
        return InputError(landmarks, "--fps", e.expected, e.got)
    if e.field == "support_height" and opts.support_height is not None:
        return InputError(poses, "--support-height", e.expected, e.got)
    source = {"right_joints": landmarks, "fps": landmarks, "object_pos": poses, "object_quat": poses}
    return InputError(source.get(e.field or "", poses), e.field, e.expected, e.got)
