"""A dynamic human hand built from a demonstration's own keypoints (stage 1: "a dynamic MANO hand").

Without MANO we build an articulated capsule hand whose palm shape and bone lengths are the medians of
the clip's keypoints of one hand (MediaPipe order, metres; stage 1 builds one per side of a two-hand demo:
from a left hand's keypoints the palm normal below points to the back of the hand, so positive flexion
bends backwards; the joint ranges are symmetric, so the hand reaches the same poses). It is an ordinary MJCF compiled by MuJoCo and
loaded through :func:`quasisim.assets.hand.load_hand`, so everything that takes a robot
:class:`~quasisim.assets.hand.HandModel` (kinematics, point sets, simulators, retargeting) takes it too.

Model (all lengths in metres, all frames parallel to the palm frame at rest):

* root body ``palm`` at the wrist keypoint 0. Palm frame: x from the wrist towards the middle MCP (9),
  z the palm normal ``(J5 - J0) x (J17 - J0)`` made orthogonal to x (the palm side of a right hand, the
  side the fingers flex towards), y = z x x. Keypoints 1, 5, 9, 13, 17 are rigid in this frame: their
  direction is the median over frames of their palm-frame coordinates, their distance from the wrist
  the median bone length.
* per finger (thumb 1-2-3-4, index 5-6-7-8, middle 9-10-11-12, ring 13-14-15-16, little 17-18-19-20)
  three bone bodies ``<finger>1..3``, each at its proximal keypoint, resting straight out along the
  wrist -> base-keypoint direction ``d``. Each has two hinges at its origin, applied in this order:
  ``<finger><k>_flex`` about ``d x z`` (positive = flexion towards the palm side) and
  ``<finger><k>_abd`` about ``flex x d``. Flexion first keeps the only singularity (abduction of
  +-90 deg, outside the range) away from strongly flexed fingers.
* capsules: palm fan (wrist to 1, 5, 9, 13, 17) and knuckle line (5-9-13-17); one tapering capsule per
  bone, the last one ending a radius short of the fingertip keypoint, which lies on its surface.
  Density 1000 kg/m^3; MuJoCo infers masses and inertias from the geoms.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from quasisim.assets.hand import HandConfig, HandModel, KeypointSpec, PointSetConfig, load_hand
from quasisim.files import cache_dir, save_text_atomic
from quasisim.keypoints import KEYPOINT_NAMES

# name: (keypoint chain base..tip, capsule radii per bone (m), flex range (rad), abd range (rad))
FINGERS: dict[str, tuple[tuple[int, int, int, int], tuple[float, float, float], float, float]] = {
    "thumb": ((1, 2, 3, 4), (0.0100, 0.0090, 0.0080), 3.0, 1.5),
    "index": ((5, 6, 7, 8), (0.0085, 0.0078, 0.0070), 2.5, 1.5),
    "middle": ((9, 10, 11, 12), (0.0085, 0.0078, 0.0070), 2.5, 1.5),
    "ring": ((13, 14, 15, 16), (0.0082, 0.0075, 0.0068), 2.5, 1.5),
    "little": ((17, 18, 19, 20), (0.0075, 0.0068, 0.0062), 2.5, 1.5),
}
PALM_RADIUS = 0.011  # m
DENSITY = 1000.0  # kg/m^3
METRIC_KEYPOINTS = (0, 4, 5, 8, 12, 16, 17, 20)  # the paper's 5 tips + 3 wrist/palm points
PALM_KEYPOINTS = (1, 5, 9, 13, 17)
# IK settings (quasisim.method.retarget.RetargetOptions fields) tuned for a tight fit: the human hand can reach every demo pose,
# so the regularisers are tiny
RETARGET_SETTINGS: dict[str, int | float] = {"iters": 250, "lr": 0.02, "smooth": 1e-7, "rest": 1e-9}
# points of every human hand's point set (~1540 at the default 6 mm spacing on GRAB's subject 1): one size for
# every demo, so that stage 1's programs are compiled once (the hand's geometry is passed to them as arrays)
HUMAN_POINTS = 1536


def palm_frames(joints: np.ndarray) -> np.ndarray:
    """Per-frame palm rotations (T, 3, 3) whose columns are the palm x, y, z axes in the world frame."""
    J = np.asarray(joints, dtype=np.float64)
    x = J[:, 9] - J[:, 0]
    x /= np.linalg.norm(x, axis=-1, keepdims=True)
    n = np.cross(J[:, 5] - J[:, 0], J[:, 17] - J[:, 0])
    z = n - np.sum(n * x, axis=-1, keepdims=True) * x
    z /= np.linalg.norm(z, axis=-1, keepdims=True)
    return np.stack([x, np.cross(z, x), z], axis=-1)


def hand_shape(joints: np.ndarray) -> tuple[dict[int, np.ndarray], dict[tuple[int, int], float]]:
    """Median palm shape and bone lengths of ``joints`` (T, 21, 3) m.

    Returns:
        ``(palm, lengths)``: palm-frame positions (3,) m of keypoints 1, 5, 9, 13, 17 (their distance
        from the wrist is the median bone length) and the median length (m) of every finger bone
        ``(parent, child)`` (keypoint indices, as in :data:`quasisim.data.demo.BONES`).
    """
    J = np.asarray(joints, dtype=np.float64)
    if J.ndim != 3 or J.shape[1:] != (21, 3) or len(J) == 0:
        raise ValueError(f"joints must have shape (T, 21, 3) with T >= 1, got {J.shape}")
    R = palm_frames(J)
    local = np.einsum("tji,tkj->tki", R, J - J[:, :1])  # (T, 21, 3) palm-frame coordinates
    lengths: dict[tuple[int, int], float] = {}
    for chain, *_ in FINGERS.values():
        for a, b in zip((0, *chain[:-1]), chain, strict=True):
            lengths[(a, b)] = float(np.median(np.linalg.norm(J[:, b] - J[:, a], axis=-1)))
    palm = {}
    for i in PALM_KEYPOINTS:
        p = np.median(local[:, i], axis=0)
        palm[i] = p * (lengths[(0, i)] / np.linalg.norm(p))
    return palm, lengths


def _v(x: np.ndarray) -> str:
    return " ".join(f"{float(c):.10g}" for c in x)


def human_hand_mjcf(joints: np.ndarray) -> str:
    """MJCF text of a right human hand whose bone lengths and palm shape are the medians of ``joints``.

    Args:
        joints: (T, 21, 3) right-hand keypoints (m), MediaPipe order, any world frame.
    """
    palm, lengths = hand_shape(joints)
    z = np.array([0.0, 0.0, 1.0])
    o = np.zeros(3)
    lines = [
        '<mujoco model="human_hand">',
        '  <compiler angle="radian" autolimits="true"/>',
        f'  <default><geom type="capsule" density="{DENSITY:g}" contype="1" conaffinity="1" '
        'rgba="0.87 0.72 0.62 1"/><joint type="hinge" limited="true"/></default>',
        "  <worldbody>",
        '    <body name="palm">',
    ]
    fan = [(o, palm[i], f"palm_0_{i}") for i in PALM_KEYPOINTS]
    knuckles = [(palm[a], palm[b], f"palm_{a}_{b}") for a, b in ((5, 9), (9, 13), (13, 17))]
    for a, b, name in fan + knuckles:
        lines.append(f'      <geom name="{name}" size="{PALM_RADIUS:g}" fromto="{_v(a)} {_v(b)}"/>')
    for finger, (chain, radii, flex_range, abd_range) in FINGERS.items():
        d = palm[chain[0]] / np.linalg.norm(palm[chain[0]])
        flex = np.cross(d, z)
        flex /= np.linalg.norm(flex)
        abd = np.cross(flex, d)
        pos, indent = palm[chain[0]], "      "
        for k in range(3):
            L, r = lengths[(chain[k], chain[k + 1])], radii[k]
            end = d * (L - r if k == 2 else L)  # the fingertip keypoint lies on the last capsule's surface
            lines += [
                f'{indent}<body name="{finger}{k + 1}" pos="{_v(pos)}">',
                f'{indent}  <joint name="{finger}{k + 1}_flex" axis="{_v(flex)}" range="{-flex_range:g} {flex_range:g}"/>',
                f'{indent}  <joint name="{finger}{k + 1}_abd" axis="{_v(abd)}" range="{-abd_range:g} {abd_range:g}"/>',
                f'{indent}  <geom name="{finger}{k + 1}" size="{r:g}" fromto="{_v(o)} {_v(end)}"/>',
            ]
            pos, indent = d * L, indent + "  "
        lines += ["      " + "  " * k + "</body>" for k in (2, 1, 0)]
    lines += ["    </body>", "  </worldbody>", "</mujoco>", ""]
    return "\n".join(lines)


def _keypoint_specs(joints: np.ndarray) -> tuple[KeypointSpec, ...]:
    """One keypoint per human keypoint: bone origins, the fingertips at the end of the last bones."""
    palm, lengths = hand_shape(joints)
    where: dict[int, tuple[str, tuple[float, float, float]]] = {0: ("palm", (0.0, 0.0, 0.0))}
    for finger, (chain, *_) in FINGERS.items():
        for k in range(3):
            where[chain[k]] = (f"{finger}{k + 1}", (0.0, 0.0, 0.0))
        d = palm[chain[0]] / np.linalg.norm(palm[chain[0]])
        tip = d * lengths[(chain[2], chain[3])]
        where[chain[3]] = (f"{finger}3", (float(tip[0]), float(tip[1]), float(tip[2])))
    return tuple(
        KeypointSpec(
            name=KEYPOINT_NAMES[i], human=i, body=where[i][0], pos=where[i][1], weight=1.0, metric=i in METRIC_KEYPOINTS
        )
        for i in range(21)
    )


def human_hand_path(joints: np.ndarray) -> Path:
    """Write the MJCF of :func:`human_hand_mjcf` into the cache (if absent) and return its path.

    The file name is the sha256 of the content, so an existing file is never rewritten.
    """
    text = human_hand_mjcf(joints)
    key = hashlib.sha256(text.encode()).hexdigest()[:24]
    path = cache_dir() / "human_hand" / f"human_hand_{key}.xml"
    if not (path.is_file() and path.read_text() == text):
        save_text_atomic(path, text)
    return path


def build_human_hand(joints: np.ndarray, name: str = "human", point_seed: int = 0) -> HandModel:
    """The dynamic human hand of ``joints`` (T, 21, 3) m as a :class:`HandModel` (see module docstring).

    The hand config has 21 keypoints (one per human keypoint, weight 1; metric: the wrist, index and
    little MCPs and the 5 tips), the default PD gains, a point set of :data:`HUMAN_POINTS` points (drawn
    with ``point_seed``), and the rigid root fit on human keypoints 0, 5, 9, 13, 17. It is marked ``per_demo``: every human hand has the
    same bodies and joints, so the simulator's programs take its geometry as arrays and serve every demo.
    """
    path = human_hand_path(joints)
    config = HandConfig(
        name=name,
        model=str(path),
        root_body="palm",
        keypoints=_keypoint_specs(joints),
        description=f"human capsule hand with median bone lengths of a demo ({path.name})",
        wrist_fit_human=(0, 5, 9, 13, 17),
        path=str(path),
        points=PointSetConfig(count=HUMAN_POINTS, seed=point_seed),
        per_demo=True,
    )
    config.validate()
    return load_hand(config)
