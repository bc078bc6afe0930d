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
from quasisim.envs.task import Contacts, TrackTask
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


def _quat_close(a, b, tol: float) -> bool:
    """Two unit quaternions (w x y z) of the same rotation within ``tol`` (either sign)."""
    a, b = np.asarray(a), np.asarray(b)
    return min(np.abs(a - b).max(), np.abs(a + b).max()) <= tol


def test_a_random_start_lands_on_the_drawn_frame_in_the_reference_replays_state(clip, monkeypatch) -> None:
    """``start: random``: the start frame is the env generator's draw after the world's, in [0, T - 2]; the world
    (a perturbed one) is in the state of the reference's nominal MuJoCo replay at that frame; the episode goes on
    from there and is never ``tracked``; a forced start works alike."""
    from gymnasium.utils import seeding

    import quasisim.limits

    _, demo, controls, scene = clip
    T = demo.n_frames
    with make_target("mujoco", scene) as tgt:
        ref = tgt.rollout(controls.q_targets)
    env = _env(clip, residual=True, overrides={"start": "random", "terminate": "unstable"})
    u = env.unwrapped
    starts = []
    for seed in range(6):
        _, info = env.reset(seed=seed)
        g, _ = seeding.np_random(seed)
        g.integers(2**31)  # the world's draw first
        assert info["start"] == int(g.integers(T - 1)) and info["world"] != -1
        starts.append(info["start"])
    assert len(set(starts)) > 2 and 0 <= min(starts) and max(starts) <= T - 2
    monkeypatch.setattr(quasisim.limits, "strict_success", lambda *a: True)  # the poses would all pass
    zeros = np.zeros(env.action_space.shape, np.float32)
    k = max(starts)
    for kw in ({"seed": starts.index(k)}, {"options": {"start": 7, "world": 4}}):
        obs, info = env.reset(**kw)
        k = info["start"]
        assert k == kw.get("options", {}).get("start", max(starts)) and u._t == k
        np.testing.assert_array_equal(u._prev, u.task.reference[k])
        assert obs[0] == pytest.approx(k / (T - 1))  # the clip's phase
        now = u._world.observe()
        np.testing.assert_allclose(now["obj_pos"], ref.object_pos[k], atol=1e-6)
        assert _quat_close(now["obj_quat"], ref.object_quat[k], 1e-6)
        np.testing.assert_allclose(now["qpos"], ref.qpos[k], atol=1e-6)
        seen, _, info = _episode(env, [zeros] * (T - 1), **kw)
        assert len(seen) == T - k and info["frames"] == T - 1  # the episode ran from frame k to the end
        assert info["tracked"] is False  # but not from frame 0
    _, _, info = _episode(env, [zeros] * (T - 1), options={"start": 0})
    assert info["tracked"] is True  # from frame 0: the (stubbed) strict success
    with pytest.raises(ValueError, match=r"start.*\[0, 18\]"):
        env.reset(options={"start": T - 1})
    env.close()


def test_a_forced_start_at_frame_0_is_the_reset_of_start_first(clip) -> None:
    actions = 0.3 * np.random.default_rng(2).uniform(-1, 1, (19, clip[3].n_dof)).astype(np.float32)
    old = _env(clip, residual=True)
    new = _env(clip, residual=True, overrides={"start": "random"})
    a = _episode(old, actions, seed=11)
    b = _episode(new, actions, seed=11, options={"start": 0})
    np.testing.assert_array_equal(np.array(a[0]), np.array(b[0]))
    assert a[1] == b[1] and len(a[1]) > 1
    info = new.reset(seed=11, options={"start": 0})[1]
    assert info == old.reset(seed=11)[1] and info["start"] == 0
    start = new.unwrapped.world_scene(info["world"]).object_pos0  # the drawn world's, not the nominal replay's
    assert not np.allclose(start, clip[1].object_pos[0], atol=1e-4)
    np.testing.assert_array_equal(new.unwrapped._world.observe()["obj_pos"], start)
    old.close()
    new.close()


def _off_by(monkeypatch, env, cm: float) -> None:
    """The env's MuJoCo world observes the object ``cm`` off the demo's position along x, at the demo's rotation."""
    from quasisim.targets.mujoco_target import MujocoTarget

    demo, world = env.unwrapped.task.demo, MujocoTarget.observe

    def observe(self):
        obs, t = world(self), env.unwrapped._t
        obs["obj_pos"] = demo.object_pos[t] + [cm / 100, 0.0, 0.0]
        obs["obj_quat"] = np.asarray(demo.object_quat[t], np.float64)
        return obs

    monkeypatch.setattr(MujocoTarget, "observe", observe)


def test_the_limits_loosen_then_tighten_over_the_envs_steps(clip, monkeypatch) -> None:
    """``limits_start: [6, 90]`` over ``limits_steps: 100``: the limits in force shrink linearly to the strict
    ones; an object 3 cm off ends the episode at the schedule's end but not at its start; the env counts its own
    steps and ``set_steps_taken`` continues the schedule from a count."""
    cfg = TrackEnvConfig.from_yaml(None, {"limits_start": [6, 90], "limits_steps": 100})
    assert [cfg.limits(n) for n in (0, 25, 50, 100, 10**6)] == [(6, 90), (5, 75), (4, 60), (2, 30), (2, 30)]
    assert TrackEnvConfig.from_yaml().limits(0) == (2.0, 30.0)  # the default: strict throughout
    env = _env(clip, residual=True, overrides={"randomize": False, "limits_start": [6, 90], "limits_steps": 100})
    _off_by(monkeypatch, env, 3.0)
    zeros = np.zeros(env.action_space.shape, np.float32)
    env.reset()
    for n in range(4):
        _, _, term, _, info = env.step(zeros)
        assert info["object_pos"] == pytest.approx(3.0) and not term  # within the loose limits
        assert info["limits"] == pytest.approx([6 - 4 * n / 100, 90 - 60 * n / 100])
    assert env.unwrapped.steps_taken == 4
    env.unwrapped.set_steps_taken(50)  # a resumed training: the schedule goes on from there
    env.reset()
    _, _, term, _, info = env.step(zeros)
    assert info["limits"] == pytest.approx([4.0, 60.0]) and not term
    _, _, term, _, info = env.step(zeros)
    assert info["limits"] == pytest.approx([3.96, 59.4]) and env.unwrapped.steps_taken == 52
    env.unwrapped.set_steps_taken(100)  # the schedule's end: the strict limits
    env.reset()
    _, _, term, _, info = env.step(zeros)
    assert info["limits"] == [2.0, 30.0] and term and info["tracked"] is False and info["frames"] == 1
    with pytest.raises(ValueError, match="set_steps_taken"):
        env.unwrapped.set_steps_taken(-1)
    env.close()


def test_new_settings_are_validated(clip) -> None:
    bad = {"start": "middle"}, {"limits_start": [1.5, 90]}, {"limits_start": [6, 20]}, {"limits_steps": -1}
    for override in bad:
        with pytest.raises(InputError, match=rf"track_env\.yaml.*'{next(iter(override))}'"):
            TrackEnvConfig.from_yaml(None, override)
    with pytest.raises(ValueError, match="start: random"):
        _env(clip, overrides={"start": "random"}, physics={"substeps": 1})


def test_a_validation_tie_keeps_the_later_model(clip, tmp_path, monkeypatch) -> None:
    """:class:`quasisim.policy.train.Selector`: a score equal to the best one so far replaces it (the later, more
    trained model); a lower one does not; a higher one does."""
    import json
    import shutil

    import quasisim.policy.controller as controller
    from quasisim.files import save_json_atomic
    from quasisim.policy.controller import Score
    from quasisim.policy.train import BEST, REFERENCE, SETUP, VALIDATION, Selector, TrainSetup

    path = clip[0]
    shutil.copyfile(path.parent / "kinematic.npz", tmp_path / REFERENCE)
    setup = TrainSetup(str(path), "ours+residual", "mujoco", "kinematic.npz")
    save_json_atomic(tmp_path / SETUP, dataclasses.asdict(setup))
    scores = {0: Score(False, 0.5, 0.5), 64: Score(False, 0.5, 0.5), 128: Score(False, 0.0, 0.9),
              192: Score(True, 0.0, 0.0)}  # fmt: skip

    class Model:
        def __init__(self, steps: int) -> None:
            self.num_timesteps = steps

        def save(self, p) -> None:
            p.write_text(str(self.num_timesteps))

    monkeypatch.setattr(controller, "validate", lambda task, model, *a: scores[model.num_timesteps])
    select = Selector(tmp_path, setup, 0)
    for steps, best in ((0, 0), (64, 64), (128, 64), (192, 192)):
        assert select(Model(steps)) == scores[steps]
        assert json.loads((tmp_path / VALIDATION).read_text())["best"]["steps"] == best
        assert (tmp_path / BEST).read_text() == str(best)


def test_the_hand_frame_in_the_observation(clip) -> None:
    """``observe_hand_frame``: 6 more numbers per hand, after the others: the object's position in the hand's frame
    (wrist keypoint; x to the middle of the index and ring finger bases, z their plane's normal) in 2 cm and its
    rotation relative to the frame in 30 deg, for a known pose."""
    from quasisim.keypoints import KEYPOINT_NAMES

    _, demo, controls, scene = clip
    cfg = TrackEnvConfig.from_yaml(None, {"observe_hand_frame": True})
    task = TrackTask(demo, scene, controls.q_targets, cfg, residual=True)
    plain = TrackTask(demo, scene, controls.q_targets, TrackEnvConfig.from_yaml(), residual=True)
    assert len(scene.hands) == 1 and task.observation_size == plain.observation_size + 6
    env = _env(clip, residual=True, overrides={"observe_hand_frame": True})
    assert env.observation_space.shape == (task.observation_size,) == env.reset()[0].shape
    env.close()
    D, K = scene.n_dof, len(scene.kp_human)
    wrist = np.array([0.1, 0.2, 0.3])
    kp = np.zeros((K, 3))
    for name, at in (("wrist", [0, 0, 0]), ("index_mcp", [0, 0.01, 0.01]), ("ring_mcp", [0, 0.01, -0.01])):
        kp[scene.kp_human == KEYPOINT_NAMES.index(name)] = wrist + at
    # the frame: x = (0, 1, 0), z = (-1, 0, 0), y = (0, 0, -1); a rotation of 120 deg about (-1, -1, 1)/sqrt 3
    obs = {"qpos": controls.q_targets[5], "qvel": np.zeros(D), "obj_pos": wrist + np.array([0.04, 0.02, 0.01]),
           "obj_quat": np.array([1.0, 0, 0, 0]), "obj_vel": np.zeros(3), "obj_angvel": np.zeros(3),
           "keypoints": kp}  # fmt: skip
    o = task.observation(5, obs)
    np.testing.assert_array_equal(o[:-6], plain.observation(5, obs))
    np.testing.assert_allclose(o[-6:-3], [1.0, -0.5, -2.0], atol=1e-6)  # (2, -1, -4) cm
    np.testing.assert_allclose(o[-3:], 4 / np.sqrt(3) * np.array([1, 1, -1]), atol=1e-5)  # 120 deg the other way


def test_the_learning_settings_pass_the_env_checker_and_skip_worlds_replays_the_starts(clip) -> None:
    """Random starts and the hand frame pass Gymnasium's checker (a limits schedule would not: it checks that a
    seed repeats the step's info, whose limits the env's step count sets); skipping ``n`` draws replays the
    worlds and the start frames of ``n`` resets."""
    overrides = {"start": "random", "observe_hand_frame": True}
    env = _env(clip, residual=True, overrides=overrides)
    check_env(env.unwrapped, skip_render_check=True)
    drawn = [env.reset(seed=5)[1]] + [env.reset()[1] for _ in range(3)]
    assert len({d["start"] for d in drawn}) > 1
    _, info = env.reset(seed=5, options={"skip_worlds": 2})  # a resumed training: worlds and starts go on
    assert [info, env.reset()[1]] == drawn[2:] and env.unwrapped.worlds_drawn == 4
    env.close()


def test_a_resumed_training_continues_the_limits_schedule(clip, tmp_path, monkeypatch) -> None:
    """``policy train --resume`` sets each environment's step count to the steps it had taken: the limits go on
    shrinking where they were (one environment in this process, 64 steps, then resumed to 128)."""
    pytest.importorskip("stable_baselines3", reason="the optional extra rl is not installed")
    from quasisim.envs.track import TrackEnv
    from quasisim.policy.train import prepare, train

    path, counts = clip[0], []
    step = TrackEnv.step
    monkeypatch.setattr(TrackEnv, "step", lambda self, a: counts.append(self.steps_taken) or step(self, a))
    out = tmp_path / "run"
    ppo = {"n_envs": 1, "n_steps": 64, "batch_size": 64, "checkpoint_every": 64, "validate_worlds": 0}
    prepare(path, out, path.parent / "kinematic.npz", "shadow", "mujoco", 3, {"limits_steps": 1000}, ppo)
    train(out, 64, progress=False)
    train(out, 128, resume=True, progress=False)
    assert counts == list(range(128))  # without set_steps_taken: 0..63 twice


# ---- reward_form: dgrasp (DGrasp's reward terms) ------------------------------------------------------------


def _dgrasp(clip, **overrides) -> TrackTask:
    _, demo, controls, scene = clip
    cfg = TrackEnvConfig.from_yaml(None, {"reward_form": "dgrasp", **overrides})
    return TrackTask(demo, scene, controls.q_targets, cfg, residual=True)


def _on_reference(task: TrackTask, t: int) -> dict:
    """Frame ``t`` exactly as the task's reference has it: the demo's object and keypoints, the reference's pose,
    nothing moving."""
    demo, D = task.demo, task.scene.n_dof
    return {"qpos": task.reference[t].copy(), "qvel": np.zeros(D), "obj_pos": demo.object_pos[t].copy(),
            "obj_quat": demo.object_quat[t].copy(), "obj_vel": np.zeros(3), "obj_angvel": np.zeros(3),
            "keypoints": demo.human_joints[t, task.scene.kp_human].copy()}  # fmt: skip


def _no_contact(task: TrackTask, weight: float = 1.0) -> Contacts:
    return Contacts(np.zeros(sum(h.n_bodies for h in task.scene.hands)), 0.05, weight)


def test_dgrasp_pos_term_weighs_fingertips_4x_in_the_objects_frame(clip) -> None:
    """``pos = -|w (x - x*)|^2``: on the reference 0; a fingertip 1 cm off costs (7/3 cm)^2 (Shadow: 5 tips of 21
    keypoints, weights 4 and 1 over their mean 36/21), the wrist 1 cm off (7/12 cm)^2, 16x less; moving hand and
    object together (a rotation and a shift) leaves it as it was, moving the object alone does not; at least -10."""
    from scipy.spatial.transform import Rotation

    from quasisim.keypoints import KEYPOINT_NAMES

    task, t = _dgrasp(clip), 12
    obs, none = _on_reference(task, t), _no_contact(task)
    assert task.dgrasp_terms(t, obs, none)["pos"] == pytest.approx(0.0, abs=1e-20)
    tip, wrist = (
        int(np.flatnonzero(task.scene.kp_human == KEYPOINT_NAMES.index(n))[0]) for n in ("index_tip", "wrist")
    )
    kp_tip, kp_wrist = obs["keypoints"].copy(), obs["keypoints"].copy()
    kp_tip[tip] += [0.0, 0.01, 0.0]
    kp_wrist[wrist] += [0.0, 0.0, -0.01]
    pos_tip = task.dgrasp_terms(t, {**obs, "keypoints": kp_tip}, none)["pos"]
    assert pos_tip == pytest.approx(-((0.01 * 7 / 3) ** 2))
    assert task.dgrasp_terms(t, {**obs, "keypoints": kp_wrist}, none)["pos"] == pytest.approx(-((0.01 * 7 / 12) ** 2))
    turn, shift = Rotation.from_rotvec([0.3, -0.5, 0.9]), np.array([0.2, -0.1, 0.05])
    q = obs["obj_quat"]
    quat = (turn * Rotation.from_quat([*q[1:], q[0]])).as_quat()
    moved = {**obs, "keypoints": turn.apply(kp_tip) + shift, "obj_pos": turn.apply(obs["obj_pos"]) + shift,
             "obj_quat": np.r_[quat[3], quat[:3]]}  # fmt: skip
    assert task.dgrasp_terms(t, moved, none)["pos"] == pytest.approx(pos_tip, rel=1e-9)
    assert task.dgrasp_terms(t, {**obs, "obj_pos": obs["obj_pos"] + shift}, none)["pos"] < -0.01
    assert task.dgrasp_terms(t, {**obs, "keypoints": obs["keypoints"] + 5.0}, none)["pos"] == -10.0


def test_dgrasp_pose_term_is_the_finger_joints_distance_to_the_reference(clip) -> None:
    """``pose = -|q - q*|`` over the finger joints (rad): two joints 0.3 and 0.4 rad off give -0.5; the base's six
    dofs do not count; at least -10."""
    task, t = _dgrasp(clip), 12
    obs, none = _on_reference(task, t), _no_contact(task)
    q = obs["qpos"].copy()
    q[[7, 12]] += [0.3, -0.4]
    q[:6] += 0.2  # the base
    assert task.dgrasp_terms(t, {**obs, "qpos": q}, none)["pose"] == pytest.approx(-0.5)
    assert task.dgrasp_terms(t, {**obs, "qpos": obs["qpos"] + 100.0}, none)["pose"] == -10.0


def test_dgrasp_contact_and_impulse_terms_count_the_demos_touching_fingertips(clip) -> None:
    """The demo touches the cube with three fingertips from frame 10 (none before): the target bodies are their
    distal phalanges. ``contact`` is the share of them pressing now; ``impulse`` their normal forces times the
    frame's duration, capped at 5 object weights; a body the demo does not touch with counts for neither."""
    task, t = _dgrasp(clip), 12
    names = [n for h in task.scene.hands for n in h.body_names]
    targets = task.contact_bodies(t)
    assert sorted(names[b] for b in targets) == ["robot0:ffdistal", "robot0:mfdistal", "robot0:thdistal"]
    assert len(task.contact_bodies(5)) == 0
    obs = _on_reference(task, t)

    def terms(pressing: dict[str, float], weight: float = 1.0, frame_t: int = t) -> dict[str, float]:
        f = np.zeros(len(names))
        for name, force in pressing.items():
            f[names.index(name)] = force
        return task.dgrasp_terms(frame_t, obs, Contacts(f, 0.05, weight))

    one = terms({"robot0:thdistal": 2.0, "robot0:palm": 7.0, "robot0:rfdistal": 3.0})
    assert one["contact"] == pytest.approx(1 / 3) and one["impulse"] == pytest.approx(2.0 * 0.05)
    two = terms({"robot0:thdistal": 2.0, "robot0:ffdistal": 4.0})
    assert two["contact"] == pytest.approx(2 / 3) and two["impulse"] == pytest.approx(6.0 * 0.05)
    every = {n: 1.0 for n in ("robot0:thdistal", "robot0:ffdistal", "robot0:mfdistal")}
    assert terms(every)["contact"] == pytest.approx(1.0)
    assert terms(every, frame_t=5)["contact"] == 0.0 and terms(every, frame_t=5)["impulse"] == 0.0  # no targets
    assert terms({"robot0:thdistal": 1000.0}, weight=0.3)["impulse"] == pytest.approx(5 * 0.3)  # 50 N s, capped
    assert terms({"robot0:thdistal": 20.0}, weight=0.3)["impulse"] == pytest.approx(1.0)  # under the cap


def test_dgrasp_velocity_penalties(clip) -> None:
    """``obj_vel = |v_object|^2``, ``body_vel`` and ``body_qvel`` the base's slide and hinge velocities squared;
    the finger joints' velocities and the object's spin do not count."""
    task, t = _dgrasp(clip), 12
    obs = _on_reference(task, t)
    qvel = np.zeros(task.scene.n_dof)
    qvel[:6] = [0.1, -0.2, 0.2, 1.0, 0.0, -2.0]
    qvel[6:] = 5.0
    moving = {**obs, "qvel": qvel, "obj_vel": np.array([1.0, 2.0, -2.0]), "obj_angvel": np.array([9.0, 9, 9])}
    terms = task.dgrasp_terms(t, moving, _no_contact(task))
    assert terms["obj_vel"] == pytest.approx(9.0)
    assert terms["body_vel"] == pytest.approx(0.09) and terms["body_qvel"] == pytest.approx(5.0)


def test_dgrasp_reward_sums_the_weighted_terms_clipped_at_minus_2(clip) -> None:
    """The reward is ``sum_k c_k term_k`` with DGrasp's coefficients, each weighted term in the info as ``r_k``
    beside the errors; a sum below ``clip`` (-2) is -2."""
    task, t = _dgrasp(clip), 12
    obs, a = _on_reference(task, t), np.zeros(task.scene.n_dof)
    f = np.zeros(sum(h.n_bodies for h in task.scene.hands))
    f[task.contact_bodies(t)[:2]] = [3.0, 1.0]
    contacts = Contacts(f, 0.05, 1.0)
    qvel = np.zeros(task.scene.n_dof)
    qvel[:6] = [0.2, 0, 0, 0, 0.4, 0]
    moving = {**obs, "qvel": qvel, "obj_vel": np.array([0.3, 0, 0])}
    r, info = task.reward(t, moving, a, contacts)
    expected = {"r_pos": 0.0, "r_pose": 0.0, "r_contact": 1.0 * 2 / 3, "r_impulse": 2.0 * 4.0 * 0.05,
                "r_obj_vel": -1.0 * 0.09, "r_body_vel": -0.5 * 0.04, "r_body_qvel": -0.5 * 0.16}  # fmt: skip
    assert {k: v for k, v in info.items() if k.startswith("r_")} == pytest.approx(expected, abs=1e-12)
    assert r == pytest.approx(sum(expected.values())) and info["object_pos"] == pytest.approx(0.0, abs=1e-9)
    fast = {**moving, "obj_vel": np.array([2.0, 0, 0])}  # -4 from the object's speed alone
    r, info = task.reward(t, fast, a, contacts)
    assert r == -2.0 and sum(v for k, v in info.items() if k.startswith("r_")) < -3.0
    assert _dgrasp(clip, **{"dgrasp_reward.clip": -10.0}).reward(t, fast, a, contacts)[0] < -3.0
    with pytest.raises(ValueError, match="contacts"):
        task.reward(t, obs, a)


def test_reward_form_tracking_is_todays_reward(clip) -> None:
    """The default form is ``tracking``: an episode's rewards are the tracking reward's closed form of each step's
    errors, ``sum_k w_k exp(-e_k / s_k) - c |a|^2 / D``, the same with ``reward_form: tracking`` set, and no DGrasp
    term in the info."""
    cfg = TrackEnvConfig.from_yaml()
    assert cfg.reward_form == "tracking"
    actions = np.random.default_rng(3).uniform(-1, 1, (5, clip[3].n_dof)).astype(np.float32)
    seen = []
    for overrides in ({}, {"reward_form": "tracking"}):
        env = _env(clip, residual=True, overrides={"terminate": "unstable", **overrides})
        env.reset(seed=1)
        rewards = []
        for a in actions:
            _, r, _, _, info = env.step(a)
            assert not any(k.startswith("r_") for k in info)
            closed = sum(w.weight * np.exp(-info[k] / w.scale) for k, w in cfg.reward.terms().items())
            assert r == closed - cfg.reward.action_cost * float(np.mean(np.square(a)))  # the same sums, bit for bit
            rewards.append(r)
        seen.append(rewards)
        env.close()
    assert seen[0] == seen[1]


@pytest.mark.parametrize("target", ["mujoco", "pybullet"])
def test_an_episode_with_the_dgrasp_reward(clip, target) -> None:
    """The env's zero-residual episode with ``reward_form: dgrasp`` in a training world (the object heavier or
    lighter than the scene's): every step's reward is the clipped sum of its ``r_*`` terms, and the contact and
    impulse terms read the world's own contacts (each hand body's force, the physics step x substeps, this world's
    object weight: with a cap of 0.001 object weights, the impulse of a frame with contacts is that cap). In
    PyBullet the fingertips reach the cube while the demo touches it (all three of them at once at some frame)."""
    overrides = {"reward_form": "dgrasp", "terminate": "unstable", "dgrasp_reward.impulse_cap": 0.001}
    env = _env(clip, residual=True, target=target, overrides=overrides)
    task = env.unwrapped.task
    env.reset(options={"world": 2})
    world = env.unwrapped._world
    weight = world.scene.obj.mass * world.scene.physics.gravity
    assert world.scene.obj.mass != task.scene.obj.mass
    shares = []
    for _ in range(task.n_frames - 1):
        _, r, done, _, info = env.step(np.zeros(env.action_space.shape, np.float32))
        terms = {k: v for k, v in info.items() if k.startswith("r_")}
        assert len(terms) == 7 and r == max(-2.0, sum(terms.values()))
        f = env.unwrapped._world.body_contact_forces()[task.contact_bodies(info["frame"])]
        impulse = min(f.sum() * world.dt * world.substeps, 0.001 * weight)
        assert info["r_impulse"] == pytest.approx(2.0 * impulse, rel=1e-12, abs=1e-15)
        assert info["r_contact"] == pytest.approx(np.mean(f > 0) if len(f) else 0.0)
        if info["r_contact"] > 0:
            assert info["r_impulse"] == pytest.approx(2.0 * 0.001 * weight, rel=1e-12)
        shares.append(info["r_contact"])
        if done:
            break
    if target == "pybullet":
        assert max(shares) == pytest.approx(1.0)
    env.close()


def test_the_dgrasp_settings_are_validated(clip) -> None:
    bad = (
        ({"reward_form": "dgrasp2"}, "reward_form"),
        ({"dgrasp_reward.impulse_cap": 0.0}, "dgrasp_reward.impulse_cap"),
        ({"dgrasp_reward.pos": "high"}, "dgrasp_reward.pos"),
        ({"dgrasp_reward.speed": 1.0}, "dgrasp_reward.speed"),
    )
    for override, name in bad:
        with pytest.raises(InputError, match=rf"track_env\.yaml.*'{name}'"):
            TrackEnvConfig.from_yaml(None, override)
    with pytest.raises(ValueError, match="reward_form: dgrasp"):
        _env(clip, overrides={"reward_form": "dgrasp"}, physics={"substeps": 1})
    with pytest.raises(ValueError, match="action_form: dgrasp"):
        _env(clip, overrides={"action_form": "dgrasp"}, physics={"substeps": 1})
