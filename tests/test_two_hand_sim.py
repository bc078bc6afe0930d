"""The quasi-physical simulator with two hands (a hand set of :func:`quasisim.assets.hand.join_hands`): each
hand's kinematics and dynamics are its own, a hand far from the object changes nothing, the trajectory's
layout matches the targets', and stage 1 pairs points within each hand."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from helpers import STIFF
from quasisim.rotations import euler_xyz_to_mat


@pytest.fixture(scope="module")
def pair(shadow):
    from quasisim.assets.hand import join_hands, load_hand

    left = load_hand("shadow", side="left")
    return shadow, left, join_hands((shadow, left))


def _pose(rng: np.random.Generator, hand, z: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    lo, hi = hand.joint_range[:, 0], hand.joint_range[:, 1]
    R = np.asarray(euler_xyz_to_mat(jnp.asarray(rng.uniform(-1, 1, 3))), np.float64)
    return rng.uniform(-0.2, 0.2, 3) + np.array([0, 0, z]), R, rng.uniform(lo, hi)


def test_hand_set_is_both_hands_side_by_side(pair) -> None:
    """Forward kinematics, keypoints and the mass matrix of the set are each hand's own (block diagonal)."""
    from quasisim.assets.hand import join_hands
    from quasisim.sim.articulation import body_jacobians, mass_matrix
    from quasisim.sim.kinematics import forward_kinematics, keypoints

    right, left, both = pair
    J, B = right.n_joints, right.n_bodies
    assert join_hands((right, left)) is both and join_hands((right,)) is right  # cached; one hand as it is
    assert both.n_hands == 2 and both.hand_joints == (J, left.n_joints) and right.hand_joints == (J,)
    np.testing.assert_array_equal(both.roots, [0, B])
    np.testing.assert_array_equal(both.body_hand, np.r_[np.zeros(B), np.ones(left.n_bodies)])
    np.testing.assert_array_equal(both.kp_human, np.r_[right.kp_human, left.kp_human + 21])
    rng = np.random.default_rng(0)
    (pr, Rr, qr), (pl, Rl, ql) = _pose(rng, right, 1.0), _pose(rng, left, 1.3)
    f = lambda h, p, R, q: forward_kinematics(h, jnp.asarray(p), jnp.asarray(R), jnp.asarray(q))  # noqa: E731
    got = f(both, np.stack([pr, pl]), np.stack([Rr, Rl]), np.r_[qr, ql])
    want_r, want_l = f(right, pr, Rr, qr), f(left, pl, Rl, ql)
    np.testing.assert_allclose(got.pos, np.concatenate([want_r.pos, want_l.pos]), atol=1e-6)
    np.testing.assert_allclose(got.rot, np.concatenate([want_r.rot, want_l.rot]), atol=1e-6)
    kp = np.concatenate([keypoints(right, want_r), keypoints(left, want_l)])
    np.testing.assert_allclose(keypoints(both, got), kp, atol=1e-6)
    arm = jnp.full(2 * J, 1e-3)
    M = mass_matrix(both, body_jacobians(both, jnp.stack([pr, pl]), jnp.stack([Rr, Rl]), jnp.r_[qr, ql]), arm)
    Mr = mass_matrix(right, body_jacobians(right, jnp.asarray(pr), jnp.asarray(Rr), jnp.asarray(qr)), arm[:J])
    Ml = mass_matrix(left, body_jacobians(left, jnp.asarray(pl), jnp.asarray(Rl), jnp.asarray(ql)), arm[J:])
    np.testing.assert_allclose(M, jax.scipy.linalg.block_diag(Mr, Ml), atol=1e-7)


@pytest.fixture(scope="module")
def cube(tmp_path_factory: pytest.TempPathFactory):
    import trimesh

    from quasisim.assets.object import load_object

    d = tmp_path_factory.mktemp("cube")
    trimesh.creation.box(extents=(0.05,) * 3).export(d / "cube.obj")
    return load_object(d / "cube.obj", density=500.0)


def test_a_hand_far_away_changes_nothing(pair, cube) -> None:
    """The left hand grasping a cube with the right hand 2 m away moves the cube and its joints as the left
    hand alone does (same points, same contacts), while the right hand follows its own root controls."""
    from quasisim.sim.build import SimOptions, build_model, default_params, hand_set_points
    from quasisim.sim.step import initial_state, rollout
    from quasisim.sim.types import Control
    from quasisim.targets.scene import Table

    right, left, both = pair
    opts = SimOptions(dt=2e-3, substeps=10, n_candidates=48, point_spacing=0.012)
    table = Table(-0.3, 0.3, -0.3, 0.3, -0.02)
    m1 = build_model(left, cube, table, opts, np.zeros(3))
    m2 = build_model(both, cube, table, opts, np.zeros(3), hand_set_points((right, left), opts))
    J = left.n_joints
    # the left palm over the cube, fingers closing on it (a pose whose points reach the cube)
    R = np.asarray(euler_xyz_to_mat(jnp.asarray([np.pi, 0.0, 0.0])), np.float32)
    q = np.clip(np.full(J, 0.4), left.joint_range[:, 0], left.joint_range[:, 1]).astype(np.float32)
    s1 = initial_state(
        m1, jnp.asarray([0.0, -0.03, 0.11]), jnp.asarray(_quat(R)), q, jnp.zeros(3), jnp.asarray([1.0, 0, 0, 0])
    )
    s2 = initial_state(
        m2, jnp.asarray([[2.0, 0.0, 0.5], [0.0, -0.03, 0.11]]), jnp.asarray([[1.0, 0, 0, 0], _quat(R)]),
        np.r_[right.rest_q(), q], jnp.zeros(3), jnp.asarray([1.0, 0, 0, 0]),
    )  # fmt: skip
    F = 6
    up = jnp.broadcast_to(jnp.asarray([0.0, 0.0, 0.05]), (F, 1, 3))
    target = jnp.broadcast_to(jnp.asarray(np.clip(q + 0.4, *left.joint_range.T)), (F, J))
    c1 = Control(up, jnp.zeros((F, 1, 3)), jnp.zeros((F, J)), target, jnp.zeros((F, J)), jnp.zeros((F, m1.n_points, 3)))
    away = jnp.broadcast_to(jnp.asarray([0.1, 0.0, 0.0]), (F, 1, 3))
    tr = jnp.broadcast_to(jnp.asarray(right.rest_q(), jnp.float32), (F, right.n_joints))
    c2 = Control(
        jnp.concatenate([away, up], 1), jnp.zeros((F, 2, 3)), jnp.zeros((F, 2 * J)), jnp.concatenate([tr, target], 1),
        jnp.zeros((F, 2 * J)), jnp.zeros((F, m2.n_points, 3)),
    )  # fmt: skip
    p1 = default_params(m1, cube.mass, cube.inertia, STIFF)
    p2 = default_params(m2, cube.mass, cube.inertia, STIFF, point_mass=p1.point_mass)
    o1 = jax.jit(lambda s: rollout(m1, p1, s, c1))(s1)
    o2 = jax.jit(lambda s: rollout(m2, p2, s, c2))(s2)
    assert float(jnp.max(o1.in_contact.sum(-1))) > 0  # the left hand does touch the cube
    assert float(jnp.linalg.norm(o1.obj_pos[-1] - s1.obj_pos)) > 1e-4  # ...and moves it
    np.testing.assert_allclose(o2.obj_pos, o1.obj_pos, atol=1e-6)
    np.testing.assert_allclose(o2.q[:, J:], o1.q, atol=1e-5)
    np.testing.assert_allclose(o2.root_pos[:, 1], o1.root_pos[:, 0], atol=1e-6)
    np.testing.assert_allclose(o2.root_pos[-1, 0], [2.0 + 0.1 * F * 10 * 2e-3, 0.0, 0.5], atol=1e-5)


def _quat(R: np.ndarray) -> np.ndarray:
    from quasisim.rotations import np_mat_to_quat

    return np.asarray(np_mat_to_quat(np.asarray(R, np.float64)), np.float32)


def test_trajectory_layout_is_the_targets(pair) -> None:
    """``[base, joints]`` per hand in the targets' PD targets; bases then joints in the simulator's trajectory."""
    from quasisim.optim.trajectory import Trajectory, join_q, split_q

    right, _, both = pair
    J = right.n_joints
    q = np.random.default_rng(1).normal(size=(5, 2 * (6 + J)))
    t = Trajectory.from_q(q, 7, both.hand_joints)
    np.testing.assert_allclose(t.base, np.c_[q[:, :6], q[:, 6 + J : 12 + J]], atol=1e-6)
    np.testing.assert_allclose(t.joints, np.c_[q[:, 6 : 6 + J], q[:, 12 + J :]], atol=1e-6)
    np.testing.assert_allclose(t.q_targets, q, atol=1e-6)
    np.testing.assert_array_equal(join_q(*split_q(q, both.hand_joints), both.hand_joints), q)
    one = Trajectory.from_q(q[:, : 6 + J], 7, right.hand_joints)
    assert one.hand_joints == () and one.base.shape == (5, 6)
    g = jax.grad(lambda tt: jnp.sum(tt.base**2))(t)  # the static layout survives differentiation
    assert g.hand_joints == t.hand_joints


def test_stage1_pairs_points_within_each_hand(pair) -> None:
    """Each human point's robot point belongs to the same hand, even where the other hand is closer."""
    from types import SimpleNamespace

    from quasisim.method.stages.point_dynamics import correspondences

    rng = np.random.default_rng(2)
    robot = rng.normal(size=(40, 3))
    robot_hand = np.r_[np.zeros(20, int), np.ones(20, int)]
    human = robot[None, rng.integers(0, 40, 30)] + 1e-3  # each near some robot point, of either hand
    human_hand = 1 - robot_hand[np.argmin(np.linalg.norm(human[0, :, None] - robot[None], axis=-1), axis=1)]
    demo = SimpleNamespace(object_pos=np.zeros((1, 3)), object_quat=np.array([[1.0, 0, 0, 0]]), n_frames=1)
    prob = SimpleNamespace(demo=demo, points_at=lambda q: robot, point_hand=robot_hand)
    idx = correspondences(prob, np.zeros((1, 3)), human, human_hand)  # type: ignore[arg-type]
    np.testing.assert_array_equal(robot_hand[idx], human_hand)
    nearest_same = [
        np.flatnonzero(robot_hand == h)[np.argmin(np.linalg.norm(robot[robot_hand == h] - x, axis=1))]
        for x, h in zip(human[0], human_hand, strict=True)
    ]
    np.testing.assert_array_equal(idx, nearest_same)
