"""``quasisim policy``: PPO trains in ``quasisim/Track-v0`` from the command line, resumes from its checkpoint,
and the trained policy is judged like every other result (metrics in MuJoCo, nominal and in the seeded
perturbed worlds, closed loop). Short runs on the bundled example; the real runs are in BENCHMARKS.md."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

from helpers import cube_example
from quasisim.method.curriculum import load_curriculum

pytest.importorskip("stable_baselines3", reason="the optional extra rl is not installed (pip install -e '.[rl]')")

TINY = ["--set", "ppo.n_steps=64", "--set", "ppo.batch_size=64", "--set", "ppo.checkpoint_every=64", "--no-progress"]
ONE = ["--set", "ppo.n_envs=1", "--set", "ppo.validate_worlds=0"]  # one process, the nominal world only


def _cli(*args: str, ok: bool = True) -> subprocess.CompletedProcess:
    r = subprocess.run([sys.executable, "-m", "quasisim.cli", "policy", *map(str, args)], capture_output=True,
                       text=True, timeout=600)  # fmt: skip
    if ok:
        assert r.returncode == 0, r.stderr[-3000:]
    return r


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    return cube_example(tmp_path_factory.mktemp("policy"))


@pytest.fixture(scope="module")
def trained(clip, tmp_path_factory):
    """ours+residual on the example's kinematic retarget (standing in for our result): 128 steps on two
    processes, then resumed to 256."""
    path = clip[0]
    out = tmp_path_factory.mktemp("trained") / "run"
    _cli("train", path, "--residual", path.parent / "kinematic.npz", "--steps", 128, "--out", out, *TINY)
    first = json.loads((out / "checkpoint.json").read_text())
    _cli("train", path, "--steps", 256, "--out", out, "--resume", "--no-progress")  # the stored settings
    return out, first


def test_training_resumes_from_its_checkpoint(trained) -> None:
    out, first = trained
    assert first["steps"] == 128 and len(first["worlds_drawn"]) == 2  # each process's training worlds so far
    info = json.loads((out / "training.json").read_text())
    assert info["env_steps"] == 256 and info["method"] == "ours+residual"
    assert info["wall_s"] > first["wall_s"]  # the resumed segment adds its time to the first's
    segments = sorted((out / "logs").glob("*/progress.csv"))
    assert len(segments) == 2
    from quasisim.policy.curves import read_curves

    steps = read_curves(out)["steps"]
    assert steps[0] == 128 and steps[-1] == 256 and np.all(np.diff(steps) > 0)
    # validated at every checkpoint from the fresh model on, across the resume; the best one kept
    validation = json.loads((out / "validation.json").read_text())
    assert [h[0] for h in validation["history"]] == [0, 64, 128, 192, 256]
    best = max(validation["history"], key=lambda h: tuple(h[1:]))
    assert info["best"]["score"] == best[1:] and (out / "best.zip").is_file()


def test_a_policy_is_judged_like_any_result(trained, tmp_path) -> None:
    out, _ = trained
    _cli("evaluate", out, "--out", tmp_path / "ev", "--robust", 2)
    m = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    assert set(m["success"]) >= {"strict", "20deg_20cm"}
    assert m["robust_closed_loop"]["n"] == 2 and "robust" not in m  # every replay of a policy is closed loop
    assert m["policy"]["training"]["env_steps"] == 256
    assert (tmp_path / "ev" / "report.html").is_file()
    # the evaluation is the policy's own replay: again, the same numbers
    _cli("evaluate", out, "--out", tmp_path / "ev2", "--robust", 2)
    m2 = json.loads((tmp_path / "ev2" / "metrics.json").read_text())
    timing = ("seconds_per_replay", "tracker")
    same = lambda r: {k: v for k, v in r.items() if k not in timing}  # noqa: E731
    assert same(m2["robust_closed_loop"]) == same(m["robust_closed_loop"]) and m2["success"] == m["success"]
    assert m2["R_err_deg"] == m["R_err_deg"] and m2["T_err_cm"] == m["T_err_cm"]
    _cli("evaluate", out, "--out", tmp_path / "final", "--robust", 0, "--model", "final")
    assert json.loads((tmp_path / "final" / "metrics.json").read_text())["policy"]["model"] == "final"


def test_mistakes_are_one_line_errors(clip, trained, tmp_path) -> None:
    path = clip[0]
    out, _ = trained
    again = _cli("train", path, "--steps", 64, "--out", out, *TINY, ok=False)
    assert again.returncode == 2 and "--resume" in again.stderr and "Traceback" not in again.stderr
    changed = _cli("train", path, "--steps", 256, "--out", out, "--resume", "--set", "ppo.n_steps=128", ok=False)
    assert changed.returncode == 2 and "Traceback" not in changed.stderr
    assert "--set" in changed.stderr and "stored settings" in changed.stderr  # not ignored silently
    nothing = _cli("train", path, "--steps", 64, "--out", tmp_path / "none", "--resume", ok=False)
    assert nothing.returncode == 2 and "setup.json" in nothing.stderr
    bad = _cli("train", path, "--steps", 64, "--out", tmp_path / "bad", "--set", "reward.x=1", ok=False)
    assert bad.returncode == 2 and "env.KEY" in bad.stderr
    unfinished = _cli("evaluate", tmp_path, "--out", tmp_path / "ev", ok=False)
    assert unfinished.returncode == 2 and "setup.json" in unfinished.stderr


def _log_std(model_zip) -> float:
    """The initial exploration noise a saved model was made with (-2.5: a residual policy; -1.0: from scratch)."""
    from stable_baselines3.common.save_util import load_from_zip_file

    return load_from_zip_file(model_zip, load_data=True)[0]["policy_kwargs"]["log_std_init"]


def test_overwrite_starts_the_training_afresh(clip, trained, tmp_path) -> None:
    """--overwrite removes everything the previous training wrote, its best model and validation too: the new
    run's checkpoints are judged among themselves, and the best model evaluated is one of the new run's. A file
    the previous training did not write stays."""
    path = clip[0]
    out = tmp_path / "again"
    shutil.copytree(trained[0], out)
    (out / "notes.txt").write_text("mine")
    assert _log_std(out / "best.zip") == -2.5  # the previous training's: ours+residual
    _cli("train", path, "--steps", 128, "--out", out, "--overwrite", *TINY)  # another reference: dgrasp-tracking
    assert _log_std(out / "best.zip") == -1.0  # the new training's model, from scratch
    validation = json.loads((out / "validation.json").read_text())
    assert [h[0] for h in validation["history"]] == [0, 64, 128]
    info = json.loads((out / "training.json").read_text())
    assert info["method"] == "dgrasp-tracking" and info["best"] == validation["best"]
    assert validation["best"]["steps"] <= 128 and json.loads((out / "checkpoint.json").read_text())["steps"] == 128
    assert len(list((out / "logs").glob("*/progress.csv"))) == 1
    assert (out / "notes.txt").read_text() == "mine"


def _invoke(*args: object):
    """``quasisim policy ARGS`` in this process (for errors raised before any training starts)."""
    from click.testing import CliRunner

    from quasisim.cli import main

    return CliRunner().invoke(main, ["policy", *map(str, args)])


def _listing(folder) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _stored_training(path, out, method: str = "dgrasp-tracking", seed: int = 3):
    """A folder as ``policy train`` leaves it once prepared (setup.json, reference.npz: the example's retarget to
    shadow, or ours+residual on it), with a final model of the previous training standing in; nothing trained."""
    from dataclasses import asdict

    from quasisim.policy.train import REFERENCE, SETUP, TrainSetup

    out.mkdir(parents=True)
    kinematic = path.parent / "kinematic.npz"
    shutil.copyfile(kinematic, out / REFERENCE)
    source = str(kinematic.resolve()) if method == "ours+residual" else "kinematic retarget to shadow"
    (out / SETUP).write_text(json.dumps(asdict(TrainSetup(str(path.resolve()), method, "mujoco", source, seed))))
    (out / "policy.zip").write_bytes(b"the previous training")
    (out / "logs" / "000").mkdir(parents=True)
    (out / "logs" / "000" / "progress.csv").write_text("time/total_timesteps\n64\n")
    return out


def test_train_refuses_a_folder_it_did_not_write(clip, tmp_path) -> None:
    """A non-empty --out without setup.json (here a data folder: meshes/, logs/) is refused, --overwrite or not,
    and nothing in it is removed."""
    path = clip[0]
    out = tmp_path / "data"
    (out / "meshes").mkdir(parents=True)
    (out / "meshes" / "cube.obj").write_text("v 0 0 0\n")
    (out / "logs").mkdir()
    (out / "logs" / "notes.txt").write_text("mine")
    before = _listing(out)
    for extra in ([], ["--overwrite"]):
        r = _invoke("train", path, "--steps", 64, "--out", out, *TINY, *ONE, *extra)
        assert r.exit_code == 2 and _listing(out) == before, r.output
        assert str(out) in r.output and "--out" in r.output and "setup.json" in r.output
        assert len(r.output.strip().splitlines()) == 1


def test_overwrite_keeps_the_previous_training_when_the_new_one_is_refused(clip, tmp_path) -> None:
    """--overwrite validates the new training (its settings, reference, method) before it removes anything of
    the previous one: a typo leaves the previous training as it was."""
    path = clip[0]
    out = _stored_training(path, tmp_path / "run")
    before = _listing(out)
    for bad, said in ((["--set", "ppo.n_step=64"], "n_step"), (["--set", "reward.x=1"], "env.KEY"),
                      (["--set", "ppo.n_steps=0"], "n_steps"), (["--residual", tmp_path / "nope.npz"], "nope.npz"),
                      (["--method", "dgrasp-tracking-curriculum", "--set", "ppo.curriculum=nope"], "nope"),
                      (["--hand", "nohand"], "nohand")):  # fmt: skip
        r = _invoke("train", path, "--steps", 64, "--out", out, "--overwrite", "--no-progress", *bad)
        assert r.exit_code == 2 and said in r.output, r.output
        assert _listing(out) == before, bad


def test_resume_refuses_options_that_differ_from_the_stored_training(clip, tmp_path) -> None:
    """--resume continues the stored training: an option given with another value than the stored one is refused,
    naming it and both values; the same values are accepted (then: nothing to resume, no checkpoint here)."""
    path = clip[0]
    out = _stored_training(path, tmp_path / "run")  # dgrasp-tracking to shadow in mujoco, seed 3
    kinematic = path.parent / "kinematic.npz"
    resume = ["train", path, "--steps", 128, "--out", out, "--resume", "--no-progress"]
    for opt, given, stored in (("--seed", "1", "3"), ("--target", "pybullet", "mujoco"), ("--hand", "allegro", "shadow"),
                               ("--method", "dgrasp-base", "dgrasp-tracking"),
                               ("--residual", str(kinematic.resolve()), "dgrasp-tracking")):  # fmt: skip
        r = _invoke(*resume, opt, given)
        assert r.exit_code == 2 and len(r.output.strip().splitlines()) == 1, r.output
        assert opt in r.output and given in r.output and stored in r.output, r.output
    same = _invoke(*resume, "--seed", 3, "--target", "mujoco", "--hand", "shadow", "--method", "dgrasp-tracking")
    assert same.exit_code == 2 and "nothing to resume" in same.output, same.output
    ours = _stored_training(path, tmp_path / "ours", "ours+residual", seed=0)
    resume[resume.index(out)] = ours
    other = tmp_path / "other.npz"
    shutil.copyfile(kinematic, other)
    r = _invoke(*resume, "--residual", other)
    assert r.exit_code == 2 and "--residual" in r.output and str(kinematic.resolve()) in r.output, r.output
    r = _invoke(*resume, "--method", "dgrasp-tracking")
    assert r.exit_code == 2 and "--method" in r.output and "ours+residual" in r.output, r.output
    same = _invoke(*resume, "--residual", kinematic, "--seed", 0)
    assert same.exit_code == 2 and "nothing to resume" in same.output, same.output


def test_a_resumed_training_continues_the_sequence_of_worlds(clip, tmp_path, monkeypatch) -> None:
    """The training worlds drawn after a resume continue those drawn before it (PPO.load seeds the environments
    again): the two segments together draw what one uninterrupted environment seeded as the trainer seeds it
    draws. One environment in this process, 64 steps, then resumed to 192."""
    import gymnasium as gym

    import quasisim.envs
    from quasisim.envs.track import TrackEnv
    from quasisim.policy.train import REFERENCE, prepare, train

    path = clip[0]
    drawn: list[int] = []
    reset = TrackEnv.reset

    def recording(self, *, seed=None, options=None):
        obs, info = reset(self, seed=seed, options=options)
        drawn.append(info["world"])
        return obs, info

    monkeypatch.setattr(TrackEnv, "reset", recording)
    out = tmp_path / "run"
    out.mkdir()
    ppo = {"n_envs": 1, "n_steps": 64, "batch_size": 64, "checkpoint_every": 64, "validate_worlds": 0}
    prepare(path, out, path.parent / "kinematic.npz", "shadow", "mujoco", 3, {}, ppo)
    train(out, 64, progress=False)
    before = drawn.copy()
    drawn.clear()
    train(out, 192, resume=True, progress=False)
    after = drawn.copy()
    assert len(before) >= 2 and len(after) >= 2 and after[0] != before[0]  # not the same worlds again
    env = gym.make(quasisim.envs.TRACK_ID, clip=path, reference=out / REFERENCE, residual=True)
    drawn.clear()
    env.reset(seed=3)  # the trainer's seed (+ the env's index, 0)
    for _ in range(len(before) + len(after) - 1):
        env.reset()
    env.close()
    assert before + after == drawn


def test_bench_policy_tabulates_policies_beside_ours(clip, tmp_path) -> None:
    """One clip: the example's kinematic retarget stands in for our result (judged with 2 perturbed worlds);
    one PPO update of each policy; our result also replayed closed loop by the tracker."""
    path = clip[0]
    runs = tmp_path / "runs"
    ours = runs / path.stem / "cascade"
    ours.mkdir(parents=True)
    (ours / "controls.npz").write_bytes((path.parent / "kinematic.npz").read_bytes())
    ev = subprocess.run([sys.executable, "-m", "quasisim.cli", "evaluate", path, ours / "controls.npz", "--out", ours,
                         "--robust", "2", "--no-render"], capture_output=True, text=True, timeout=600)  # fmt: skip
    assert ev.returncode == 0, ev.stderr[-2000:]
    out = tmp_path / "bench"
    args = ["bench", "policy", path.parent, "--clips", path.stem, "--runs", runs, "--steps", 1024, "--robust", 2,
            "--workers", 1, "--out", out]  # fmt: skip
    r = subprocess.run([sys.executable, "-m", "quasisim.cli", *map(str, args)], capture_output=True, text=True,
                       timeout=900)  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    rows = json.loads((out / "policy.json").read_text())
    methods = {row["method"] for row in rows}
    policies = {"ours+residual", "dgrasp-tracking"}
    assert methods == {*policies, *(f"{m} (final model)" for m in policies), "ours (cascade) open loop",
                       "ours (cascade) closed loop"}  # fmt: skip
    trained = [row for row in rows if row["env_steps"] is not None]
    assert len(trained) == 4 and all(row["env_steps"] == 1024 for row in trained)
    text = (out / "policy.md").read_text()
    assert "| ours+residual | 1 |" in text and path.stem in text
    dgrasp = out / path.stem / "dgrasp-tracking" / "train"
    setup = json.loads((dgrasp / "setup.json").read_text())
    assert setup["method"] == "dgrasp-tracking" and setup["reference_source"].startswith("kinematic")
    _cli("curves", dgrasp, out / path.stem / "ours+residual" / "train", "--out", tmp_path / "curves.png")
    assert (tmp_path / "curves.png").stat().st_size > 10_000
    # a second run keeps the trained policies and their judgements
    before = (out / path.stem / "ours+residual" / "eval" / "metrics.json").stat().st_mtime_ns
    r2 = subprocess.run([sys.executable, "-m", "quasisim.cli", *map(str, args)], capture_output=True, text=True,
                        timeout=900)  # fmt: skip
    assert r2.returncode == 0 and "from the start" not in r2.stdout
    assert (out / path.stem / "ours+residual" / "eval" / "metrics.json").stat().st_mtime_ns == before
    # --report-only tabulates what is finished at --steps, trains and judges nothing
    for n, policies_in in ((1024, 4), (2048, 0)):
        args_n = [*args[: args.index("--steps") + 1], n, *args[args.index("--steps") + 2 :], "--report-only"]
        r3 = subprocess.run([sys.executable, "-m", "quasisim.cli", *map(str, args_n)], capture_output=True, text=True,
                            timeout=900)  # fmt: skip
        assert r3.returncode == 0 and "up to" not in r3.stdout, r3.stderr[-2000:]  # no training started
        rows = json.loads((out / "policy.json").read_text())
        assert sum(row["env_steps"] is not None for row in rows) == policies_in and len(rows) == policies_in + 2
    assert json.loads((dgrasp / "training.json").read_text())["env_steps"] == 1024


def test_dgrasp_base_trains_on_its_guide_and_is_judged_on_the_clip(clip, tmp_path) -> None:
    """dgrasp-base on a cube lift whose fingers slide up the faces after the grasp: the policy trains against
    the guide (the first grasp carried with the cube), resumes, and is judged against the clip itself."""
    import dataclasses

    from quasisim.data.demo import load_demo, save_demo
    from quasisim.eval.evaluate import scene_surface
    from quasisim.eval.metrics import evaluate_rollout
    from quasisim.policy.evaluate import evaluate_policy
    from quasisim.policy.train import TrainSetup, training_task

    path, demo = clip[0], clip[1]
    shutil.copytree(path.parent / "meshes", tmp_path / "meshes")
    slide = np.zeros_like(demo.right_joints)
    slide[11:, :, 2] = 0.002 * np.arange(1, demo.n_frames - 10)[:, None]
    mesh = tmp_path / "meshes" / demo.object_mesh_path.name
    sliding = save_demo(dataclasses.replace(demo, right_joints=demo.right_joints + slide, object_mesh_path=mesh),
                        tmp_path / "slide.npz")  # fmt: skip
    out = tmp_path / "base"
    refused = _cli("train", sliding, "--method", "dgrasp-base", "--residual", out, "--steps", 64, "--out", out,
                   ok=False)  # fmt: skip
    assert refused.returncode == 2 and "ours+residual" in refused.stderr and "Traceback" not in refused.stderr
    one = ["--set", "ppo.n_envs=1", "--set", "ppo.validate_worlds=1"]  # one process, one validation world
    _cli("train", sliding, "--method", "dgrasp-base", "--steps", 64, "--out", out, *TINY, *one)
    assert json.loads((out / "checkpoint.json").read_text())["steps"] == 64
    _cli("train", sliding, "--steps", 128, "--out", out, "--resume", "--no-progress")
    setup = TrainSetup.read(out)
    assert setup.method == "dgrasp-base" and setup.guide == str((out / "guide.npz").resolve())
    assert json.loads((out / "guide.json").read_text())["hands"]["right"] == {"grasp_frame": 10,
                                                                              "rule": "force closure"}  # fmt: skip
    assert json.loads((out / "training.json").read_text())["env_steps"] == 128
    clip_demo, guide = load_demo(sliding), load_demo(out / "guide.npz")
    assert np.abs(guide.right_joints - clip_demo.right_joints)[11:].max() > 0.01  # the guide holds the grasp
    task, _ = training_task(out, setup)
    np.testing.assert_array_equal(task.demo.right_joints, guide.right_joints)  # trained against the guide
    ev = evaluate_policy(out, tmp_path / "ev", 1)
    judged = {
        name: evaluate_rollout(d, ev.rollout, scene_surface(ev.scene, ev.rollout.qpos))[0]["MPJPE_mm"]
        for name, d in (("clip", clip_demo), ("guide", guide))
    }
    assert ev.metrics["MPJPE_mm"] == judged["clip"] != judged["guide"]  # judged against the clip
    m = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    assert m["policy"]["method"] == "dgrasp-base" and m["robust_closed_loop"]["n"] == 1


def test_dgrasp_tracking_curriculum_trains_through_the_curriculum_then_in_the_target(
    clip, tmp_path, monkeypatch
) -> None:
    """dgrasp-tracking-curriculum with the short curriculum, 64 env steps per simulator: the environments step its
    five analytical simulators in order, soft to stiff, then MuJoCo; a training stopped inside the curriculum
    resumes in the simulator where it stopped; the policy is judged in MuJoCo. One process; an unknown
    curriculum is refused before training."""
    from quasisim.envs.track import TrackEnv
    from quasisim.policy.evaluate import evaluate_policy
    from quasisim.policy.train import prepare, train
    from quasisim.targets.quasi_target import QuasiTarget

    path = clip[0]
    refused = _cli("train", path, "--method", "dgrasp-tracking-curriculum", "--steps", 64, "--out", tmp_path / "no",
                   "--set", "ppo.curriculum=nope", ok=False)  # fmt: skip
    assert refused.returncode == 2 and "default" in refused.stderr and "Traceback" not in refused.stderr
    stepped: list = []
    make = TrackEnv._make_world

    def recording(self, scene):  # which simulator each new environment steps: a stage's settings, or None (MuJoCo)
        world = make(self, scene)
        stepped.append((world.stage, world.substeps) if isinstance(world, QuasiTarget) else None)
        return world

    monkeypatch.setattr(TrackEnv, "_make_world", recording)
    out = tmp_path / "curric"
    out.mkdir()
    ppo = {"n_envs": 1, "n_steps": 64, "batch_size": 64, "checkpoint_every": 64, "validate_worlds": 0,
           "curriculum": "short", "curriculum_stage_steps": 64}  # fmt: skip
    prepare(path, out, None, "shadow", "mujoco", 0, {}, ppo, "dgrasp-tracking-curriculum")
    cur = load_curriculum("short")
    # as stage 2 steps them at the fast budget: 10 substeps per frame in the soft ones, 20 in the stiffest
    stages = [(cur.contact(i), 20 if i == cur.stiffest else 10) for i, st in enumerate(cur.stages) if not st.residual]
    assert len(stages) == 5 and cur.stiffest == 4
    train(out, 192, progress=False)  # three of the five simulators
    assert stepped == stages[:3]
    assert json.loads((out / "checkpoint.json").read_text())["span"] == 2
    stepped.clear()
    train(out, 448, resume=True, progress=False)  # the other two, then MuJoCo for 128 steps
    assert stepped == [*stages[3:], None]
    info = json.loads((out / "training.json").read_text())
    assert info["env_steps"] == 448 and info["method"] == "dgrasp-tracking-curriculum"
    ev = evaluate_policy(out, tmp_path / "ev", 1)
    assert ev.rollout.target == "mujoco" and ev.metrics["policy"]["method"] == "dgrasp-tracking-curriculum"


def test_bench_policy_reads_our_metrics_from_the_batch_where_the_run_folder_has_none(tmp_path) -> None:
    """A folder of bench transfer whose outputs stayed on another machine keeps clip.json and the plan only."""
    from quasisim.bench.policy import _our_metrics
    from quasisim.errors import QuasisimError

    clip_dir = tmp_path / "grab_x"
    (clip_dir / "cascade").mkdir(parents=True)
    row = {"success": {"strict": True}, "robust": {"n": 8}}
    (clip_dir / "clip.json").write_text(json.dumps({"clip": "grab_x", "runs": {"cascade": {"row": {"metrics": row}}}}))
    assert _our_metrics(clip_dir, "cascade") == row
    (clip_dir / "cascade" / "metrics.json").write_text(json.dumps({"success": {"strict": False}}))
    assert _our_metrics(clip_dir, "cascade") == {"success": {"strict": False}}  # the run's own file first
    with pytest.raises(QuasisimError, match="no run 'ours'"):
        _our_metrics(clip_dir, "ours")


def test_bench_policy_refuses_a_folder_trained_with_other_settings(tmp_path) -> None:
    from dataclasses import asdict

    from quasisim.bench.policy import _train
    from quasisim.errors import QuasisimError
    from quasisim.policy.train import SETUP, TrainSetup

    folder = tmp_path / "train"
    folder.mkdir()
    setup = TrainSetup("clip.npz", "dgrasp-tracking", "mujoco", "kinematic", ppo_overrides={"log_std_init": -2.5})
    (folder / SETUP).write_text(json.dumps(asdict(setup)))
    with pytest.raises(QuasisimError, match="another --out"):
        _train(tmp_path / "clip.npz", folder, "dgrasp-tracking", tmp_path, 64, 0, ({}, {}))
