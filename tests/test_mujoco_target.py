"""MuJoCo target, what only MuJoCo has: its PD actuators, its warnings, ``mujoco.rollout`` of candidate windows
(the behaviour both targets share is tested once for both in test_targets.py)."""

from __future__ import annotations

import numpy as np
import pytest

from helpers import box_object, scene_with, smooth_targets
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


def _overlapping(shadow, overlap: float):
    """A scene whose box overlaps one of the hand's collision geoms (at the hand's zero pose) by ``overlap`` m,
    and that pose; the box is moved along the two shapes' closest-point direction (``mj_geomDistance``)."""
    import mujoco

    q = np.zeros(6 + shadow.n_joints)
    q[:3] = (0.0, 0.0, 1.2)
    box = box_object()
    box.content_hash = "box"  # one object: set_world may edit a model of it
    sc = scene_with(shadow, box, object_pos=(0.0, 0.0, 1.1))
    for _ in range(3):  # distances between convex meshes converge in a step or two
        mm = make_target("mujoco", sc).mm
        d = mujoco.MjData(mm.model)
        mm.set_state(d, q, sc.object_pos0, sc.object_quat0)
        hand = list(mm.grip_geoms)
        obj = int(np.flatnonzero(mm.model.geom_bodyid == mm.obj_body)[0])
        ft = np.zeros(6)
        dists = [(mujoco.mj_geomDistance(mm.model, d, g, obj, 1.0, ft), g, ft.copy()) for g in hand]
        dist, _, ft = min(dists, key=lambda x: x[0])
        toward = (ft[:3] - ft[3:]) / max(np.linalg.norm(ft[:3] - ft[3:]), 1e-12) * np.sign(dist)
        sc = scene_with(shadow, box, object_pos=sc.object_pos0 + (dist + overlap) * toward)
    return sc, q


def test_a_negative_contact_margin_lets_the_hand_into_the_object_by_that_much(shadow) -> None:
    """``physics.contact_margin`` < 0 (the sampler's ``thin`` world): a hand geom 1 mm inside the object touches it
    in the nominal world and with a 0.5 mm margin, not with a 2 mm one; the box on the table rests at the same
    height whatever the margin (only the hand's geoms carry it); and ``set_world`` gives the
    compiled model the margin that compiling gives it."""
    import dataclasses

    from quasisim.targets.mujoco_target import hand_object_contacts

    def thin(sc, m):
        return dataclasses.replace(sc, physics=dataclasses.replace(sc.physics, contact_margin=m))

    sc, q = _overlapping(shadow, 0.001)
    pose = (q[None], sc.object_pos0[None], sc.object_quat0[None])
    counts = [hand_object_contacts(make_target("mujoco", thin(sc, m)).mm, *pose)[0] for m in (0.0, -0.0005, -0.002)]
    assert counts[0] > 0 and counts[1] > 0 and counts[2] == 0, counts

    rest = scene_with(shadow, object_pos=(0.0, 0.0, 0.83))  # the box drops 5 mm onto the table, the hand far above
    far = np.zeros((2, 6 + shadow.n_joints))
    far[:, :3] = (0.0, 0.0, 1.5)
    z = []
    for m in (0.0, -0.002):
        with make_target("mujoco", thin(rest, m)) as tgt:
            tgt.reset(far[0])
            for _ in range(20):
                tgt.advance(far[0], far[1])
            z.append(tgt.observe()["obj_pos"][2])
    assert z[0] == pytest.approx(z[1], abs=1e-6) and z[0] == pytest.approx(0.825, abs=2e-4), z

    compiled = make_target("mujoco", thin(sc, -0.002)).mm
    edited = make_target("mujoco", sc)
    assert edited.set_world(thin(sc, -0.002))
    np.testing.assert_array_equal(edited.mm.model.geom_margin, compiled.model.geom_margin)
    assert (compiled.model.geom_margin[compiled.grip_geoms] == -0.002).all()
    assert (np.delete(compiled.model.geom_margin, compiled.grip_geoms) == 0).all()
