"""Closed-loop MPC: the observed quasi-physical state of a target's observation, the loop itself (the targets'
observations themselves: test_targets.py)."""

from __future__ import annotations

from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from quasisim.method.problem import make_problem


@pytest.fixture(scope="module")
def short(tmp_path_factory: pytest.TempPathFactory):
    from quasisim.assets.hand import load_hand
    from quasisim.data.demo import load_demo
    from quasisim.data.synthetic import write_example
    from quasisim.method.retarget import kinematic_controls
    from quasisim.targets.build import load_object_for, scene_for
    from quasisim.targets.scene import place_hands

    p: Path = write_example("cube_lift", tmp_path_factory.mktemp("mpc"), n_frames=12)
    demo = load_demo(p)
    hand = load_hand("shadow")
    c = kinematic_controls(hand, demo, "shadow")
    obj = load_object_for(demo)
    return demo, hand, obj, c, scene_for(demo, place_hands((hand,), c.base_rots), obj)


def test_observed_state_matches_the_observation(short) -> None:
    from quasisim.optim.trajectory import observed_state
    from quasisim.rotations import np_mat_to_quat
    from quasisim.sim.kinematics import fk_full, keypoints
    from quasisim.sim.step import object_pose
    from quasisim.targets import make_target

    demo, hand, obj, c, scene = short
    model = make_problem(demo, scene.placements, 20, 128, obj).model
    tgt = make_target("mujoco", scene)
    tgt.reset(c.q_targets[0])
    for t in range(3):
        tgt.advance(c.q_targets[t], c.q_targets[t + 1])
    obs = tgt.observe()
    s = observed_state(model, obs, jnp.asarray(np_mat_to_quat(scene.base_rots[0]), jnp.float32))
    pos, _quat = object_pose(model, s)
    np.testing.assert_allclose(np.asarray(pos), obs["obj_pos"], atol=1e-5)
    import jax

    from quasisim.optim.objective import hand_keypoints

    kp = np.asarray(hand_keypoints(model, jax.tree_util.tree_map(lambda x: x[None], s)))[0]
    kp_ref = np.asarray(keypoints(hand, fk_full(hand, jnp.asarray(scene.base_rots[0]), jnp.asarray(obs["qpos"]))))
    np.testing.assert_allclose(kp, kp_ref, atol=2e-5)
    np.testing.assert_allclose(kp, obs["keypoints"], atol=2e-5)  # and MuJoCo's own sites


@pytest.mark.slow
def test_mpc_loop_applies_what_it_plans_and_lowers_its_window_loss(short) -> None:
    """The closed loop changes the plan, the applied targets replayed open-loop give the same run
    (MuJoCo is deterministic), the first frame is left alone, and the Adam steps lower the window loss
    they optimise (a wrong gradient would leave the plan's own loss the best)."""
    from quasisim.method.config import TransferConfig
    from quasisim.method.curriculum import load_curriculum
    from quasisim.method.options import MPCOptions
    from quasisim.method.stages.mpc import run_mpc
    from quasisim.targets import make_target

    demo, _hand, obj, c, scene = short
    prob = make_problem(demo, scene.placements, 5, 32, obj)
    cur = load_curriculum("default")
    opts = MPCOptions(horizon=2, steps=3, lr=1e-3, soften=0, soften_range=0.1, seed=0)
    weights = TransferConfig.from_yaml().weights
    res = run_mpc(demo, scene, prob.model, prob.params(cur.contact(cur.stiffest)), c.q_targets, opts, weights, False)
    assert res.q_targets.shape == c.q_targets.shape and len(res.window_loss) == demo.n_frames - 1
    np.testing.assert_array_equal(res.q_targets[0], c.q_targets[0])
    assert np.abs(res.q_targets - c.q_targets).max() > 1e-4
    again = make_target("mujoco", scene).rollout(res.q_targets)
    np.testing.assert_allclose(again.object_pos, res.rollout.object_pos, atol=1e-12)
    np.testing.assert_allclose(again.qpos, res.rollout.qpos, atol=1e-12)
    lowered = res.window_loss < res.window_loss_start
    assert lowered.mean() >= 0.8, (res.window_loss, res.window_loss_start)
    assert res.window_loss.mean() < 0.99 * res.window_loss_start.mean()
