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
``left_joints``    (T, 21, 3)  m     optional: left-hand keypoints, same conventions (true positions, not mirrored)
=================  ==========  ====  =====================================================
"""

from __future__ import annotations

import hashlib
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from quasisim.errors import InputError
from quasisim.files import npz_array, npz_member, npz_number, npz_str, open_npz, save_npz_atomic
from quasisim.keypoints import BONES, FINGERTIPS, KEYPOINT_NAMES, N_KEYPOINTS  # noqa: F401 (the format's names)

FORMAT = "quasisim-demo-v1"
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
# Plausible ranges (SI units): a demo outside them is refused with a message naming the field.
FPS_RANGE = (1.0, 1000.0)  # Hz
COORD_MAX = 10.0  # m, |coordinate| of any keypoint or object position (the scene is a table top)
SUPPORT_RANGE = (0.01, 5.0)  # m, table-top height above the floor
BONE_RANGE = (0.005, 0.15)  # m, median length over the clip of each bone (GRAB hands: 15-95 mm)
PALM_RATIO = 1.3  # median wrist-to-finger-base length over the longest median finger bone (reordered keypoints: < 1.1)
MIN_HAND_EXTENT = 0.02  # m, wrist to the farthest keypoint in every frame (less: a collapsed skeleton)
SIDES = ("right", "left")  # the demo's hands, in the order of every concatenation over hands
HAND_OBJECT_MAX = 1.0  # m, the hand (keypoint mean) must come this close to the object origin at some frame
MAX_SPEED = 15.0  # m/s, any hand keypoint or the object origin between two frames (GRAB, ARCTIC: < 3.5 m/s)
REST_GAP = (-0.01, 0.2)  # m, the object's lowest point at frame 0 relative to the table top (GRAB, ARCTIC: 0)
LONG_CLIP = 1500  # frames; longer clips get a warning with an estimate of time and memory


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
        left_joints: (T, 21, 3) left-hand keypoints (m; true positions, not mirrored), or None (one hand).
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
    left_joints: np.ndarray | None = None

    @property
    def sides(self) -> tuple[str, ...]:
        """The demo's hands: ``("right",)`` or ``("right", "left")``."""
        return SIDES if self.left_joints is not None else SIDES[:1]

    @property
    def human_joints(self) -> np.ndarray:
        """(T, 21 H, 3) keypoints of all H hands, ``[right_joints, left_joints]`` (left indices 21..41)."""
        if self.left_joints is None:
            return self.right_joints
        return np.concatenate([self.right_joints, self.left_joints], axis=1)

    def joints_of(self, side: str) -> np.ndarray:
        """(T, 21, 3) the keypoints of the ``side`` hand."""
        j = self.right_joints if side == "right" else self.left_joints if side == "left" else None
        if j is None:
            raise ValueError(f"demo {self.name} has no {side} hand")
        return j

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
            left_joints=None if self.left_joints is None else self.left_joints[start:stop],
        )
        validate_arrays(d, self.path)
        return d


def validate_arrays(demo: Demo, path: str | Path | None) -> None:
    """Check shapes, finiteness, frame counts, quaternion norms and plausible scales; raise :class:`InputError`."""
    T = demo.right_joints.shape[0]
    if demo.right_joints.shape != (T, N_KEYPOINTS, 3):
        raise InputError(path, "right_joints", f"shape (T, {N_KEYPOINTS}, 3)", f"{demo.right_joints.shape}")
    if T < 2:
        raise InputError(path, "right_joints", "at least 2 frames", f"{T} frame(s)")
    if demo.left_joints is not None and demo.left_joints.shape != (T, N_KEYPOINTS, 3):
        raise InputError(
            path, "left_joints", f"shape ({T}, {N_KEYPOINTS}, 3) (same T as right_joints)", f"{demo.left_joints.shape}"
        )
    for key, arr, tail in (("object_pos", demo.object_pos, (3,)), ("object_quat", demo.object_quat, (4,))):
        if arr.shape != (T, *tail):
            raise InputError(path, key, f"shape ({T}, {tail[0]}) (same T as right_joints)", f"{arr.shape}")
    for key, arr in (
        *_hand_arrays(demo),
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
    if not FPS_RANGE[0] <= demo.fps <= FPS_RANGE[1]:
        raise InputError(path, "fps", f"a frame rate in [{FPS_RANGE[0]:g}, {FPS_RANGE[1]:g}] Hz", f"{demo.fps:g}")
    if not SUPPORT_RANGE[0] <= demo.support_height <= SUPPORT_RANGE[1]:
        lo, hi = SUPPORT_RANGE
        raise InputError(
            path, "support_height", f"a table-top height in [{lo:g}, {hi:g}] m", f"{demo.support_height:g}"
        )
    validate_scales(demo, path)


def _hand_arrays(demo: Demo) -> list[tuple[str, np.ndarray]]:
    """(field name, (T, 21, 3) keypoints) of each of the demo's hands."""
    return [(f"{side}_joints", demo.joints_of(side)) for side in demo.sides]


def validate_scales(demo: Demo, path: str | Path | None) -> None:
    """Refuse coordinates far from a table top, a hand skeleton that is not a human hand's of its side
    (collapsed keypoints, bones far from human lengths, e.g. centimetres stored as metres, a mirrored hand)
    and a hand that never comes near the object."""
    for key, arr in (*_hand_arrays(demo), ("object_pos", demo.object_pos)):
        big = np.abs(arr).reshape(len(arr), -1).max(axis=1)
        if (big > COORD_MAX).any():
            t = int(np.argmax(big > COORD_MAX))
            raise InputError(
                path, key, f"coordinates within +-{COORD_MAX:g} m (metres)", f"{big[t]:.3g} m at frame {t}"
            )
    for side in demo.sides:
        _validate_hand(demo.joints_of(side), side, demo.object_pos, path)
    for key, arr in (*_hand_arrays(demo), ("object_pos", demo.object_pos)):  # a jump: a tracking glitch or wrong fps
        speed = np.linalg.norm(np.diff(arr, axis=0), axis=-1).reshape(len(arr) - 1, -1).max(axis=1) * demo.fps
        if (speed > MAX_SPEED).any():
            t = int(np.argmax(speed > MAX_SPEED))
            raise InputError(
                path, key, f"motion below {MAX_SPEED:g} m/s between frames at {demo.fps:g} fps (a jump or a wrong fps?)",
                f"{speed[t]:.3g} m/s from frame {t} to {t + 1}",
            )  # fmt: skip


def _validate_hand(j: np.ndarray, side: str, object_pos: np.ndarray, path: str | Path | None) -> None:
    """Check one hand's keypoints ``j`` (T, 21, 3) (field ``<side>_joints``): a human hand skeleton of that
    side in MediaPipe order that comes within :data:`HAND_OBJECT_MAX` of ``object_pos`` (T, 3) at some frame."""
    key = f"{side}_joints"
    bones = np.stack([np.linalg.norm(j[:, b] - j[:, a], axis=-1) for a, b in BONES], axis=1)
    med = np.median(bones, axis=0)
    lo, hi = BONE_RANGE
    for k in np.flatnonzero((med < lo) | (med > hi)):
        a, b = BONES[k]
        raise InputError(
            path, key, f"a human hand skeleton (median bone lengths {lo * 1e3:g}-{hi * 1e3:g} mm)",
            f"bone {KEYPOINT_NAMES[a]}-{KEYPOINT_NAMES[b]} {med[k] * 1e3:.3g} mm",
        )  # fmt: skip
    palm = np.mean([med[BONES.index((0, k))] for k in (5, 9, 13, 17)])
    finger = max(med[k] for k, (a, _) in enumerate(BONES) if a != 0)
    if palm < PALM_RATIO * finger:
        raise InputError(
            path, key, f"keypoints in MediaPipe order (wrist to finger bases > {PALM_RATIO:g} x the longest "
            "finger bone; GRAB and ARCTIC hands: 2.3-2.5 x)", f"{palm / finger:.2f} x (another keypoint order?)",
        )  # fmt: skip
    extent = np.linalg.norm(j - j[:, :1], axis=-1).max(axis=1)
    if (extent < MIN_HAND_EXTENT).any():
        t = int(np.argmax(extent < MIN_HAND_EXTENT))
        raise InputError(
            path, key, f"keypoints spread over at least {MIN_HAND_EXTENT * 1e3:g} mm in every frame",
            f"a collapsed skeleton at frame {t} ({extent[t] * 1e3:.3g} mm)",
        )  # fmt: skip
    # a right hand: the thumb's MCP lies on the palm side of the plane wrist, index MCP, little MCP (every
    # frame of every GRAB and ARCTIC clip); a left hand has it on the other side, and so has a mirrored one
    palm = np.cross(j[:, 5] - j[:, 0], j[:, 17] - j[:, 0])
    sign = 1.0 if side == "right" else -1.0
    ok = sign * np.einsum("ti,ti->t", palm, j[:, 2] - j[:, 0]) > 0
    if ok.mean() < 0.5:
        other = "left" if side == "right" else "right"
        raise InputError(
            path, key, f"a {side} hand (thumb on the palm side; true positions, not mirrored)",
            f"a {other} or mirrored hand in {100 * (1 - ok.mean()):.0f}% of the frames",
        )  # fmt: skip
    gap = np.linalg.norm(j.mean(axis=1) - object_pos, axis=-1)
    if gap.min() > HAND_OBJECT_MAX:
        raise InputError(
            path, "object_pos", f"the object within {HAND_OBJECT_MAX:g} m of the {side} hand at some frame",
            f"{gap.min():.3g} m at the closest frame",
        )  # fmt: skip


# what every command costs whatever the clip's length (start-up, compiling, the scene): the constant term of
# the clip-length warning's estimate (docs/history "Commands on long clips")
BASE_S, BASE_MB = 15.0, 600.0


def warn_long_clip(demo: Demo, s_per_frame: float, mb_per_frame: float, what: str) -> None:
    """One line on stderr for a clip longer than :data:`LONG_CLIP` frames: an estimate of ``what``'s wall
    time and peak memory, ``BASE + T * per_frame`` for ``T`` frames (both linear in the frames)."""
    T = demo.n_frames
    if T > LONG_CLIP:
        minutes = (BASE_S + T * s_per_frame) / 60
        print(
            f"warning: {demo.name}: {T} frames (more than {LONG_CLIP}); {what} will take about "
            f"{minutes:.{0 if minutes >= 10 else 1}f} min and {(BASE_MB + T * mb_per_frame) / 1024:.1f} GB of memory",
            file=sys.stderr,
        )


def content_hash(demo: Demo) -> str:
    """16 hex digits of sha256 over what defines the demo: keypoints, object poses, fps, table height and the
    mesh file's bytes (not its file name or compression, so a rewritten copy hashes the same)."""
    h = hashlib.sha256()
    for a in (demo.right_joints, demo.object_pos, demo.object_quat, np.array([demo.fps, demo.support_height])):
        h.update(np.ascontiguousarray(a, np.float64).tobytes())
    if demo.left_joints is not None:  # after the one-hand content, so one-hand hashes stay as they were
        h.update(b"left_joints" + np.ascontiguousarray(demo.left_joints, np.float64).tobytes())
    h.update(demo.object_mesh_path.read_bytes())
    return h.hexdigest()[:16]


def _mesh_path(path: Path, mesh_name: str) -> Path:
    """The mesh file named by ``object_mesh``, confined to the demo's ``meshes/`` folder."""
    rel = Path(mesh_name)
    if not mesh_name.strip() or rel.is_absolute() or ".." in rel.parts:
        raise InputError(path, "object_mesh", "a file name inside the demo's meshes/ folder", repr(mesh_name))
    mesh_path = (path.parent / "meshes").resolve() / rel
    if not mesh_path.is_file():
        raise InputError(path, "object_mesh", f"a mesh file at {mesh_path}", "no such file")
    return mesh_path


def _one_line(text: str, key: str, path: Path) -> str:
    """A name field: non-empty, one line (it heads summaries and warnings)."""
    if not text.strip() or not text.isprintable():
        raise InputError(path, key, "a non-empty name on one line", repr(text)[:80])
    return text


def load_demo(path: str | Path, check_mesh: bool = True) -> Demo:
    """Read and validate a ``quasisim-demo-v1`` file (and its object mesh unless ``check_mesh`` is false).

    Raises:
        InputError: on any problem, naming the file, the field and what was expected.
    """
    path = Path(path)
    with open_npz(path, FORMAT, ".npz file") as z:
        missing = [k for k in REQUIRED_KEYS if k not in z.files]
        if "format" in missing:
            raise InputError(path, "format", f"the key 'format' = '{FORMAT}'", "no such key")
        fmt = npz_str(z, "format", path)
        if fmt != FORMAT:
            raise InputError(path, "format", f"'{FORMAT}'", f"'{fmt}'")
        if missing:
            raise InputError(
                path, missing[0], "a key present in every demo file", f"missing (keys: {', '.join(z.files)})"
            )
        name = _one_line(npz_str(z, "name", path), "name", path)
        object_name = _one_line(npz_str(z, "object_name", path), "object_name", path)
        mesh_name = npz_str(z, "object_mesh", path)
        source = npz_str(z, "source", path) if "source" in z.files else ""
        fps = npz_number(z, "fps", path)
        support = npz_number(z, "support_height", path)
        joints = npz_array(z, "right_joints", path, ("T", N_KEYPOINTS, 3))
        opos = npz_array(z, "object_pos", path, ("T", 3))
        oquat = npz_array(z, "object_quat", path, ("T", 4))
        left = npz_array(z, "left_joints", path, ("T", N_KEYPOINTS, 3)) if "left_joints" in z.files else None
        for k in z.files:  # every member must be readable (a damaged or pickled extra is refused too)
            npz_member(z, k, path)
    mesh_path = _mesh_path(path, mesh_name)
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
        left_joints=left,
    )
    validate_arrays(demo, path)
    if check_mesh:
        from quasisim.assets.object import load_object  # heavy imports (trimesh, JAX): only when a demo is read

        obj = load_object(mesh_path, name=object_name)  # readable, watertight, plausible size; cached for later use
        _check_resting(demo, obj.vertices, path)
    return demo


def _check_resting(demo: Demo, vertices: np.ndarray, path: Path) -> None:
    """The object starts on the table: its lowest point at frame 0 near ``support_height`` (not inside it)."""
    from quasisim.rotations import np_quat_to_mat

    low = float((vertices @ np_quat_to_mat(demo.object_quat[0]).T + demo.object_pos[0])[:, 2].min())
    gap = low - demo.support_height
    if not REST_GAP[0] <= gap <= REST_GAP[1]:
        raise InputError(
            path, "support_height", f"the table top under the object at frame 0 (its lowest point {low:.3f} m, "
            f"{-REST_GAP[0] * 100:g} cm below to {REST_GAP[1] * 100:g} cm above)", f"{demo.support_height:.3f} m",
        )  # fmt: skip


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
        **({} if demo.left_joints is None else {"left_joints": np.asarray(demo.left_joints, dtype=np.float32)}),
    )
