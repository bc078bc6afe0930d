"""DGrasp-Base's guide (:mod:`quasisim.policy.dgrasp`): the force-closure test against its closed form, the first
grasp frame's rules in order, and the grasp carried rigidly with the object. The training end to end is in
``test_policy.py``."""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial.transform import Rotation

from quasisim.policy.dgrasp import RULES, carry_grasp, first_grasp, force_closure, grasp_guide


def test_two_contacts_close_exactly_when_the_line_between_them_lies_in_both_friction_cones() -> None:
    """A cube's opposite faces close at any friction; two adjacent faces (their normals 90 deg apart, the line
    between the contacts 45 deg off each normal) close iff atan(mu) >= 45 deg, i.e. mu >= 1."""
    opposite = np.array([[0.02, 0, 0], [-0.02, 0, 0]]), np.array([[-1.0, 0, 0], [1.0, 0, 0]])
    adjacent = np.array([[0.02, 0, 0], [0, 0.02, 0]]), np.array([[-1.0, 0, 0], [0, -1.0, 0]])
    assert force_closure(*opposite, mu=0.05)
    assert not force_closure(*adjacent, mu=0.9) and force_closure(*adjacent, mu=1.1)
    same_face = np.array([[0.02, 0, 0], [0.02, 0.01, 0]]), np.array([[-1.0, 0, 0], [-1.0, 0, 0]])
    assert not force_closure(*same_face, mu=10.0)  # both push the same way: no closure at any friction
    three = np.concatenate([adjacent[0], [[-0.02, 0, 0]]]), np.concatenate([adjacent[1], [[1.0, 0, 0]]])
    assert force_closure(*three, mu=0.1)  # an antipodal pair among more contacts


def test_the_first_grasp_frame_takes_force_closure_first_then_fewer_contacts() -> None:
    T = 6
    pts, nrm = np.zeros((T, 5, 3)), np.zeros((T, 5, 3))
    pts[:, 0], nrm[:, 0] = [0.02, 0, 0], [-1, 0, 0]  # thumb on +x
    pts[:, 1], nrm[:, 1] = [0.02, 0.01, 0], [-1, 0, 0]  # index on +x too (no closure)
    pts[:, 2], nrm[:, 2] = [-0.02, 0, 0], [1, 0, 0]  # middle on -x (closure with the thumb)
    touch = np.zeros((T, 5), bool)
    touch[1, 0] = True  # one contact
    touch[2, :2] = True  # two, same face
    touch[4, [0, 2]] = True  # an antipodal pair
    assert first_grasp(touch, pts, nrm, 0.5) == (4, RULES[0])
    touch[4] = False
    assert first_grasp(touch, pts, nrm, 0.5) == (2, RULES[1])
    touch[2] = False
    assert first_grasp(touch, pts, nrm, 0.5) == (1, RULES[2])
    assert first_grasp(np.zeros((T, 5), bool), pts, nrm, 0.5) == (0, RULES[3])


def test_after_the_grasp_frame_the_hand_moves_rigidly_with_the_object() -> None:
    rng = np.random.default_rng(0)
    T, g = 12, 5
    joints = rng.normal(size=(T, 21, 3)) * 0.05
    pos = np.cumsum(rng.normal(size=(T, 3)) * 0.01, axis=0)
    rot = Rotation.from_rotvec(np.cumsum(rng.normal(size=(T, 3)) * 0.2, axis=0)).as_matrix()
    out = carry_grasp(joints, pos, rot, g)
    np.testing.assert_array_equal(out[:g], joints[:g])  # the approach as demonstrated
    np.testing.assert_allclose(out[g], joints[g], atol=1e-12)  # the grasp frame's own hand
    local = np.einsum("tji,tkj->tki", rot, out - pos[:, None])  # R_t^T (x'_t - p_t)
    np.testing.assert_allclose(local[g:], np.broadcast_to(local[g], local[g:].shape), atol=1e-12)
    assert not np.allclose(local[:g], local[g])  # (the demo's own hand is not rigid with the object)


def test_the_guide_of_a_clip_holds_the_first_grasp_while_the_demo_fingers_slide(tmp_path) -> None:
    """On the bundled cube lift (thumb and fingers on opposite faces from frame 10), with the fingers made to
    slide after the grasp: the guide's grasp frame is where contact begins, by force closure; from it on the
    guide keeps that frame's hand in the cube's frame, while the demo's fingers move on; before it, the demo."""
    from quasisim.data.demo import load_demo
    from quasisim.data.synthetic import write_example

    demo = load_demo(write_example("cube_lift", tmp_path, n_frames=20))
    g0 = grasp_guide(demo, 0.01, 1.0)[1]["right"]
    assert g0["rule"] == RULES[0] and 0 < g0["grasp_frame"] < demo.n_frames - 1
    g = g0["grasp_frame"]
    slide = np.zeros_like(demo.right_joints)
    slide[g + 1 :, :, 2] = 0.002 * np.arange(1, demo.n_frames - g)[:, None]  # up the faces, 2 mm a frame
    sliding = dataclasses.replace(demo, right_joints=demo.right_joints + slide)
    guide, info = grasp_guide(sliding, 0.01, 1.0)
    assert info["right"] == g0 and guide.n_frames == demo.n_frames
    np.testing.assert_array_equal(guide.right_joints[: g + 1], sliding.right_joints[: g + 1])
    np.testing.assert_allclose(guide.right_joints[g:], demo.right_joints[g:], atol=1e-9)  # the cube carries it
    np.testing.assert_array_equal(guide.object_pos, demo.object_pos)  # the object's path is the demo's own
