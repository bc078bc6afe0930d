"""The target simulators through their one interface (:class:`quasisim.targets.base.Target`), every test run on
MuJoCo and PyBullet: PD tracking, object physics, and the interface's promises (rollout = reset + observe +
advance, exact save/restore, window rollouts, observed velocities, judge). Backend-specific checks live in
test_mujoco_target.py and test_pybullet_target.py."""

from __future__ import annotations

import importlib
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from helpers import box_object, scene_with, smooth_targets
from quasisim import targets
from quasisim.targets import TARGETS, Prediction, Prune, Target, make_target, pd_gains, pd_schedule


def _installed(name: str) -> bool:
    """Whether target ``name``'s module (and so its simulator) imports here."""
    try:
        importlib.import_module(targets.BACKENDS[name].split(":")[0])
    except ImportError:
        return False
    return True


# every registered target (a new backend in quasisim.targets.BACKENDS is tested here as it is added)
BACKENDS = [
    pytest.param(n, marks=pytest.mark.skipif(not _installed(n), reason=f"{n}'s simulator is not installed"))
    for n in TARGETS
]
SUBSTEPS = {"mujoco": 25, "pybullet": 100}  # at 20 fps: 2 ms and 0.5 ms physics steps (known backends)


def _contact_scene(shadow):
    """A box dropped between the fingers of a closing hand: contacts, a moving object (m)."""
    sc = scene_with(shadow, object_pos=(0.0, 0.0, 0.86))
    return sc, smooth_targets(shadow, 8, np.array([0.0, -0.1, 0.95]), np.array([0.0, 0.05, -0.02]), 0.8)


def _same(a: dict, b: dict, atol: float = 0.0) -> None:
    for k in a:
        np.testing.assert_allclose(a[k], b[k], rtol=0, atol=atol, err_msg=k)


# ---- the shared pieces ---------------------------------------------------------------------------------


def test_import_is_light_and_names_the_targets() -> None:
    code = "import sys, quasisim.targets; print(sorted(m for m in ('mujoco', 'pybullet', 'jax') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
    with pytest.raises(Exception, match="valid options: mujoco, pybullet"):
        make_target("isaac", None)
    assert {"mujoco", "pybullet"} <= set(TARGETS) and TARGETS == tuple(targets.BACKENDS)


def test_pd_schedule_is_the_frame_law() -> None:
    """Per step ``(1 - s) qa + s qb`` with ``s = (k + 1) / n`` and the velocity ``(qb - qa) fps``, bit for bit, for
    one frame and for batched windows alike."""
    rng = np.random.default_rng(1)
    wins = rng.normal(size=(3, 4, 5))
    pd, ff = pd_schedule(wins[:, :-1], wins[:, 1:], 7, 20.0)
    assert pd.shape == (3, 3, 7, 5) and ff.shape == (3, 3, 5)
    for i in range(3):
        for f in range(3):
            qa, qb = wins[i, f], wins[i, f + 1]
            one, v = pd_schedule(qa, qb, 7, 20.0)
            np.testing.assert_array_equal(one, pd[i, f])
            np.testing.assert_array_equal(v, (qb - qa) * 20.0)
            np.testing.assert_array_equal(ff[i, f], v)
            for k in range(7):
                s = (k + 1) / 7
                assert np.array_equal(pd[i, f, k], (1 - s) * qa + s * qb)
            np.testing.assert_array_equal(one[-1], qb)


def test_pd_gains_per_dof(shadow) -> None:
    g, pd, J = pd_gains(shadow), shadow.config.pd, shadow.n_joints
    assert all(len(x) == 6 + J for x in g)
    np.testing.assert_array_equal(g.kp[:6], [pd.base_pos.kp] * 3 + [pd.base_rot.kp] * 3)
    np.testing.assert_array_equal(g.kv[6:], pd.joint.kv)
    assert np.isinf(g.force_limit[:6]).all() and (g.force_limit[6:] == pd.joint_force_limit).all()
    assert (g.damping[:6] == 0).all() and (g.damping[6:] == pd.joint_damping).all()


# ---- behaviour, both backends --------------------------------------------------------------------------


@pytest.mark.parametrize("backend", BACKENDS)
def test_pd_tracking_free_space(backend: str, shadow) -> None:
    with make_target(backend, scene_with(shadow, object_pos=(2.0, 0.0, 0.825))) as tgt:
        assert isinstance(tgt, Target) and tgt.name == backend
        q = smooth_targets(shadow, 40, np.array([0.0, 0.0, 1.2]), np.array([0.1, 0.0, 0.05]), 0.5)
        q[:, 3:6] = np.linspace(0, 1, 40)[:, None] * [0.3, -0.4, 0.5]
        r = tgt.rollout(q)
        assert r.target == backend and r.substeps == SUBSTEPS.get(backend, r.substeps)
        assert r.dt * r.substeps == pytest.approx(0.05)
        assert r.qpos.shape == q.shape and r.keypoints.shape == (40, len(shadow.kp_names), 3)
        assert np.isfinite(r.qpos).all() and np.isfinite(r.keypoints).all()
        joints = {"mujoco": 0.1, "pybullet": 0.05}[backend]  # rad
        assert np.abs(r.qpos[-1, :3] - q[-1, :3]).max() < 0.005
        assert np.abs(r.qpos[-1, 3:6] - q[-1, 3:6]).max() < 0.02
        assert np.abs(r.qpos[-1, 6:] - q[-1, 6:]).max() < joints
        assert np.abs(r.qpos - q).max() < joints  # the whole way, not only at the end
        with pytest.raises(ValueError, match=r"q_targets must have shape \(T, 28\)"):
            tgt.rollout(q[:, :10])


@pytest.mark.parametrize("backend", BACKENDS)
def test_object_rests_and_falls_onto_table(backend: str, shadow) -> None:
    q = smooth_targets(shadow, 40, np.array([0.0, 0.0, 1.5]), np.zeros(3), 0.0)
    r = make_target(backend, scene_with(shadow, object_pos=(0.0, 0.0, 0.825))).rollout(q)
    assert np.abs(r.object_pos - r.object_pos[0]).max() < 0.002  # 2 s untouched: stays put
    assert abs(r.object_pos[-1, 2] - 0.825) < 0.002
    r = make_target(backend, scene_with(shadow, object_pos=(0.0, 0.0, 0.875))).rollout(q[:30])
    assert abs(r.object_pos[-1, 2] - 0.825) < 0.003  # lands: bottom face on the top at 0.8
    assert np.abs(r.object_quat[-1] - [1, 0, 0, 0]).max() < 1e-3


@pytest.mark.parametrize("backend", BACKENDS)
def test_hand_pushes_object(backend: str, shadow) -> None:
    # fingers horizontal: the base frame is turned 90 deg about y (base angles stay 0, away from gimbal lock);
    # the palm sweeps through the box's position at table height
    base_rot = Rotation.from_euler("y", 90, degrees=True).as_matrix()
    sc = scene_with(shadow, obj=box_object(density=200.0), object_pos=(0.0, 0.0, 0.825), base_rot=base_rot)
    q = smooth_targets(shadow, 30, np.array([-0.2, 0.0, 0.84]), np.array([0.3, 0.0, 0.0]), 0.0)
    with make_target(backend, sc) as tgt:
        r = tgt.rollout(q)
    assert np.isfinite(r.qpos).all()
    assert np.linalg.norm(r.object_pos[-1, :2] - r.object_pos[0, :2]) > 0.01


@pytest.mark.parametrize("backend", BACKENDS)
def test_rollout_reproducible_and_close(backend: str, shadow) -> None:
    sc, q = _contact_scene(shadow)
    tgt = make_target(backend, sc)
    r1, r2 = tgt.rollout(q), tgt.rollout(q)
    assert np.array_equal(r1.qpos, r2.qpos) and np.array_equal(r1.object_pos, r2.object_pos)
    assert np.array_equal(r1.keypoints, r2.keypoints)
    assert r1.object_pos[-1, 2] < 0.86  # falling
    tgt.close()
    tgt.close()


# ---- the interface's promises --------------------------------------------------------------------------


@pytest.mark.parametrize("backend", BACKENDS)
def test_rollout_is_reset_observe_advance(backend: str, shadow) -> None:
    sc, q = _contact_scene(shadow)
    with make_target(backend, sc) as tgt:
        r = tgt.rollout(q)
        tgt.reset(q[0], (q[1] - q[0]) * sc.fps)
        frames = []
        for t in range(len(q)):
            frames.append(tgt.observe())
            if t < len(q) - 1:
                tgt.advance(q[t], q[t + 1])
        again = tgt.recorded(frames, 0.0)
    for k in ("qpos", "object_pos", "object_quat", "keypoints"):
        np.testing.assert_array_equal(getattr(again, k), getattr(r, k), err_msg=k)
    assert again.extras == r.extras and again.dt == r.dt and again.substeps == r.substeps


@pytest.mark.parametrize("backend", BACKENDS)
def test_reset_places_hands_and_object(backend: str, shadow) -> None:
    sc, q = _contact_scene(shadow)
    qd = np.random.default_rng(0).normal(0.0, 0.1, sc.n_dof)
    with make_target(backend, sc) as tgt:
        tgt.reset(q[0], qd)
        o = tgt.observe()
    np.testing.assert_allclose(o["qpos"], q[0], atol=1e-12)
    np.testing.assert_allclose(o["qvel"], qd, atol=1e-12)
    np.testing.assert_allclose(o["obj_pos"], sc.object_pos0, atol=1e-12)
    assert abs(abs(o["obj_quat"] @ sc.object_quat0) - 1) < 1e-12
    assert np.abs(o["obj_vel"]).max() == 0 and np.abs(o["obj_angvel"]).max() == 0
    assert o["keypoints"].shape == (len(shadow.kp_names), 3)


@pytest.mark.parametrize("backend", BACKENDS)
def test_save_restore_round_trip(backend: str, shadow) -> None:
    """Advance, save, advance two frames (the object lands); restore, advance the same two frames: the same
    state to 1e-12."""
    sc, q = _contact_scene(shadow)
    with make_target(backend, sc) as tgt:
        tgt.reset(q[0], (q[1] - q[0]) * sc.fps)
        tgt.advance(q[0], q[1])
        state = tgt.save_state()
        saved = tgt.observe()
        tgt.advance(q[1], q[2])
        tgt.advance(q[2], q[3])
        first = tgt.observe()
        tgt.restore_state(state)
        _same(tgt.observe(), saved, 1e-12)
        tgt.advance(q[1], q[2])
        tgt.advance(q[2], q[3])
        _same(tgt.observe(), first, 1e-12)
        tgt.release_state(state)
    assert np.abs(first["obj_pos"] - saved["obj_pos"]).max() > 1e-3  # the object moved in between


@pytest.mark.parametrize("backend", BACKENDS)
def test_rollout_windows_match_advancing_by_hand(backend: str, shadow) -> None:
    """Candidate 0 of a batch equals advancing its window from the same state; the state is left as it was.
    With ``qd0`` the candidates start with their own hand velocity, as a replay of their window would."""
    sc, q = _contact_scene(shadow)
    metric = sc.kp_metric
    rng = np.random.default_rng(3)
    with make_target(backend, sc, threads=2) as tgt:
        for start, with_qd0 in ((0, True), (2, False)):
            wins = np.repeat(q[None, start : start + 4], 3, axis=0)
            wins[1:, 1:] += rng.normal(0.0, 0.01, wins[1:, 1:].shape)
            qd0 = (wins[:, 1] - wins[:, 0]) * sc.fps if with_qd0 else None
            tgt.reset(q[0], None if qd0 is None else qd0[0])
            for t in range(start):
                tgt.advance(q[t], q[t + 1])
            before = tgt.observe()
            pred = tgt.rollout_windows(wins, qd0)
            _same(tgt.observe(), before)  # left where it was
            H = wins.shape[1] - 1
            assert pred.qpos.shape == (3, H, sc.n_dof) and pred.keypoints.shape == (3, H, int(metric.sum()), 3)
            assert pred.n_steps >= 3 * H * tgt.substeps
            for f in range(H):
                tgt.advance(wins[0, f], wins[0, f + 1])
                o = tgt.observe()
                np.testing.assert_allclose(pred.qpos[0, f], o["qpos"], atol=1e-9)
                np.testing.assert_allclose(pred.obj_pos[0, f], o["obj_pos"], atol=1e-9)
                np.testing.assert_allclose(pred.obj_quat[0, f], o["obj_quat"], atol=1e-9)
                np.testing.assert_allclose(pred.keypoints[0, f], o["keypoints"][metric], atol=1e-9)
            assert np.abs(pred.qpos[1] - pred.qpos[0]).max() > 1e-4  # the candidates differ


@pytest.mark.parametrize("backend", BACKENDS)
def test_pruned_windows_go_on_only_for_the_kept(backend: str, shadow) -> None:
    """With a :class:`Prune`, every candidate runs its first frames as without it; ``keep`` sees those frames
    and only the candidates it returns run the rest, as an unbroken rollout does (MuJoCo: up to the solver's
    warm start); the others' later frames are NaN, and the physics steps count what ran."""
    sc, q = _contact_scene(shadow)
    rng = np.random.default_rng(4)
    wins = np.repeat(q[None, 1:6], 4, axis=0)
    wins[1:, 1:] += rng.normal(0.0, 0.01, wins[1:, 1:].shape)
    seen = []

    def keep(head: Prediction) -> np.ndarray:
        seen.append(head)
        return np.array([3, 1])

    with make_target(backend, sc, threads=2) as tgt:
        tgt.reset(q[0], None)
        tgt.advance(q[0], q[1])
        before = tgt.observe()
        full = tgt.rollout_windows(wins)
        pruned = tgt.rollout_windows(wins, None, Prune(2, keep))
        _same(tgt.observe(), before)  # left where it was
    (head,) = seen
    assert head.obj_pos.shape == (4, 2, 3)
    np.testing.assert_array_equal(head.obj_pos, full.obj_pos[:, :2])
    np.testing.assert_array_equal(pruned.qpos[:, :2], full.qpos[:, :2])
    assert np.isnan(pruned.obj_pos[[0, 2], 2:]).all() and np.isnan(pruned.keypoints[[0, 2], 2:]).all()
    for k in ("qpos", "obj_pos", "keypoints"):
        np.testing.assert_allclose(getattr(pruned, k)[[1, 3]], getattr(full, k)[[1, 3]], rtol=0, atol=1e-6, err_msg=k)
    extra = 1 if backend == "mujoco" else 0  # mujoco.rollout runs one more step per rollout (lagging sensors)
    assert pruned.n_steps == 4 * (2 * tgt.substeps + extra) + 2 * (2 * tgt.substeps + extra)


def _rot(quat_wxyz: np.ndarray) -> Rotation:
    return Rotation.from_quat(quat_wxyz, scalar_first=True)


def test_a_missing_capability_says_so() -> None:
    """The base's window rollouts with initial velocities need ``set_hands``; a backend without it refuses."""

    class Bare(Target):
        name, dt = "bare", 0.01
        scene = SimpleNamespace(fps=20.0, kp_metric=np.array([True]))
        reset = observe = advance = lambda self, *a: None
        save_state = restore_state = lambda self, *a: None

    with Bare() as t, pytest.raises(NotImplementedError, match="target bare: setting the hands"):
        t.rollout_windows(np.zeros((2, 3, 4)), np.zeros((2, 4)))


def _throw(tgt: Target, v_com: np.ndarray, w: np.ndarray) -> None:
    """Give the object a world linear velocity of its centre of mass and a world angular velocity (each
    backend's own convention; the test checks that observe undoes it)."""
    if tgt.name == "mujoco":
        mm, d = tgt.mm, tgt.data  # type: ignore[attr-defined]
        o = mm.obj_qpos
        R = _rot(d.qpos[o + 3 : o + 7]).as_matrix()
        com = R @ np.asarray(tgt.scene.obj.com)
        d.qvel[mm.obj_dof : mm.obj_dof + 3] = v_com - np.cross(w, com)  # free joint: the frame origin's velocity
        d.qvel[mm.obj_dof + 3 : mm.obj_dof + 6] = R.T @ w  # ... and the body-frame angular velocity
    else:
        tgt.pb.resetBaseVelocity(tgt.obj_id, v_com.tolist(), w.tolist(), physicsClientId=tgt.client)  # type: ignore[attr-defined]


@pytest.mark.parametrize("backend", BACKENDS)
def test_observed_velocities_match_finite_differences(backend: str, shadow) -> None:
    """A spinning cube (isotropic inertia: constant angular velocity) in free flight, away from the table: the
    observed centre-of-mass velocity is the mean of its start and end over a frame (constant gravity), the
    angular velocity the rotation over the frame."""
    obj = box_object()
    obj.com = obj.com + np.array([0.01, -0.005, 0.0])  # the origin off the centre of mass
    sc = scene_with(shadow, obj=obj, object_pos=(2.0, 0.0, 1.5))
    q = smooth_targets(shadow, 3, np.array([0.0, 0.0, 1.2]), np.array([0.02, 0.0, 0.0]), 0.0)
    v, w = np.array([0.2, -0.1, 0.5]), np.array([3.0, -2.0, 1.0])
    with make_target(backend, sc) as tgt:
        tgt.reset(q[0])
        _throw(tgt, v, w)
        a = tgt.observe()
        tgt.advance(q[0], q[0])
        b = tgt.observe()
    frame = 1.0 / sc.fps

    def com(o: dict) -> np.ndarray:
        return o["obj_pos"] + _rot(o["obj_quat"]).as_matrix() @ obj.com

    np.testing.assert_allclose(a["obj_vel"], v, atol=1e-9)
    np.testing.assert_allclose(a["obj_angvel"], w, atol=1e-9)
    np.testing.assert_allclose(b["obj_vel"] - a["obj_vel"], [0, 0, -9.81 * frame], atol=1e-3)  # free fall
    # semi-implicit Euler: the positions lag the mean velocity by half a step of gravity (MuJoCo: 0.01 m/s)
    np.testing.assert_allclose((com(b) - com(a)) / frame, (a["obj_vel"] + b["obj_vel"]) / 2, atol=0.015)
    turn = _rot(b["obj_quat"]) * _rot(a["obj_quat"]).inv()
    np.testing.assert_allclose(turn.as_rotvec() / frame, a["obj_angvel"], atol=0.01)
    np.testing.assert_allclose(b["obj_angvel"], a["obj_angvel"], atol=0.01)


@pytest.mark.parametrize("backend", BACKENDS)
def test_hand_velocities_match_finite_differences(backend: str, shadow) -> None:
    """Targets moving at constant velocity (started at it), each finger joint at its own rate: the observed hand
    velocity against central differences of the observed positions over a frame (on average over the fingers:
    their soft PD gains ring and some reach their limits; the exact check is reset's velocity read back)."""
    sc = scene_with(shadow, object_pos=(2.0, 0.0, 0.825))
    s = np.linspace(0.0, 1.0, 12)[:, None]
    q = np.zeros((12, sc.n_dof))
    q[:, :3] = [0.0, 0.0, 1.2] + s * [0.1, 0.05, 0.0]
    q[:, 3:6] = s * [0.1, -0.1, 0.2]
    q[:, 6:] = np.clip(s * np.linspace(0.2, 0.8, shadow.n_joints), shadow.joint_range[:, 0], shadow.joint_range[:, 1])
    with make_target(backend, sc) as tgt:
        r = []
        tgt.reset(q[0], (q[1] - q[0]) * sc.fps)
        for t in range(len(q) - 1):
            r.append(tgt.observe())
            tgt.advance(q[t], q[t + 1])
    pos, vel = np.array([o["qpos"] for o in r]), np.array([o["qvel"] for o in r])
    err = np.abs((pos[2:] - pos[:-2]) * sc.fps / 2 - vel[1:-1])
    assert err[:, :6].max() < 0.03 and err[:, 6:].mean() < 0.05, err.max(0)  # m/s, rad/s
    assert np.abs(vel[1:, 6:]).mean() > 0.5  # the fingers do move (rad/s)


@pytest.mark.parametrize("backend", BACKENDS)
def test_judge_is_the_clip_cost_of_the_rollout(backend: str, shadow) -> None:
    from quasisim.method.config import TransferConfig
    from quasisim.optim.objective import clip_cost

    sc, q = _contact_scene(shadow)
    T, K = len(q), 21
    rng = np.random.default_rng(4)
    demo = SimpleNamespace(
        human_joints=rng.normal(0.0, 0.05, (T, K, 3)) + np.array([0.0, -0.1, 0.95]),
        object_pos=np.tile(sc.object_pos0, (T, 1)), object_quat=np.tile(sc.object_quat0, (T, 1)),
    )  # fmt: skip
    w = TransferConfig.from_yaml().weights
    with make_target(backend, sc) as tgt:
        j = tgt.judge(demo, q, w)  # type: ignore[arg-type]
        assert j == clip_cost(demo, tgt.rollout(q), w)  # type: ignore[arg-type]
    assert np.isfinite(j) and j > 0
