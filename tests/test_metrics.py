"""Metrics on cases computed by hand."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from quasisim.eval.metrics import (
    PerFrame,
    chamfer_mm,
    evaluate_rollout,
    human_surface_points,
    object_errors,
    summarize,
)


def _quat_z(deg: float) -> np.ndarray:
    a = np.radians(deg) / 2
    return np.array([np.cos(a), 0.0, 0.0, np.sin(a)])


def test_object_errors_by_hand() -> None:
    ref_q = np.array([_quat_z(0), _quat_z(90)])
    q = np.array([_quat_z(30), -_quat_z(90)])  # sign flip is the same rotation
    r, t = object_errors(np.zeros((2, 3)), ref_q, np.array([[0.03, 0.04, 0.0], [0.0, 0.0, 0.0]]), q)
    np.testing.assert_allclose(r, [30.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(t, [5.0, 0.0], atol=1e-9)


def test_summary_and_success_thresholds() -> None:
    pf = PerFrame(
        rot_deg=np.array([8.0, 12.0]),
        trans_cm=np.array([1.0, 1.5]),
        mpjpe_mm=np.array([90.0, 110.0]),
        cd_mm=np.array([5.0, 7.0]),
    )
    m = summarize(pf)
    assert set(m) == {"R_err_deg", "T_err_cm", "MPJPE_mm", "CD_mm", "success"}
    assert m["R_err_deg"] == 10.0 and m["T_err_cm"] == 1.25 and m["MPJPE_mm"] == 100.0 and m["CD_mm"] == 6.0
    assert m["success"] == {"10deg_10cm": True, "15deg_15cm": True, "20deg_20cm": True, "strict": True}
    pf2 = PerFrame(np.array([10.0, 10.5]), np.array([1.0, 2.5]), np.array([100.0, 100.0]), np.array([1.0, 1.0]))
    s = summarize(pf2)["success"]
    assert s == {"10deg_10cm": False, "15deg_15cm": True, "20deg_20cm": True, "strict": False}
    pf3 = PerFrame(np.array([5.0, 31.0]), np.array([0.0, 0.0]), np.array([10.0, 10.0]), np.array([1.0, 1.0]))
    assert summarize(pf3)["success"]["strict"] is False  # one frame over 30 deg


def test_chamfer_by_hand() -> None:
    a = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    b = np.array([[0.0, 0.002, 0]])
    # a->b: (0.002 + sqrt(1 + 4e-6)) / 2 ; b->a: 0.002
    expect = 500.0 * ((0.002 + np.sqrt(1 + 4e-6)) / 2 + 0.002)
    assert abs(chamfer_mm(a, b) - expect) < 1e-9
    assert chamfer_mm(a, a) == 0.0


def test_mpjpe_and_rollout_metrics() -> None:
    T = 3
    joints = np.random.default_rng(0).normal(size=(T, 21, 3))
    demo = SimpleNamespace(
        name="x",
        n_frames=T,
        right_joints=joints,
        object_pos=np.zeros((T, 3)),
        object_quat=np.tile([1.0, 0, 0, 0], (T, 1)),
    )
    idx = np.array([0, 4, 8])
    kp = joints[:, idx] + np.array([0.003, 0.004, 0.0])  # 5 mm everywhere
    roll = SimpleNamespace(
        object_pos=np.zeros((T, 3)),
        object_quat=np.tile([1.0, 0, 0, 0], (T, 1)),
        robot_keypoints=kp,
        human_keypoint_index=idx,
    )
    m, _pf = evaluate_rollout(demo, roll, robot_surface=None)
    assert abs(m["MPJPE_mm"] - 5.0) < 1e-9 and m["R_err_deg"] == 0.0 and m["T_err_cm"] == 0.0
    assert np.isnan(m["CD_mm"])


def test_human_surface_points_on_capsules() -> None:
    joints = np.zeros((1, 21, 3))
    joints[0, :, 0] = np.arange(21) * 0.02  # a straight line of keypoints
    pts = human_surface_points(joints)
    # every point is 8-10 mm from the line (the capsules' radii)
    d = np.linalg.norm(pts[0, :, 1:], axis=1)
    assert d.min() > 0.0 and d.max() <= 0.0100001
