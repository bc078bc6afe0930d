"""DGrasp's form of action in ``quasisim/Track-v0`` (``action_form: dgrasp``; :meth:`TrackTask.dgrasp_targets`).

A zero action holds the measured fingers and wrist rotation and puts the wrist at the goal; a full action steps
each kind of dof by DGrasp's scale, no further than the joint limits; the goal wrist moves rigidly with the object
(a hand-made turn and shift, answer written out); the env holds each frame's targets with no velocity fed forward
(MuJoCo's controls after a step); refused with ``residual=True``; the default form gives today's targets and
transitions bit for bit.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import quasisim.envs
from helpers import cube_example
from quasisim.envs.config import TrackEnvConfig
from quasisim.envs.task import TrackTask, dof_scale
from quasisim.errors import InputError
from quasisim.targets.base import pd_schedule


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """The bundled example (20 frames), its kinematic retarget (``kinematic.npz`` beside it) and their scene."""
    return cube_example(tmp_path_factory.mktemp("dgrasp_action"))


def _task(clip, residual: bool = False, **overrides) -> TrackTask:
    _, demo, controls, scene = clip
    return TrackTask(demo, scene, controls.q_targets, TrackEnvConfig.from_yaml(None, overrides), residual)


def _env(clip, **kw) -> gym.Env:
    path = clip[0]
    return gym.make(quasisim.envs.TRACK_ID, clip=path, reference=path.parent / "kinematic.npz", **kw)


def _observed(task: TrackTask, t: int, qpos: np.ndarray, frame: int) -> dict:
    """A hand-made observation at ``t``: the hands at ``qpos``, the object at the demo's pose at ``frame``."""
    demo, D = task.demo, task.scene.n_dof
    return {"qpos": qpos, "qvel": np.zeros(D), "obj_pos": demo.object_pos[frame].copy(),
            "obj_quat": demo.object_quat[frame].copy(), "obj_vel": np.zeros(3), "obj_angvel": np.zeros(3),
            "keypoints": demo.human_joints[frame, task.scene.kp_human].copy()}  # fmt: skip


def test_a_zero_action_holds_the_measured_fingers_and_pulls_the_base_to_the_goal(clip) -> None:
    """Zero action: the finger joints and base hinges are the measured ones exactly, the base slides the
    reference's base at ``t + 1`` (the object where the demo has it at ``t + 1``), not the measured base. A full
    action steps them by 0.015 rad, 0.01 rad and 1 mm (an action beyond 1 no further); a finger at its upper limit
    stays there."""
    task, t = _task(clip, action_form="dgrasp"), 8
    ref = task.reference
    rng = np.random.default_rng(0)
    q = ref[t].copy()
    q[:3] += [0.02, -0.03, 0.01]  # the wrist away from the reference's
    q[3:] += rng.uniform(-0.02, 0.02, len(q) - 3)  # hinges and fingers measured elsewhere
    lo, hi = task.bounds
    j = int(task.joint_cols[np.isfinite(hi[task.joint_cols])][3])
    q[j] = hi[j]  # one finger at its upper limit
    obs, D = _observed(task, t, q, t + 1), task.scene.n_dof
    zero = task.targets(t, np.zeros(D), obs)
    np.testing.assert_array_equal(zero[6:], q[6:])  # fingers: the measured pose, bit for bit
    np.testing.assert_array_equal(zero[3:6], q[3:6])  # base hinges too
    np.testing.assert_allclose(zero[:3], ref[t + 1, :3], rtol=0, atol=1e-12)  # base slides: the goal
    assert np.linalg.norm(zero[:3] - q[:3]) > 0.03
    full = task.targets(t, np.ones(D), obs)
    step = full - zero
    np.testing.assert_allclose(step[:3], 0.001, rtol=1e-9)
    np.testing.assert_allclose(step[3:6], 0.01, rtol=1e-9)
    free = np.setdiff1d(task.joint_cols, [j])
    np.testing.assert_allclose(step[free][q[free] + 0.015 <= hi[free]], 0.015, rtol=1e-9)
    assert full[j] == hi[j]  # clipped to the joint limit
    np.testing.assert_array_equal(task.targets(t, np.full(D, 5.0), obs), full)  # actions clipped to [-1, 1]
    back = task.targets(t, -np.ones(D), obs)
    np.testing.assert_allclose(zero[free] - back[free], np.clip(q[free] - lo[free], 0.0, 0.015), rtol=1e-9)


def test_the_goal_wrist_moves_rigidly_with_the_object(clip) -> None:
    """The object turned 90 deg about the world z axis through its centre and shifted by ``d`` from the demo's
    pose at ``t + 1``: the goal wrist is ``x + d + (-r_y, r_x, r_z)``, ``r`` the reference wrist's offset from the
    demo object at ``t + 1``. With the object where the demo has it, the goal is the reference's wrist."""
    task, t = _task(clip, action_form="dgrasp"), 12
    demo, ref = task.demo, task.reference
    x, d = demo.object_pos[t + 1], np.array([0.05, -0.02, 0.1])
    r = ref[t + 1, :3] - x
    w, v = demo.object_quat[t + 1, 0], demo.object_quat[t + 1, 1:]
    c = np.sqrt(0.5)  # the quaternion of 90 deg about z: (c, 0, 0, c); composed on the world side, by hand
    turned = np.array([c * w - c * v[2], c * v[0] - c * v[1], c * v[1] + c * v[0], c * v[2] + c * w])
    obs = {**_observed(task, t, ref[t].copy(), t + 1), "obj_pos": x + d, "obj_quat": turned}
    expected = x + d + np.array([-r[1], r[0], r[2]])
    np.testing.assert_allclose(task.goal_base(t, obs)[0], expected, rtol=0, atol=1e-12)
    q = task.targets(t, np.zeros(task.scene.n_dof), obs)
    np.testing.assert_allclose(q[:3], expected, rtol=0, atol=1e-12)
    assert np.linalg.norm(r[:2]) > 0.01  # the turn moves the goal (the wrist is off the turn's axis)
    at_demo = task.goal_base(t, _observed(task, t, ref[t].copy(), t + 1))
    np.testing.assert_allclose(at_demo[0], ref[t + 1, :3], rtol=0, atol=1e-12)


def test_the_env_feeds_no_velocity_forward_under_dgrasp(clip) -> None:
    """MuJoCo's controls after each step of an episode with ``action_form: dgrasp``: the PD targets are the
    task's targets for the action, held over the frame, and the feed-forward actuators are 0; the default form
    feeds ``(q - q_prev) fps`` forward (not 0). Gymnasium's checker passes."""
    rng = np.random.default_rng(1)
    env = _env(clip, overrides={"action_form": "dgrasp", "terminate": "unstable"})
    check_env(env.unwrapped, skip_render_check=True)
    task = env.unwrapped.task
    env.reset(options={"world": 3})
    for _ in range(4):
        a = rng.uniform(-1, 1, env.action_space.shape).astype(np.float32)
        q = task.targets(env.unwrapped._t, a, env.unwrapped._obs)
        env.step(a)
        world = env.unwrapped._world
        np.testing.assert_array_equal(world.data.ctrl[world.mm.ff_act], 0.0)
        np.testing.assert_array_equal(world.data.ctrl[world.mm.pd_act], q)
    env.close()
    env = _env(clip, overrides={"terminate": "unstable"})
    env.reset(options={"world": 3})
    env.step(np.full(env.action_space.shape, 0.5, np.float32))  # the delta form: the velocity of 0.5 s_delta
    world = env.unwrapped._world
    assert np.abs(world.data.ctrl[world.mm.ff_act][:6]).min() > 0.1  # the base (a finger may sit at a limit)
    env.close()


def test_dgrasp_action_is_refused_with_residual_and_validated(clip) -> None:
    with pytest.raises(ValueError, match=r"action_form: dgrasp.*residual=False"):
        _env(clip, residual=True, overrides={"action_form": "dgrasp"})
    with pytest.raises(ValueError, match="action_form: dgrasp"):
        _task(clip, residual=True, action_form="dgrasp")
    bad = (
        ({"action_form": "delta"}, "action_form"),
        ({"dgrasp_action.fingers": 0.0}, "dgrasp_action.fingers"),
        ({"dgrasp_action.root": -0.001}, "dgrasp_action.root"),
        ({"dgrasp_action.wrist": 0.01}, "dgrasp_action.wrist"),
    )
    for override, name in bad:
        with pytest.raises(InputError, match=rf"track_env\.yaml.*'{name}'"):
            TrackEnvConfig.from_yaml(None, override)


@pytest.mark.parametrize("residual", [True, False])
def test_the_default_action_form_is_todays(clip, residual) -> None:
    """``action_form: default`` (the default): the targets are today's closed form, ``clip(b + s a, min(lo, b),
    max(hi, b))`` with ``b`` the reference at ``t + 1`` (residual) or the measured pose and ``s`` the residual or
    delta scale, bit for bit; each frame's schedule starts from the previous targets; an episode's transitions are
    the same with the setting given, and MuJoCo feeds ``(q - q_prev) fps`` forward."""
    scene, cfg = clip[3], TrackEnvConfig.from_yaml()
    assert cfg.action_form == "default"
    task = _task(clip, residual)
    s = dof_scale(scene, cfg.residual_scale if residual else cfg.delta_scale)
    rng = np.random.default_rng(2)
    lo, hi = task.bounds
    for t in (0, 7, 17):
        obs = _observed(task, t, task.reference[t] + rng.uniform(-0.05, 0.05, scene.n_dof), t)
        a = rng.uniform(-1.5, 1.5, scene.n_dof)
        b = task.reference[t + 1] if residual else obs["qpos"]
        expected = np.clip(b + s * np.clip(a, -1, 1), np.minimum(lo, b), np.maximum(hi, b))
        np.testing.assert_array_equal(task.targets(t, a, obs), expected)
        prev = task.reference[t]
        assert task.schedule_from(prev, expected) is prev
    actions = rng.uniform(-1, 1, (5, scene.n_dof)).astype(np.float32)
    seen = []
    for overrides in ({}, {"action_form": "default"}):
        env = _env(clip, residual=residual, overrides={"terminate": "unstable", **overrides})
        obs, _ = env.reset(seed=4)
        run, prev = [obs], env.unwrapped._prev
        for a in actions:
            q = env.unwrapped.task.targets(env.unwrapped._t, a, env.unwrapped._obs)
            run.append(env.step(a)[0])
            world = env.unwrapped._world
            _, ff = pd_schedule(prev, q, world.substeps, scene.fps)
            np.testing.assert_array_equal(world.data.ctrl[world.mm.ff_act], ff)
            prev = q
        seen.append(np.array(run))
        env.close()
    np.testing.assert_array_equal(seen[0], seen[1])


def test_a_dgrasp_policy_is_judged_as_it_trained(clip) -> None:
    """The evaluation's replay (quasisim.targets.perturb.replay) drives the world with a learned policy's own
    schedule: under ``action_form: dgrasp`` every frame holds its targets (no velocity fed forward), and the
    replay equals the env's episode for the same actions; a default-form policy feeds velocity forward."""
    from quasisim.policy.controller import LearnedPolicy
    from quasisim.targets import make_target
    from quasisim.targets.perturb import replay

    class Constant:  # a stand-in for a trained model: the same action every frame
        def predict(self, obs, deterministic=True):
            return np.full(task.scene.n_dof, 0.3, np.float32), None

    for form in ("dgrasp", "default"):
        task = _task(clip, action_form=form, terminate="unstable")
        env = _env(clip, overrides={"action_form": form, "terminate": "unstable", "randomize": False})
        env.reset()
        for _ in range(len(task.reference) - 1):
            env.step(np.full(env.action_space.shape, 0.3, np.float32))
        episode = env.unwrapped._world.observe()
        env.close()
        with make_target("mujoco", task.scene) as world:
            run = replay(world, task.reference, LearnedPolicy(task, Constant()))
            ff = world.data.ctrl[world.mm.ff_act].copy()
        np.testing.assert_allclose(run.object_pos[-1], episode["obj_pos"], atol=1e-9)
        np.testing.assert_allclose(run.qpos[-1], episode["qpos"], atol=1e-9)
        if form == "dgrasp":
            np.testing.assert_array_equal(ff, 0.0)
        else:
            assert np.abs(ff).max() > 0
