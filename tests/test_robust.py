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
    else:

        def record(*a, **k):
            seen["spec"] = quasisim.method.spec.TransferSpec(robust=a[12], robust_set=tuple(k["robust_set"].items()))
            seen["ranges"] = k["closed_loop"][0]

        monkeypatch.setattr(quasisim.bench.transfer, "run_transfer_bench", record)
        args = ["bench", "transfer", str(tmp_path / "clips"), "--out", str(tmp_path / "o"), "--closed-loop", *opts]
    res = CliRunner().invoke(main, args, catch_exceptions=True)
    assert "spec" in seen, res.output
    spec = seen["spec"]
    ranges = seen.get("ranges", spec.ranges)
    cfgs = dataclasses.replace(spec, ranges=ranges).robust_configs()
    assert [(c.name, c.n, c.seed, c.friction) for c in cfgs] == [("robust_wide", 3, 9, 0.3), ("robust_mine", 3, 9, 0.3)]
    assert cfgs[1].mass == 0.4 and ranges == ("wide", str(mine.resolve()))
