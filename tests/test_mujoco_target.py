"""MuJoCo target: PD tracking, object at rest on the finite table, hand-object contact."""

from __future__ import annotations

import numpy as np

from helpers import box_object, scene_with
from quasisim.targets import make_target


def _targets(hand, T: int, start: np.ndarray, move: np.ndarray, flex: float) -> np.ndarray:
    s = np.linspace(0, 1, T)
    s = s * s * (3 - 2 * s)
    q = np.zeros((T, 6 + hand.n_joints))
    q[:, :3] = start + s[:, None] * move
    lo, hi = hand.joint_range[:, 0], hand.joint_range[:, 1]
    q[:, 6:] = np.clip(s[:, None] * flex, lo, hi)
    return q


def test_pd_tracking_free_space(shadow) -> None:
    sc = scene_with(shadow, object_pos=(2.0, 0.0, 0.825))
    tgt = make_target("mujoco", sc)
    q = _targets(shadow, 40, np.array([0.0, 0.0, 1.2]), np.array([0.1, 0.0, 0.05]), 0.5)
    r = tgt.rollout(q)
    assert np.isfinite(r.qpos).all()
    assert np.abs(r.qpos[-1, :3] - q[-1, :3]).max() < 0.005
    assert np.abs(r.qpos[-1, 6:] - q[-1, 6:]).max() < 0.1
    assert r.keypoints.shape == (40, len(shadow.kp_names), 3) and r.substeps == 25


def test_object_rests_on_table(shadow) -> None:
    sc = scene_with(shadow, object_pos=(0.0, 0.0, 0.825))
    q = _targets(shadow, 40, np.array([0.0, 0.0, 1.5]), np.zeros(3), 0.0)
    r = make_target("mujoco", sc).rollout(q)
    assert np.abs(r.object_pos - r.object_pos[0]).max() < 0.002  # 2 s untouched: stays put
    assert abs(r.object_pos[-1, 2] - 0.825) < 0.002


def test_object_falls_onto_table(shadow) -> None:
    sc = scene_with(shadow, object_pos=(0.0, 0.0, 0.875))
    q = _targets(shadow, 30, np.array([0.0, 0.0, 1.5]), np.zeros(3), 0.0)
    r = make_target("mujoco", sc).rollout(q)
    assert abs(r.object_pos[-1, 2] - 0.825) < 0.003  # lands: bottom face on the top at 0.8


def test_hand_pushes_object(shadow) -> None:
    # the palm sweeps through the box's position at table height
    from scipy.spatial.transform import Rotation

    # fingers horizontal: the base frame is turned 90 deg about y (base angles stay 0, away from gimbal lock)
    base_rot = Rotation.from_euler("y", 90, degrees=True).as_matrix()
    sc = scene_with(shadow, obj=box_object(density=200.0), object_pos=(0.0, 0.0, 0.825), base_rot=base_rot)
    q = _targets(shadow, 40, np.array([-0.2, 0.0, 0.84]), np.array([0.3, 0.0, 0.0]), 0.0)
    r = make_target("mujoco", sc).rollout(q)
    assert np.linalg.norm(r.object_pos[-1, :2] - r.object_pos[0, :2]) > 0.01
