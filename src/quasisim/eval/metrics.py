"""Tracking metrics of a target rollout against the demonstration (DESIGN section 5, paper "Metrics").

Per sequence of N frames:

* ``R_err_deg``: mean over frames of the angle of ``q_ref^-1 q_sim`` (degrees).
* ``T_err_cm``: mean object translation error (cm).
* ``MPJPE_mm``: mean over frames and metric keypoints of |human keypoint - corresponding robot keypoint| (mm);
  with two hands, over the metric keypoints of both.
* ``CD_mm``: mean over frames of the symmetric Chamfer distance between human and robot hand surface
  points, ``0.5 * (mean_a min_b |a - b| + mean_b min_a |a - b|)`` (mm). Human surface points are sampled
  on capsules around the 20 bones of the keypoint skeleton (radius 8-10 mm; the demo format carries no
  hand mesh); robot surface points on the hand's collision geoms (both hands' surfaces with two hands).
* ``object_motion``: did the simulated object move as the demo's did? The demo's height gain (highest
  frame above the first) and its largest displacement from the start (at frame ``t*``) against the
  rollout's own: the rollout must rise at least half as high as the demo and its displacement at ``t*``
  (from its own start) must be within half the demo's displacement of the demo's. Demo motions under
  2 cm are not required (they are within the strict tolerance).
* ``success``: ``strict``: at every frame the object is within 2 cm and 30 deg of the reference; the paper's
  thresholds ``R_err <= X deg and T_err <= X cm and MPJPE <= X cm`` for X in 10, 15, 20. Every criterion
  also requires ``object_motion``: a run whose object did not move as in the demo succeeds at none.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from quasisim.data.demo import BONES, Demo
from quasisim.limits import (  # noqa: F401 (the limits' names, as the evaluation's users import them)
    MOVE_FRACTION,
    MOVE_MIN_CM,
    STRICT_CM,
    STRICT_DEG,
    ObjectMotion,
    object_errors,
    object_motion,
    within_strict,
)

THRESHOLDS = (10, 15, 20)
METRIC_KEYS = ("R_err_deg", "T_err_cm", "MPJPE_mm", "CD_mm", "object_motion", "success")
SUCCESS_KEYS = ("10deg_10cm", "15deg_15cm", "20deg_20cm", "strict")  # the order of the benchmark tables
PAPER_KEYS = SUCCESS_KEYS[:3]  # the paper's thresholds (mean errors); shown after "strict"


@dataclass(frozen=True, eq=False)
class PerFrame:
    """Per-frame errors (T,): object rotation (deg), translation (cm), MPJPE (mm), Chamfer (mm)."""

    rot_deg: np.ndarray
    trans_cm: np.ndarray
    mpjpe_mm: np.ndarray
    cd_mm: np.ndarray


def success_flags(
    r_deg: float, t_cm: float, mpjpe_mm: float, rot_deg: np.ndarray, trans_cm: np.ndarray, moved: bool
) -> dict[str, bool]:
    """The paper's thresholds on mean errors and ``strict`` (every frame), each requiring ``moved``."""
    out = {f"{x}deg_{x}cm": bool(moved and r_deg <= x and t_cm <= x and mpjpe_mm <= 10.0 * x) for x in THRESHOLDS}
    out["strict"] = bool(moved and within_strict(rot_deg, trans_cm))
    return out


def summarize(pf: PerFrame, motion: ObjectMotion) -> dict[str, Any]:
    """The ``metrics.json`` dictionary from per-frame errors and the object's motion."""
    r, t, m, c = (float(np.mean(a)) for a in (pf.rot_deg, pf.trans_cm, pf.mpjpe_mm, pf.cd_mm))
    return {
        "R_err_deg": r,
        "T_err_cm": t,
        "MPJPE_mm": m,
        "CD_mm": c,
        "object_motion": motion.to_json(),
        "success": success_flags(r, t, m, pf.rot_deg, pf.trans_cm, motion.as_demo),
    }


def mpjpe_per_frame(human: np.ndarray, robot_kp: np.ndarray, human_index: np.ndarray) -> np.ndarray:
    """(T,) mean keypoint error in mm; ``human`` (T, 21 H, 3) (H hands), ``robot_kp`` (T, K, 3), ``human_index`` (K,)."""
    return 1000.0 * np.linalg.norm(human[:, human_index] - robot_kp, axis=-1).mean(axis=1)


@cache
def _capsule_directions(n_per_bone: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    t = rng.uniform(0.0, 1.0, n_per_bone)
    ang = rng.uniform(0.0, 2 * np.pi, n_per_bone)
    sph = rng.normal(size=(n_per_bone, 3))
    sph /= np.linalg.norm(sph, axis=1, keepdims=True)
    return t, ang, sph


def human_surface_points(joints: np.ndarray, n_per_bone: int = 60) -> np.ndarray:
    """(T, P, 3) points on capsules around the bones of the keypoint skeleton ``joints`` (T, 21, 3)."""
    t, ang, sph = _capsule_directions(n_per_bone)
    out = []
    for a, b in BONES:
        r = 0.010 if a == 0 else 0.009 if b <= 4 else 0.008
        pa, pb = joints[:, a], joints[:, b]
        axis = pb - pa
        axis_n = axis / np.maximum(np.linalg.norm(axis, axis=-1, keepdims=True), 1e-9)
        ref = np.where(np.abs(axis_n[:, :1]) < 0.9, np.array([1.0, 0, 0]), np.array([0, 1.0, 0]))
        u = np.cross(axis_n, ref)
        u /= np.linalg.norm(u, axis=-1, keepdims=True)
        v = np.cross(axis_n, u)
        ring = np.cos(ang)[None, :, None] * u[:, None] + np.sin(ang)[None, :, None] * v[:, None]
        out.append(pa[:, None] + t[None, :, None] * axis[:, None] + r * ring)
        out.append(pb[:, None] + r * sph[None, : n_per_bone // 3])  # cap at the child joint
    return np.concatenate(out, axis=1)


def chamfer_mm(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric Chamfer distance between point sets (P, 3) and (Q, 3), in mm."""
    da, _ = cKDTree(b).query(a)
    db, _ = cKDTree(a).query(b)
    return float(500.0 * (da.mean() + db.mean()))


def evaluate_rollout(demo: Demo, rollout: Any, robot_surface: np.ndarray | None) -> tuple[dict[str, Any], PerFrame]:
    """Metrics of a target ``rollout`` against ``demo``.

    Args:
        rollout: a :class:`quasisim.targets.TargetRollout` (object pose, keypoints per frame; its
            ``human_keypoint_index`` indexes ``demo.human_joints``, every hand's keypoints).
        robot_surface: (T, P, 3) robot hand surface points per frame (all hands) for CD, or None (CD = NaN).
    """
    T = demo.n_frames
    if rollout.object_pos.shape[0] != T:
        raise ValueError(f"rollout has {rollout.object_pos.shape[0]} frames, demo {demo.name} has {T}")
    rot, trans = object_errors(demo.object_pos, demo.object_quat, rollout.object_pos, rollout.object_quat)
    mp = mpjpe_per_frame(demo.human_joints, rollout.robot_keypoints, rollout.human_keypoint_index)
    if robot_surface is None:
        cd = np.full(T, np.nan)
    else:
        hs = np.concatenate([human_surface_points(demo.joints_of(s)) for s in demo.sides], axis=1)
        cd = np.array([chamfer_mm(hs[t], robot_surface[t]) for t in range(T)])
    pf = PerFrame(rot, trans, mp, cd)
    return summarize(pf, object_motion(demo.object_pos, rollout.object_pos)), pf
