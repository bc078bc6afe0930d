"""MuJoCo target, what only MuJoCo has: its PD actuators, its warnings, ``mujoco.rollout`` of candidate windows
(the behaviour both targets share is tested once for both in test_targets.py)."""

from __future__ import annotations

import numpy as np
import pytest

from helpers import scene_with, smooth_targets
from quasisim.targets import Target, make_target, pd_gains, pd_schedule


def test_actuators_and_joints_carry_the_pd_gains(shadow) -> None:
    """One PD actuator (kp, bias -kp q - kv qd, force range on the joints) and one feed-forward actuator (kv)
    per dof, joint damping: all from pd_gains."""
    tgt = make_target("mujoco", scene_with(shadow))
    m, mm, g = tgt.mm.model, tgt.mm, pd_gains(shadow)
    np.testing.assert_array_equal(m.actuator_gainprm[mm.pd_act, 0], g.kp)
    np.testing.assert_array_equal(m.actuator_biasprm[mm.pd_act, 1:3], np.stack([-g.kp, -g.kv], 1))
    np.testing.assert_array_equal(m.actuator_gainprm[mm.ff_act, 0], g.kv)
    limited = m.actuator_forcelimited[mm.pd_act].astype(bool)
    np.testing.assert_array_equal(limited, np.isfinite(g.force_limit))
    np.testing.assert_array_equal(m.actuator_forcerange[mm.pd_act][limited, 1], g.force_limit[limited])
    assert not m.actuator_forcelimited[mm.ff_act].any()
    np.testing.assert_array_equal(m.dof_damping[mm.hand_dof], g.damping)


def test_advance_applies_the_schedule(shadow) -> None:
    """The controls MuJoCo holds after a frame are the schedule's last step and its velocity."""
    sc = scene_with(shadow, object_pos=(2.0, 0.0, 0.825))
    q = smooth_targets(shadow, 3, np.array([0.0, 0.0, 1.2]), np.array([0.05, 0.0, 0.0]), 0.4)
    tgt = make_target("mujoco", sc)
    with pytest.raises(RuntimeError, match="call reset first"):
        tgt.observe()
    tgt.reset(q[0])
    tgt.advance(q[1], q[2])
    pd, ff = pd_schedule(q[1], q[2], tgt.substeps, sc.fps)
    np.testing.assert_array_equal(tgt.data.ctrl[tgt.mm.pd_act], pd[-1])
    np.testing.assert_array_equal(tgt.data.ctrl[tgt.mm.ff_act], ff)
    assert tgt.data.time == pytest.approx(tgt.substeps * tgt.dt)


def test_mujoco_rollout_windows_equal_the_generic_loop(shadow) -> None:
    """``mujoco.rollout`` on the sensor model (threads, one extra step for the lagging sensors) predicts what
    the base class's loop (save_state, advance, observe, restore_state) measures on the target itself."""
    sc = scene_with(shadow, object_pos=(0.0, 0.0, 0.86))
    q = smooth_targets(shadow, 6, np.array([0.0, -0.1, 0.95]), np.array([0.0, 0.05, -0.02]), 0.8)
    rng = np.random.default_rng(0)
    wins = np.repeat(q[None, :4], 4, axis=0)
    wins[1:, 1:] += rng.normal(0.0, 0.01, wins[1:, 1:].shape)
    qd0 = (wins[:, 1] - wins[:, 0]) * sc.fps
    with make_target("mujoco", sc, threads=2) as tgt:
        tgt.reset(q[0], qd0[0])
        fast = tgt.rollout_windows(wins, qd0)
        loop = Target.rollout_windows(tgt, wins, qd0)
    for k in ("qpos", "obj_pos", "obj_quat", "keypoints"):
        np.testing.assert_allclose(getattr(fast, k), getattr(loop, k), rtol=0, atol=1e-9, err_msg=k)
    assert fast.n_steps == 4 * (3 * tgt.substeps + 1) and loop.n_steps == 4 * 3 * tgt.substeps


def test_warnings_are_counted_per_run(shadow) -> None:
    """A run's TargetRollout carries MuJoCo's warning counts of that run (a fresh MjData per reset)."""
    sc = scene_with(shadow, object_pos=(2.0, 0.0, 0.825))
    q = smooth_targets(shadow, 3, np.array([0.0, 0.0, 1.2]), np.zeros(3), 0.0)
    tgt = make_target("mujoco", sc)
    bad = q.copy()
    bad[1:, 0] = 1e30  # an absurd target: MuJoCo flags the controls and velocities
    r = tgt.rollout(bad)
    assert r.extras["sim_warnings"]["BADCTRL"] > 0 and r.instability.startswith("mujoco warned: ")
    r = tgt.rollout(q)
    assert set(r.extras["sim_warnings"]) >= {"BADQACC", "BADQPOS"} and not any(r.extras["sim_warnings"].values())
