"""Baseline sample-target: predictive sampling in the target simulator with the target as its model."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import yaml

from quasisim.errors import QuasisimError
from quasisim.method.config import TransferConfig
from quasisim.method.options import SAMPLING_MODES, SamplingOptions
from quasisim.method.stages.sampling import (
    UNSTABLE_COST,
    Prediction,
    copy_scenes,
    cost_bounds,
    knot_basis,
    pruner,
    robust_scores,
    run_sampling,
    sample_windows,
    strict_hinge,
    window_costs,
)

W = TransferConfig.from_yaml().weights  # the shipped objective weights

OPTS = SamplingOptions(
    samples=8, horizon=4, knots=3, noise_base_pos=0.004, noise_base_rot=0.04, noise_joints=0.08,
    noise_scales=(0.5, 1.0, 2.0), mode="predictive", temperature=0.003, seed=0, threads=2, kinematic_alternative=False,
)  # fmt: skip
ZERO = dataclasses.replace(OPTS, noise_base_pos=0.0, noise_base_rot=0.0, noise_joints=0.0)


def _inputs(demo):
    from quasisim.assets.hand import load_hand
    from quasisim.method.retarget import retarget
    from quasisim.targets.build import load_object_for, scene_for
    from quasisim.targets.scene import Placement

    hand = load_hand("shadow")
    rt = retarget(hand, demo)
    return demo, rt.q, scene_for(demo, (Placement(hand, rt.base_rot),), load_object_for(demo))


@pytest.fixture(scope="module")
def real(data_dir: Path):
    """12 frames of a real clip from the lift-off (clip frame 30), where replaying the plan loses the cube."""
    from quasisim.data.demo import load_demo

    return _inputs(load_demo(data_dir / "grab_s1_cubesmall_lift.npz").slice(30, 42))


@pytest.fixture(scope="module")
def synth(tmp_path_factory: pytest.TempPathFactory):
    """The synthetic cube lift (no ../shared needed), 12 frames."""
    from quasisim.data.demo import load_demo
    from quasisim.data.synthetic import write_example

    return _inputs(load_demo(write_example("cube_lift", tmp_path_factory.mktemp("st"), n_frames=12)))


def _replay(scene, q):
    from quasisim.targets import make_target

    return make_target("mujoco", scene).rollout(q)


# ---- options -----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("samples", 0, "samples"),
        ("horizon", -1, "horizon"),
        ("knots", 1.5, "knots"),
        ("threads", True, "threads"),
        ("noise_joints", -0.1, "noise_joints"),
        ("noise_scales", (), "noise_scales"),
        ("noise_scales", (1.0, float("nan")), "noise_scales"),
        ("noise_scales", (1.0, "2"), "noise_scales"),
        ("temperature", 0.0, "temperature"),
        ("temperature", float("inf"), "temperature"),
        ("seed", None, "seed"),
        ("mode", "cem", "valid options: mppi, predictive"),
        ("backtrack", -1, "backtrack"),
        ("backtrack_budget", 1.5, "backtrack_budget"),
        ("backtrack_samples", 0, "backtrack_samples"),
        ("strict_weight", float("nan"), "strict_weight"),
        ("strict_margin", -0.1, "strict_margin"),
        ("robust_copies", -1, "robust_copies"),
        ("robust_top", 0, "robust_top"),
        ("robust_seed", 1.0, "robust_seed"),
        ("backtrack_copies", 1, "backtrack_copies"),
        ("kinematic_alternative", "yes", "kinematic_alternative"),
        ("screen", 0, "screen"),
        ("replan", 0, "replan"),
        ("replan_margin", 0.0, "replan_margin"),
        ("replan_margin", float("inf"), "replan_margin"),
        ("replan_margin", "0.5", "replan_margin"),
        ("widen_margin", -1.0, "widen_margin"),
        ("backtrack_retries", -1, "backtrack_retries"),
        ("backtrack_strict_weight", -0.5, "backtrack_strict_weight"),
        ("backtrack_after_lost", 0, "backtrack_after_lost"),
        ("prune_frames", -1, "prune_frames"),
        ("prune_keep", 0.0, "prune_keep"),
        ("prune_keep", 1.5, "prune_keep"),
        ("backtrack_limit", 0.0, "backtrack_limit"),
        ("backtrack_limit", 1.2, "backtrack_limit"),
        ("grasp_weight", -0.1, "grasp_weight"),
        ("grasp_margin", 1.0, "grasp_margin"),
        ("grasp_slots", 0, "grasp_slots"),
    ],
)
def test_bad_options_raise(field: str, value: object, match: str) -> None:
    with pytest.raises(QuasisimError, match=match):
        dataclasses.replace(OPTS, **{field: value})


def test_docstring_yaml_builds_the_options() -> None:
    """The suggested YAML block in the module docstring is complete and valid (every field is required)."""
    import quasisim.method.stages.sampling as st
    from quasisim.config import build

    block = st.__doc__.split("::", 1)[1]
    opts = build(SamplingOptions, yaml.safe_load(block)["sampling"], None)
    shipped = TransferConfig.from_yaml().sampling  # the docstring suggests the shipped sizes
    assert (opts.samples, opts.horizon, opts.knots) == (shipped.samples, shipped.horizon, shipped.knots)
    assert opts.mode in SAMPLING_MODES
    assert opts.noise_scales == (0.5, 1.0, 2.0)
    with pytest.raises(QuasisimError, match="seed"):
        build(SamplingOptions, {k: v for k, v in yaml.safe_load(block)["sampling"].items() if k != "seed"}, None)


def test_bad_target_and_plan_raise(synth) -> None:
    demo, plan, scene = synth
    with pytest.raises(QuasisimError, match="valid options: mujoco, pybullet"):
        run_sampling(demo, scene, plan, OPTS, W, target="isaac", progress=False)
    with pytest.raises(QuasisimError, match="plan must have shape"):
        run_sampling(demo, scene, plan[:-1], OPTS, W, progress=False)


# ---- sampling and scoring ------------------------------------------------------------------------------


def test_knots_noise_and_limits() -> None:
    B = knot_basis(6, 3)
    np.testing.assert_allclose(B.sum(1), 1.0)
    np.testing.assert_allclose(B[[0, -1]], [[1, 0, 0], [0, 0, 1]])
    np.testing.assert_allclose(knot_basis(4, 1), np.ones((4, 1)))
    J = 3
    nominal = np.zeros((5, 6 + J))
    nominal[:, 6] = 0.95  # near the upper limit of joint 0
    nominal[2, 7] = -1.2  # the nominal itself below the lower limit of joint 1
    lo, hi = np.full(J, -1.0), np.array([1.0, 1.0, np.inf])
    opts = dataclasses.replace(OPTS, samples=200, horizon=4, noise_joints=0.5)
    w = sample_windows(np.random.default_rng(0), nominal, opts, lo, hi)
    assert w.shape == (200, 5, 6 + J)
    np.testing.assert_array_equal(w[0], nominal)
    np.testing.assert_array_equal(w[:, 0], np.broadcast_to(nominal[0], (200, 6 + J)))  # frame t is fixed
    assert w[:, :, 6].max() == 1.0 and w[:, [1, 3, 4], 7].min() == -1.0  # clipped to the limits
    assert w[:, 2, 7].min() == -1.2 and w[:, :, 8].max() > 1.0  # widened to the nominal; unlimited
    # the std of the base position noise at a knot frame is noise_base_pos x the cycled multiplier
    d = w[1:, 1, 0] - nominal[1, 0]
    sc = np.asarray(opts.noise_scales)[np.arange(199) % 3]
    assert 0.8 < np.std(d / sc) / opts.noise_base_pos < 1.2


def test_window_costs_terms_and_mask() -> None:
    N, H, K = 2, 3, 4
    wins = np.zeros((N, H + 1, 8))
    wins[1, 2, 0] = 0.1  # second differences 0.1, -0.2 of one of 6 base columns
    q = np.tile([1.0, 0, 0, 0], (N, H, 1))
    pred = Prediction(np.zeros((N, H, 8)), np.zeros((N, H, 3)), q, np.zeros((N, H, K, 3)), 0)
    ref_pos = np.array([[0.01, 0, 0], [0.02, 0, 0], [9.0, 0, 0]])  # frame 2 masked out
    ref_kp = np.zeros((H, K, 3))
    ref_kp[:, :, 2] = 0.003
    ref_quat = np.tile([np.cos(0.1), np.sin(0.1), 0, 0], (H, 1))
    c = window_costs(
        wins, pred, ref_pos, ref_quat, ref_kp, np.array([1.0, 1.0, 0.0]), dataclasses.replace(W, smooth=2.0)
    )
    base = 0.015 + (1 - np.cos(0.1)) + 0.003
    # float32, the objective of the gradient-based MPC (quasisim.optim.objective)
    np.testing.assert_allclose(c, [base, base + 2.0 * (0.01 + 0.04) / 12], rtol=2e-6)


def test_strict_hinge_closed_form() -> None:
    """Frames at 1 cm, 3 cm and 36 deg off the reference are 0.5, 1.5 and 1.2 of the strict limits (2 cm,
    30 deg); past a margin of 0.75: 0, 0.75 and 0.45, averaged over the unmasked frames; the window cost adds
    it times the weight."""
    H = 4
    ref_pos, ref_quat = np.zeros((H, 3)), np.tile([1.0, 0, 0, 0], (H, 1))
    pos = np.array([[[0.01, 0, 0], [0.03, 0, 0], [0, 0, 0], [5.0, 0, 0]]])
    a = np.radians(36.0) / 2
    quat = np.tile([1.0, 0, 0, 0], (1, H, 1))
    quat[0, 2] = [np.cos(a), 0, 0, np.sin(a)]
    mask = np.array([1.0, 1.0, 1.0, 0.0])  # frame 3 past the clip's end
    np.testing.assert_allclose(strict_hinge(pos, quat, ref_pos, ref_quat, mask, 0.75), [(0.75 + 0.45) / 3])
    np.testing.assert_allclose(strict_hinge(pos, quat, ref_pos, ref_quat, mask, 2.0), [0.0])
    pred = Prediction(np.zeros((1, H, 8)), pos, quat, np.zeros((1, H, 2, 3)), 0)
    wins, kp = np.zeros((1, H + 1, 8)), np.zeros((H, 2, 3))
    plain = window_costs(wins, pred, ref_pos, ref_quat, kp, mask, W)
    hinged = window_costs(wins, pred, ref_pos, ref_quat, kp, mask, W, strict=(0.1, 0.75))
    np.testing.assert_allclose(hinged - plain, [0.1 * 0.4], rtol=1e-6)


def test_back_up_bookkeeping_survives_chained_back_ups() -> None:
    """Back-ups from frame 50 to 45, then from 46 to 41, then from 42 to 37: the states older than 40 were
    released while the loop stood at frame 50, so the third goes back to frame 40, the oldest state kept (it
    once raised KeyError); without a back-up the states older than t - 2 backtrack are released."""
    from quasisim.method.stages.sampling import _kept_states

    kept = list(range(40, 51))  # after frame 50: frames 40..50 (backtrack 5: 10 frames kept)
    back, drop = _kept_states(kept, 50, 45, 10)
    assert back == 45 and drop == [46, 47, 48, 49, 50]
    kept = [k for k in kept if k not in drop] + [46]
    back, drop = _kept_states(kept, 46, 41, 10)
    assert back == 41 and drop == [42, 43, 44, 45, 46]
    back, drop = _kept_states([40, 41, 42], 42, 37, 10)
    assert back == 40 and drop == [41, 42]
    assert _kept_states(list(range(30, 42)), 41, None, 10) == (None, [30])


def test_a_frame_that_leaves_the_limits_again_backs_up_further() -> None:
    """Step 6's choice: the first back-up from frame 50 goes ``backtrack`` frames back, a retry from the same
    frame ``backtrack`` further; past ``backtrack_retries`` or the clip's budget, none."""
    from quasisim.method.stages.sampling import _back_up_to

    opts = dataclasses.replace(OPTS, backtrack=5, backtrack_budget=3, backtrack_retries=1)
    assert _back_up_to(50, True, opts, {}) == 45
    assert _back_up_to(50, True, opts, {50: 1}) == 40
    assert _back_up_to(50, True, opts, {50: 2}) is None  # one retry only
    assert _back_up_to(50, False, opts, {}) is None  # on track
    assert _back_up_to(50, True, opts, {20: 2, 30: 1}) is None  # the budget is spent
    assert _back_up_to(7, True, opts, {7: 1}) == 1  # not before frame 1
    assert _back_up_to(50, True, dataclasses.replace(opts, backtrack_retries=0), {50: 1}) is None


def test_robust_scores_average_the_copies() -> None:
    """Step 7's score: the top candidates' cost in the target averaged with their costs in the copies (an
    unstable copy rollout counts UNSTABLE_COST); the rest can never be chosen."""
    costs = np.array([0.3, 0.1, 0.2, 0.5])
    top = np.array([1, 2])
    s = robust_scores(costs, [np.array([0.5, 0.2]), np.array([np.nan, 0.2])], top)
    np.testing.assert_allclose(s[top], [(0.1 + 0.5 + UNSTABLE_COST) / 3, 0.2])
    assert np.isinf(s[[0, 3]]).all()
    np.testing.assert_array_equal(robust_scores(costs, [], top)[top], costs[top])


def test_robust_scores_with_a_risk_measure() -> None:
    """worst: the largest of a candidate's costs over the target and the copies; cvar 0.5: the mean of its
    largest half (ceil); a candidate robust in every copy beats one cheaper on average with a bad copy."""
    costs = np.array([0.1, 0.3])
    top = np.array([0, 1])
    copies = [np.array([0.05, 0.3]), np.array([0.9, 0.3]), np.array([0.0, 0.3])]  # candidate 0: one bad copy
    mean, worst = robust_scores(costs, copies, top), robust_scores(costs, copies, top, "worst")
    cvar = robust_scores(costs, copies, top, "cvar", 0.5)
    np.testing.assert_allclose(mean, [0.2625, 0.3])
    np.testing.assert_allclose(worst, [0.9, 0.3])
    np.testing.assert_allclose(cvar, [(0.9 + 0.1) / 2, 0.3])
    assert np.argmin(mean) == 0 and np.argmin(worst) == 1 and np.argmin(cvar) == 1
    with pytest.raises(QuasisimError, match="robust_risk"):
        dataclasses.replace(OPTS, robust_risk="max")


def test_copies_are_perturbed_away_from_the_judged_replays(real) -> None:
    """The copies are drawn as the robust replays are (the shipped ranges), but from robust_seed, so the
    planner never sees the scenes its robust success is judged in (configs/robust.yaml seed 0)."""
    from quasisim.eval.robust import RobustConfig, perturbed_scene

    scene = real[2]
    copies = copy_scenes(scene, dataclasses.replace(OPTS, robust_copies=3))
    judged = [perturbed_scene(scene, RobustConfig.from_yaml(), i) for i in range(8)]
    assert len(copies) == 3 and RobustConfig.from_yaml().seed != OPTS.robust_seed
    masses = {round(c.obj.mass / scene.obj.mass, 12) for c in copies}
    assert len(masses) == 3 and all(0.85 <= m <= 1.15 for m in masses)
    assert masses.isdisjoint({round(j.obj.mass / scene.obj.mass, 12) for j in judged})


def test_named_worlds_are_the_corner_of_the_ranges_and_a_thinner_grip(real) -> None:
    """``robust_worlds``: the copies start with the named worlds (corner: mass high, friction low, gains low at the
    ends of configs/robust.yaml's ranges, the object where it starts; thin: the hands' contact margin -robust_thin;
    corner-thin: both), then the random copies; an unknown name is refused listing the names."""
    from quasisim.errors import QuasisimError
    from quasisim.eval.robust import RobustConfig

    scene, r = real[2], RobustConfig.from_yaml()
    opts = dataclasses.replace(
        OPTS, robust_worlds=("corner", "thin", "corner-thin"), robust_thin=0.002, robust_copies=1
    )
    corner, thin, both, random = copy_scenes(scene, opts)
    for w in (corner, both):
        assert w.obj.mass == pytest.approx(scene.obj.mass * (1 + r.mass))
        assert w.physics.friction == pytest.approx(scene.physics.friction * (1 - r.friction))
        assert w.physics.gain_scale == pytest.approx(scene.physics.gain_scale * (1 - r.pd_gains))
        np.testing.assert_array_equal(w.object_pos0, scene.object_pos0)
    assert corner.physics.contact_margin == 0 and thin.physics.contact_margin == both.physics.contact_margin == -0.002
    assert thin.obj.mass == scene.obj.mass and thin.physics.friction == scene.physics.friction
    assert random.physics.contact_margin == 0 and random.obj.mass != scene.obj.mass
    with pytest.raises(QuasisimError, match="valid options: corner, corner-thin, thin"):
        dataclasses.replace(OPTS, robust_worlds=("cornr",))


# ---- the control loop in MuJoCo ------------------------------------------------------------------------


def test_zero_noise_is_a_replay_of_the_plan(real) -> None:
    """Zero noise: every candidate is the nominal, so the run is a plain replay of the plan; the candidate
    rollouts (state copy, per-step controls, sensor timing) predict the replay's frames exactly."""
    from quasisim.targets import make_target

    demo, plan, scene = real
    res = run_sampling(demo, scene, plan, ZERO, W, progress=False)
    rep = _replay(scene, plan)
    np.testing.assert_array_equal(res.q_targets, plan)
    np.testing.assert_allclose(res.rollout.qpos, rep.qpos, atol=1e-9)
    np.testing.assert_allclose(res.rollout.object_pos, rep.object_pos, atol=1e-9)
    np.testing.assert_allclose(res.rollout.keypoints, rep.keypoints, atol=1e-9)
    assert res.prediction_error.max() <= 1e-9
    assert res.q_targets.shape == plan.shape and res.window_loss.shape == (demo.n_frames - 1,)
    assert res.n_physics_steps == (demo.n_frames - 1) * (8 * (4 * 25 + 1) + 25)

    with make_target("mujoco", scene, threads=2) as tgt:  # a whole window, from the start state
        tgt.reset(plan[0], None)
        win = plan[None, :5]
        pred = tgt.rollout_windows(win, (win[:, 1] - win[:, 0]) * demo.fps)
    np.testing.assert_allclose(pred.qpos[0], rep.qpos[1:5], atol=1e-9)
    np.testing.assert_allclose(pred.obj_pos[0], rep.object_pos[1:5], atol=1e-9)
    np.testing.assert_allclose(pred.keypoints[0], rep.keypoints[1:5][:, scene.hands[0].kp_metric], atol=1e-9)


def test_best_candidate_lowers_the_first_window_cost(real) -> None:
    """At frame 0 the chosen window is cheaper than the nominal, whose cost (scored from a plain replay of
    the plan) the loop's own candidate 0 reproduces; the applied run is a replay of the applied targets."""
    from quasisim.optim.objective import window_references

    demo, plan, scene = real
    res = run_sampling(demo, scene, plan, OPTS, W, progress=False)
    rep = _replay(scene, plan)
    H, km = OPTS.horizon, scene.hands[0].kp_metric
    ref_pos, ref_quat, ref_kp = (
        x[1 : H + 1] for x in window_references(demo, scene.hands[0].kp_human, np.flatnonzero(km), H)
    )
    pred = Prediction(rep.qpos[None, 1 : H + 1], rep.object_pos[None, 1 : H + 1], rep.object_quat[None, 1 : H + 1],
                      rep.keypoints[None, 1 : H + 1][:, :, km], 0)  # fmt: skip
    nominal = window_costs(plan[None, : H + 1], pred, ref_pos, ref_quat, ref_kp, np.ones(H), W)[0]
    zero = run_sampling(demo, scene, plan, dataclasses.replace(ZERO, samples=1), W, progress=False)
    np.testing.assert_allclose(zero.window_loss[0], nominal, rtol=1e-9)
    assert res.window_loss[0] < nominal - 0.005  # seeds 0-3: 0.015-0.058 lower (nominal 0.099)
    assert res.prediction_error.max() <= 1e-9
    assert np.abs(res.q_targets - plan).max() > 1e-4
    np.testing.assert_array_equal(res.q_targets[0], plan[0])
    again = _replay(scene, res.q_targets)
    np.testing.assert_allclose(again.qpos, res.rollout.qpos, atol=1e-9)
    np.testing.assert_allclose(again.object_pos, res.rollout.object_pos, atol=1e-9)


def test_kinematic_keypoints_are_the_targets_keypoints(real) -> None:
    """The pre-screen's forward kinematics puts the metric keypoints where MuJoCo reports them, along a
    replay of the plan (float32: within 1e-5 m)."""
    from quasisim.method.stages.sampling import kinematic_keypoints

    _demo, plan, scene = real
    rep = _replay(scene, plan)
    kp = kinematic_keypoints(scene)(rep.qpos)
    assert kp.shape == (len(plan), int(np.sum(scene.kp_metric)), 3)
    np.testing.assert_allclose(kp, rep.keypoints[:, scene.kp_metric], atol=1e-5)


def test_screened_keeps_the_nominal_and_the_cheapest() -> None:
    from quasisim.method.stages.sampling import screened

    wins = np.arange(6.0)[:, None, None] * np.ones((6, 3, 2))
    costs = np.array([9.0, 5.0, 1.0, 4.0, 0.5, 7.0])
    np.testing.assert_array_equal(screened(wins, 3, costs)[:, 0, 0], [0.0, 4.0, 2.0])


def test_pre_screen_rolls_out_as_many_windows_and_chooses_among_the_cheapest(real) -> None:
    """screen 2: twice the windows are drawn, the same number rolled out (same physics steps); the windows
    rolled out are the kinematically cheapest of their draw, so their hand-tracking cost is lower than
    without the pre-screen; the run is still a replay of the targets it applied."""
    from quasisim.method.stages.sampling import Transitions, kinematic_costs, kinematic_keypoints
    from quasisim.optim.objective import window_references

    demo, plan, scene = real
    kept = {screen: Transitions() for screen in (1, 2)}
    res = {
        screen: run_sampling(demo, scene, plan, dataclasses.replace(OPTS, screen=screen), W, progress=False,
                             transitions=kept[screen])
        for screen in (1, 2)
    }  # fmt: skip
    assert res[1].n_physics_steps == res[2].n_physics_steps
    assert not np.array_equal(res[1].q_targets, res[2].q_targets)
    again = _replay(scene, res[2].q_targets)
    np.testing.assert_allclose(again.object_pos, res[2].rollout.object_pos, atol=1e-9)
    H, km, kp = OPTS.horizon, np.flatnonzero(scene.kp_metric), kinematic_keypoints(scene)
    ref_pos, ref_quat, ref_kp = window_references(demo, scene.kp_human, km, H)

    def mean_hand_cost(steps: list[dict[str, np.ndarray]]) -> float:
        out = []
        for t, r in enumerate(steps):
            w = slice(t + 1, t + H + 1)
            cost = lambda wins, pred: window_costs(wins, pred, ref_pos[w], ref_quat[w], ref_kp[w], np.ones(H), W)  # noqa: B023, E731
            out.append(kinematic_costs(r["windows"], kp, ref_pos[w], ref_quat[w], cost)[1:].mean())
        return float(np.mean(out))

    assert mean_hand_cost(kept[2].steps) < 0.9 * mean_hand_cost(kept[1].steps)


def test_deterministic_for_a_seed(real) -> None:
    demo, plan, scene = real
    a = run_sampling(demo, scene, plan, OPTS, W, progress=False)
    b = run_sampling(demo, scene, plan, dataclasses.replace(OPTS, threads=1), W, progress=False)
    c = run_sampling(demo, scene, plan, dataclasses.replace(OPTS, seed=1), W, progress=False)
    np.testing.assert_array_equal(a.q_targets, b.q_targets)
    np.testing.assert_array_equal(a.window_loss, b.window_loss)
    np.testing.assert_array_equal(a.rollout.object_pos, b.rollout.object_pos)
    assert not np.array_equal(a.q_targets, c.q_targets)


def test_backing_up_restores_the_target_exactly(real) -> None:
    """The plan's replay loses the cube (the real fixture), so frames leave the strict limits and the loop
    backs up. With zero noise every re-planned frame is the plan again: the run equals the plain replay,
    back-ups and all (the target's saved states restore it exactly). With noise the backed-up run is still
    a replay of the targets it applied, and it rolled out more windows than the run without back-ups."""
    demo, plan, scene = real
    zero = run_sampling(demo, scene, plan, dataclasses.replace(ZERO, backtrack=3), W, progress=False)
    assert zero.backups >= 1
    np.testing.assert_array_equal(zero.q_targets, plan)
    np.testing.assert_allclose(zero.rollout.object_pos, _replay(scene, plan).object_pos, atol=1e-9)

    plain = run_sampling(demo, scene, plan, OPTS, W, progress=False)
    back = run_sampling(
        demo, scene, plan, dataclasses.replace(OPTS, backtrack=3, backtrack_budget=2), W, progress=False
    )
    assert plain.backups == 0 and 1 <= back.backups <= 2
    assert back.n_physics_steps > plain.n_physics_steps
    again = _replay(scene, back.q_targets)
    np.testing.assert_allclose(again.qpos, back.rollout.qpos, atol=1e-9)
    np.testing.assert_allclose(again.object_pos, back.rollout.object_pos, atol=1e-9)
    assert back.prediction_error.max() <= 1e-9
    from quasisim.method.stages.sampling import Transitions

    kept = Transitions()  # recording: every step as it ran, the same window count each, the applied one kept
    rec = run_sampling(
        demo,
        scene,
        plan,
        dataclasses.replace(OPTS, backtrack=3, backtrack_budget=2),
        W,
        progress=False,
        transitions=kept,
    )
    np.testing.assert_array_equal(rec.q_targets, back.q_targets)
    assert len(kept.steps) > demo.n_frames - 1
    assert {r["windows"].shape for r in kept.steps} == {(OPTS.samples, OPTS.horizon + 1, plan.shape[1])}
    # the applied window's first frame is where the next step starts, except where the loop backed up
    pairs = list(zip(kept.steps, kept.steps[1:], strict=False))
    cont = [np.abs(n["start_obj_pos"] - r["obj_pos"][int(r["chosen"]), 0]).max() <= 1e-9 for r, n in pairs]
    assert rec.backups >= 1 and sum(cont) == len(pairs) - rec.backups
    # each step's frame goes back at a back-up
    frames = np.array([int(r["frame"]) for r in kept.steps])
    assert np.sum(np.diff(frames) < 0) == rec.backups and frames[-1] == demo.n_frames - 2


def test_no_back_up_once_a_frame_stayed_outside_the_limits(real) -> None:
    """With zero noise a re-planned frame is the plan again, so the first frame that leaves the limits leaves
    them again after its back-up and stays out (no retries): strict is lost. Without
    ``backtrack_after_lost`` that is the run's only back-up; with it every later frame outside the limits
    backs up as well, up to the budget, for the same applied targets and more physics steps."""
    demo, plan, scene = real
    opts = dataclasses.replace(ZERO, backtrack=3, backtrack_budget=4, backtrack_retries=0)
    stop = run_sampling(demo, scene, plan, dataclasses.replace(opts, backtrack_after_lost=False), W, progress=False)
    more = run_sampling(demo, scene, plan, opts, W, progress=False)
    assert stop.backups == 1 and more.backups == 4
    assert stop.backup_frames.shape == (1, 2) and more.backup_frames.shape == (4, 2)
    # each back-up goes 3 frames back from the frame that left the limits (at least to frame 1), in order
    left, to = more.backup_frames.T
    np.testing.assert_array_equal(to, np.maximum(1, left - 3))
    assert stop.backup_frames[0, 0] == left[0] and np.all(np.diff(left) > 0)
    np.testing.assert_array_equal(stop.q_targets, plan)
    np.testing.assert_array_equal(more.q_targets, plan)
    assert stop.n_physics_steps < more.n_physics_steps


def test_a_tighter_back_up_limit_backs_up_inside_the_limits_and_loses_only_outside(data_dir: Path) -> None:
    """``backtrack_limit`` L < 1: a frame backs up as soon as the object passes L x the strict limits. With
    zero noise every re-planned frame is the plan again, so from the plain replay's per-frame fraction f of
    the limits: every frame t >= 2 with f > L backs up once (no retries) in order, from the first with f > L
    to the first with f > 1, which stays outside and is lost (no back-up after it without
    ``backtrack_after_lost``); frames between L and 1 that come back the same are not lost. L = 1 is the old
    rule: the first back-up leaves from the first frame outside the limits."""
    from quasisim.data.demo import load_demo
    from quasisim.method.stages.sampling import strict_fractions

    # 12 frames before the lift-off, where the plan's replay creeps towards the limits, then leaves them
    demo, plan, scene = _inputs(load_demo(data_dir / "grab_s1_cubesmall_lift.npz").slice(20, 32))
    rep = _replay(scene, plan)
    trans, rot = strict_fractions(rep.object_pos, rep.object_quat, demo.object_pos, demo.object_quat)
    f = np.maximum(trans, rot)
    limit, frame = 0.5, np.arange(len(f))
    first_out = int(np.flatnonzero((f > 1.0) & (frame >= 2))[0])
    near = np.flatnonzero((f > limit) & (frame >= 2) & (frame <= first_out))
    assert near[0] < first_out  # the fixture has frames between the margin and the limits
    opts = dataclasses.replace(
        ZERO, backtrack=3, backtrack_budget=20, backtrack_retries=0, backtrack_after_lost=False, backtrack_limit=limit
    )
    margin = run_sampling(demo, scene, plan, opts, W, progress=False)
    np.testing.assert_array_equal(margin.backup_frames[:, 0], near)
    np.testing.assert_array_equal(margin.q_targets, plan)
    old = run_sampling(demo, scene, plan, dataclasses.replace(opts, backtrack_limit=1.0), W, progress=False)
    np.testing.assert_array_equal(old.backup_frames[:, 0], [first_out])
    assert margin.n_physics_steps > old.n_physics_steps


def test_robust_copies(real, monkeypatch: pytest.MonkeyPatch) -> None:
    """Copies that are the target itself (no perturbation) score every candidate as the target does: the run
    is the run without copies, back-ups included (the copies are put back with the target). Copies whose
    object starts 5 cm away (off the strict limits from the start) never score a candidate. Perturbed copies
    change the choice; the run is still a replay of its own targets in the unperturbed target, and the copies
    rolled out the top candidates and followed every applied frame."""
    import quasisim.method.stages.sampling as st

    demo, plan, scene = real
    opts = dataclasses.replace(OPTS, backtrack=3, backtrack_budget=2)
    plain = run_sampling(demo, scene, plan, opts, W, progress=False)
    with monkeypatch.context() as m:
        m.setattr(st, "copy_scenes", lambda sc, o: [sc] * o.robust_copies)
        same = run_sampling(demo, scene, plan, dataclasses.replace(opts, robust_copies=2), W, progress=False)
        both = dataclasses.replace(opts, robust_copies=2, backtrack_copies=True)  # copies leave when the target does
        same_back = run_sampling(demo, scene, plan, both, W, progress=False)
    np.testing.assert_array_equal(same.q_targets, plain.q_targets)
    np.testing.assert_array_equal(same_back.q_targets, plain.q_targets)
    assert same.backups == same_back.backups == plain.backups >= 1
    off = dataclasses.replace(scene, object_pos0=scene.object_pos0 + np.array([0.05, 0.0, 0.0]))
    with monkeypatch.context() as m:
        m.setattr(st, "copy_scenes", lambda sc, o: [off] * o.robust_copies)
        lost = run_sampling(demo, scene, plan, dataclasses.replace(OPTS, robust_copies=2), W, progress=False)
    np.testing.assert_array_equal(lost.q_targets, run_sampling(demo, scene, plan, OPTS, W, progress=False).q_targets)

    flat = dataclasses.replace(OPTS, robust_copies=2, robust_top=4)
    base = run_sampling(demo, scene, plan, OPTS, W, progress=False)
    rob = run_sampling(demo, scene, plan, flat, W, progress=False)
    assert not np.array_equal(rob.q_targets, base.q_targets)
    again = _replay(scene, rob.q_targets)
    np.testing.assert_allclose(again.object_pos, rob.rollout.object_pos, atol=1e-9)
    per_window = OPTS.horizon * 25 + 1  # physics steps of one window in MuJoCo (test_zero_noise_...)
    extra = (rob.n_physics_steps - base.n_physics_steps) / ((demo.n_frames - 1) * 2)  # per copy and step
    assert 25 < extra <= 4 * per_window + 25  # every applied frame; the windows while the copy is on track


def test_alternative_plan_is_taken_when_it_is_better(synth) -> None:
    """A plan 12 cm above the cube never grasps it; with the kinematic retarget as an alternative, zero-noise
    sampling switches to it at the first frame and then follows it exactly (its windows cost less). With
    noise, sampling around the alternative too lifts the cube as the demo does, which sampling around the
    high plan alone never does: the alternative changes the result and lowers the whole-clip objective."""
    from quasisim.optim.objective import clip_cost

    demo, plan, scene = synth
    high = plan.copy()
    high[1:, 2] += 0.12
    alone = run_sampling(demo, scene, high, ZERO, W, progress=False)
    both = run_sampling(demo, scene, high, ZERO, W, progress=False, alternatives=(plan,))
    np.testing.assert_array_equal(alone.q_targets, high)  # zero noise, no alternative: a replay of the plan
    np.testing.assert_array_equal(both.q_targets, plan)
    assert both.window_loss.sum() < alone.window_loss.sum()
    # judged over the whole clip in MuJoCo: measured 0.157 alone, 0.040 with the alternative
    assert clip_cost(demo, both.rollout, W) < 0.5 * clip_cost(demo, alone.rollout, W)

    noisy_alone = run_sampling(demo, scene, high, OPTS, W, progress=False)
    noisy_both = run_sampling(demo, scene, high, OPTS, W, progress=False, alternatives=(plan,))
    assert np.abs(noisy_both.q_targets - noisy_alone.q_targets).max() > 0.05  # measured: the base 12 cm lower
    # whole-clip objective measured 0.139 alone, 0.026 with the alternative
    assert clip_cost(demo, noisy_both.rollout, W) < 0.5 * clip_cost(demo, noisy_alone.rollout, W)
    # the object as in the demo (lifted 12 cm over the clip): largest position error measured 1.1 cm with
    # the alternative; 12.0 cm alone (the cube never leaves the table)
    err = lambda r: np.abs(r.object_pos - demo.object_pos).max()  # noqa: E731
    assert demo.object_pos[-1, 2] - demo.object_pos[0, 2] > 0.1
    assert err(noisy_both.rollout) < 0.03 < 0.1 < err(noisy_alone.rollout)


def test_mppi_applies_the_weighted_mean(synth) -> None:
    demo, plan, scene = synth
    opts = dataclasses.replace(OPTS, mode="mppi")
    res = run_sampling(demo, scene, plan, opts, W, progress=False)
    assert res.q_targets.shape == plan.shape and np.isnan(res.prediction_error).all()
    assert np.isfinite(res.window_loss).all() and np.abs(res.q_targets - plan).max() > 1e-5
    np.testing.assert_allclose(_replay(scene, res.q_targets).qpos, res.rollout.qpos, atol=1e-9)
    cold = run_sampling(demo, scene, plan, dataclasses.replace(opts, temperature=1e-9), W, progress=False)
    best = run_sampling(demo, scene, plan, OPTS, W, progress=False)
    np.testing.assert_allclose(cold.q_targets, best.q_targets, atol=1e-12)  # T -> 0: the best candidate


# ---- PyBullet ------------------------------------------------------------------------------------------


def test_pybullet_variant_runs(synth) -> None:
    pytest.importorskip("pybullet")
    from quasisim.targets.pybullet_target import PybulletTarget

    demo, plan, scene = synth
    demo, plan = demo.slice(0, 4), plan[:4]
    opts = dataclasses.replace(OPTS, samples=3, horizon=2)
    res = run_sampling(demo, scene, plan, opts, W, target="pybullet", progress=False)
    J = scene.hands[0].n_joints
    r = res.rollout
    assert res.q_targets.shape == (4, 6 + J) and res.window_loss.shape == (3,)
    assert r.target == "pybullet" and r.qpos.shape == (4, 6 + J) and r.object_quat.shape == (4, 4)
    assert r.keypoints.shape == (4, len(scene.hands[0].kp_names), 3)
    assert res.n_physics_steps == 3 * (3 * 2 * 100 + 100)
    assert res.prediction_error.max() < 1e-9  # restoreState gives the exact state back
    with PybulletTarget(scene) as tgt:
        again = tgt.rollout(res.q_targets)
    np.testing.assert_allclose(again.qpos, r.qpos, atol=1e-9)
    np.testing.assert_allclose(again.object_pos, r.object_pos, atol=1e-9)
    # a perturbed copy (its own PyBullet client) scores the best candidates beside the target and backs up with it
    opts = dataclasses.replace(opts, robust_copies=1, robust_top=2, backtrack=1)
    rob = run_sampling(demo, scene, plan, opts, W, target="pybullet", progress=False)
    assert rob.n_physics_steps > res.n_physics_steps
    with PybulletTarget(scene) as tgt:
        np.testing.assert_allclose(tgt.rollout(rob.q_targets).object_pos, rob.rollout.object_pos, atol=1e-9)


def test_pybullet_backs_up_exactly(real) -> None:
    """Back-ups in PyBullet (saveState / restoreState, states released as the loop moves on): a demo whose
    object jumps 3 cm from frame 4 on puts every frame after it over the strict limit; with zero noise the
    backed-up run is still the plain replay of the plan."""
    pytest.importorskip("pybullet")
    from quasisim.targets.pybullet_target import PybulletTarget

    demo, plan, scene = real
    moved = demo.object_pos.copy()
    moved[4:, 0] += 0.03
    demo = dataclasses.replace(demo, object_pos=moved)
    opts = dataclasses.replace(ZERO, samples=2, horizon=2, backtrack=3, backtrack_samples=2)
    res = run_sampling(demo, scene, plan, opts, W, target="pybullet", progress=False)
    assert res.backups >= 1
    np.testing.assert_array_equal(res.q_targets, plan)
    with PybulletTarget(scene) as tgt:
        again = tgt.rollout(plan)
    np.testing.assert_allclose(again.object_pos, res.rollout.object_pos, atol=1e-9)
    np.testing.assert_allclose(again.qpos, res.rollout.qpos, atol=1e-9)


def test_replanning_within_a_margin_plans_afresh_where_the_object_nears_the_limits(real) -> None:
    """``replan_margin``: a frame after the first of a window is applied unplanned only where the chosen
    candidate predicted the object within that fraction of the strict limits; a margin nothing meets is
    planning every frame (bit for bit), one everything meets is plain ``replan``."""
    from quasisim.eval.metrics import STRICT_CM, STRICT_DEG, object_errors
    from quasisim.method.stages.sampling import Transitions

    demo, plan, scene = real
    T = demo.n_frames
    every = run_sampling(demo, scene, plan, OPTS, W, progress=False)
    three = run_sampling(demo, scene, plan, dataclasses.replace(OPTS, replan=3), W, progress=False)
    never = run_sampling(demo, scene, plan, dataclasses.replace(OPTS, replan=3, replan_margin=1e-9), W, progress=False)
    np.testing.assert_array_equal(never.q_targets, every.q_targets)
    always = run_sampling(demo, scene, plan, dataclasses.replace(OPTS, replan=3, replan_margin=1e9), W, progress=False)
    np.testing.assert_array_equal(always.q_targets, three.q_targets)
    kept, margin = Transitions(), 0.7
    opts = dataclasses.replace(OPTS, replan=3, replan_margin=margin)
    run_sampling(demo, scene, plan, opts, W, progress=False, transitions=kept)
    planned = [int(r["frame"]) for r in kept.steps] + [T - 1]
    assert 1 < len(planned) - 1 < T - 1  # some frames applied unplanned, some planned afresh
    for r, nxt in zip(kept.steps, planned[1:], strict=True):
        t, best = int(r["frame"]), int(r["chosen"])
        n = min(3, T - 1 - t)  # predicted frames t+1 .. t+n inside the clip
        ref_pos, ref_quat = demo.object_pos[t + 1 : t + 1 + n], demo.object_quat[t + 1 : t + 1 + n]
        rot, trans = object_errors(ref_pos, ref_quat, r["obj_pos"][best, :n], r["obj_quat"][best, :n])
        calm = np.maximum(trans / STRICT_CM, rot / STRICT_DEG) < margin
        applied = nxt - t  # frames this plan applied: the first, then while calm (up to 3)
        assert calm[1:applied].all()
        assert applied == n or not calm[applied]


def test_retried_back_ups_reach_further_and_still_replay_exactly(real) -> None:
    """With zero noise every re-planned frame is the plan again, so a frame that left the limits leaves them
    again: with ``backtrack_retries`` 1 the loop backs up a second time from it, further back (more back-ups
    and more physics steps than without), and the run is still the plan's exact replay."""
    demo, plan, scene = real
    opts = dataclasses.replace(ZERO, backtrack=3, backtrack_budget=100)  # a budget never spent
    once = run_sampling(demo, scene, plan, opts, W, progress=False)
    twice = run_sampling(demo, scene, plan, dataclasses.replace(opts, backtrack_retries=1), W, progress=False)
    assert 1 <= once.backups < twice.backups <= 2 * once.backups
    assert twice.n_physics_steps > once.n_physics_steps
    np.testing.assert_array_equal(twice.q_targets, plan)
    np.testing.assert_allclose(twice.rollout.object_pos, _replay(scene, plan).object_pos, atol=1e-9)


def test_re_planned_frames_can_weigh_the_strict_limits(real) -> None:
    """``backtrack_strict_weight``: the hinge on the strict limits at that weight only on frames re-planned
    after a back-up. Weight 0 is the default (strict_weight 0) exactly; a heavy weight applies the same
    frames up to the first back-up's frame, chooses other windows after it, and is still a replay of what it
    applied."""
    from quasisim.method.stages.sampling import Transitions

    demo, plan, scene = real
    opts = dataclasses.replace(OPTS, backtrack=3, backtrack_budget=2)
    kept = Transitions()
    base = run_sampling(demo, scene, plan, opts, W, progress=False, transitions=kept)
    zero = run_sampling(demo, scene, plan, dataclasses.replace(opts, backtrack_strict_weight=0.0), W, progress=False)
    np.testing.assert_array_equal(zero.q_targets, base.q_targets)
    heavy = run_sampling(demo, scene, plan, dataclasses.replace(opts, backtrack_strict_weight=10.0), W, progress=False)
    frames = np.array([int(r["frame"]) for r in kept.steps])
    first_back = int(frames[1:][np.diff(frames) < 0][0])  # the frame the first back-up returned to
    np.testing.assert_array_equal(heavy.q_targets[: first_back + 1], base.q_targets[: first_back + 1])
    assert not np.array_equal(heavy.q_targets, base.q_targets)
    np.testing.assert_allclose(_replay(scene, heavy.q_targets).object_pos, heavy.rollout.object_pos, atol=1e-9)


def test_steps_that_start_with_the_object_astray_sample_more(real) -> None:
    """``widen_margin``: a step that starts with the object beyond that fraction of the strict limits rolls
    out ``backtrack_samples`` x the windows, the others the usual count (counted exactly in physics steps,
    the strays found from the recorded start states); a margin nothing crosses changes nothing."""
    from quasisim.eval.metrics import STRICT_CM, STRICT_DEG, object_errors
    from quasisim.method.stages.sampling import Transitions

    demo, plan, scene = real
    T, applied = demo.n_frames, (demo.n_frames - 1) * 25  # the applied frames' own physics steps
    every = run_sampling(demo, scene, plan, OPTS, W, progress=False)
    never = run_sampling(demo, scene, plan, dataclasses.replace(OPTS, widen_margin=1e9), W, progress=False)
    np.testing.assert_array_equal(never.q_targets, every.q_targets)
    per_step = (every.n_physics_steps - applied) // (T - 1)  # one step's rollouts
    kept, opts = Transitions(), dataclasses.replace(OPTS, widen_margin=0.65)
    wide = run_sampling(demo, scene, plan, opts, W, progress=False, transitions=kept)
    t = np.array([int(r["frame"]) for r in kept.steps])
    rot, trans = object_errors(
        demo.object_pos[t], demo.object_quat[t], *(np.stack([r[f"start_obj_{k}"] for r in kept.steps]) for k in ("pos", "quat"))
    )  # fmt: skip
    strays = int(np.sum((np.maximum(trans / STRICT_CM, rot / STRICT_DEG) > 0.65) & (t > 0)))
    assert 0 < strays < T - 2
    assert wide.n_physics_steps - applied == per_step * (T - 1 + (OPTS.backtrack_samples - 1) * strays)


def test_replanning_every_few_frames_applies_what_was_predicted(real) -> None:
    """``replan`` 3: each chosen window's first three frames are applied before planning again, so a third
    of the steps roll out windows; the applied frames are what the chosen candidate predicted (the target is
    deterministic) and the run is a replay of its targets. With zero noise it is the plan's replay."""
    from quasisim.method.stages.sampling import Transitions

    demo, plan, scene = real
    T = demo.n_frames
    zero = run_sampling(demo, scene, plan, dataclasses.replace(ZERO, replan=3), W, progress=False)
    np.testing.assert_array_equal(zero.q_targets, plan)
    np.testing.assert_allclose(zero.rollout.object_pos, _replay(scene, plan).object_pos, atol=1e-9)
    every = run_sampling(demo, scene, plan, OPTS, W, progress=False)
    kept = Transitions()
    three = run_sampling(demo, scene, plan, dataclasses.replace(OPTS, replan=3), W, progress=False, transitions=kept)
    assert [int(r["frame"]) for r in kept.steps] == list(range(0, T - 1, 3))
    rollouts = lambda r: r.n_physics_steps - (T - 1) * 25  # noqa: E731  (the applied frames' own steps)
    assert rollouts(three) * 3 == pytest.approx(rollouts(every), rel=0.1)
    assert three.prediction_error.max() <= 1e-9 and three.backups == 0
    np.testing.assert_allclose(_replay(scene, three.q_targets).object_pos, three.rollout.object_pos, atol=1e-9)
    assert not np.array_equal(three.q_targets, every.q_targets)


def test_cost_bounds_never_exceed_the_cost_and_reach_it_with_every_frame() -> None:
    """cost_bounds from the first F frames: at most the window cost (the later frames' errors set to 0, every
    term a mean of non-negative per-frame errors), rising with F, the cost itself at F = H; the pruner keeps
    the ceil(prune_keep N) lowest bounds and is off at 0 frames or at the horizon."""
    rng = np.random.default_rng(0)
    N, H, K = 6, 4, 5
    ref_pos, ref_kp = rng.normal(size=(H, 3)), rng.normal(size=(H, K, 3))
    ref_quat = np.tile([1.0, 0.0, 0.0, 0.0], (H, 1))
    quat = rng.normal(size=(N, H, 4))
    pred = Prediction(
        qpos=np.zeros((N, H, 8)), obj_pos=ref_pos + rng.normal(0, 0.05, (N, H, 3)),
        obj_quat=quat / np.linalg.norm(quat, axis=-1, keepdims=True), keypoints=ref_kp + rng.normal(0, 0.05, (N, H, K, 3)),
        n_steps=0,
    )  # fmt: skip
    wins = rng.normal(0, 0.1, (N, H + 1, 8))

    def cost(w: np.ndarray, p: Prediction) -> np.ndarray:
        return window_costs(w, p, ref_pos, ref_quat, ref_kp, np.ones(H), W, strict=(0.5, 0.75))

    def head(f: int) -> Prediction:
        return dataclasses.replace(
            pred, obj_pos=pred.obj_pos[:, :f], obj_quat=pred.obj_quat[:, :f], keypoints=pred.keypoints[:, :f]
        )

    full = cost(wins, pred)
    bounds = np.stack([cost_bounds(head(f), wins, ref_pos, ref_quat, ref_kp, cost) for f in range(1, H + 1)])
    assert (np.diff(bounds, axis=0) >= -1e-7).all() and (bounds[:-1] <= full + 1e-7).all()
    np.testing.assert_allclose(bounds[-1], full, rtol=1e-6)
    assert (bounds[0] < full - 1e-4).all()  # a real bound, not the cost
    opts = dataclasses.replace(OPTS, samples=2, prune_frames=2, prune_keep=0.4)
    p = pruner(opts, wins, lambda h, w: cost_bounds(h, w, ref_pos, ref_quat, ref_kp, cost))
    assert p is not None and p.frames == 2
    np.testing.assert_array_equal(np.sort(p.keep(head(2))), np.sort(np.argsort(bounds[1])[:3]))
    p = pruner(dataclasses.replace(opts, samples=5), wins, lambda h, w: full)
    assert p is not None and len(p.keep(head(2))) == 5  # at least one plan's samples go on
    assert pruner(dataclasses.replace(opts, samples=6), wins, lambda h, w: full) is None  # all of them: no pruning
    assert pruner(OPTS, wins, lambda h, w: full) is None  # prune_frames 0: off
    assert pruner(dataclasses.replace(opts, prune_frames=H), wins, lambda h, w: full) is None


def test_pruned_sampling_rolls_out_fewer_frames_and_still_replays_exactly(real) -> None:
    """With pruning (windows around the plan and around an alternative, so a step holds twice the samples)
    the loop simulates fewer physics steps, chooses only candidates that ran their whole window, and its
    recorded run is still the exact replay of the targets it applied; recording transitions rolls every window
    out in full (the run equals the unpruned one)."""
    from quasisim.method.stages.sampling import Transitions

    demo, plan, scene = real
    opts = dataclasses.replace(OPTS, backtrack=0)  # the same steps with and without pruning
    alt = (plan + 0.01,)
    plain = run_sampling(demo, scene, plan, opts, W, progress=False, alternatives=alt)
    pruned_opts = dataclasses.replace(opts, prune_frames=1, prune_keep=0.5)
    pruned = run_sampling(demo, scene, plan, pruned_opts, W, progress=False, alternatives=alt)
    assert pruned.n_physics_steps < 0.8 * plain.n_physics_steps  # a window: 1 + 3 / 2 of 4 frames
    assert np.isfinite(pruned.window_loss).all()
    np.testing.assert_allclose(pruned.rollout.object_pos, _replay(scene, pruned.q_targets).object_pos, atol=1e-9)
    recorded = run_sampling(
        demo, scene, plan, pruned_opts, W, progress=False, alternatives=alt, transitions=Transitions()
    )
    np.testing.assert_array_equal(recorded.q_targets, plain.q_targets)


def test_grip_bias_presses_held_back_finger_joints_only() -> None:
    """The bias is ``grip * sign(q - qpos)`` on finger columns more than ``grip_gap`` from their targets, 0 on
    the base and on joints that follow their targets; no grip, no bias."""
    from quasisim.method.stages.sampling import biased, grip_bias

    fingers = np.array([False] * 6 + [True] * 4)
    q = np.zeros(10)
    qpos = np.array([0.5] * 6 + [-0.1, 0.1, 0.01, 0.0])
    b = grip_bias(q, qpos, fingers, 0.05, 0.02)
    np.testing.assert_array_equal(b, [0.0] * 6 + [0.05, -0.05, 0.0, 0.0])
    assert grip_bias(q, qpos, fingers, 0.0, 0.02) is None
    wins = np.ones((3, 4, 10))
    run = biased(wins, b, np.full(10, 7.0))
    np.testing.assert_array_equal(run[:, 0], 7.0)
    np.testing.assert_array_equal(run[:, 1:], wins[:, 1:] + b)


def test_grip_presses_and_still_replays_exactly(real) -> None:
    """With a grip the applied targets are the chosen windows plus each step's bias, so they differ from the
    run without it on the frames where the cube holds fingers back; the run is still a replay of the applied
    targets (the windows were rolled out as the target is driven)."""
    demo, plan, scene = real
    base = run_sampling(demo, scene, plan, OPTS, W, progress=False)
    grip = run_sampling(demo, scene, plan, dataclasses.replace(OPTS, grip=0.05), W, progress=False)
    assert grip.prediction_error.max() <= 1e-9
    np.testing.assert_allclose(_replay(scene, grip.q_targets).object_pos, grip.rollout.object_pos, atol=1e-9)
    d = np.abs(grip.q_targets - base.q_targets)
    assert d[:, 6:].max() >= 0.05 - 1e-9  # a finger target pressed by the grip
    np.testing.assert_array_equal(grip.q_targets[0], plan[0])
