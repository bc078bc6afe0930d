"""The default method, the cascade: sampling in the target first (stage ``quick``), ending the run where its
result passes strict success in MuJoCo; the curriculum and sampling around its plan only where it fails."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from helpers import cube_example
from quasisim.errors import QuasisimError
from test_transfer import CURRICULUM, TINY


def test_the_method_follows_from_the_stages_and_a_preset_refuses_other_stages() -> None:
    from quasisim.bench.transfer import run_spec
    from quasisim.method.registry import CASCADE
    from quasisim.method.spec import FULL_STAGES, TransferSpec

    assert (TransferSpec().checked().method, TransferSpec().checked().stages) == ("cascade", CASCADE)
    assert TransferSpec(stages=("1", "2")).checked().method == "ours"
    assert TransferSpec(method="ours").checked().stages == FULL_STAGES
    assert TransferSpec(stages=()).checked().stages == ()  # no stages given is not the default stages
    assert TransferSpec(method="sample-target").checked().stages == ("sample",)
    with pytest.raises(QuasisimError, match="method ours"):
        TransferSpec(method="cascade", stages=("1", "2")).checked()
    # a benchmark run of the cascade keeps the curriculum (its stages 1 and 2 use it); sample-target has none
    assert run_spec("cascade", FULL_STAGES, TransferSpec()).curriculum == "short"
    assert run_spec("sample-target", FULL_STAGES, TransferSpec()).curriculum == "none"


def test_sampling_stops_at_the_first_frame_that_stays_outside_the_strict_limits(tmp_path: Path) -> None:
    from quasisim.limits import STRICT_CM, STRICT_DEG, object_errors
    from quasisim.method.config import TransferConfig
    from quasisim.method.stages.sampling import run_sampling

    _, demo, controls, scene = cube_example(tmp_path)
    cfg = TransferConfig.from_yaml()
    # the kinematic retarget alone (one window, the nominal; no back-ups) does not lift the cube
    opts = dataclasses.replace(cfg.sampling, samples=1, screen=1, backtrack=0, prune_frames=0)
    full = run_sampling(demo, scene, controls.q_targets, opts, cfg.weights, progress=False)
    rot, trans = object_errors(demo.object_pos, demo.object_quat, full.rollout.object_pos, full.rollout.object_quat)
    off = np.flatnonzero((trans > STRICT_CM) | (rot > STRICT_DEG))
    assert full.stopped_at is None and len(off), "the nominal alone should leave the strict limits"

    stop = run_sampling(
        demo, scene, controls.q_targets, dataclasses.replace(opts, stop_when_lost=True), cfg.weights, progress=False
    )
    t = int(off[0])
    assert stop.stopped_at == t
    assert len(stop.rollout.object_pos) == t + 1  # the frames observed up to the lost one
    np.testing.assert_array_equal(stop.q_targets[: t + 1], full.q_targets[: t + 1])  # the same run until then
    np.testing.assert_array_equal(stop.q_targets[t + 1 :], controls.q_targets[t + 1 :])  # then the plan's targets
    assert stop.n_physics_steps < full.n_physics_steps


def _run(demo: Path, out: Path, overrides: dict, curriculum: str = "short") -> tuple[dict, dict, list[str]]:
    from quasisim.method.config import TransferConfig
    from quasisim.method.spec import TransferSpec
    from quasisim.pipeline import run_transfer

    spec = TransferSpec(curriculum=curriculum, render=False, progress=False, robust=0)
    run_transfer(demo, out, spec, TransferConfig.from_yaml(overrides=overrides))
    metrics = json.loads((out / "metrics.json").read_text())
    summary = json.loads((out / "summary.json").read_text())
    return metrics, summary, sorted(p.stem for p in (out / "checkpoints").glob("*.npz"))


@pytest.mark.slow
def test_the_cascade_ends_after_sampling_where_it_passes_strict_success_in_mujoco(tmp_path: Path) -> None:
    from quasisim.method.stages.selection import passes
    from quasisim.targets import make_target

    path, demo, kinematic, scene = cube_example(tmp_path)
    _, summary, ck = _run(path, tmp_path / "run", {})
    assert ck == ["kinematic", "quick"]  # no curriculum
    quick = np.load(tmp_path / "run" / "checkpoints" / "quick.npz")
    assert bool(quick["passed"]) and int(quick["stopped_at"]) == -1
    q = np.load(tmp_path / "run" / "controls.npz")["q_targets"]
    np.testing.assert_array_equal(q, quick["q_targets"])  # the run ended with the quick result
    with make_target("mujoco", scene) as tg:  # the gate's judge tells a passing plan from the retarget, which fails
        assert passes(demo, tg.rollout(q)) and not passes(demo, tg.rollout(kinematic.q_targets))
    assert "extra_sim_qpos" not in np.load(tmp_path / "run" / "controls.npz")  # no quasi-physical plan
    assert set(summary["seconds"]) >= {"retarget", "quick"} and "stage1" not in summary["seconds"]


@pytest.mark.slow
def test_the_cascade_runs_the_curriculum_where_sampling_loses_the_object(tmp_path: Path) -> None:
    path, *_ = cube_example(tmp_path)
    (tmp_path / "tiny.yaml").write_text(CURRICULUM)
    lose = {"sampling.samples": 1, "sampling.screen": 1, "sampling.backtrack": 0, "sampling.prune_frames": 0}
    _, summary, ck = _run(path, tmp_path / "run", {**TINY, **lose}, str(tmp_path / "tiny.yaml"))
    assert "quick" in ck and "stage1_human" in ck and any(c.startswith("stage2_") for c in ck) and "sample" in ck
    assert {"quick", "stage1", "stage2", "sample", "select"} <= set(summary["seconds"])
    # the first step stopped early: its partial result is not a candidate of the selection
    costs = json.loads(str(np.load(tmp_path / "run" / "controls.npz")["extra_selection_costs"]))
    assert "sample-target" not in costs and {"kinematic", "curriculum"} <= set(costs)


def test_robust_choice_keeps_the_plan_passing_strict_closed_loop_in_the_most_training_worlds(monkeypatch) -> None:
    """Among candidates that pass strict nominally: most training worlds strict, then the lower objective; a
    candidate failing nominally is never judged or kept; equal trajectories are judged once."""
    from quasisim.method.options import RobustSelectOptions
    from quasisim.method.stages import selection

    q = {n: np.full((3, 2), i, np.float64) for i, n in enumerate("abcd")}
    q["a2"] = q["a"].copy()
    closed = {0: 0.5, 1: 0.75, 2: 0.75, 3: 1.0}
    judged = []

    def fake_closed(prob, target, traj, opts, weights):
        judged.append(int(traj[0, 0]))
        return closed[int(traj[0, 0])]

    monkeypatch.setattr(selection, "closed_loop_success", fake_closed)
    monkeypatch.setattr(selection, "passes_strict", lambda prob, target, traj: int(traj[0, 0]) != 3)  # d fails
    costs = {"a": 0.1, "b": 0.3, "c": 0.2, "d": 0.0, "a2": 0.1}
    ro = RobustSelectOptions(worlds=4)
    best, scores = selection.robust_choice(None, "mujoco", q, costs, ro, None)
    assert best == "c" and set(scores) == {"a", "a2", "b", "c"} and sorted(judged) == [0, 1, 2]
    closed[1] = 1.0  # b now passes in every world: kept although its objective is higher
    assert selection.robust_choice(None, "mujoco", q, costs, ro, None)[0] == "b"
    monkeypatch.setattr(selection, "passes_strict", lambda *a: False)
    assert selection.robust_choice(None, "mujoco", q, costs, ro, None) == (None, {})


def test_closed_loop_success_tracks_in_training_worlds_never_the_evaluations(tmp_path: Path, monkeypatch) -> None:
    """The gate's worlds: robust.yaml's ranges drawn with robust_select.seed (the evaluation's seed is 0), each
    replayed closed loop; the fraction passing strict."""
    import quasisim.targets.perturb as perturb
    from quasisim.eval.robust import replays
    from quasisim.method.config import TransferConfig
    from quasisim.method.options import RobustSelectOptions
    from quasisim.method.stages.selection import closed_loop_success

    _, demo, controls, scene = cube_example(tmp_path)
    worlds, real = [], perturb.perturbed_scene
    monkeypatch.setattr(perturb, "perturbed_scene", lambda sc, cfg, i: worlds.append((cfg.seed, i)) or real(sc, cfg, i))
    prob = type("P", (), {"demo": demo, "scene": scene})()
    weights = TransferConfig.from_yaml().weights
    assert closed_loop_success(prob, "mujoco", controls.q_targets, RobustSelectOptions(worlds=0), weights) is None
    ro = RobustSelectOptions(worlds=2, seed=3, tracker="track_fast.yaml")
    frac = closed_loop_success(prob, "mujoco", controls.q_targets, ro, weights)
    assert worlds == [(3, 0), (3, 1)] and replays(8).seed not in {s for s, _ in worlds}
    assert frac == 0.0  # the kinematic retarget does not lift the cube, closed loop or not


@pytest.mark.slow
def test_the_cascade_gate_asks_for_closed_loop_success_in_training_worlds(tmp_path: Path, monkeypatch) -> None:
    """A quick result that passes strict nominally, judged closed loop in 2 training worlds: with the gate at 0
    the run ends there (the note gives the closed-loop figure); where those worlds say no, the curriculum runs."""
    from quasisim.method.stages import quick

    path, *_ = cube_example(tmp_path)
    (tmp_path / "tiny.yaml").write_text(CURRICULUM)
    on = {**TINY, "robust_select.worlds": 2, "robust_select.gate": 0.0}
    _, summary, ck = _run(path, tmp_path / "open", on, str(tmp_path / "tiny.yaml"))
    assert ck == ["kinematic", "quick"]
    assert any("closed loop in" in n and "of 2 training worlds" in n for n in summary["notes"]), summary["notes"]
    monkeypatch.setattr(quick, "closed_loop_success", lambda *a: 0.5)
    _, summary, ck = _run(path, tmp_path / "gated", {**on, "robust_select.gate": 0.75}, str(tmp_path / "tiny.yaml"))
    assert "stage1_human" in ck and {"stage1", "stage2", "sample", "select"} <= set(summary["seconds"])
    assert any("closed loop in only 50 % of 2 training worlds" in n for n in summary["notes"])
    # the quick result stays a candidate of the selection, which judged the nominal passers closed loop
    costs = json.loads(str(np.load(tmp_path / "gated" / "controls.npz")["extra_selection_costs"]))
    assert "sample-target" in costs


def test_robust_select_at_its_defaults_leaves_a_runs_identity_as_it_was() -> None:
    """Runs made before robust_select existed stay finished runs (resume, report-only passes); turning it on
    changes the identity of the stages that read it."""
    from quasisim.method.config import TransferConfig
    from quasisim.method.registry import CASCADE
    from quasisim.method.stage import declared_stages

    stages = declared_stages(CASCADE)
    off = TransferConfig.from_yaml().identity("fast", stages)
    on = TransferConfig.from_yaml(overrides={"robust_select.worlds": 8}).identity("fast", stages)
    assert "robust_select" not in off and on["robust_select"] == {"worlds": 8}
    assert {k: v for k, v in on.items() if k != "robust_select"} == off


def test_the_margin_stage_at_its_default_leaves_a_cascade_runs_identity_as_it_was() -> None:
    """Stage margin, idle at robust_select.margin 0, is left out of a run's recorded stages, so the cascade
    runs made before it existed (benchmarks/runs: stages quick, 1, 2, sample, select) stay finished runs;
    with a margin it is recorded, and its setting changes the config hash."""
    from quasisim.batch import Run, Settings, identity
    from quasisim.method.spec import TransferSpec

    run = Run(name="cascade", spec=TransferSpec().checked())
    off, on = identity(run, Settings()), identity(run, Settings(overrides={"robust_select.margin": 0.8}))
    assert off["stages"] == ["quick", "1", "2", "sample", "select"]
    assert on["stages"] == [*off["stages"], "margin"] and on["config_sha256"] != off["config_sha256"]


@pytest.mark.slow
def test_the_margin_stage_samples_a_plan_riding_the_limits_again_after_the_quick_step_ended_the_run(
    tmp_path: Path,
) -> None:
    """robust_select.margin m: the quick step ends the run with a plan passing strict at largest error e; the
    margin stage still runs and, for m < e, samples that plan again from itself and keeps the result only where
    its largest error is smaller (the controls' plan is the kept one, its error the one recorded, never above
    e); for m above e it samples nothing and the plan stays as it was."""
    from types import SimpleNamespace

    from quasisim.method.stages.selection import largest_error

    path, demo, _, scene = cube_example(tmp_path)
    prob = SimpleNamespace(demo=demo, scene=scene)
    _, _, ck = _run(path, tmp_path / "base", {})
    q0 = np.load(tmp_path / "base" / "controls.npz")["q_targets"]
    e0 = largest_error(prob, "mujoco", q0)
    assert ck == ["kinematic", "quick"] and 0 < e0 <= 1
    _, summary, ck = _run(path, tmp_path / "tight", {"robust_select.margin": 0.5 * e0})
    d, q = np.load(tmp_path / "tight" / "checkpoints" / "margin.npz"), np.load(tmp_path / "tight" / "controls.npz")
    assert "margin" in ck and bool(d["sampled"]) and float(d["before"]) == pytest.approx(e0)
    assert float(d["after"]) <= e0 and "margin" in summary["seconds"]
    assert largest_error(prob, "mujoco", q["q_targets"]) == pytest.approx(float(d["after"]))
    assert (float(d["after"]) < e0) == ("extra_before_margin_q" in q.files)
    assert any(n.startswith("margin: sampled again") for n in summary["notes"]), summary["notes"]
    _, summary, _ = _run(path, tmp_path / "loose", {"robust_select.margin": min(0.99, e0 + 0.01)})
    assert not bool(np.load(tmp_path / "loose" / "checkpoints" / "margin.npz")["sampled"])
    np.testing.assert_array_equal(np.load(tmp_path / "loose" / "controls.npz")["q_targets"], q0)
