"""The world model fitted across clips (quasisim.method.world_model, transitions, world_fit; ``quasisim fit``)."""

from __future__ import annotations

import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from quasisim.errors import InputError


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, str]:
    """A 16-frame synthetic clip (its folder: the data), sample-target with 5 samples of 3 frames, recorded."""
    from quasisim.data.synthetic import write_example
    from quasisim.method.config import TransferConfig
    from quasisim.method.spec import TransferSpec
    from quasisim.pipeline import run_transfer

    root = tmp_path_factory.mktemp("world")
    demo = write_example("cube_lift", root / "data", n_frames=16)
    # no back-ups: one recorded step per frame
    cfg = TransferConfig.from_yaml(overrides={"sampling.samples": 5, "sampling.horizon": 3, "sampling.backtrack": 0})
    spec = TransferSpec(method="sample-target", render=False, progress=False)
    run_transfer(demo, root / "runs" / demo.stem / "sample-target", spec, cfg,
                 record_transitions=root / "runs" / demo.stem / "sample-target" / "transitions")  # fmt: skip
    return root / "runs", demo.parent, demo.stem


def test_quat_exp_inverts_quat_log() -> None:
    from quasisim.rotations import quat_exp, quat_log

    d = np.random.default_rng(0).normal(size=(50, 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    angle = np.concatenate([np.linspace(0.01, 3.1, 40), np.full(10, 1e-7)])  # shortest arcs, and tiny ones
    v = jnp.asarray(d * angle[:, None], jnp.float32)
    v = jnp.concatenate([v, jnp.zeros((1, 3))])
    q = quat_exp(v)
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-6)
    np.testing.assert_allclose(quat_log(q), v, atol=1e-5)
    np.testing.assert_array_equal(quat_exp(jnp.zeros(3)), [1.0, 0.0, 0.0, 0.0])


def _state(rng: np.random.Generator) -> object:
    from quasisim.sim.types import State

    q = rng.normal(size=4)
    f = lambda *s: jnp.asarray(rng.normal(size=s), jnp.float32)  # noqa: E731
    return State(f(1, 3), jnp.asarray([[1.0, 0, 0, 0]]), f(5), f(5), f(4, 3), f(4, 3), f(3),
                 jnp.asarray(q / np.linalg.norm(q), jnp.float32), f(3), f(3), f(4, 3), f(4), f(6, 3), f(6))  # fmt: skip


def test_the_correction_target_turns_the_simulators_state_into_the_targets() -> None:
    """apply_correction(s, e, correction_target(s, e, truth)) is the truth's object state (any start frame s)."""
    from quasisim.method.world_model import apply_correction, correction_target

    rng = np.random.default_rng(1)
    s, e, truth = _state(rng), _state(rng), _state(rng)
    got = apply_correction(s, e, correction_target(s, e, truth))
    for k in ("obj_pos", "obj_vel", "obj_angvel"):
        np.testing.assert_allclose(getattr(got, k), getattr(truth, k), atol=1e-5, err_msg=k)
    assert abs(abs(float(jnp.dot(got.obj_quat, truth.obj_quat))) - 1.0) < 1e-6
    np.testing.assert_array_equal(got.q, e.q)  # the hand is the simulator's


@pytest.mark.slow
def test_windows_are_the_recorded_states(recorded: tuple[Path, Path, str]) -> None:
    """``final`` windows follow the applied run frame by frame; ``sampled`` windows start from the step's state
    and the chosen one's first frame is the run's next frame."""
    from quasisim.method.transitions import clip_problem, load_clip, transition_files

    runs, data, name = recorded
    (path,) = transition_files(runs)
    prob = clip_problem(path, data, 10, 64)
    with np.load(path) as z:
        d = {k: z[k] for k in z.files}
    fin = load_clip(path, prob, "final", horizon=4)
    assert fin.horizon == 4 and len(fin) == 16 - 4 and fin.demo == name
    np.testing.assert_array_equal(fin.obj_pos[3, 2], d["run_obj_pos"][5])
    np.testing.assert_array_equal(fin.q_targets[3], d["applied"][3:8])
    np.testing.assert_array_equal(fin.keypoints[0, 1], d["run_keypoints"][1, d["kp_metric_index"]])
    smp = load_clip(path, prob, "sampled", per_step=3)
    assert smp.horizon == 3 and len(smp) == 15 * 3
    for t in (0, 7):
        i = 3 * t  # the chosen window comes first in each step's group
        np.testing.assert_array_equal(smp.q_targets[i], d["windows"][t, d["chosen"][t]])
        np.testing.assert_array_equal(smp.qpos[i, 0], d["start_qpos"][t])
        np.testing.assert_array_equal(smp.obj_quat[i, 1], d["run_obj_quat"][t + 1])
    with pytest.raises(ValueError, match="valid: final, sampled"):
        load_clip(path, prob, "all")


@pytest.mark.slow
@pytest.mark.extended
def test_fit_trains_a_correction_that_predicts_the_target_better(
    recorded: tuple[Path, Path, str], tmp_path: Path
) -> None:
    """``quasisim fit`` end to end on one recorded clip (held out: none): the file records what it was trained on
    and loads back; the untrained correction is exactly the analytical simulator; the trained one predicts the
    target's next frame better than it on the windows it was trained on; a rerun reuses the clip's pairs."""
    from click.testing import CliRunner

    from quasisim.cli import main
    from quasisim.method.transitions import clip_problem, load_clip, transition_files
    from quasisim.method.world_fit import stiffest_params
    from quasisim.method.world_model import WorldModel, init_correction, predict, teacher_forced

    runs, data, name = recorded
    out = tmp_path / "w.eqx"
    args = [
        "fit",
        str(runs),
        "--data",
        str(data),
        "--out",
        str(out),
        "--held-out",
        "",
        "--steps",
        "400",
        "--workers",
        "1",
    ]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, res.output
    wm = WorldModel.load(out)
    assert wm.info["trained_on"] == [name] and wm.info["held_out"] == [] and wm.info["hand"] == "shadow"
    assert wm.info["losses"][-1] < 0.5 * wm.info["losses"][0]
    part = next((tmp_path / "w.eqx.parts").iterdir())
    mtime = part.stat().st_mtime_ns
    assert CliRunner().invoke(main, [*args[:-4], "--steps", "1", "--workers", "1"]).exit_code == 0
    assert part.stat().st_mtime_ns == mtime  # pairs reused, not recomputed

    (path,) = transition_files(runs)
    prob = clip_problem(path, data, 20, 128)
    params = stiffest_params(prob)
    w = load_clip(path, prob, "final", horizon=1)
    feats, target = teacher_forced(params, w, wm.cfg)
    zero = init_correction(wm.cfg, feats.extra, target)
    nominal = predict(params, None, w, wm.cfg)
    np.testing.assert_allclose(predict(params, zero, w, wm.cfg)["obj_pos"], nominal["obj_pos"], atol=1e-6)
    fitted = predict(params, wm.net, w, wm.cfg)
    err = lambda p: np.linalg.norm(p["obj_pos"] - w.obj_pos[:, 1:], axis=-1).mean()  # noqa: E731
    assert err(fitted) < 0.7 * err(nominal), (err(fitted), err(nominal))

    # the benchmarks: the table names every window set and predictor; the speed table every batch size
    bench = tmp_path / "bench"
    world = ["bench", "world", str(runs), "--model", str(out), "--data", str(data), "--clips", name, "--horizons", "6",
             "--out", str(bench)]  # fmt: skip
    res = CliRunner().invoke(main, world)
    assert res.exit_code == 0, res.output
    rows = json.loads((bench / "world.json").read_text())
    assert {(r["windows"], r["predictor"]) for r in rows} == {
        (w, p) for w in ("final 6", "sampled 3") for p in ("zero motion", "nominal", "world model")
    }  # fmt: skip
    assert f"clips here that it was trained on: {name}" in (bench / "world.md").read_text()
    cached = bench / "clips" / f"{name}.json"
    stamp = cached.stat().st_mtime_ns
    res = CliRunner().invoke(main, world)
    assert res.exit_code == 0 and cached.stat().st_mtime_ns == stamp  # the same model: the clip is not redone
    assert json.loads((bench / "world.json").read_text()) == rows
    res = CliRunner().invoke(main, ["bench", "windows", str(path), "--data", str(data), "--windows", "6", "--batch",
                                    "4", "--out", str(tmp_path / "speed")])  # fmt: skip
    assert res.exit_code == 0, res.output
    speed = json.loads((tmp_path / "speed" / "windows.json").read_text())
    assert [(r["batch"], r["windows"]) for r in speed] == [(4, 6)] and speed[0]["windows_per_s"] > 0


@pytest.mark.slow
@pytest.mark.extended  # a world-model benchmark, outside the default method
def test_bench_world_without_a_model_compares_the_nominal_simulator_with_its_variants(
    recorded: tuple[Path, Path, str], tmp_path: Path
) -> None:
    """No --model: zero motion and the nominal simulator on the clips named; --variant adds the nominal
    simulator built with the table on mesh samples, which predicts other states; unknown variants are refused
    with the valid ones."""
    from click.testing import CliRunner

    from quasisim.cli import main

    runs, data, name = recorded
    args = ["bench", "world", str(runs), "--data", str(data), "--clips", name, "--horizons", "2", "--out",
            str(tmp_path / "b")]  # fmt: skip
    res = CliRunner().invoke(main, [*args, "--variant", "no such thing"])
    assert res.exit_code != 0 and "valid: normal force x3" in res.output and "table on mesh samples" in res.output
    res = CliRunner().invoke(main, [*args, "--variant", "table on mesh samples"])
    assert res.exit_code == 0, res.output
    rows = json.loads((tmp_path / "b" / "world.json").read_text())
    assert {(r["windows"], r["predictor"]) for r in rows} == {
        ("final 2", "zero motion"), ("final 2", "nominal"), ("final 2", "table on mesh samples"),
        ("sampled 3", "zero motion"), ("sampled 3", "nominal"), ("sampled 3", "table on mesh samples"),
    }  # fmt: skip
    by = {(r["windows"], r["predictor"]): r for r in rows}
    assert by[("final 2", "nominal")]["pos_cm"] != by[("final 2", "table on mesh samples")]["pos_cm"]
    assert "No world model" in (tmp_path / "b" / "world.md").read_text()


def test_a_file_that_is_not_a_world_model_is_refused_naming_it(tmp_path: Path) -> None:
    from quasisim.method.world_model import WorldModel

    bad = tmp_path / "x.eqx"
    bad.write_bytes(b'{"format": "something-else"}\n\x00\x01')
    with pytest.raises(InputError, match=r"x\.eqx: field 'format': expected a quasisim-world-model-v1 file"):
        WorldModel.load(bad)
    good_head = json.dumps({"format": "quasisim-world-model-v1", "config": {}}).encode()
    bad.write_bytes(good_head + b"\n\x00\x01")  # a file cut short
    with pytest.raises(InputError, match=r"x\.eqx: expected a complete world model file, got damaged"):
        WorldModel.load(bad)
    bad.write_bytes(json.dumps({"format": "quasisim-world-model-v1", "config": {"layers": 3}}).encode() + b"\n")
    with pytest.raises(InputError, match="field 'config': expected the settings of WorldModelConfig"):
        WorldModel.load(bad)
    bad.write_bytes(b"\x89PNG\r\n")
    with pytest.raises(InputError, match=r"x\.eqx"):
        WorldModel.load(bad)
    with pytest.raises(InputError, match="no such file"):
        WorldModel.load(tmp_path / "missing.eqx")


def test_fit_refuses_a_folder_without_transitions(tmp_path: Path) -> None:
    from click.testing import CliRunner

    from quasisim.cli import main

    res = CliRunner().invoke(main, ["fit", str(tmp_path), "--data", str(tmp_path), "--out", str(tmp_path / "w.eqx")])
    assert res.exit_code != 0
    assert "expected a folder holding recorded transitions" in res.output and "Traceback" not in res.output
    assert json.dumps(res.output).count("\\n") <= 2


def test_bench_windows_refuses_bad_batch_sizes(tmp_path: Path) -> None:
    from click.testing import CliRunner

    from quasisim.cli import main

    f = tmp_path / "t.npz"
    f.write_bytes(b"x")
    for bad in ("0", "a,b", ""):
        res = CliRunner().invoke(main, ["bench", "windows", str(f), "--data", str(tmp_path), "--batch", bad])
        assert res.exit_code != 0 and "--batch: expected comma-separated positive integers" in res.output, bad


def test_random_regret_is_the_mean_over_every_draw_of_k() -> None:
    """The order-statistics expectation of bench screen's random baseline equals the brute-force mean over
    all k-subsets; one drawn at random is 1 by definition, all N is 0."""
    from itertools import combinations

    from quasisim.bench.screen import random_regret

    c = np.array([0.3, 0.1, 0.7, 0.2, 0.9, 0.4])
    span = c.mean() - c.min()
    for k in range(1, len(c) + 1):
        brute = np.mean([(min(c[list(s)]) - c.min()) / span for s in combinations(range(len(c)), k)])
        assert random_regret(c, k) == pytest.approx(brute, rel=1e-12)
    assert random_regret(c, 1) == pytest.approx(1.0) and random_regret(c, len(c)) == 0.0


def test_selection_of_a_perfect_and_of_a_reversed_predictor() -> None:
    """A predictor that orders candidates as the target does has rank 1, regret 0 and always finds the best;
    one that orders them backwards has rank -1 and, taking its single cheapest, the target's worst."""
    from quasisim.bench.screen import selection

    rng = np.random.default_rng(0)
    c = rng.random((7, 10))
    good, bad = selection(c, 2 * c + 1, (1, 3)), selection(c, -c, (1, 3))
    assert good["spearman"] == pytest.approx(1.0) and good["regret_1"] == 0.0 and good["hit_1"] == 1.0
    assert bad["spearman"] == pytest.approx(-1.0) and bad["hit_3"] == 0.0
    worst = np.mean((c.max(1) - c.min(1)) / (c.mean(1) - c.min(1)))
    assert bad["regret_1"] == pytest.approx(worst) and bad["regret_1"] > 1.0
    assert good["random_3"] == bad["random_3"] < 1.0


@pytest.mark.extended  # a world-model benchmark, outside the default method
def test_bench_screen_scores_every_candidate_and_checks_the_recorded_costs(
    recorded: tuple[Path, Path, str], tmp_path: Path
) -> None:
    """bench screen on the recorded clip: the target's costs computed again equal the recorded ones; every
    predictor has a row; the kinematic predictor holds the object still (no object rank). A file whose
    costs were not made with these frames and settings is refused, naming it."""
    from click.testing import CliRunner

    from quasisim.cli import main
    from quasisim.method.transitions import transition_files

    runs, data, name = recorded
    args = ["bench", "screen", str(runs), "--data", str(data), "--clips", name, "--top", "1,2,5"]
    res = CliRunner().invoke(main, [*args, "--out", str(tmp_path / "s")])
    assert res.exit_code == 0, res.output
    rows = {r["predictor"]: r for r in json.loads((tmp_path / "s" / "screen.json").read_text())}
    assert set(rows) == {"kinematic, object still", "nominal", "nominal hands, object still"}
    for r in rows.values():
        assert r["cost_check"] <= 1e-4 and r["steps"] == 15 and r["candidates"] == 5
        assert r["random_1"] == pytest.approx(1.0) and r["regret_5"] == 0.0 and r["hit_5"] == 1.0
        assert -1.0 <= r["spearman"] <= 1.0 and r["s_per_window"] > 0 and r["target_s_per_window"] > 0
    assert np.isnan(rows["kinematic, object still"]["object_rank"])
    assert np.isfinite(rows["nominal"]["object_rank"])

    src = transition_files(runs)[0]
    bad = tmp_path / "bad" / name / "sample-target" / "transitions" / src.name
    bad.parent.mkdir(parents=True)
    with np.load(src) as z:
        arrays = {k: z[k] for k in z.files}
    np.savez(bad, **{**arrays, "frame": arrays["frame"] + 1})
    res = CliRunner().invoke(main, ["bench", "screen", str(tmp_path / "bad"), "--data", str(data), "--clips", name,
                                    "--out", str(tmp_path / "s2")])  # fmt: skip
    assert res.exit_code != 0 and str(bad) in res.output and "differ from the recorded ones" in res.output
