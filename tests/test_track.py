"""Closed-loop tracking (:mod:`quasisim.method.track`) and closed-loop robust success (:mod:`quasisim.eval.robust`).

The tracker's model is the nominal target re-synced to the observed state: ``Target.sync`` puts an observation
back exactly (MuJoCo and PyBullet); the tracker never holds the world's hidden parameters and decides the same
from the same observation whatever they are; in the nominal world it follows the plan; the wide set's push
reaches the object; the CLI writes ``robust_closed_loop`` beside ``robust``.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest

from helpers import cube_example
from quasisim.errors import InputError
from quasisim.eval.robust import RobustConfig, perturbed_scene, push_of, replay, replays
from quasisim.method.config import TransferConfig
from quasisim.method.track import Tracker, TrackOptions, closed_loop, shift_bases
from quasisim.targets import OBS_KEYS, make_target

FAST = TrackOptions(every=2, samples=6, horizon=3)  # a cheap tracker for tests


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """The bundled example (20 frames), its kinematic retarget and their scene."""
    return cube_example(tmp_path_factory.mktemp("track"))


@pytest.fixture(scope="module")
def sampled(clip):
    """A plan that lifts the cube: sample-target's PD targets of the example (its sampling stage, ~6 s)."""
    from quasisim.method.stages.sampling import run_sampling

    _, demo, controls, scene = clip
    cfg = TransferConfig.from_yaml()
    return run_sampling(demo, scene, controls.q_targets, cfg.sampling, cfg.weights, progress=False).q_targets


def _mid_run_observation(target, q: np.ndarray, frames: int) -> dict[str, np.ndarray]:
    target.reset(q[0], (q[1] - q[0]) * target.scene.fps)
    for t in range(frames):
        target.advance(q[t], q[t + 1])
    return target.observe()


@pytest.mark.parametrize("backend", ["mujoco", "pybullet"])
def test_sync_puts_an_observed_state_back_exactly(clip, backend) -> None:
    _, _, controls, scene = clip
    q = controls.q_targets
    with make_target(backend, scene) as world, make_target(backend, scene) as model:
        obs = _mid_run_observation(world, q, 8)
        assert np.abs(obs["obj_vel"]).max() + np.abs(obs["qvel"]).max() > 1e-3  # a moving state, not a rest
        model.reset(q[0])
        model.sync(obs)
        back = model.observe()
        for k in OBS_KEYS:
            np.testing.assert_allclose(back[k], obs[k], atol=1e-9, err_msg=k)
        world.advance(q[8], q[9])
        model.advance(q[8], q[9])
        a, b = world.observe(), model.observe()
        # one frame on from the synced copy: the same physics (solver warm start and contact history aside)
        assert np.abs(a["qpos"] - b["qpos"]).max() < 1e-3 and np.abs(a["obj_pos"] - b["obj_pos"]).max() < 1e-3


def test_shifting_the_plan_moves_every_keypoint_by_the_offset(clip) -> None:
    _, _, controls, scene = clip
    d = np.array([0.004, -0.003, 0.0])
    q = controls.q_targets[5]
    with make_target("mujoco", scene) as tg:
        tg.reset(q)
        before = tg.observe()["keypoints"]
        tg.reset(shift_bases(scene, q[None], d)[0])
        after = tg.observe()["keypoints"]
    np.testing.assert_allclose(after - before, np.broadcast_to(d, before.shape), atol=1e-9)


@pytest.mark.parametrize("adapt", [False, True])
def test_the_tracker_never_reads_the_worlds_hidden_parameters(clip, sampled, adapt) -> None:
    """A world whose object is 2x heavier, with half the friction and 5 mm off its start: the tracker's model
    keeps the nominal mass and friction, and a
    tracker fed the same observed states from a world with the nominal parameters decides the same targets
    (also when it learns the world, ``adapt``: its models come from the nominal scene and the training ranges)."""
    _, demo, _, scene = clip
    q, weights = sampled, TransferConfig.from_yaml().weights
    opts = dataclasses.replace(FAST, samples=16, adapt=adapt)
    heavy = dataclasses.replace(scene.obj, mass=2 * scene.obj.mass, inertia=2 * scene.obj.inertia)
    object.__setattr__(heavy, "_memo", scene.obj._memo)
    heavy_scene = dataclasses.replace(
        scene,
        obj=heavy,
        physics=dataclasses.replace(scene.physics, friction=0.5 * scene.physics.friction),
        object_pos0=scene.object_pos0 + np.array([0.004, -0.003, 0.0]),
    )
    seen, acted = [], []
    with make_target("mujoco", heavy_scene) as world, Tracker(demo, scene, q, opts, weights) as a:
        world.reset(q[0], (q[1] - q[0]) * scene.fps)
        obs, prev = world.observe(), q[0]
        a.start(obs)
        for t in range(len(q) - 1):
            seen.append(obs)
            acted.append(a.act(t, obs))
            world.advance(prev, acted[-1])
            prev, obs = acted[-1], world.observe()

        def friction(m) -> float:  # of the geoms that collide
            return float(m.geom_friction[(m.geom_contype | m.geom_conaffinity) > 0, 0].max())

        w = world.mm.model  # the world is what the test says (twice the mass, half the friction) ...
        assert w.body_mass[world.mm.obj_body] == pytest.approx(2 * scene.obj.mass)
        assert friction(w) == pytest.approx(0.5 * scene.physics.friction)
        for t in a.models:  # ... and no model of the tracker's holds either (adapt's stay within the ranges)
            assert t.mm.model.body_mass[t.mm.obj_body] <= 1.151 * scene.obj.mass
            assert friction(t.mm.model) >= 0.79 * scene.physics.friction
    moved = np.abs(np.asarray(acted) - shift_bases(scene, q[1:], a.offset)).max()
    assert moved > 1e-4  # the tracker re-planned away from the plan in the heavy world
    with make_target("mujoco", scene) as twin, Tracker(demo, scene, q, opts, weights) as b:
        twin.reset(q[0], (q[1] - q[0]) * scene.fps)
        twin.sync(seen[0])
        b.start(twin.observe())
        for t in range(len(q) - 1):
            twin.sync(seen[t])  # the nominal world, put into the state the heavy one was observed in
            np.testing.assert_allclose(b.act(t, twin.observe()), acted[t], atol=1e-9, err_msg=f"frame {t}")


def test_in_the_nominal_world_the_tracker_follows_the_plans_rollout(clip) -> None:
    _, demo, controls, scene = clip
    q = controls.q_targets
    with make_target("mujoco", scene) as tg:
        nominal = tg.rollout(q)
    maker = closed_loop(FAST)(demo, scene, q, "mujoco")
    with make_target("mujoco", scene) as world:
        tracker = maker()
        run = replay(world, q, tracker)
        tracker.close()
    assert tracker.replans == len(range(0, len(q) - 1, 2))
    c = tracker.cost()  # the time per control step: re-planning steps and following ones (every 2)
    assert len(tracker.step_seconds) == len(q) - 1 and 0 < c["step_ms_p50"] <= c["step_ms_p95"]
    assert np.abs(run.object_pos - nominal.object_pos).max() < 2e-3
    assert np.abs(run.keypoints - nominal.keypoints).max() < 5e-3


def test_the_wide_set_pushes_the_object_mid_clip_and_keeps_the_default_worlds(clip) -> None:
    _, _, controls, scene = clip
    wide, default = replays(2, "wide"), replays(2)
    assert wide.name == "robust_wide" and wide.closed_loop_key == "robust_wide_closed_loop"
    assert wide.mass == pytest.approx(2 * default.mass) and wide.push > 0 and default.push == 0
    frame, dv = push_of(wide, 0, len(controls.q_targets))
    assert frame == round(0.5 * (len(controls.q_targets) - 1)) and dv[2] == 0
    assert np.linalg.norm(dv) == pytest.approx(wide.push)
    assert push_of(default, 0, 20) is None
    # the default worlds are the ones drawn before the push existed (5 draws, seeded by (seed, i))
    u = np.random.default_rng([default.seed, 1]).uniform(-1.0, 1.0, size=5)
    assert perturbed_scene(scene, default, 1).obj.mass == pytest.approx(scene.obj.mass * (1 + default.mass * u[0]))
    q = controls.q_targets
    with make_target("mujoco", scene) as world:
        still = replay(world, q)
        pushed = replay(world, q, push=(frame, dv))
    np.testing.assert_array_equal(pushed.object_pos[: frame + 1], still.object_pos[: frame + 1])
    moved = pushed.object_pos[frame + 1] - still.object_pos[frame + 1]  # a cube on the table: friction stops it
    assert np.linalg.norm(moved) > 2e-4 and np.dot(moved, dv) / np.linalg.norm(moved) / wide.push > 0.9


def test_bad_tracker_settings_name_the_field(tmp_path) -> None:
    with pytest.raises(InputError, match="every"):
        TrackOptions.from_yaml(None, {"every": -1})
    with pytest.raises(InputError, match="samples"):
        TrackOptions.from_yaml(None, {"samples": 1})
    with pytest.raises(InputError, match="noise_joints"):
        TrackOptions.from_yaml(None, {"noise_joints": -1.0})
    with pytest.raises(InputError, match="push"):
        RobustConfig(push=5.0)
    with pytest.raises(InputError, match="grip"):
        TrackOptions.from_yaml(None, {"grip": [-0.1]})
    with pytest.raises(InputError, match="len\\(grip\\)"):
        TrackOptions.from_yaml(None, {"grip": [0.05, 0.1], "samples": 3})


def test_the_shipped_trackers_load_and_the_real_time_one_plans_beside_the_controller() -> None:
    """Every shipped tracker preset is valid; ``track_realtime.yaml`` re-plans every ``lead`` frames (a planner
    that may take that many frame periods per re-plan) with a smaller search than the fast one."""
    from quasisim.method.options import tracker_file

    names = [p.name for p in tracker_file("track.yaml").parent.glob("track*.yaml") if p.name != "track_env.yaml"]
    assert {"track.yaml", "track_fast.yaml", "track_realtime.yaml"} <= set(names)
    opts = {n: TrackOptions.preset(n) for n in names}
    rt, fast = opts["track_realtime.yaml"], opts["track_fast.yaml"]
    assert rt.lead == rt.every > 1 and opts["track.yaml"].lead == fast.lead == 0
    assert rt.samples * rt.horizon < fast.samples * fast.horizon


def test_evaluate_closed_loop_writes_both_loops_for_both_sets(clip, tmp_path) -> None:
    path, _, _, _ = clip
    out = tmp_path / "eval"
    cmd = [sys.executable, "-m", "quasisim.cli", "evaluate", str(path), str(path.parent / "kinematic.npz"), "--out", str(out),
           "--no-render", "--robust", "1", "--closed-loop", "--ranges", "default,wide"]  # fmt: skip
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    m = json.loads((out / "metrics.json").read_text())
    for key in ("robust", "robust_closed_loop", "robust_wide", "robust_wide_closed_loop"):
        assert m[key]["n"] == 1 and set(m[key]) >= {"seed", "strict", "20deg_20cm", "unstable"}, key
    assert m["robust_closed_loop"]["tracker"]["replans"] == 19 and m["robust_closed_loop"]["seconds_per_replay"] > 0
    assert "closed loop strict" in r.stdout
    bad = subprocess.run([*cmd[:-5], "--closed-loop", "--overwrite"], capture_output=True, text=True, timeout=600)
    assert bad.returncode != 0 and "--robust N" in bad.stderr
    bad = subprocess.run([*cmd[:-1], "huge", "--overwrite"], capture_output=True, text=True, timeout=600)
    assert bad.returncode != 0 and "default" in bad.stderr and "wide" in bad.stderr


def test_the_tracker_drives_pybullet_through_the_same_interface(clip) -> None:
    """PyBullet as world and model: the same tracker, re-planning with PyBullet's window rollouts."""
    _, demo, controls, scene = clip
    q = controls.q_targets[:8]
    opts = TrackOptions(every=2, samples=3, horizon=2)
    with make_target("pybullet", scene) as tg:
        nominal = tg.rollout(q)
    with make_target("pybullet", scene) as world, Tracker(demo, scene, q, opts, TransferConfig.from_yaml().weights,
                                                            "pybullet", nominal) as tracker:  # fmt: skip
        run = replay(world, q, tracker)
    assert tracker.replans == 4 and tracker.physics_steps > 0 and run.target == "pybullet"
    assert np.abs(run.object_pos - nominal.object_pos).max() < 2e-3


def test_transfer_and_the_bench_pass_write_closed_loop_beside_open_loop(clip, tmp_path) -> None:
    """``transfer --robust 1 --closed-loop`` judges its result both ways; the bench pass over finished runs
    (:mod:`quasisim.bench.closed_loop`) adds both sets, caches each run's result and tabulates open / closed."""
    from click.testing import CliRunner

    from quasisim.bench import closed_loop as cl
    from quasisim.cli import main
    from quasisim.data.controls import load_controls

    path = clip[0]
    run = tmp_path / "runs" / path.stem / "retarget"
    args = ["transfer", str(path), "--method", "kinematic", "--out", str(run), "--no-render", "--robust", "1"]
    r = CliRunner().invoke(main, [*args, "--closed-loop"])
    assert r.exit_code == 0, r.output
    m = json.loads((run / "metrics.json").read_text())
    assert m["robust"]["n"] == m["robust_closed_loop"]["n"] == 1 and "robust_wide" not in m
    assert "closed loop strict" in r.output
    rows = [{"clip": path.stem, "method": "retarget", "seconds": {"sample": 1.0}}]
    first = cl.add_closed_loop(rows, tmp_path / "runs", {path.stem: path}, 1, ("default",), "mujoco", 1)
    (cached,) = run.glob("robust_closed_loop-*.json")  # one cache per (run, set)
    stamp = cached.stat().st_mtime_ns
    out = cl.add_closed_loop(rows, tmp_path / "runs", {path.stem: path}, 1, ("default", "wide"), "mujoco", 1)
    assert {"robust", "robust_closed_loop", "robust_wide", "robust_wide_closed_loop"} <= set(out[0])
    assert out[0]["robust"] == m["robust"]  # the same seeded worlds as the run's own judging
    assert out[0]["robust_closed_loop"] == first[0]["robust_closed_loop"] and cached.stat().st_mtime_ns == stamp
    assert len(list(run.glob("robust_closed_loop-*.json"))) == 2  # the set added later reused the first
    (run / "controls.npz").rename(run / "moved.npz")  # a cached run needs no controls
    again = cl.add_closed_loop(rows, tmp_path / "runs", {path.stem: path}, 1, ("default", "wide"), "mujoco", 1)
    assert again == out
    c = load_controls(run / "moved.npz")  # the run planned again: other controls are judged again
    dataclasses.replace(c, q_targets=c.q_targets + 0.01).save(run / "controls.npz")
    cl.add_closed_loop(rows, tmp_path / "runs", {path.stem: path}, 1, ("default",), "mujoco", 1)
    assert cached.stat().st_mtime_ns != stamp
    assert json.loads(cached.read_text())["controls_sha256"] == cl.controls_sha(run)
    text = "\n".join(cl.markdown(out, ("retarget",), ("default", "wide")))
    assert "| robust | retarget | 1 |" in text and "| robust_wide | retarget | 1 |" in text


def test_two_hands_are_tracked_and_shifted_together(tmp_path) -> None:
    """A two-hand demo: both hands' bases move with the object's start offset, and closed-loop replays run."""
    from click.testing import CliRunner

    from quasisim.cli import main
    from quasisim.data.controls import load_controls
    from quasisim.data.demo import load_demo
    from quasisim.data.synthetic import write_example
    from quasisim.eval.evaluate import hands_of
    from quasisim.targets.build import scene_for
    from quasisim.targets.scene import place_hands

    demo_path = write_example("cube_lift", tmp_path, n_frames=12, two_hands=True)
    r = CliRunner().invoke(main, ["retarget", str(demo_path), "--hand", "shadow", "--out", str(tmp_path / "k")])
    assert r.exit_code == 0, r.output
    ev = tmp_path / "ev"
    args = ["evaluate", str(demo_path), str(tmp_path / "k" / "kinematic.npz"), "--out", str(ev), "--no-render"]
    r = CliRunner().invoke(main, [*args, "--robust", "1", "--closed-loop", "--track-set", "samples=4"])
    assert r.exit_code == 0, r.output
    m = json.loads((ev / "metrics.json").read_text())
    assert m["robust_closed_loop"]["tracker"]["replans"] > 0
    c = load_controls(tmp_path / "k" / "kinematic.npz")
    scene = scene_for(load_demo(demo_path), place_hands(hands_of(c, None), c.base_rots))
    d = np.array([0.003, 0.002, 0.0])
    moved = shift_bases(scene, c.q_targets, d) - c.q_targets
    assert len(scene.dof_slices) == 2
    for sl in scene.dof_slices:
        np.testing.assert_allclose(moved[:, sl.start : sl.start + 3], np.broadcast_to(d, (len(moved), 3)))
        assert not moved[:, sl.start + 3 : sl.stop].any()


class _Recorder:
    """A policy that applies the plan as it is and keeps what it was shown."""

    def __init__(self, q: np.ndarray) -> None:
        self.q, self.seen = q, []

    def start(self, obs):
        pass

    def act(self, t, obs):
        self.seen.append(obs)
        return self.q[t + 1]

    def cost(self):
        return {}

    def close(self):
        pass


def test_sensing_noise_and_latency_reach_the_controller_and_never_the_world(clip, sampled) -> None:
    from quasisim.eval.robust import finger_columns
    from quasisim.targets.perturb import Sensor

    _, _, _, scene = clip
    q = sampled
    cfg = replays(1, "sensing")
    assert cfg.senses and cfg.latency == 1 and cfg.obs_pos == pytest.approx(0.002) and not replays(1).senses
    fingers = finger_columns(scene)
    assert fingers.sum() == scene.hands[0].n_joints and not fingers[:6].any()
    world_scene = perturbed_scene(scene, cfg, 0)
    with make_target("mujoco", world_scene) as world:
        blind = replay(world, q)  # open loop: what the world does with the plan
        rec = _Recorder(q)
        run = replay(world, q, rec, sensor=Sensor(cfg, 0, fingers))
        # the same plan applied through a noisy, late sensor: the world runs bit for bit as open loop
        np.testing.assert_array_equal(run.object_pos, blind.object_pos)
        np.testing.assert_array_equal(run.qpos, blind.qpos)
        late = _Recorder(q)
        replay(
            world,
            q,
            late,
            sensor=Sensor(dataclasses.replace(cfg, obs_pos=0.0, obs_rot=0.0, obs_joints=0.0), 0, fingers),
        )
    seen = rec.seen  # what the controller was shown at frames 0 .. T-2 (it acts T-1 times)
    assert len(seen) == len(q) - 1
    # latency 1, no noise: at frame t the controller sees the world's frame t - 1 (frame 0 at the start)
    for t, obs in enumerate(late.seen):
        np.testing.assert_array_equal(obs["obj_pos"], run.object_pos[max(0, t - 1)])
        np.testing.assert_array_equal(obs["qpos"], run.qpos[max(0, t - 1)])
    # with noise: object position off by ~obs_pos per axis, finger joints by ~obs_joints, the base exact
    dp = np.array([o["obj_pos"] for o in seen]) - run.object_pos[np.maximum(0, np.arange(len(seen)) - 1)]
    dq = np.array([o["qpos"] for o in seen]) - run.qpos[np.maximum(0, np.arange(len(seen)) - 1)]
    assert 0.5 * cfg.obs_pos < dp.std() < 1.5 * cfg.obs_pos
    assert 0.5 * cfg.obs_joints < dq[:, fingers].std() < 1.5 * cfg.obs_joints
    assert np.abs(dq[:, ~fingers]).max() == 0.0
    rot = [np.degrees(2 * np.arccos(min(1.0, abs(float(np.dot(o["obj_quat"], run.object_quat[max(0, t - 1)]))))))
           for t, o in enumerate(seen)]  # fmt: skip
    assert 1.0 < np.mean(rot) < 6.0  # 2 deg per axis: about 3.2 deg on average


def test_a_late_observation_is_brought_up_to_date_through_the_targets_applied_since(clip, sampled) -> None:
    """Latency: an observation stamped two frames old is synced into the model and advanced through the two
    targets applied since; the tracker re-plans from that prediction, close to the world's state now."""
    _, demo, _, scene = clip
    q, weights = sampled, TransferConfig.from_yaml().weights
    with make_target("mujoco", scene) as world, Tracker(demo, scene, q, FAST, weights) as tr:
        world.reset(q[0], (q[1] - q[0]) * scene.fps)
        obs, prev, past = world.observe(), q[0], []
        tr.start(obs)
        for t in range(12):
            past.append(obs)
            nxt = tr.act(t, obs)
            world.advance(prev, nxt)
            prev, obs = nxt, world.observe()
        late = {**past[-2], "frame": np.array(10)}  # frame 10's state, seen at frame 12
        now = tr._now(12, late)
    assert np.linalg.norm(past[-2]["obj_pos"] - obs["obj_pos"]) > 2e-3  # the cube moved in those two frames
    assert np.linalg.norm(now["obj_pos"] - obs["obj_pos"]) < 2e-4
    assert np.abs(now["qpos"] - obs["qpos"]).max() < 2e-3
    assert tr._now(12, obs) is obs  # a current observation is taken as it is


@pytest.mark.parametrize("gains", [1.0, 0.9])
def test_the_tracker_learns_the_gains_of_the_world_from_observed_transitions(clip, sampled, gains) -> None:
    """adapt: in a world whose PD gains are 0.9x the nominal, the observed transitions pick the model with 0.9x
    gains; in the nominal world the nominal model stays. The world is only observed (the same hidden-parameter
    rule as above: the models are built from the nominal scene and the training ranges)."""
    from quasisim.targets.perturb import scaled_scene

    _, demo, _, scene = clip
    q, weights = sampled, TransferConfig.from_yaml().weights
    opts = dataclasses.replace(FAST, adapt=True)
    with make_target("mujoco", scaled_scene(scene, gains=gains)) as world, Tracker(demo, scene, q, opts, weights) as tr:
        replay(world, q, tr)
        chosen = tr.models.index(tr.model)
        gain_of = [m.scene.physics.gain_scale / scene.physics.gain_scale for m in tr.models]
    assert len(tr.models) == 7 and chosen == int(np.argmin(tr.scores))
    assert gain_of[chosen] == pytest.approx(gains)
    if gains == 1.0:
        assert chosen == 0


def _sensed_replay(clip, sampled, opts: TrackOptions, cfg: RobustConfig, after: int) -> tuple[Tracker, float, float]:
    """The plan tracked in the nominal world seen through ``cfg``'s sensor: the tracker, and the mean distance
    (m) to the world's object position of its estimate and of the observations, over the frames after ``after``."""
    from quasisim.eval.robust import finger_columns
    from quasisim.targets.perturb import Sensor

    _, demo, _, scene = clip
    q, weights = sampled, TransferConfig.from_yaml().weights
    seen, est, true = [], [], []
    with make_target("mujoco", scene) as world, Tracker(demo, scene, q, opts, weights) as tr:
        sensor = Sensor(cfg, 0, finger_columns(scene))
        world.reset(q[0], (q[1] - q[0]) * scene.fps)
        obs, prev = world.observe(), q[0]
        shown = sensor.see(obs)
        tr.start(shown)
        for t in range(len(q) - 1):
            nxt = tr.act(t, shown)
            if t > after:
                seen.append(shown["obj_pos"]), est.append(tr._est["obj_pos"]), true.append(obs["obj_pos"])
            world.advance(prev, nxt)
            prev, obs = nxt, world.observe()
            shown = sensor.see(obs)
    err = lambda x: float(np.linalg.norm(np.array(x) - np.array(true), axis=1).mean())  # noqa: E731
    return tr, err(est), err(seen)


def test_a_low_observation_gain_filters_the_sensors_noise(clip, sampled) -> None:
    """obs_gain 0.3: the state the tracker re-plans from (its estimate: the model's prediction moved 30 % toward
    each observation) is closer to the world's state than the noisy observations it was given."""
    opts = dataclasses.replace(FAST, every=1, obs_gain=0.3)
    _, err_est, err_obs = _sensed_replay(clip, sampled, opts, RobustConfig(n=1, obs_pos=0.004), after=0)
    assert err_est < 0.6 * err_obs, (err_est, err_obs)


@pytest.mark.parametrize("ratio", [0.0, 0.1, 1.0])
def test_a_learned_gain_finds_the_kalman_gain_of_a_random_walk(ratio) -> None:
    """A random walk (step variance q) seen through white noise (variance r), its model "the state stays": the
    learned gain settles at the steady-state Kalman gain, ``k^2 / (1 - k) = q / r`` (0.27 for q / r = 0.1,
    0.62 for 1), and stays at 1 for an exact sensor (r = 0)."""
    from quasisim.method.track import learn_innovation

    rng = np.random.default_rng(1)
    q, r = (1.0, 0.0) if ratio == 0 else (ratio, 1.0)
    x, est, s, ks = 0.0, 0.0, None, []
    for _ in range(3000):
        x += np.sqrt(q) * rng.standard_normal()
        e = x + np.sqrt(r) * rng.standard_normal() - est  # the prediction: the last estimate
        s = learn_innovation(s, np.array([e]), 0.98)
        est += float(s.k[0]) * e
        ks.append(float(s.k[0]))
    k = float(np.mean(ks[1000:]))
    optimum = 1.0 if r == 0 else (-ratio + np.sqrt(ratio**2 + 4 * ratio)) / 2
    assert abs(k - optimum) < 0.1, (k, optimum)


def test_learned_gains_filter_the_noisy_sensors_and_trust_the_exact_ones(clip, sampled) -> None:
    """obs_adapt with 4 mm noise on the object's observed position (a 20-frame clip): its learned gain falls and
    the estimate comes closer to the world than the observations; the object's velocity, observed without
    noise, keeps a gain near 1."""
    opts = dataclasses.replace(FAST, every=1, obs_adapt=True)
    tr, err_est, err_obs = _sensed_replay(clip, sampled, opts, RobustConfig(n=1, obs_pos=0.004), after=8)
    cost = tr.cost()
    assert err_est < 0.85 * err_obs, (err_est, err_obs)
    assert tr._gains[-1]["obj_pos"] < 0.8 and cost["gain_obj_vel"] > 0.9, (tr._gains[-1], cost)


def test_a_replan_beside_the_controller_changes_only_the_frames_after_its_lead(clip, sampled) -> None:
    """lead 2: the re-plan that starts at frame t plans from the state predicted at t + 2 and leaves the targets
    of frames up to t + 2 as they were committed (a planner in its own thread cannot change what the controller
    applies meanwhile); in a perturbed world it still re-plans (its result differs from the plan), and it keeps
    the re-plan times that real time is judged by."""
    from quasisim.targets.perturb import scaled_scene

    _, demo, _, scene = clip
    q, weights = sampled, TransferConfig.from_yaml().weights
    opts = dataclasses.replace(FAST, every=2, lead=2)
    calls = []
    world_scene = scaled_scene(scene, friction=0.7, gains=0.9)
    with make_target("mujoco", world_scene) as world, Tracker(demo, scene, q, opts, weights) as tr:
        plan = tr._replan

        def watched(t: int, obs: dict) -> None:
            before = tr._work.copy()
            plan(t, obs)
            calls.append((t, before, tr._work.copy(), obs["obj_pos"]))

        tr._replan = watched
        run = replay(world, q, tr)
    assert [c[0] for c in calls] == list(range(2, len(q) - 1, 2))  # started at 0, 2, ..., acting 2 frames on
    for t, before, after, _ in calls:
        np.testing.assert_array_equal(after[: t + 1], before[: t + 1], err_msg=f"re-plan for frame {t}")
    assert any(not np.array_equal(a[t + 1 :], b[t + 1 :]) for t, b, a, _ in calls)
    # it planned from the state predicted 2 frames ahead: closer to the world's then than the observation was
    ahead = np.array([np.linalg.norm(p - run.object_pos[t]) for t, _, _, p in calls])
    seen = np.array([np.linalg.norm(run.object_pos[t - 2] - run.object_pos[t]) for t, _, _, _ in calls])
    assert ahead.mean() < 0.5 * seen.mean() and seen.max() > 2e-3
    assert np.isfinite(run.object_pos).all()
    c = tr.cost()
    assert len(tr.replan_seconds) == len(calls) and 0 < c["replan_ms_p50"] <= c["replan_ms_p95"]


def test_closed_loop_caches_made_before_a_tracker_setting_existed_still_match() -> None:
    """Settings added to the tracker later (``lead``, ``keep``, ``shift_fade``, ``obs_adapt``, ``grip``) stay out of the cache
    key at their dataclass defaults, so caches made before they existed still match (the tracker without grip in
    the 8 default worlds: ``af3385856ff8``, tracked in benchmarks/runs/grab25-cascade-b); set, they make caches
    of their own (the shipped tracker, ``grip: [0.1]``: ``12ac6fe8e9f1``, tracked beside it)."""
    from quasisim.bench import closed_loop as cl

    old = {"sets": {"default": {}}, "target": "mujoco"}
    later = ("lead", "keep", "shift_fade", "obs_adapt", "obs_adapt_decay", "grip", "grip_gap", "object_weight",
             "worlds", "world_thin", "world_risk", "world_cvar", "grasp_weight", "grasp_margin", "grasp_slots")  # fmt: skip
    assert cl._track_dict(TrackOptions()) == {
        k: v for k, v in dataclasses.asdict(TrackOptions()).items() if k not in ("path", *later)
    }
    no_grip = cl.settings(8, "default", cl._track_dict(TrackOptions.from_yaml(None, {"grip": []})), "mujoco")
    assert cl.cache_name(no_grip) == "robust_closed_loop-af3385856ff8.json"
    default = cl.settings(8, "default", cl._track_dict(TrackOptions.from_yaml()), "mujoco")
    assert cl.cache_name(default) == "robust_closed_loop-12ac6fe8e9f1.json"
    variants = [TrackOptions(), TrackOptions(lead=2), TrackOptions(keep=0.1), TrackOptions(shift_fade=0.03),
                TrackOptions(obs_adapt=True)]  # fmt: skip
    changed = (("lead", 2), ("keep", 0.1), ("shift_fade", 0.03), ("obs_adapt", True))
    for o, (k, v) in zip(variants[1:], changed, strict=True):
        assert cl._track_dict(o)[k] == v
    assert len({cl.cache_name({**old, "track": cl._track_dict(o)}) for o in variants}) == 5


@pytest.mark.parametrize("keep", [0.0, 0.999999])
def test_keep_leaves_the_plan_where_no_candidate_is_clearly_cheaper(clip, sampled, keep) -> None:
    """keep: a candidate replaces the current window only below (1 - keep) x its cost. In a world with less
    friction and weaker gains the cheapest candidates move the plan (keep 0); with keep near 1 none is cheap
    enough, and the targets applied are the plan's own (shifted by the start offset) at every frame."""
    from quasisim.targets.perturb import scaled_scene

    _, demo, _, scene = clip
    q, weights = sampled, TransferConfig.from_yaml().weights
    opts = dataclasses.replace(FAST, keep=keep)
    world_scene = scaled_scene(scene, friction=0.7, gains=0.9)
    with make_target("mujoco", world_scene) as world, Tracker(demo, scene, q, opts, weights) as tr:
        replay(world, q, tr)
    T = len(q)
    assert tr.replans > 0 and np.array_equal(tr._work[:T], tr._planned[:T]) == (keep > 0)


def test_the_shift_weight_fades_with_the_objects_travel_and_never_returns() -> None:
    """w_t = min_{u <= t} max(0, 1 - |p_u - p_0| / s): 1 at rest, linear in the travel, 0 beyond s, and it
    stays 0 when the object comes back to its start; all 1 without a fade."""
    from quasisim.method.track import shift_weights

    travel = np.array([0.0, 0.0, 0.01, 0.02, 0.04, 0.0, 0.01])
    p = np.stack([travel, np.zeros(7), np.full(7, 0.1)], axis=1)
    np.testing.assert_allclose(shift_weights(p, 0.04), [1, 1, 0.75, 0.5, 0, 0, 0])
    np.testing.assert_array_equal(shift_weights(p, 0.0), np.ones(7))


def test_a_fading_shift_moves_the_hands_by_the_offset_at_rest_and_by_none_once_the_object_travelled(clip, sampled):
    """The world's object starts 5 mm off; the tracker (no re-planning) shifts the hands by that offset while the
    object rests and, with shift_fade, applies the plan's own targets once the object has travelled the fade."""
    from quasisim.method.track import shift_weights

    _, demo, _, scene = clip
    q, weights, d = sampled, TransferConfig.from_yaml().weights, np.array([0.004, -0.003, 0.0])
    world_scene = dataclasses.replace(scene, object_pos0=scene.object_pos0 + d)
    opts = dataclasses.replace(FAST, every=0, shift_fade=0.01)
    with make_target("mujoco", world_scene) as world, Tracker(demo, scene, q, opts, weights) as tr:
        replay(world, q, tr)
        w = shift_weights(tr.nominal.object_pos, 0.01)
    T = len(q)
    assert w[1] > 0.95 and w[-1] == 0  # the example's cube rests (settling), then is lifted more than 1 cm
    np.testing.assert_allclose(tr.offset, d, atol=1e-6)
    base = scene.dof_slices[0].start
    shifted = tr._work[1:T, base : base + 3] - q[1:, base : base + 3]
    np.testing.assert_allclose(shifted, w[1:, None] * tr.offset, atol=1e-9)
    np.testing.assert_allclose(tr._ref[0][:T] - tr.nominal.object_pos, w[:, None] * tr.offset, atol=1e-9)


def test_grip_candidates_press_only_the_fingers_the_object_holds_back_harder(clip, sampled) -> None:
    """grip (0.1,): at every re-plan one candidate is the current window with ``0.1 sign(q* - q)`` added on the
    frames after the first to exactly the finger joints more than ``grip_gap`` from their targets (never to the
    bases); holding the cube, some fingers are held back, so the bias is not empty."""
    from quasisim.targets.perturb import finger_columns, scaled_scene

    _, demo, _, scene = clip
    q, weights = sampled, TransferConfig.from_yaml().weights
    opts = dataclasses.replace(FAST, grip=(0.1,))
    fingers, seen = finger_columns(scene), []
    with (
        make_target("mujoco", scaled_scene(scene, friction=0.6)) as world,
        Tracker(demo, scene, q, opts, weights) as tr,
    ):
        plan, rollout = tr._replan, tr.model.rollout_windows

        def watched(t: int, obs: dict) -> None:
            seen.append([obs["qpos"]])
            plan(t, obs)

        def windows(wins: np.ndarray, *args, **kwargs):
            seen[-1].append(wins.copy())
            return rollout(wins, *args, **kwargs)

        tr._replan, tr.model.rollout_windows = watched, windows
        replay(world, q, tr)
    held = 0
    for qpos, wins in seen:
        current, gripped = wins[0], wins[-2]
        gap = np.where(fingers, current[0] - qpos, 0.0)
        want = np.where(np.abs(gap) > opts.grip_gap, 0.1 * np.sign(gap), 0.0)
        np.testing.assert_allclose(gripped[1:] - current[1:], np.broadcast_to(want, current[1:].shape), atol=1e-12)
        np.testing.assert_array_equal(gripped[0], current[0])
        held += int(np.any(want != 0))
    assert len(seen) > 3 and held > 0


def test_object_weight_scales_only_the_object_terms_of_the_window_cost(clip, sampled) -> None:
    """object_weight 3: the tracker's window cost weighs the object's translation and rotation 3x, the hand's
    keypoints and the smoothness as the objective does."""
    _, demo, _, scene = clip
    w = TransferConfig.from_yaml().weights
    with Tracker(demo, scene, sampled, dataclasses.replace(FAST, object_weight=3.0), w) as tr:
        got = tr.weights
    assert (got.obj_pos, got.obj_rot) == (3 * w.obj_pos, 3 * w.obj_rot)
    assert (got.hand, got.smooth) == (w.hand, w.smooth)


def test_a_tracker_weighing_worlds_chooses_by_the_worst_cost_over_its_models(clip, sampled, monkeypatch) -> None:
    """worlds: a named world that is the nominal scene itself leaves every choice as without it (the worst of two
    equal costs); the corner of the ranges rolls every re-plan's windows out once more and, in a world with less
    friction and weaker gains, changes what the tracker applies; an unknown world is refused naming the field."""
    import quasisim.method.track as tk
    from quasisim.targets.perturb import scaled_scene

    _, demo, _, scene = clip
    q, weights = sampled, TransferConfig.from_yaml().weights
    world_scene = scaled_scene(scene, friction=0.7, gains=0.9)

    def run(opts):
        with make_target("mujoco", world_scene) as world, Tracker(demo, scene, q, opts, weights) as tr:
            roll = replay(world, q, tr)
        return tr, np.array(tr._history), roll

    plain, applied, _ = run(FAST)
    with monkeypatch.context() as m:
        m.setattr(tk, "named_world", lambda sc, name, thin: sc)
        same, applied_same, _ = run(dataclasses.replace(FAST, worlds=("corner",)))
    np.testing.assert_array_equal(applied_same, applied)
    assert same.physics_steps > 1.9 * plain.physics_steps
    corner, applied_corner, _ = run(dataclasses.replace(FAST, worlds=("corner",)))
    assert corner.world_models[0].scene.physics.friction < scene.physics.friction
    assert not np.array_equal(applied_corner, applied)
    with pytest.raises(InputError, match="worlds"):
        TrackOptions(worlds=("cornr",))


def test_a_tracker_with_the_grasp_margin_keeps_its_contacts_inside_shrunk_cones(clip, sampled) -> None:
    """grasp_weight: the re-plans' windows are rolled out with their contacts and the cost adds the load beyond
    cones shrunk by half; in a world with less friction and weaker gains the tracker applies targets whose
    replay there carries less of it (read from the world's contacts frame by frame); a bad margin names the
    field."""
    from quasisim.targets.grasp import slack_excess
    from quasisim.targets.perturb import scaled_scene

    _, demo, _, scene = clip
    q, weights = sampled, TransferConfig.from_yaml().weights
    world_scene = scaled_scene(scene, friction=0.7, gains=0.9)

    def excess(opts: TrackOptions) -> tuple[Tracker, float]:
        with make_target("mujoco", world_scene) as world, Tracker(demo, scene, q, opts, weights) as tr:
            replay(world, q, tr)
            applied = np.array(tr._history)
            world.reset(applied[0], (applied[1] - applied[0]) * scene.fps)
            out = []
            for t in range(len(applied) - 1):
                world.advance(applied[t], applied[t + 1])
                out.append(slack_excess(world.contact_cones(8), 0.5))
        return tr, float(np.mean(out))

    plain, ex_plain = excess(FAST)
    firm, ex_firm = excess(dataclasses.replace(FAST, grasp_weight=1.0, grasp_margin=0.5))
    assert firm.physics_steps == plain.physics_steps  # the contacts ride along the same rollouts
    assert ex_plain > 0.1 and ex_firm < 0.8 * ex_plain
    with pytest.raises(InputError, match="grasp_margin"):
        TrackOptions(grasp_margin=1.0)
