"""Robust success (:mod:`quasisim.eval.robust`): the perturbed targets are what the settings say, seeded, and
reach the simulators (gains in MuJoCo's actuators); replays in unperturbed copies agree with the nominal
judgement; ``evaluate --robust N`` writes the fractions into metrics.json; bad settings name the field."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest

from helpers import cube_example
from quasisim.errors import InputError
from quasisim.eval.replay_failures import REPLAY_LABELS
from quasisim.eval.robust import ROBUST_PATH, RobustConfig, perturbed_scene, robust_success


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """The bundled example (20 frames), its kinematic retarget and their scene."""
    return cube_example(tmp_path_factory.mktemp("robust"))


def test_the_shipped_settings_load_and_bad_ones_name_the_field(tmp_path) -> None:
    cfg = RobustConfig.from_yaml()
    assert cfg.n == 0 and (cfg.mass, cfg.friction, cfg.object_pos, cfg.pd_gains) == (0.15, 0.20, 0.003, 0.10)
    assert RobustConfig.from_yaml(None, {"n": 3}).n == 3
    with pytest.raises(InputError, match=r"friction.*\[0, 1\)"):
        RobustConfig.from_yaml(None, {"friction": 1.5})
    bad = tmp_path / "robust.yaml"
    bad.write_text(ROBUST_PATH.read_text().replace("n: 0 ", "n: -1 "))
    with pytest.raises(InputError, match=rf"{bad}.*n.*>= 0"):
        RobustConfig.from_yaml(bad)


def test_perturbed_scenes_stay_within_their_ranges_and_are_seeded(clip) -> None:
    _, _, _, scene = clip
    cfg = RobustConfig.from_yaml()
    copies = [perturbed_scene(scene, cfg, i) for i in range(20)]
    mass = np.array([s.obj.mass for s in copies]) / scene.obj.mass
    fric = np.array([s.physics.friction for s in copies]) / scene.physics.friction
    gain = np.array([s.physics.gain_scale for s in copies])
    shift = np.array([s.object_pos0 - scene.object_pos0 for s in copies])
    for ratio, r in ((mass, cfg.mass), (fric, cfg.friction), (gain, cfg.pd_gains)):
        assert np.all(np.abs(ratio - 1) <= r) and np.ptp(ratio) > r  # within the range, and spread over it
    assert np.all(np.abs(shift[:, :2]) <= cfg.object_pos) and np.all(shift[:, 2] == 0)
    for s in copies:  # inertia scales with the mass (the same shape, another density)
        np.testing.assert_allclose(s.obj.inertia, scene.obj.inertia * s.obj.mass / scene.obj.mass, rtol=1e-12)
    again = perturbed_scene(scene, cfg, 7)
    assert again.obj.mass == copies[7].obj.mass and np.array_equal(again.object_pos0, copies[7].object_pos0)
    other = perturbed_scene(scene, dataclasses.replace(cfg, seed=1), 7)
    assert other.obj.mass != copies[7].obj.mass
    assert scene.physics.gain_scale == 1.0 and scene.obj.mass == copies[0].obj.mass / mass[0]  # untouched


def test_the_gain_scale_reaches_mujocos_actuators(clip) -> None:
    import mujoco

    from quasisim.targets import pd_gains
    from quasisim.targets.mujoco_target import build_spec

    _, _, _, scene = clip
    scaled = dataclasses.replace(scene, physics=dataclasses.replace(scene.physics, gain_scale=1.1))
    m0, m1 = build_spec(scene, visual=False).compile(), build_spec(scaled, visual=False).compile()
    kp = pd_gains(scene.hands[0]).kp
    pd = [i for i in range(m0.nu) if mujoco.mj_id2name(m0, mujoco.mjtObj.mjOBJ_ACTUATOR, i).startswith("pd/")]
    np.testing.assert_allclose(m0.actuator_gainprm[pd, 0], kp, rtol=1e-12)
    np.testing.assert_allclose(m1.actuator_gainprm[pd, 0], 1.1 * kp, rtol=1e-12)
    np.testing.assert_allclose(m1.actuator_biasprm[pd, 2], 1.1 * m0.actuator_biasprm[pd, 2], rtol=1e-12)


def test_replays_in_unperturbed_copies_agree_with_the_nominal_judgement(clip) -> None:
    from quasisim.eval.evaluate import evaluate_controls

    _, demo, controls, scene = clip
    none = RobustConfig(n=3, mass=0.0, friction=0.0, object_pos=0.0, pd_gains=0.0)
    ev = evaluate_controls(demo, controls, "mujoco", None, render=False, scene=scene, robust=none)
    r = ev.metrics["robust"]
    assert r["n"] == 3 and r["unstable"] == 0
    for k, ok in ev.metrics["success"].items():
        assert r[k] == float(ok), k
    assert robust_success(demo, scene, controls.q_targets, "mujoco", dataclasses.replace(none, n=0)) == {}


def test_evaluate_writes_robust_success_in_the_worlds_asked(clip, tmp_path) -> None:
    """``--robust 2 --robust-set seed=7`` and a ranges file of the user's own: metrics.json holds, per set,
    what replaying those worlds in-process gives (the seed and ranges reach the replays)."""
    from quasisim.eval.robust import replays

    path, demo, controls, scene = clip
    mine = tmp_path / "my ranges.yaml"
    mine.write_text("mass: 0.5\nfriction: 0.5\nobject_pos: 0.02\npd_gains: 0.5\n")
    out = tmp_path / "ev"
    cmd = [sys.executable, "-m", "quasisim.cli", "evaluate", str(path), str(path.parent / "kinematic.npz"),
           "--out", str(out), "--no-render", "--robust", "2", "--robust-set", "seed=7",
           "--ranges", f"default,{mine}"]  # fmt: skip
    res = subprocess.run(cmd, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    m = json.loads((out / "metrics.json").read_text())
    assert (m["robust"]["n"], m["robust"]["seed"]) == (2, 7) and (m["robust_my_ranges"]["seed"]) == 7
    for key, ranges in (("robust", "default"), ("robust_my_ranges", str(mine))):
        want = robust_success(demo, scene, controls.q_targets, "mujoco", replays(2, ranges, {"seed": 7}))
        why = want.pop("failures")  # per replay, in order: a label of each, a pass for every strict success
        assert m[key].pop("failures") == why, key
        assert [f["replay"] for f in why] == [0, 1] and {f["label"] for f in why} <= {"pass", *REPLAY_LABELS}
        assert sum(f["label"] == "pass" for f in why) >= 2 * want["strict"]
        assert m[key] == pytest.approx(want), key
    assert "robust success" in res.stdout and "robust success strict" in (out / "report.html").read_text()


def test_robust_settings_and_ranges_files_are_checked(tmp_path) -> None:
    from quasisim.errors import QuasisimError
    from quasisim.eval.robust import replays

    cfg = replays(None, "wide", {"seed": 7, "mass": 0.3})
    assert (cfg.seed, cfg.mass, cfg.name, cfg.push) == (7, 0.3, "robust_wide", RobustConfig.from_yaml(
        ROBUST_PATH.parent / "robust_wide.yaml").push)  # fmt: skip
    named = tmp_path / "r.yaml"
    named.write_text("name: robust_lab\nseed: 3\n")
    assert (replays(4, str(named)).name, replays(4, str(named)).seed, replays(4, str(named)).n) == ("robust_lab", 3, 4)
    with pytest.raises(QuasisimError, match=r"--robust-set n: not settable.*--robust N"):
        replays(None, "default", {"n": 3})
    with pytest.raises(InputError, match=r"bogus.*one of the keys"):
        replays(None, "default", {"bogus": 1})
    with pytest.raises(InputError, match=r"mass.*\[0, 1\)"):
        replays(None, "default", {"mass": 2.0})
    with pytest.raises(
        QuasisimError, match=r"unknown perturbation ranges .nosuch\.yaml.; valid options: default, wide"
    ):
        replays(None, "nosuch.yaml")


@pytest.mark.parametrize("command", ["transfer", "batch", "bench transfer"])
def test_every_command_carries_the_robust_settings_to_its_judging(command, tmp_path, monkeypatch) -> None:
    """``--robust``, ``--ranges`` (a file of the user's own) and ``--robust-set`` of transfer, batch and bench
    transfer reach what judges the runs (the command's worker function is replaced by a recorder)."""
    from click.testing import CliRunner

    import quasisim.batch
    import quasisim.bench.transfer
    import quasisim.pipeline
    from quasisim.cli import main

    mine = tmp_path / "mine.yaml"
    mine.write_text("mass: 0.4\n")
    seen: dict = {}
    (tmp_path / "clips").mkdir()
    demo = tmp_path / "clips" / "a.npz"
    demo.write_bytes(b"")
    opts = ["--robust", "3", "--ranges", f"wide,{mine}", "--robust-set", "seed=9", "--robust-set", "friction=0.3"]

    class Recorded(Exception):
        pass

    def recorder(spec_at: int):
        def record(*a, **k):
            seen["spec"] = a[spec_at]
            raise Recorded

        return record

    if command == "transfer":
        monkeypatch.setattr(quasisim.pipeline, "run_transfer", recorder(2))
        args = ["transfer", str(demo), "--out", str(tmp_path / "o"), *opts]
    elif command == "batch":
        monkeypatch.setattr(quasisim.batch, "run_batch_command", recorder(3))
        args = ["batch", str(tmp_path / "clips"), "--out", str(tmp_path / "o"), *opts]
    else:  # transfer_rows and the closed-loop pass run; the batch and the pass's judging are replaced
        import quasisim.bench.closed_loop
        from quasisim.eval.robust import replays

        def batch(js, *a, **k):
            seen["spec"] = js[0].runs[0].spec  # what transfer_rows made of the options: the batch judges with it
            return type("Result", (), {"rows": [], "failures": {}})()

        def closed(rows, out, paths, n, sets, target, workers, track, robust_set):
            seen["ranges"], seen["closed"] = sets, [replays(n, r, robust_set) for r in sets]  # as judge_run does
            raise Recorded

        monkeypatch.setattr(quasisim.bench.transfer, "run_batch", batch)
        monkeypatch.setattr(quasisim.bench.closed_loop, "add_closed_loop", closed)
        args = ["bench", "transfer", str(tmp_path / "clips"), "--out", str(tmp_path / "o"), "--closed-loop", *opts]
    res = CliRunner().invoke(main, args, catch_exceptions=True)
    assert "spec" in seen, res.output
    spec = seen["spec"]
    ranges = seen.get("ranges", spec.ranges)
    cfgs = seen.get("closed") or spec.robust_configs()
    if "closed" in seen:  # the batch judges its runs open loop in the default worlds, with the same replays
        assert [(c.name, c.n, c.seed, c.friction) for c in spec.robust_configs()] == [("robust", 3, 9, 0.3)]
    assert [(c.name, c.n, c.seed, c.friction) for c in cfgs] == [("robust_wide", 3, 9, 0.3), ("robust_mine", 3, 9, 0.3)]
    assert cfgs[1].mass == 0.4 and ranges == ("wide", str(mine.resolve()))


def _draws_and_noise(cfg: RobustConfig, i: int) -> tuple[float, ...]:
    """World ``i`` of ``cfg`` as numbers: its 6 draws (mass ... push) and its sensor's first noise draw."""
    from quasisim.targets.perturb import Sensor, _draws

    return (*_draws(cfg, i), Sensor(cfg, i, np.zeros(3, bool))._rng.standard_normal())


def test_the_methods_worlds_are_never_the_worlds_it_is_judged_in(monkeypatch) -> None:
    """robust_select.seed (the cascade's gate and selection) and sampling.robust_seed (the sampling stage's copies)
    draw their worlds from a stream of their own: whatever the integer seeds, no world the method chooses plans in is
    a world that ``--robust-set seed=N`` judges them in. The judging worlds are those they always were
    (``default_rng([seed, i])``), so the robust figures already published stay valid."""
    import quasisim.method.track as track
    import quasisim.targets.perturb as perturb
    from quasisim.eval.robust import replays
    from quasisim.method.config import TransferConfig
    from quasisim.method.options import RobustSelectOptions
    from quasisim.method.stages import sampling
    from quasisim.method.stages.selection import closed_loop_success

    method: list[tuple[RobustConfig, int]] = []
    monkeypatch.setattr(
        perturb, "world_replays", lambda sc, q, tgt, cfg, pol: method.extend((cfg, i) for i in range(cfg.n)) or iter(())
    )
    monkeypatch.setattr(track, "closed_loop", lambda *a, **k: lambda *b: None)
    prob = type("P", (), {"demo": None, "scene": None})()
    for seed in (1, 2, 7):
        closed_loop_success(prob, "mujoco", np.zeros((2, 3)), RobustSelectOptions(worlds=4, seed=seed), None)
    monkeypatch.setattr(sampling, "perturbed_scene", lambda sc, cfg, i: method.append((cfg, i)))
    opts = TransferConfig.from_yaml().sampling
    for seed in (0, 1, 2, 7):
        sampling.copy_scenes(None, dataclasses.replace(opts, robust_seed=seed, robust_copies=4))
    assert len(method) == 3 * 4 + 4 * 4
    judged = {_draws_and_noise(replays(8, "default", {"seed": s}), i) for s in range(10) for i in range(8)}
    assert len(judged) == 80
    assert judged.isdisjoint(_draws_and_noise(cfg, i) for cfg, i in method)
    cfg = replays(8, "default", {"seed": 3})  # the judging worlds, as published
    np.testing.assert_array_equal(perturb._draws(cfg, 5), np.random.default_rng([3, 5]).uniform(-1.0, 1.0, size=6))
    # the method's seeds lie in [0, 2**32), where that separation holds (perturb.TrainingWorlds)
    from quasisim.errors import QuasisimError

    with pytest.raises(InputError, match=r"robust_select\.seed.*\[0, 2\*\*32\)"):
        TransferConfig.from_yaml(overrides={"robust_select.seed": 2**32})
    with pytest.raises(QuasisimError, match=r"robust_seed.*\[0, 2\*\*32\), got -1"):
        dataclasses.replace(opts, robust_seed=-1)


def test_a_batch_resumed_with_other_judging_settings_is_refused(tmp_path) -> None:
    """A run's robust replays (``--robust``), perturbation sets (``--ranges``) and their overrides (``--robust-set``)
    are part of its identity in ``clip.json``: a batch (or a report-only pass) into the same OUT with other ones
    is refused in one line naming the option, the stored and the given value; folders written before the judging
    settings were recorded are checked against the replays their rows hold."""
    from quasisim.batch import CLIP_FILE, Job, Run, Settings, _persist, finished_runs
    from quasisim.errors import QuasisimError
    from quasisim.method.spec import TransferSpec

    out, s = tmp_path / "out", Settings()

    def job(**judging) -> Job:
        return Job(tmp_path / "a.npz", (Run("cascade", TransferSpec(**{"robust": 8, **judging})),))

    row = {"clip": "a", "run": "cascade", "metrics": {"robust": {"n": 8, "seed": 0, "strict": 0.5, "unstable": 0}}}
    _persist(out, job(), s, {"files": {}, "rows": [row]})
    assert finished_runs(out, job(), s) == {"cascade": row}
    refusals = {
        "--robust-set seed: stored 0, given 1": job(robust_set=(("seed", 1),)),
        "--robust-set friction: stored 0.2, given 0.3": job(robust_set=(("friction", 0.3),)),
        "--robust: stored 8, given 3": job(robust=3),
        "--ranges: stored robust, given robust_wide": job(ranges=("wide",)),
    }
    for msg, other in refusals.items():
        for any_revision in (False, True):  # a batch, a report-only pass
            with pytest.raises(QuasisimError, match=rf"^{out / 'a'}: run 'cascade' .*{msg}") as e:
                finished_runs(out, other, s, any_revision)
            assert "\n" not in str(e.value)
    legacy = json.loads((out / "a" / CLIP_FILE).read_text())  # as clip.json was written before this
    legacy["runs"]["cascade"]["identity"].pop("judging")
    (out / "a" / CLIP_FILE).write_text(json.dumps(legacy))
    assert finished_runs(out, job(), s) == {"cascade": row}
    assert finished_runs(out, job(robust_set=(("friction", 0.3),)), s) == {"cascade": row}  # not recorded then
    for msg in ("--robust-set seed: stored 0, given 1", "--robust: stored 8, given 3"):
        with pytest.raises(QuasisimError, match=msg):
            finished_runs(out, refusals[msg], s)


def test_bench_transfer_into_an_out_judged_otherwise_exits_2(tmp_path) -> None:
    """``quasisim bench transfer --report-only`` with another ``--robust-set seed`` than the OUT was judged with:
    exit 2, one line naming the option and both values."""
    from click.testing import CliRunner

    from quasisim.batch import Job, Run, Settings, _persist
    from quasisim.bench.transfer import run_spec
    from quasisim.cli import main
    from quasisim.method.spec import TransferSpec

    data, out = tmp_path / "clips", tmp_path / "out"
    data.mkdir()
    (data / "a.npz").write_bytes(b"")
    base = TransferSpec(render=False, progress=False, robust=8)
    row = {"clip": "a", "run": "cascade", "metrics": {"robust": {"n": 8, "seed": 0, "strict": 0.5, "unstable": 0}}}
    job = Job(data / "a.npz", (Run("cascade", run_spec("cascade", ("1", "2"), base)),))
    _persist(out, job, Settings(keep_scratch=True), {"files": {}, "rows": [row]})
    args = ["bench", "transfer", str(data), "--out", str(out), "--runs", "cascade", "--robust", "8", "--report-only"]
    res = CliRunner().invoke(main, [*args, "--robust-set", "seed=1"])
    assert res.exit_code == 2, res.output
    assert "--robust-set seed: stored 0, given 1" in res.output and len(res.output.strip().splitlines()) == 1
