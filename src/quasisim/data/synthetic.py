"""Synthetic example demonstrations: a kinematic right hand grasps, lifts (and turns) a primitive object.

The examples need no data folder and are written in the ``quasisim-demo-v1`` format (see
:mod:`quasisim.data.demo`): metres, world z up, object pose ``R(q) @ v + pos`` with ``q`` = w, x, y, z.

Each clip follows the structure of the real GRAB clips (60 frames at 20 fps by default): the hand
approaches from ~19 cm away (first third), closes its fingers around the resting object (until half
time), then lifts it by 12 cm (and turns it) while the object moves rigidly with the hand.

The hand is a forward-kinematic skeleton in MediaPipe keypoint order with constant bone lengths taken
from GRAB right hands. Grasps are solved by inverse kinematics on closed-form signed distances: the
grasping fingertip keypoints (pad centres) end :data:`TIP_GAP` from the surface, every other keypoint
stays clear of the object and of the table.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import numpy as np
import trimesh
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from quasisim.data.demo import Demo, save_demo
from quasisim.errors import choice_error
from quasisim.files import atomic_path

EXAMPLES = ("cube_lift", "cylinder_lift_turn")
SUPPORT_HEIGHT = 0.8  # m, table-top height
TIP_GAP = 0.008  # m, fingertip keypoint (pad centre) to object surface during the grasp
CLEARANCE = 0.012  # m, minimum distance of non-tip keypoints to the object / table in the solved grasp
PREGRASP_OPEN = 0.03  # m, fingertips this much further out along the surface normal before closing

# ---- hand model ----------------------------------------------------------------------------------
# Hand frame: origin at the wrist, x towards the middle MCP, y towards the little finger, z out of the
# palm (palm side). The fingers flex towards +z, so n = (J5 - J0) x (J17 - J0) points to the palm side,
# as for a real right hand.
_THUMB_E1 = np.array([0.68, -0.45, 0.52]) / np.linalg.norm([0.68, -0.45, 0.52])
_THUMB_E3 = np.array([-0.10, 0.67, 0.73]) - np.dot([-0.10, 0.67, 0.73], _THUMB_E1) * _THUMB_E1
_THUMB_E3 /= np.linalg.norm(_THUMB_E3)
# name: (keypoint indices base..tip, base position (m), bone lengths (m), e1, e3, rest splay (rad))
_FINGERS = {
    "thumb": ((1, 2, 3, 4), (0.021, -0.027, 0.016), (0.032, 0.028, 0.031), _THUMB_E1, _THUMB_E3, 0.0),
    "index": ((5, 6, 7, 8), (0.084, -0.024, 0.0), (0.034, 0.024, 0.025), (1, 0, 0), (0, 0, 1), -0.08),
    "middle": ((9, 10, 11, 12), (0.093, 0.0, -0.004), (0.035, 0.026, 0.027), (1, 0, 0), (0, 0, 1), 0.0),
    "ring": ((13, 14, 15, 16), (0.083, 0.024, -0.004), (0.032, 0.025, 0.025), (1, 0, 0), (0, 0, 1), 0.08),
    "little": ((17, 18, 19, 20), (0.071, 0.042, 0.0), (0.025, 0.019, 0.022), (1, 0, 0), (0, 0, 1), 0.16),
}  # fmt: skip
_NAMES = tuple(_FINGERS)
# Per-finger parameters q = (splay, base flexion, middle flexion) in rad; the distal joint follows the
# middle one with this ratio.
_COUPLING = {"thumb": 0.9, "index": 0.7, "middle": 0.7, "ring": 0.7, "little": 0.7}
_LO = {"thumb": (-0.8, -0.8, 0.0), "other": (-0.3, -0.2, 0.0)}
_HI = {"thumb": (0.8, 1.2, 1.6), "other": (0.3, 1.6, 1.9)}
_GRASP_PRIOR = np.array([[0.0, 0.3, 0.5]] + [[0.0, 0.6, 0.8]] * 4)  # preferred grasp shape
_REST = np.array([[0.0, 0.1, 0.15], [0.0, 0.15, 0.25], [0.0, 0.15, 0.25], [0.0, 0.2, 0.3], [0.0, 0.25, 0.35]])


def _chain(name: str, q: np.ndarray) -> np.ndarray:
    """(4, 3) keypoints base..tip of one finger in the hand frame (m) for parameters ``q`` (rad)."""
    _, base, lengths, e1, e3, splay0 = _FINGERS[name]
    e1, e3 = np.asarray(e1, float), np.asarray(e3, float)
    e2 = np.cross(e3, e1)
    if name == "thumb":  # q[0] turns the flexion plane about the first bone (opposition)
        d, e3 = e1, np.cos(q[0]) * e3 - np.sin(q[0]) * e2
    else:  # q[0] spreads the finger in the palm plane
        d = np.cos(splay0 + q[0]) * e1 + np.sin(splay0 + q[0]) * e2
    phis = np.cumsum([q[1], q[2], _COUPLING[name] * q[2]])
    pts = [np.asarray(base, float)]
    for L, phi in zip(lengths, phis, strict=True):
        pts.append(pts[-1] + L * (np.cos(phi) * d + np.sin(phi) * e3))
    return np.stack(pts)


def hand_keypoints(q: np.ndarray) -> np.ndarray:
    """(21, 3) keypoints in the hand frame (m) for (5, 3) finger parameters (thumb..little, rad)."""
    out = np.zeros((21, 3))
    for i, name in enumerate(_NAMES):
        out[list(_FINGERS[name][0])] = _chain(name, q[i])
    return out


# ---- objects ------------------------------------------------------------------------------------


def _box_sdf(half: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    def sdf(p: np.ndarray) -> np.ndarray:
        d = np.abs(p) - half
        return np.linalg.norm(np.maximum(d, 0.0), axis=-1) + np.minimum(d.max(axis=-1), 0.0)

    return sdf


def _cylinder_sdf(radius: float, height: float) -> Callable[[np.ndarray], np.ndarray]:
    def sdf(p: np.ndarray) -> np.ndarray:
        d = np.stack([np.linalg.norm(p[..., :2], axis=-1) - radius, np.abs(p[..., 2]) - height / 2], -1)
        return np.linalg.norm(np.maximum(d, 0.0), axis=-1) + np.minimum(d.max(axis=-1), 0.0)

    return sdf


@dataclasses.dataclass(frozen=True)
class _Spec:
    """One example: object, grasp layout (hand frame, m) and the carry motion."""

    object_name: str
    mesh: Callable[[], trimesh.Trimesh]
    sdf: Callable[[np.ndarray], np.ndarray]  # object frame, positive outside (m)
    rest_rot: np.ndarray  # object rotation at rest (world)
    hand_rot: np.ndarray  # hand rotation during the grasp (world)
    centre: tuple[float, float, float]  # object origin in the hand frame (m)
    contacts: dict[str, tuple[float, float, float]]  # rough fingertip contacts in the hand frame (m)
    lift: float = 0.12  # m
    turn_axis: tuple[float, float, float] = (1.0, 0.0, 0.0)  # world axis through the object centre
    turn_deg: float = 0.0


_PALM_DOWN = np.diag([1.0, -1.0, -1.0])  # hand x forward (world +x), palm facing down


def _yawed(yaw: float) -> np.ndarray:
    """Palm-down hand rotation turned by ``yaw`` (rad) about the world vertical."""
    return Rotation.from_rotvec([0.0, 0.0, yaw]).as_matrix() @ _PALM_DOWN


def _spec(name: str) -> _Spec:
    # Layouts found offline by optimising object placement and finger parameters together for
    # opposing contacts with clearance; at run time only the fingers are re-solved (deterministic).
    if name == "cube_lift":  # precision grasp: thumb on the near face, index and middle on the far face
        return _Spec(
            object_name="cube",
            mesh=lambda: trimesh.creation.box(extents=(0.05, 0.05, 0.05)),
            sdf=_box_sdf(np.full(3, 0.025)),
            rest_rot=np.eye(3),
            hand_rot=_yawed(0.086),
            centre=(0.0865, -0.0158, 0.0786),
            contacts={"thumb": (0.0525, -0.0129, 0.0922), "index": (0.1211, -0.0266, 0.063),
                      "middle": (0.1187, 0.0, 0.0661)},
        )  # fmt: skip
    if name == "cylinder_lift_turn":  # lying cylinder, thumb against four fingers; turned 50 deg (roll)
        return _Spec(
            object_name="cylinder",
            mesh=lambda: trimesh.creation.cylinder(radius=0.025, height=0.12, sections=64),
            sdf=_cylinder_sdf(0.025, 0.12),
            rest_rot=Rotation.from_rotvec([np.pi / 2, 0, 0]).as_matrix(),  # axis along world y
            hand_rot=_yawed(0.189),
            centre=(0.0779, 0.0107, 0.0796),
            contacts={"thumb": (0.0515, -0.0133, 0.0924), "index": (0.1148, -0.0262, 0.0645),
                      "middle": (0.1109, 0.0, 0.0667), "ring": (0.1034, 0.0256, 0.0619),
                      "little": (0.0907, 0.0452, 0.0527)},
            turn_deg=50.0,
        )  # fmt: skip
    raise choice_error("example", name, EXAMPLES)


# ---- grasp solving --------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class _Layout:
    """World poses at the grasp: object rest pose and hand pose (rotation maps hand to world frame)."""

    obj_rot: np.ndarray
    obj_pos: np.ndarray
    hand_rot: np.ndarray
    hand_pos: np.ndarray

    def clearance(self, spec: _Spec, p_hand: np.ndarray) -> np.ndarray:
        """Distance (m) of hand-frame points to the object or the table top, whichever is nearer."""
        world = p_hand @ self.hand_rot.T + self.hand_pos
        d_obj = spec.sdf((world - self.obj_pos) @ self.obj_rot)
        return np.minimum(d_obj, world[..., 2] - SUPPORT_HEIGHT)

    def object_distance(self, spec: _Spec, p_hand: np.ndarray) -> np.ndarray:
        """Signed distance (m, positive outside) of hand-frame points to the object."""
        return spec.sdf((p_hand @ self.hand_rot.T + self.hand_pos - self.obj_pos) @ self.obj_rot)

    def normal(self, spec: _Spec, p_hand: np.ndarray, eps: float = 1e-6) -> np.ndarray:
        """Unit outward surface normal of the object at hand-frame point ``p_hand`` (hand frame)."""
        world = p_hand @ self.hand_rot.T + self.hand_pos
        local = (world - self.obj_pos) @ self.obj_rot
        g = np.array([spec.sdf(local + e) - spec.sdf(local - e) for e in np.eye(3) * eps])
        return (self.hand_rot.T @ self.obj_rot @ g) / np.linalg.norm(g)


def _layout(spec: _Spec, mesh: trimesh.Trimesh) -> _Layout:
    """Object resting on the table at (0.45, 0) m, the hand placed around it as in ``spec``."""
    z0 = SUPPORT_HEIGHT - (mesh.vertices @ spec.rest_rot.T)[:, 2].min()
    obj_pos = np.array([0.45, 0.0, z0])
    return _Layout(spec.rest_rot, obj_pos, spec.hand_rot, obj_pos - spec.hand_rot @ np.asarray(spec.centre))


def _solve_finger(spec: _Spec, lay: _Layout, name: str, target: np.ndarray | None) -> np.ndarray:
    """Finger parameters (rad) putting the tip at ``target`` (hand frame, m), keypoints clear of things."""
    key = "thumb" if name == "thumb" else "other"
    prior = _GRASP_PRIOR[_NAMES.index(name)]
    margin = np.array([CLEARANCE, CLEARANCE, TIP_GAP if target is not None else CLEARANCE])

    def residual(q: np.ndarray) -> np.ndarray:
        pts = _chain(name, q)
        r = [0.01 * (q - prior), 3.0 * np.maximum(0.0, margin - lay.clearance(spec, pts[1:]))]
        if target is not None:
            r.append(pts[3] - target)
        return np.concatenate(r)

    q0 = np.clip(prior, _LO[key], _HI[key])
    return least_squares(residual, q0, bounds=(_LO[key], _HI[key]), xtol=1e-12, ftol=1e-12).x


def _grasp(spec: _Spec, lay: _Layout) -> tuple[np.ndarray, np.ndarray]:
    """(pre-grasp, grasp) finger parameters, each (5, 3) rad."""
    pre, grasp = _REST.copy(), _REST.copy()
    for i, name in enumerate(_NAMES):
        if name not in spec.contacts:
            grasp[i] = pre[i] = _solve_finger(spec, lay, name, None)
            continue
        p = np.asarray(spec.contacts[name], float)
        for _ in range(8):  # project the rough contact onto the surface offset by TIP_GAP
            dist = lay.object_distance(spec, p[None])[0]
            p = p - (dist - TIP_GAP) * lay.normal(spec, p)
        grasp[i] = _solve_finger(spec, lay, name, p)
        pre[i] = _solve_finger(spec, lay, name, p + PREGRASP_OPEN * lay.normal(spec, p))
    return pre, grasp


# ---- trajectory -----------------------------------------------------------------------------------


def _min_jerk(t: np.ndarray, t0: float, t1: float) -> np.ndarray:
    """Minimum-jerk blend 0 -> 1 between frames ``t0`` and ``t1`` (zero velocity and acceleration)."""
    u = np.clip((t - t0) / max(t1 - t0, 1e-9), 0.0, 1.0)
    return u**3 * (10.0 - 15.0 * u + 6.0 * u * u)


def make_example(name: str, n_frames: int = 60, fps: float = 20.0, seed: int = 0) -> tuple[Demo, trimesh.Trimesh]:
    """Build the example ``name`` (one of :data:`EXAMPLES`).

    Args:
        name: example name.
        n_frames: number of frames (>= 12); the phases scale with it (approach, close, carry).
        fps: frame rate (Hz); speeds scale with it (60 frames at 20 fps peak below 0.5 m/s).
        seed: 0 gives the canonical layout; any other seed rotates the whole scene about the vertical
            axis and shifts it on the table (rigidly, so contacts and clearances are unchanged).

    Returns:
        ``(demo, mesh)``: the demo (``object_mesh_path`` is the bare file name ``<name>.obj``, to be
        placed in a ``meshes/`` folder, see :func:`write_example`) and the object mesh (object frame, m).
    """
    spec = _spec(name)
    if n_frames < 12:
        raise ValueError(f"n_frames must be >= 12, got {n_frames}")
    mesh = spec.mesh()
    lay = _layout(spec, mesh)
    pre, grasp = _grasp(spec, lay)

    t = np.arange(n_frames, dtype=float)
    t_app, t_grasp, t_end = round(n_frames / 3), round(n_frames / 2), n_frames - 1
    s_app = _min_jerk(t, 0, t_app)[:, None, None]
    s_close = _min_jerk(t, t_app, t_grasp)[:, None, None]
    q = _REST + s_app * (pre - _REST) + s_close * (grasp - pre)

    carry = t_end - t_grasp
    s_lift = _min_jerk(t, t_grasp, t_grasp + (0.7 if spec.turn_deg else 0.9) * carry)
    s_turn = _min_jerk(t, t_grasp + 0.3 * carry, t_end)
    turn = Rotation.from_rotvec(np.outer(s_turn * np.radians(spec.turn_deg), spec.turn_axis)).as_matrix()
    approach = Rotation.from_rotvec(np.outer(1.0 - s_app[:, 0, 0], [0.0, 0.0, -0.35])).as_matrix()
    start_offset = np.array([-0.09, 0.03, 0.16])  # m, hand start relative to its grasp pose
    a = s_app[:, 0, 0]
    lift = np.outer(s_lift, [0.0, 0.0, spec.lift])

    hand_rot = turn @ approach @ lay.hand_rot
    hand_pos = lay.obj_pos + np.einsum("tij,j->ti", turn, lay.hand_pos - lay.obj_pos)
    hand_pos += lift + np.outer(1.0 - a, start_offset)
    obj_rot = turn @ lay.obj_rot
    obj_pos = lay.obj_pos + lift

    if seed:  # rigid scene variation: yaw about the object's rest position and a shift on the table
        rng = np.random.default_rng(seed)
        yaw = Rotation.from_rotvec([0.0, 0.0, rng.uniform(-np.pi, np.pi)]).as_matrix()
        shift = np.array([*rng.uniform(-0.05, 0.05, 2), 0.0])
        hand_pos = lay.obj_pos + shift + (hand_pos - lay.obj_pos) @ yaw.T
        obj_pos = lay.obj_pos + shift + (obj_pos - lay.obj_pos) @ yaw.T
        hand_rot, obj_rot = yaw @ hand_rot, yaw @ obj_rot

    local = np.stack([hand_keypoints(qi) for qi in q])
    joints = np.einsum("tij,tkj->tki", hand_rot, local) + hand_pos[:, None]
    xyzw = Rotation.from_matrix(obj_rot).as_quat()
    quat = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)
    flip = np.cumprod(np.where(np.sum(quat[1:] * quat[:-1], axis=1) < 0, -1.0, 1.0))
    quat[1:] *= flip[:, None]
    demo = Demo(
        name=name,
        fps=float(fps),
        right_joints=joints,
        object_name=spec.object_name,
        object_mesh_path=Path(f"{name}.obj"),
        object_pos=obj_pos,
        object_quat=quat,
        support_height=SUPPORT_HEIGHT,
        source=f"quasisim.data.synthetic:{name} seed={seed}",
    )
    return demo, mesh


def with_mirrored_left(demo: Demo) -> Demo:
    """``demo`` with a left hand: the mirror image of its right hand across the vertical plane through the
    object's first position normal to x (a left hand, true positions: ``left_joints``); for two-hand tests."""
    x0 = float(demo.object_pos[0, 0])
    left = np.asarray(demo.right_joints, np.float64).copy()
    left[..., 0] = 2.0 * x0 - left[..., 0]
    return dataclasses.replace(demo, left_joints=left, name=f"{demo.name}_two_hands")


def write_example(
    name: str, out_dir: str | Path, n_frames: int = 60, fps: float = 20.0, two_hands: bool = False
) -> Path:
    """Write ``out_dir/<name>.npz`` and ``out_dir/meshes/<name>.obj`` atomically; return the npz path.
    ``two_hands``: add the mirror image of the right hand as the left hand (:func:`with_mirrored_left`)."""
    demo, mesh = make_example(name, n_frames=n_frames, fps=fps)
    demo = with_mirrored_left(demo) if two_hands else demo
    name = demo.name
    out_dir = Path(out_dir)
    mesh_path = out_dir / "meshes" / f"{name}.obj"
    with atomic_path(mesh_path) as tmp:
        mesh.export(tmp, file_type="obj")
    return save_demo(dataclasses.replace(demo, object_mesh_path=mesh_path), out_dir / f"{name}.npz")


def write_examples(out_dir: str | Path, names: tuple[str, ...] | list[str] = EXAMPLES) -> list[Path]:
    """:func:`write_example` for each of ``names``; returns the npz paths."""
    return [write_example(n, out_dir) for n in names]
