"""Stage 3: the replay buffer, prediction windows and fitting the simulator to MuJoCo."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import numpy as np
import pytest


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory):
    from quasisim.assets.hand import load_hand
    from quasisim.data.demo import load_demo
    from quasisim.data.synthetic import write_example
    from quasisim.method.config import TransferConfig
    from quasisim.method.curriculum import load_curriculum
    from quasisim.method.problem import make_problem
    from quasisim.method.replay import collect
    from quasisim.method.retarget import retarget
    from quasisim.method.stages.fit_to_target import noisy_variants
    from quasisim.targets.scene import Placement

    p: Path = write_example("cube_lift", tmp_path_factory.mktemp("s3"), n_frames=24)
    demo, hand = load_demo(p), load_hand("shadow")
    rt = retarget(hand, demo)
    prob = make_problem(demo, (Placement(hand, rt.base_rot),), 5, 32)
    cfg = TransferConfig.from_yaml()
    cur = load_curriculum("default")
    variants = noisy_variants(rt.q, 1, cfg.sampling, 0, prob.scene)
    buf = collect(prob.scene, [rt.q, *variants], demo.fps)
    return prob, cfg, prob.params(cur.contact(cur.stiffest)), buf, rt.q, variants


def test_noisy_variants_are_smooth_perturbations_within_limits(setup) -> None:
    prob, _cfg, _p, buf, q, variants = setup
    v = variants[0]
    assert v.shape == q.shape and np.array_equal(v[0], q[0])  # the start is not perturbed
    assert 1e-3 < np.abs(v - q).max() < 0.5
    hand = prob.placements[0].hand
    lo, hi = hand.joint_range.T
    limited = hand.joint_limited
    assert np.all((v[:, 6:] >= np.minimum(lo, q[:, 6:]) - 1e-12)[:, limited])
    assert np.all((v[:, 6:] <= np.maximum(hi, q[:, 6:]) + 1e-12)[:, limited])
    assert buf.n_rollouts == 2 and np.array_equal(buf.q_targets[1], v)


@pytest.mark.slow
def test_fit_lowers_the_prediction_loss_and_residuals_start_at_zero(setup) -> None:
    from quasisim.method.replay import predict, split_starts, windows
    from quasisim.method.stages.fit_to_target import SimFit, fit, window_loss
    from quasisim.sim.build import attach_residual
    from quasisim.sim.residual import ResidualConfig, ResidualNets

    prob, cfg, p0, buf, _q, _v = setup
    demo, m, bq, obj = prob.demo, prob.model, prob.base_quat, prob.obj
    opts = dataclasses.replace(cfg.stage3, horizon=3, steps=10, batch=4)
    train_s, _ = split_starts(buf.n_rollouts, demo.n_frames, opts.horizon, opts.held_out)
    train = windows(m, buf, train_s, opts.horizon, bq)
    w = cfg.weights.arrays()
    loss = jax.jit(lambda p: window_loss(m, p, train, demo.fps, bq, w))
    nominal = float(loss(SimFit.nominal().apply(p0, obj.mass, obj.inertia)))
    f, losses = fit(m, p0, train, demo.fps, bq, obj.mass, obj.inertia, opts, w)
    fitted = float(loss(f.apply(p0, obj.mass, obj.inertia)))
    # measured on all training windows (the fit saw minibatches): lower than the nominal simulator
    assert len(losses) == opts.steps and fitted < nominal, (nominal, fitted, f.describe(obj.mass))

    # the residual networks start at zero: attached, they predict what the analytical model does, to the
    # rounding of another compiled program (up to 1.3e-6 measured under the tests' XLA flags; a residual force
    # of 0.1 N would move the object by millimetres over these 3-frame windows)
    m2, p2 = attach_residual(m, p0, ResidualNets(ResidualConfig(), seed=0))
    a = predict(m, p0, train, demo.fps, bq)
    b = predict(m2, p2, train, demo.fps, bq)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), atol=1e-5)


@pytest.mark.slow
def test_world_model_rounds_keep_the_best_controls_judged_in_the_target(setup) -> None:
    """Each round's controls are judged by ``cost``; the best seen is returned (the start when no round beats
    it), the fitted simulator's error on each round's new rollout is measured and the rollouts are kept."""
    from quasisim.method.stages.fit_to_target import SimFit, world_model_rounds
    from quasisim.optim.trajectory import Trajectory

    prob, cfg, p0, buf, q, _v = setup
    opts = dataclasses.replace(cfg.stage3, horizon=3, steps=3, batch=4, variants=1, rounds=2)
    start, f0 = Trajectory.from_q(q, prob.model.n_points), SimFit.nominal()
    shift = np.zeros(q.shape[1])
    shift[2] = 0.01  # each round lifts the base PD targets by 1 cm

    def improve(traj: Trajectory, f: SimFit, p) -> Trajectory:
        assert isinstance(f, SimFit) and p.residual is None
        return Trajectory.from_q(traj.q_targets + shift, prob.model.n_points)

    def run(cost):
        w = cfg.weights.arrays()
        return world_model_rounds(prob, prob.model, p0, start, f0, buf, opts, cfg.sampling, w, improve, cost)[0]

    higher = run(lambda x: -float(x[:, 2].mean()))  # the target "prefers" the raised hand: the last round wins
    assert int(higher["best_round"]) == 2 and np.allclose(higher["q_targets"], q + 2 * shift)
    assert higher["round_costs"].shape == (3,) and np.all(np.diff(higher["round_costs"]) < 0)
    assert higher["round_errors"].shape == (2, 3) and np.all(np.isfinite(higher["round_errors"]))
    assert int(higher["buffer_rollouts"]) == buf.n_rollouts + 2 * (1 + opts.variants)  # each round's rollouts added
    lower = run(lambda x: float(x[:, 2].mean()))  # every round is worse: the start is kept
    assert int(lower["best_round"]) == 0 and np.array_equal(lower["q_targets"], q)


def test_ablation_flags_and_the_run_identity() -> None:
    """The flags remove networks; stage 3's networks count in a run's identity only when it has stage 3."""
    from quasisim.errors import QuasisimError
    from quasisim.method.spec import TransferSpec, networks_from_flags

    assert networks_from_flags(False, False, False) == ("local", "global", "control")
    assert networks_from_flags(True, False, False) == ("control",)
    assert networks_from_flags(False, True, True) == ("global",)
    full = TransferSpec(stages=("1", "2", "3", "sample"), render=False).checked()
    assert full.identity()["networks"] == ("local", "global", "control")
    assert "networks" not in TransferSpec(render=False).checked().identity()  # default stages: no stage 3
    with pytest.raises(QuasisimError, match="valid"):
        TransferSpec(networks=("locl",)).checked()
