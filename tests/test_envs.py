"""The tracking environment ``quasisim/Track-v0`` (:mod:`quasisim.envs`).

Gymnasium's own checker passes; a residual episode of zero actions in the nominal world is exactly the
reference's MuJoCo replay (:meth:`Target.rollout`); seeded resets repeat the same worlds and transitions, also in
a vector of processes; the reward is its closed form at zero error; leaving the strict limits ends an episode;
bad input names the file and the field.
"""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import quasisim.envs
from helpers import cube_example
from quasisim.envs.config import TrackEnvConfig
from quasisim.envs.task import TrackTask
from quasisim.errors import InputError
from quasisim.targets import make_target


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """The bundled example (20 frames), its kinematic retarget (``kinematic.npz`` beside it) and their scene."""
    return cube_example(tmp_path_factory.mktemp("envs"))


def _env(clip, **kw) -> gym.Env:
    path = clip[0]
    return gym.make(quasisim.envs.TRACK_ID, clip=path, reference=path.parent / "kinematic.npz", **kw)


def _episode(env, actions, **reset) -> tuple[list, list, dict]:
    obs, _ = env.reset(**reset)
    seen, rewards, info = [obs], [], {}
    for a in actions:
        obs, r, term, trunc, info = env.step(a)
        seen.append(obs)
        rewards.append(r)
        if term or trunc:
            break
    return seen, rewards, info


@pytest.mark.parametrize("residual", [True, False])
def test_gymnasium_env_checker_passes(clip, residual) -> None:
    env = _env(clip, residual=residual)
    check_env(env.unwrapped, skip_render_check=True)
    env.close()


@pytest.mark.parametrize("target", ["mujoco", "pybullet"])
def test_zero_residual_in_the_nominal_world_is_the_reference_replay(clip, target) -> None:
    _, demo, controls, scene = clip
    env = _env(clip, residual=True, target=target, overrides={"terminate": "unstable"})
    zeros = [np.zeros(env.action_space.shape, np.float32)] * (demo.n_frames - 1)
    _, _, info = _episode(env, zeros, options={"world": None})
    world = env.unwrapped._world
    assert info["frames"] == demo.n_frames - 1
    end = world.observe()
    with make_target(target, scene) as tgt:
        ref = tgt.rollout(controls.q_targets)
    np.testing.assert_array_equal(end["obj_pos"], ref.object_pos[-1])
    np.testing.assert_array_equal(end["qpos"], ref.qpos[-1])
    env.close()


def test_seeded_resets_repeat_worlds_and_transitions(clip) -> None:
    rng = np.random.default_rng(0)
    env = _env(clip, residual=True)
    actions = rng.uniform(-1, 1, (19, env.action_space.shape[0])).astype(np.float32)
    a = _episode(env, actions, seed=7)
    b = _episode(env, actions, seed=7)
    c = _episode(env, actions, seed=8)
    np.testing.assert_array_equal(np.array(a[0]), np.array(b[0]))
    assert a[1] == b[1]
    assert not np.array_equal(a[0][0], c[0][0])  # another world: the object starts elsewhere
    env.close()


def test_skip_worlds_goes_on_after_the_first_worlds_of_a_seed(clip) -> None:
    env = _env(clip, residual=True)
    worlds = [env.reset(seed=5)[1]["world"]] + [env.reset()[1]["world"] for _ in range(3)]
    assert env.unwrapped.worlds_drawn == 4
    _, info = env.reset(seed=5, options={"skip_worlds": 2})
    assert [info["world"], env.reset()[1]["world"]] == worlds[2:] and env.unwrapped.worlds_drawn == 4
    with pytest.raises(ValueError, match=r"skip_worlds.*>= 0"):
        env.reset(options={"skip_worlds": -1})
    env.close()


def test_resets_set_the_world_on_the_compiled_model(clip, monkeypatch) -> None:
    """MuJoCo: the model is compiled at the first reset only; later resets set the world's object mass and
    inertia, friction, PD gains and object position on it, with the same transitions, bit for bit, as a model
    compiled for that world (a fresh env's first reset), whichever worlds came before."""
    import quasisim.targets.mujoco_target as mt

    built = []
    spec = mt.build_spec
    monkeypatch.setattr(mt, "build_spec", lambda *a, **k: built.append(1) or spec(*a, **k))
    kw = {"residual": True, "overrides": {"terminate": "unstable"}}
    env = _env(clip, **kw)
    actions = 0.3 * np.random.default_rng(1).uniform(-1, 1, (19, env.action_space.shape[0])).astype(np.float32)
    seen = {w: _episode(env, actions, options={"world": w}) for w in (4, 9, None)}
    assert len(built) == 1  # compiled once, at the first reset
    assert not np.array_equal(seen[4][0][-1], seen[9][0][-1])  # the worlds differ
    for w in (9, None):
        fresh = _env(clip, **kw)
        obs, rewards, _ = _episode(fresh, actions, options={"world": w})
        np.testing.assert_array_equal(np.array(obs), np.array(seen[w][0]))
        assert rewards == seen[w][1] and len(rewards) == 19
        fresh.close()
    env.close()


def test_a_vector_of_processes_matches_single_envs(clip) -> None:
    path = clip[0]
    kw = {"clip": path, "reference": path.parent / "kinematic.npz", "residual": True}
    vec = gym.make_vec(quasisim.envs.TRACK_ID, num_envs=2, vectorization_mode="async",
                       vector_kwargs={"context": "spawn"}, **kw)  # fmt: skip
    obs, _ = vec.reset(seed=[3, 4])
    a = np.full((2, vec.single_action_space.shape[0]), 0.3, np.float32)
    obs1, r, *_ = vec.step(a)
    vec.close()
    for i, seed in enumerate((3, 4)):
        env = _env(clip, residual=True)
        o0, _ = env.reset(seed=seed)
        o1, ri, *_ = env.step(a[i])
        np.testing.assert_array_equal(o0, obs[i])
        np.testing.assert_array_equal(o1, obs1[i])
        assert ri == r[i]
        env.close()


def test_reward_at_zero_error_is_the_sum_of_the_weights(clip) -> None:
    _, demo, controls, scene = clip
    cfg = TrackEnvConfig.from_yaml()
    task = TrackTask(demo, scene, controls.q_targets, cfg, residual=True)
    t = 10
    obs = {"obj_pos": demo.object_pos[t], "obj_quat": demo.object_quat[t],
           "keypoints": demo.human_joints[t, scene.kp_human]}  # fmt: skip
    a = np.full(scene.n_dof, 0.5)
    r, e = task.reward(t, obs, a)
    assert task.touch.any()  # the example's fingertips touch the cube: the contact term is tested
    assert max(e.values()) < 1e-9
    weights = sum(term.weight for term in cfg.reward.terms().values())
    assert r == pytest.approx(weights - cfg.reward.action_cost * 0.25)
    # the object 1 cm off: 1 cm of position error, and the touching fingertips 1 cm off in its frame
    moved = {**obs, "obj_pos": demo.object_pos[t] + [0.01, 0, 0]}
    r1, e1 = task.reward(t, moved, a)
    assert e1["object_pos"] == pytest.approx(1.0) and e1["contact"] == pytest.approx(1.0)
    lost = sum(w.weight * (1 - np.exp(-1.0 / w.scale)) for w in (cfg.reward.object_pos, cfg.reward.contact))
    assert r - r1 == pytest.approx(lost)


def test_leaving_the_strict_limits_ends_the_episode(clip) -> None:
    env = _env(clip, residual=False, overrides={"randomize": False})
    away = np.zeros(env.action_space.shape, np.float32)
    away[2] = -1.0  # the base slides down 2 cm a frame: the hand cannot lift the cube
    _, _, info = _episode(env, [away] * 19)
    assert info["tracked"] is False
    assert info["frames"] < 19
    assert info["object_pos"] > 2.0 or info["object_rot"] > 30.0
    env.close()


@pytest.mark.parametrize("share", [0.4, 1.0])
def test_tracked_is_strict_success(clip, monkeypatch, share) -> None:
    """``info["tracked"]`` is the evaluation's strict success (:func:`quasisim.limits.strict_success`): within the
    strict limits at every frame *and* the object moved as in the demo. A demo lifting the cube 3 cm; the world's
    observations with the object scripted to move ``share`` of the demo's way: at 40 % every frame is within
    2 cm, but the object rose 1.2 of 3 cm (less than half): not tracked; the whole way: tracked."""
    from quasisim.data.demo import load_demo, save_demo
    from quasisim.limits import STRICT_CM, strict_success
    from quasisim.targets.mujoco_target import MujocoTarget

    path, demo, _, _ = clip
    p0 = demo.object_pos[0]
    low = load_demo(save_demo(dataclasses.replace(demo, object_pos=p0 + 0.25 * (demo.object_pos - p0)),
                              path.parent / "cube_low_lift.npz"))  # fmt: skip
    env = gym.make(quasisim.envs.TRACK_ID, clip=low.path, reference=path.parent / "kinematic.npz", residual=True)
    seen = []

    def observe(self):
        obs, t = observe.world(self), env.unwrapped._t
        obs["obj_pos"] = low.object_pos[0] + share * (low.object_pos[t] - low.object_pos[0])
        obs["obj_quat"] = np.asarray(low.object_quat[t], np.float64)
        seen.append((obs["obj_pos"], obs["obj_quat"]))
        return obs

    observe.world = MujocoTarget.observe
    monkeypatch.setattr(MujocoTarget, "observe", observe)
    zeros = np.zeros(env.action_space.shape, np.float32)
    _, _, info = _episode(env, [zeros] * (low.n_frames - 1), options={"world": None})
    pos, quat = (np.array(x) for x in zip(*seen, strict=True))
    assert info["frames"] == low.n_frames - 1 and len(pos) == low.n_frames  # the clip's end, every frame within
    assert 100 * np.linalg.norm(pos - low.object_pos, axis=-1).max() <= STRICT_CM
    assert info["tracked"] is strict_success(low.object_pos, low.object_quat, pos, quat) is (share == 1.0)
    env.close()


def test_bad_input_names_the_file_and_the_field(clip, tmp_path) -> None:
    path, _, controls, _ = clip
    short = dataclasses.replace(controls, q_targets=controls.q_targets[:-2])
    short.save(tmp_path / "short.npz")
    with pytest.raises(InputError, match=r"short\.npz.*q_targets"):
        gym.make(quasisim.envs.TRACK_ID, clip=path, reference=tmp_path / "short.npz")
    with pytest.raises(InputError, match=r"controls\.npz"):
        gym.make(quasisim.envs.TRACK_ID, clip=path, reference=tmp_path)
    with pytest.raises(InputError, match="terminate"):
        TrackEnvConfig.from_yaml(None, {"terminate": "never"})


def test_a_blow_up_ends_the_episode_with_no_reward(clip) -> None:
    """MuJoCo resets a state whose accelerations blow up (and warns): the episode must end there, unrewarded,
    not go on from the reset state."""
    env = _env(clip, residual=False, overrides={"randomize": False, "terminate": "unstable"})
    env.reset()
    world = env.unwrapped._world
    world.data.qvel[world.mm.hand_dof] = 1e12  # hands MuJoCo will not integrate (the object at rest)
    _, r, terminated, _, info = env.step(np.zeros(env.action_space.shape, np.float32))
    assert terminated and r == 0.0 and info["unstable"] and info["tracked"] is False
    env.close()


def test_bench_env_times_resets_and_steps(clip) -> None:
    """``quasisim bench env``: one markdown row of the environment's speed, with the counts asked for."""
    import subprocess
    import sys

    path = clip[0]
    args = ["bench", "env", path, "--reference", path.parent / "kinematic.npz", "--resets", 3, "--steps", 30]
    r = subprocess.run([sys.executable, "-m", "quasisim.cli", *map(str, args)], capture_output=True, text=True,
                       timeout=300)  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]
    row = r.stdout.strip().splitlines()[-1].strip("|").split("|")
    assert "resets/s" in r.stdout and int(row[2]) == 3 and int(row[5]) == 30
    assert all(float(x) > 0 for x in row)
