"""Stage ``select``: the whole-clip tracking objective of a target rollout, and the best trajectory kept."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from quasisim.errors import QuasisimError
from quasisim.method.config import TransferConfig
from quasisim.method.select import best_in_target, clip_cost
from quasisim.targets import TargetRollout


@pytest.fixture(scope="module")
def cube(example_dir: Path):
    from quasisim.assets.hand import load_hand
    from quasisim.data.demo import load_demo
    from quasisim.method.retarget import kinematic_controls
    from quasisim.targets.build import scene_for
    from quasisim.targets.scene import place_hands

    demo = load_demo(example_dir / "cube_lift.npz")
    hand = load_hand("shadow")
    c = kinematic_controls(hand, demo, "shadow")
    return demo, scene_for(demo, place_hands((hand,), c.base_rots)), c.q_targets


def _perfect(demo) -> TargetRollout:
    """A rollout that follows the demo exactly (one robot keypoint per human keypoint)."""
    T = demo.n_frames
    kp = np.asarray(demo.right_joints, np.float64)
    return TargetRollout(
        "mujoco", np.zeros((T, 7)), demo.object_pos.copy(), demo.object_quat.copy(), kp, np.arange(21),
        np.ones(21, bool), 0.002, 25, 0.0,
    )  # fmt: skip


def test_clip_cost_closed_form(cube) -> None:
    demo = cube[0]
    w = TransferConfig.from_yaml().weights
    assert clip_cost(demo, _perfect(demo), w) == pytest.approx(0.0, abs=1e-5)  # sqrt(|x|^2 + 1e-12) per term
    r = _perfect(demo)
    shifted = dataclasses.replace(r, object_pos=r.object_pos + np.array([0.01, 0.0, 0.0]))  # 1 cm off at every frame
    assert clip_cost(demo, shifted, w) == pytest.approx(0.01 * w.obj_pos, abs=1e-5)
    hand = dataclasses.replace(r, keypoints=r.keypoints + np.array([0.0, 0.0, 0.02]))  # keypoints 2 cm off
    assert clip_cost(demo, hand, w) == pytest.approx(0.02 * w.hand, abs=1e-5)
    bad = dataclasses.replace(r, object_pos=np.where(np.arange(demo.n_frames)[:, None] == 5, np.nan, r.object_pos))
    assert clip_cost(demo, bad, w) == float("inf")


def test_best_in_target_keeps_the_better_trajectory(cube) -> None:
    demo, scene, q = cube
    w = TransferConfig.from_yaml().weights
    away = q.copy()
    away[:, 2] += 0.15  # the hand 15 cm above where it should be: the cube is never grasped
    for order in (("away", "kinematic"), ("kinematic", "away")):
        cands = {"away": away, "kinematic": q}
        best, costs = best_in_target(demo, scene, "mujoco", {k: cands[k] for k in order}, w)
        assert best == "kinematic" and costs["away"] > costs["kinematic"]
    best, costs = best_in_target(demo, scene, "mujoco", {"a": q, "b": q.copy()}, w)
    assert best == "a" and costs["a"] == costs["b"]  # deterministic replay; ties keep the first listed


def test_select_is_a_stage() -> None:
    from quasisim.bench.transfer import jobs, run_spec
    from quasisim.method.spec import TransferSpec, parse_stages

    assert parse_stages("1,2,mpc,select") == ("1", "2", "mpc", "select")
    base = TransferSpec(render=False, progress=False)
    specs = {r: run_spec(r, ("1", "2"), base) for r in ("default", "default+mpc", "default+mpc+select")}
    assert specs["default+mpc+select"].stages == ("1", "2", "mpc", "select")
    (job,) = jobs([Path("x.npz")], specs)
    assert [(r.name, r.seed_from) for r in job.runs] == [
        ("default", None), ("default+mpc", "default"), ("default+mpc+select", "default+mpc"),
    ]  # fmt: skip
    # stage 3's ablations as benchmark rows
    ablation = run_spec("default+3+mpc:no-residual:no-control-transform", ("1", "2"), base)
    assert ablation.stages == ("1", "2", "3", "mpc") and ablation.networks == ()
    assert run_spec("default+3+mpc:no-local-residual", ("1", "2"), base).networks == ("global", "control")
    for bad in ("default+mpc:no-residual", "default+3:no-thing", "default+4"):
        with pytest.raises(QuasisimError, match="valid forms"):
            run_spec(bad, ("1", "2"), base)


def test_transfer_with_select_outputs_the_best_seen(example_dir: Path, tmp_path: Path) -> None:
    """A short transfer with stages sample, select: the output is the candidate with the lowest objective
    (recorded in the controls), and the metrics judge that trajectory."""
    import json

    from quasisim.data.controls import load_controls
    from quasisim.method.spec import TransferSpec
    from quasisim.pipeline import run_transfer

    cfg = TransferConfig.from_yaml(overrides={"sampling.samples": 4, "sampling.horizon": 3})
    spec = TransferSpec(stages=("sample", "select"), render=False, progress=False)
    res = run_transfer(example_dir / "cube_lift.npz", tmp_path / "run", spec, cfg)
    c = load_controls(tmp_path / "run" / "controls.npz")
    costs = json.loads(str(c.extras["selection_costs"]))
    assert set(costs) == {"last stage", "sampling nominal", "curriculum", "kinematic"}
    assert str(c.extras["selected"]) == min(costs, key=costs.__getitem__)
    assert costs[str(c.extras["selected"])] <= costs["last stage"]
    assert res.record.notes and "kept" in res.record.notes[-1]
