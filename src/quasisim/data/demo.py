"""Human hand-object demonstrations in the ``quasisim-demo-v1`` npz format: reader, writer, validator.

One clip per ``.npz`` (see ``docs/demo_format.md``):

=================  ==========  ====  =====================================================
key                shape       unit  meaning
=================  ==========  ====  =====================================================
``format``         () str            always ``"quasisim-demo-v1"``
``name``           () str            clip name
``fps``            ()          Hz    frame rate
``right_joints``   (T, 21, 3)  m     right-hand keypoints, MediaPipe order, world frame, z up
``object_name``    () str            object name
``object_mesh``    () str            mesh file name inside the sibling folder ``meshes/``
``object_pos``     (T, 3)      m     object frame origin in the world
``object_quat``    (T, 4)            object orientation, unit quaternion w, x, y, z
``support_height`` ()          m     z of the table top under the object
=================  ==========  ====  =====================================================
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from quasisim.errors import InputError
from quasisim.files import open_npz, save_npz_atomic

FORMAT = "quasisim-demo-v1"
N_KEYPOINTS = 21
FINGERTIPS = (4, 8, 12, 16, 20)
KEYPOINT_NAMES = (
    "wrist",
    "thumb_cmc", "thumb_mcp", "thumb_ip", "thumb_tip",
    "index_mcp", "index_pip", "index_dip", "index_tip",
    "middle_mcp", "middle_pip", "middle_dip", "middle_tip",
    "ring_mcp", "ring_pip", "ring_dip", "ring_tip",
    "little_mcp", "little_pip", "little_dip", "little_tip",
)  # fmt: skip
# Bones of the human hand skeleton as (parent, child) keypoint pairs.
BONES = tuple(
    (a, b)
    for chain in ((0, 1, 2, 3, 4), (0, 5, 6, 7, 8), (0, 9, 10, 11, 12), (0, 13, 14, 15, 16), (0, 17, 18, 19, 20))
    for a, b in itertools.pairwise(chain)
)
REQUIRED_KEYS = (
    "format",
    "name",
    "fps",
    "right_joints",
    "object_name",
    "object_mesh",
    "object_pos",
    "object_quat",
    "support_height",
)
QUAT_TOL = 1e-3


@dataclass(frozen=True, eq=False)
class Demo:
    """A validated demonstration. Arrays are float64; quaternions are w, x, y, z.

    Attributes:
        name: clip name.
        fps: frame rate (Hz).
        right_joints: (T, 21, 3) right-hand keypoints (m).
        object_name: object name.
        object_mesh_path: absolute path of the object mesh.
        object_pos: (T, 3) object origin (m).
        object_quat: (T, 4) object orientation, unit, sign-continuous.
        support_height: table-top height (m).
        source: free-form provenance string.
        path: file this demo was read from, if any.
    """

    name: str
    fps: float
    right_joints: np.ndarray
    object_name: str
    object_mesh_path: Path
    object_pos: np.ndarray
    object_quat: np.ndarray
    support_height: float
    source: str = ""
    path: Path | None = None
    extras: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        return int(self.right_joints.shape[0])

    @property
    def dt(self) -> float:
        return 1.0 / self.fps

    def slice(self, start: int, stop: int) -> Demo:
        """Frames ``[start, stop)`` as a new demo (validated)."""
        d = Demo(
            name=self.name,
            fps=self.fps,
            right_joints=self.right_joints[start:stop],
            object_name=self.object_name,
            object_mesh_path=self.object_mesh_path,
            object_pos=self.object_pos[start:stop],
            object_quat=self.object_quat[start:stop],
            support_height=self.support_height,
            source=self.source,
            path=self.path,
        )
        validate_arrays(d, self.path)
        return d


def _str_field(z: np.lib.npyio.NpzFile, key: str, path: Path) -> str:
    a = z[key]
    if a.shape != () or a.dtype.kind not in "US":
        raise InputError(path, key, "a 0-d string array", f"dtype {a.dtype} shape {a.shape}")
    return str(a)


def _scalar_field(z: np.lib.npyio.NpzFile, key: str, path: Path) -> float:
    a = z[key]
    if a.shape != () or a.dtype.kind not in "fiu":
        raise InputError(path, key, "a 0-d number", f"dtype {a.dtype} shape {a.shape}")
    v = float(a)
    if not np.isfinite(v):
        raise InputError(path, key, "a finite number", str(v))
    return v


def _array_field(z: np.lib.npyio.NpzFile, key: str, path: Path, tail: tuple[int, ...]) -> np.ndarray:
    a = z[key]
    want = "(T, " + ", ".join(str(t) for t in tail) + ")"
    if a.dtype.kind not in "fiu":
        raise InputError(path, key, f"a numeric array of shape {want}", f"dtype {a.dtype}")
    if a.ndim != 1 + len(tail) or tuple(a.shape[1:]) != tail:
        raise InputError(path, key, f"shape {want}", f"shape {tuple(a.shape)}")
    return np.asarray(a, dtype=np.float64)


def validate_arrays(demo: Demo, path: str | Path | None) -> None:
    """Check shapes, finiteness, frame counts and quaternion norms; raise :class:`InputError`."""
    T = demo.right_joints.shape[0]
    if demo.right_joints.shape != (T, N_KEYPOINTS, 3):
        raise InputError(path, "right_joints", f"shape (T, {N_KEYPOINTS}, 3)", f"{demo.right_joints.shape}")
    if T < 2:
        raise InputError(path, "right_joints", "at least 2 frames", f"{T} frame(s)")
    for key, arr, tail in (("object_pos", demo.object_pos, (3,)), ("object_quat", demo.object_quat, (4,))):
        if arr.shape != (T, *tail):
            raise InputError(path, key, f"shape ({T}, {tail[0]}) (same T as right_joints)", f"{arr.shape}")
    for key, arr in (
        ("right_joints", demo.right_joints),
        ("object_pos", demo.object_pos),
        ("object_quat", demo.object_quat),
    ):
        bad = ~np.isfinite(arr)
        if bad.any():
            frame = int(np.argwhere(bad)[0][0])
            raise InputError(path, key, "finite values", f"NaN or inf at frame {frame}")
    norms = np.linalg.norm(demo.object_quat, axis=-1)
    off = np.abs(norms - 1.0) > QUAT_TOL
    if off.any():
        t = int(np.argmax(off))
        raise InputError(
            path, "object_quat", f"unit quaternions (|q| = 1 +- {QUAT_TOL:g})", f"|q| = {norms[t]:.4g} at frame {t}"
        )
    if not (demo.fps > 0):
        raise InputError(path, "fps", "a positive frame rate", str(demo.fps))
    if not np.isfinite(demo.support_height):
        raise InputError(path, "support_height", "a finite number", str(demo.support_height))


def load_demo(path: str | Path) -> Demo:
    """Read and validate a ``quasisim-demo-v1`` file.

    Raises:
        InputError: on any problem, naming the file, the field and what was expected.
    """
    path = Path(path)
    with open_npz(path, FORMAT, ".npz file") as z:
        missing = [k for k in REQUIRED_KEYS if k not in z.files]
        if "format" in missing:
            raise InputError(path, "format", f"the key 'format' = '{FORMAT}'", "no such key")
        try:
            fmt = _str_field(z, "format", path)
        except ValueError as e:  # object arrays need pickle
            raise InputError(path, "format", "a 0-d string array", f"unreadable ({e})") from None
        if fmt != FORMAT:
            raise InputError(path, "format", f"'{FORMAT}'", f"'{fmt}'")
        if missing:
            raise InputError(
                path, missing[0], "a key present in every demo file", f"missing (keys: {', '.join(z.files)})"
            )
        try:
            name = _str_field(z, "name", path)
            object_name = _str_field(z, "object_name", path)
            mesh_name = _str_field(z, "object_mesh", path)
            source = _str_field(z, "source", path) if "source" in z.files else ""
            fps = _scalar_field(z, "fps", path)
            support = _scalar_field(z, "support_height", path)
            joints = _array_field(z, "right_joints", path, (N_KEYPOINTS, 3))
            opos = _array_field(z, "object_pos", path, (3,))
            oquat = _array_field(z, "object_quat", path, (4,))
        except ValueError as e:
            if isinstance(e, InputError):
                raise
            raise InputError(path, None, "arrays without pickled objects", str(e)) from None
    mesh_path = (path.parent / "meshes" / mesh_name).resolve()
    if not mesh_path.is_file():
        raise InputError(path, "object_mesh", f"a mesh file at {mesh_path}", "no such file")
    demo = Demo(
        name=name,
        fps=fps,
        right_joints=joints,
        object_name=object_name,
        object_mesh_path=mesh_path,
        object_pos=opos,
        object_quat=oquat,
        support_height=support,
        source=source,
        path=path.resolve(),
    )
    validate_arrays(demo, path)
    return demo


def save_demo(demo: Demo, path: str | Path) -> Path:
    """Write ``demo`` to ``path`` atomically; the mesh must already be in ``path``'s sibling ``meshes/``."""
    path = Path(path)
    validate_arrays(demo, path)
    mesh_dir = path.parent / "meshes"
    if demo.object_mesh_path.resolve().parent != mesh_dir.resolve():
        raise InputError(path, "object_mesh", f"the mesh inside {mesh_dir}", str(demo.object_mesh_path))
    q = np.asarray(demo.object_quat, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return save_npz_atomic(
        path,
        format=np.array(FORMAT),
        source=np.array(demo.source),
        name=np.array(demo.name),
        fps=np.array(demo.fps, dtype=np.float32),
        right_joints=np.asarray(demo.right_joints, dtype=np.float32),
        object_name=np.array(demo.object_name),
        object_mesh=np.array(demo.object_mesh_path.name),
        object_pos=np.asarray(demo.object_pos, dtype=np.float32),
        object_quat=q.astype(np.float32),
        support_height=np.array(demo.support_height, dtype=np.float32),
    )
