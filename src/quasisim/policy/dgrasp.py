"""DGrasp-Base's guide: the demonstration as the original DGrasp sees it (the paper's baselines, supplement
"DGrasp-Base").

DGrasp is told one grasp, not a trajectory: the reference grasp is the demo's **first grasp frame** ``g``, the
first frame where at least two fingertips touch the object and their contacts form a force closure. After the
grasp only the root is guided: the grasp is carried along the object's path. :func:`grasp_guide` writes both into
a demo of its own (the *guide*) whose hand keypoints are

    x'_t = x_t                                   for t < g   (the approach, as demonstrated)
    x'_t = p_t + R_t R_g^T (x_g - p_g)           for t >= g  (the grasp of frame g, rigid with the object)

with ``p_t, R_t`` the demo object's pose. The policy trains and is observed against the guide: the reference PD
targets are the guide's kinematic retarget, the keypoint and contact rewards its keypoints; the object's path
and every judgement (success, metrics) stay the demo's own.

**Force closure** of two frictional point contacts (Nguyen 1988): contacts ``c_i, c_j`` with inward surface
normals ``n_i, n_j`` (the object's faces nearest each fingertip) form a force closure iff the line between them
lies in both friction cones, ``angle(n_i, c_j - c_i) <= atan(mu)`` and ``angle(n_j, c_i - c_j) <= atan(mu)``.
A frame with such an antipodal pair among its touching fingertips is a grasp (sufficient for closure with more
contacts too; the test the paper names asks for any closure, which a pair of three or more contacts may reach
without an antipodal pair: our frame can come later than theirs). Where no frame of a hand has one, the first
frame with two touching fingertips is taken, then the first with one; :func:`first_grasp` says which rule
decided.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from quasisim.data.demo import Demo
from quasisim.keypoints import FINGERTIPS

RULES = ("force closure", "two contacts", "one contact", "no contact")  # first_grasp's rules, in order


def _rotations(quat: np.ndarray) -> np.ndarray:
    """(T, 3, 3) from (T, 4) w x y z."""
    from scipy.spatial.transform import Rotation

    q = np.asarray(quat, np.float64)
    return Rotation.from_quat(np.concatenate([q[:, 1:], q[:, :1]], axis=1)).as_matrix()


def tip_contacts(demo: Demo, side: str, mesh: Any, radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ``side`` hand's fingertips against the object, in the object's frame: ``touch`` (T, 5) within
    ``radius`` m of the surface or inside it, ``points`` (T, 5, 3) the nearest surface points (m), ``normals``
    (T, 5, 3) the inward unit normals of the faces they lie on."""
    tips = demo.joints_of(side)[:, list(FINGERTIPS)]  # (T, 5, 3)
    R = _rotations(demo.object_quat)
    local = np.einsum("tji,tfj->tfi", R, tips - demo.object_pos[:, None]).reshape(-1, 3)
    points, dist, face = mesh.nearest.on_surface(local)
    touch = (dist < radius) | mesh.contains(local)
    shape = tips.shape
    return touch.reshape(shape[:2]), points.reshape(shape), -mesh.face_normals[face].reshape(shape)


def force_closure(points: np.ndarray, normals: np.ndarray, mu: float) -> bool:
    """Whether two of the contacts ``points`` (N, 3) with inward unit ``normals`` (N, 3) form a frictional
    force closure (an antipodal pair within the friction cones of coefficient ``mu``)."""
    cos_cone = np.cos(np.arctan(mu))
    for i in range(len(points)):
        for j in range(i + 1, len(points)):
            d = points[j] - points[i]
            n = np.linalg.norm(d)
            if n < 1e-9:
                continue
            if normals[i] @ d / n >= cos_cone and normals[j] @ -d / n >= cos_cone:
                return True
    return False


def first_grasp(touch: np.ndarray, points: np.ndarray, normals: np.ndarray, mu: float) -> tuple[int, str]:
    """The first grasp frame of one hand (``tip_contacts``' arrays) and the rule of :data:`RULES` that found it
    (frame 0 where no fingertip ever touches)."""
    count = touch.sum(axis=1)
    for t in np.flatnonzero(count >= 2):
        if force_closure(points[t, touch[t]], normals[t, touch[t]], mu):
            return int(t), RULES[0]
    for k, rule in ((2, RULES[1]), (1, RULES[2])):
        hit = np.flatnonzero(count >= k)
        if len(hit):
            return int(hit[0]), rule
    return 0, RULES[3]


def carry_grasp(joints: np.ndarray, obj_pos: np.ndarray, obj_rot: np.ndarray, g: int) -> np.ndarray:
    """(T, 21, 3) ``joints`` up to frame ``g``, then frame ``g``'s hand carried rigidly with the object
    (``obj_pos`` (T, 3), ``obj_rot`` (T, 3, 3))."""
    local = (joints[g] - obj_pos[g]) @ obj_rot[g]  # R_g^T (x_g - p_g), row vectors
    out = joints.copy()
    out[g:] = obj_pos[g:, None] + np.einsum("tij,kj->tki", obj_rot[g:], local)
    return out


def grasp_guide(demo: Demo, radius: float, mu: float) -> tuple[Demo, dict[str, Any]]:
    """DGrasp-Base's guide of ``demo`` (module docstring) and, per hand, its grasp frame and the rule that chose
    it. ``radius``: a fingertip within this distance (m) of the surface touches; ``mu``: the friction
    coefficient of the closure test."""
    from quasisim.assets.object import quiet_trimesh
    from quasisim.targets.build import load_object_for

    with quiet_trimesh():
        mesh = load_object_for(demo).to_trimesh()
    R = _rotations(demo.object_quat)
    hands, info = {}, {}
    for side in demo.sides:
        g, rule = first_grasp(*tip_contacts(demo, side, mesh, radius), mu)
        hands[f"{side}_joints"] = carry_grasp(demo.joints_of(side), demo.object_pos, R, g)
        info[side] = {"grasp_frame": g, "rule": rule}
    guide = dataclasses.replace(demo, source=f"DGrasp-Base guide of {demo.name}", path=None, **hands)
    return guide, info
