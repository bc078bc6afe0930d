"""A simulator of the physics curriculum behind the target interface (:mod:`quasisim.targets.quasi_target`), which
DGrasp-Tracking w/ curriculum trains in: it rolls a clip out exactly as stage 2's simulator does, observes the
hands as MuJoCo does (the same keypoints within the two simulators' tracking difference), restores its state
exactly, and takes a perturbed world's parameters."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from helpers import cube_example
from quasisim.method.curriculum import load_curriculum
from quasisim.targets import make_target
from quasisim.targets.quasi_target import QuasiTarget


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    return cube_example(tmp_path_factory.mktemp("quasi"))


@pytest.mark.parametrize("stage", [0, 8])  # the relaxed point set (alpha 0.1, d_c 0.1 m), the stiffest analytical
def test_a_clip_rolls_out_as_stage_two_simulates_it(clip, stage) -> None:
    from quasisim.method.problem import make_problem
    from quasisim.sim.step import object_pose

    _, demo, controls, scene = clip
    contact = load_curriculum("default").contact(stage)
    target = QuasiTarget(scene, contact)
    got = target.rollout(controls.q_targets, init_qvel=False)  # from rest, as stage 2 starts
    prob = make_problem(demo, scene.placements, 20, 128)
    states = prob.simulate(prob.params(contact), prob.trajectory(controls.q_targets))
    pos, quat = (np.asarray(x) for x in object_pose(prob.model, states))
    np.testing.assert_allclose(got.object_pos[1:], pos, atol=1e-5)
    np.testing.assert_allclose(np.abs(np.sum(got.object_quat[1:] * quat, axis=1)), 1.0, atol=1e-5)
    # the joints within float32 rounding: one frame per call here, one scan over the clip there (a stiff contact
    # amplifies the last digits: 1e-4 rad at the stiffest simulator)
    np.testing.assert_allclose(got.qpos[1:, 6:], np.asarray(states.q), atol=1e-3)
    assert np.abs(got.object_pos[-1] - got.object_pos[0]).max() > 1e-3  # the hand touched the cube: contacts compared


def test_the_hands_are_observed_as_mujoco_observes_them(clip) -> None:
    _, _, controls, scene = clip
    q = controls.q_targets
    quasi = QuasiTarget(scene, load_curriculum("default").contact(8)).rollout(q)
    mj = make_target("mujoco", scene).rollout(q)
    np.testing.assert_allclose(quasi.qpos[:, :6], q[:, :6], atol=1e-6)  # the kinematic bases follow the targets
    assert np.abs(quasi.keypoints - mj.keypoints).max() < 0.01  # same keypoints, two PD-driven simulators
    assert quasi.keypoints.shape == mj.keypoints.shape


def test_a_saved_state_is_restored_exactly(clip) -> None:
    _, _, controls, scene = clip
    q = controls.q_targets
    target = QuasiTarget(scene, load_curriculum("default").contact(3))
    target.reset(q[0])
    target.advance(q[0], q[1])
    saved = target.save_state()
    target.advance(q[1], q[2])
    first = target.observe()
    target.restore_state(saved)
    target.advance(q[1], q[2])
    again = target.observe()
    for k in first:
        np.testing.assert_array_equal(first[k], again[k])


def test_a_perturbed_world_sets_its_parameters(clip) -> None:
    from quasisim.targets.perturb import scaled_scene

    _, _, controls, scene = clip
    contact = load_curriculum("default").contact(8)
    target = QuasiTarget(scene, contact)
    heavy = scaled_scene(scene, mass=2.0, friction=0.5, gains=1.5)
    heavy = dataclasses.replace(heavy, object_pos0=scene.object_pos0 + np.array([0.002, 0.0, 0.0]))
    assert target.set_world(heavy)
    p, p0 = target.params, QuasiTarget(scene, contact).params
    np.testing.assert_allclose(p.obj_mass, 2.0 * p0.obj_mass, rtol=1e-6)
    np.testing.assert_allclose(p.mu, 0.5 * p0.mu, rtol=1e-6)
    np.testing.assert_allclose(p.joint_kp, 1.5 * p0.joint_kp, rtol=1e-6)
    target.reset(controls.q_targets[0])
    np.testing.assert_allclose(target.observe()["obj_pos"], heavy.object_pos0, atol=1e-6)
    other = dataclasses.replace(scene, obj=dataclasses.replace(scene.obj, name="another"))
    assert not target.set_world(other)  # another object: the caller builds a simulator for it
