"""Metrics on cases computed by hand."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from quasisim.eval.metrics import (
    ObjectMotion,
    PerFrame,
    chamfer_mm,
    evaluate_rollout,
    human_surface_points,
    object_errors,
    object_motion,
    summarize,
)

STILL = ObjectMotion(0.0, 0.0, 0.0, 0.0)  # a demo that does not move its object: no motion required


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
    m = summarize(pf, STILL)
    assert set(m) == {"R_err_deg", "T_err_cm", "MPJPE_mm", "CD_mm", "object_motion", "success"}
    assert m["R_err_deg"] == 10.0 and m["T_err_cm"] == 1.25 and m["MPJPE_mm"] == 100.0 and m["CD_mm"] == 6.0
    assert m["success"] == {"10deg_10cm": True, "15deg_15cm": True, "20deg_20cm": True, "strict": True}
    pf2 = PerFrame(np.array([10.0, 10.5]), np.array([1.0, 2.5]), np.array([100.0, 100.0]), np.array([1.0, 1.0]))
    s = summarize(pf2, STILL)["success"]
    assert s == {"10deg_10cm": False, "15deg_15cm": True, "20deg_20cm": True, "strict": False}
    pf3 = PerFrame(np.array([5.0, 31.0]), np.array([0.0, 0.0]), np.array([10.0, 10.0]), np.array([1.0, 1.0]))
    assert summarize(pf3, STILL)["success"]["strict"] is False  # one frame over 30 deg


def _lift(T: int, height: float) -> np.ndarray:
    """(T, 3) positions rising linearly by ``height`` m over the second half of the clip."""
    pos = np.zeros((T, 3))
    pos[:, 2] = height * np.clip(np.linspace(-1.0, 1.0, T), 0.0, None)
    return pos


def test_object_motion_by_hand() -> None:
    demo = _lift(11, 0.12)
    m = object_motion(demo, _lift(11, 0.0013) + 0.3)  # rose 0.13 cm (its own start is elsewhere)
    assert m.demo_lift_cm == pytest.approx(12.0) and m.lift_cm == pytest.approx(0.13)
    assert m.demo_displacement_cm == pytest.approx(12.0) and m.displacement_error_cm == pytest.approx(11.87)
    assert not m.lift_ok and not m.displacement_ok and not m.as_demo
    half = object_motion(demo, _lift(11, 0.061))  # just over half the lift: lifted, displacement 5.9 of 12 off
    assert half.lift_ok and half.displacement_ok and half.as_demo
    assert not object_motion(demo, _lift(11, 0.059)).as_demo  # just under half
    side = np.zeros((11, 3))
    side[:, 0] = np.linspace(0.0, 0.10, 11)  # pushed 10 cm along x, no lift
    assert object_motion(side, side).as_demo
    wrong = object_motion(side, -side)  # pushed the other way: no lift asked for, displacement 20 cm off
    assert wrong.lift_ok and not wrong.displacement_ok and not wrong.as_demo
    assert object_motion(_lift(11, 0.015), _lift(11, 0.0)).as_demo  # 1.5 cm: within the strict tolerance


def test_not_moved_as_in_the_demo_is_never_a_success() -> None:
    # the case: mean errors small (half the clip is the approach), the object never lifted
    T = 40
    ref = _lift(T, 0.12)
    pf = PerFrame(np.zeros(T), 100.0 * np.abs(ref[:, 2]), np.full(T, 5.0), np.full(T, 5.0))
    ok = summarize(pf, object_motion(ref, ref))
    not_lifted = summarize(pf, object_motion(ref, np.zeros((T, 3))))
    assert ok["T_err_cm"] < 10.0 and ok["success"]["10deg_10cm"]
    assert not any(not_lifted["success"].values())
    assert not_lifted["object_motion"]["as_demo"] is False and not_lifted["object_motion"]["lift_cm"] == 0.0


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
        human_joints=joints,
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


def test_mpjpe_over_both_hands() -> None:
    """Two hands: robot keypoints index [right_joints, left_joints]; the left hand's indices are 21..41."""
    T = 3
    rng = np.random.default_rng(1)
    right, left = rng.normal(size=(T, 21, 3)), rng.normal(size=(T, 21, 3))
    both = np.concatenate([right, left], axis=1)
    idx = np.array([0, 4, 8, 21, 25, 29])
    kp = both[:, idx].copy()
    kp[:, 3:] += np.array([0.0, 0.0, 0.010])  # the left hand's keypoints 10 mm off, the right hand's exact
    demo = SimpleNamespace(name="x", n_frames=T, right_joints=right, left_joints=left, human_joints=both,
                           object_pos=np.zeros((T, 3)), object_quat=np.tile([1.0, 0, 0, 0], (T, 1)))  # fmt: skip
    roll = SimpleNamespace(object_pos=demo.object_pos, object_quat=demo.object_quat, robot_keypoints=kp,
                           human_keypoint_index=idx)  # fmt: skip
    m, _pf = evaluate_rollout(demo, roll, robot_surface=None)
    assert abs(m["MPJPE_mm"] - 5.0) < 1e-9  # the mean over both hands' keypoints


def test_human_surface_points_on_capsules() -> None:
    joints = np.zeros((1, 21, 3))
    joints[0, :, 0] = np.arange(21) * 0.02  # a straight line of keypoints
    pts = human_surface_points(joints)
    # every point is 8-10 mm from the line (the capsules' radii)
    d = np.linalg.norm(pts[0, :, 1:], axis=1)
    assert d.min() > 0.0 and d.max() <= 0.0100001
