"""PyBullet target, what only PyBullet has: link frames vs our FK, shape conventions, tracking near gimbal lock,
the object's inertial frame, no self-collision, state ids (the behaviour both targets share is tested once
for both in test_targets.py)."""

from __future__ import annotations

import dataclasses
import tempfile
from pathlib import Path
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from helpers import box_object, scene_with, smooth_targets
from quasisim.assets.hand import SLIDE, Geom
from quasisim.rotations import np_quat_to_mat
from quasisim.sim.kinematics import fk_full, keypoints
from quasisim.targets import make_target
from quasisim.targets.pybullet_target import COLLISION_MARGIN, PybulletTarget, _geom_shape

pytest.importorskip("pybullet")


def _random_q(hand, rng: np.random.Generator) -> np.ndarray:
    lo = np.where(hand.joint_limited, hand.joint_range[:, 0], -np.pi)
    hi = np.where(hand.joint_limited, hand.joint_range[:, 1], np.pi)
    return np.concatenate([rng.uniform(-1, 1, 3), rng.uniform(-1.4, 1.4, 3), rng.uniform(lo, hi)])


def _twisted(shadow):
    """Shadow with what the real models lack: joint anchors off the body origin, a body with two joints
    (FFJ3 moved onto ffproximal, so ffknuckle is jointless), a slide joint, more geom types."""
    rng = np.random.default_rng(5)
    jb, jt, jr = shadow.joint_body.copy(), shadow.joint_type.copy(), shadow.joint_range.copy()
    jb[0] = 2
    k = shadow.joint_names.index("robot0:THJ2")
    jt[k], jr[k] = SLIDE, [-0.01, 0.01]
    box = box_object((0.01, 0.02, 0.03))
    one, rgba = np.array([1.0, 0, 0, 0]), np.ones(4)
    tilt = np.array([0.9, 0.3, 0.1, 0.2]) / np.linalg.norm([0.9, 0.3, 0.1, 0.2])
    extra = (
        Geom("sph", 1, "sphere", np.array([0.01, 0, 0]), np.array([0.0, 0.01, 0.0]), one, True, rgba),
        Geom("cyl", 3, "cylinder", np.array([0.006, 0.015, 0]), np.array([0.0, 0.0, 0.01]), tilt, True, rgba),
        Geom("ell", 13, "ellipsoid", np.array([0.01, 0.02, 0.015]), np.array([0.0, 0.01, 0.0]), one, True, rgba),
        Geom("msh", 20, "mesh", np.zeros(3), np.array([0.01, 0, 0]), one, True, rgba, box.vertices, box.faces),
    )
    anchors = rng.uniform(-0.01, 0.01, (shadow.n_joints, 3))
    return dataclasses.replace(
        shadow,
        joint_body=jb,
        joint_type=jt,
        joint_range=jr,
        joint_pos=anchors,
        geoms=shadow.geoms + extra,
    )


def _check_fk(hand, n: int = 6) -> None:
    rng = np.random.default_rng(0)
    base_rot = Rotation.random(random_state=3).as_matrix()
    fk = jax.jit(lambda q: fk_full(hand, jnp.asarray(base_rot), q))
    with PybulletTarget(scene_with(hand, base_rot=base_rot, object_pos=(2.0, 0.0, 0.825))) as tgt:
        for _ in range(n):
            q = _random_q(hand, rng)
            tgt.set_state(q)
            poses = fk(jnp.asarray(q))
            pos, rot = tgt.body_poses()
            assert np.abs(tgt.joint_states()[0] - q).max() < 1e-9
            assert np.abs(pos - np.asarray(poses.pos)).max() < 1e-5
            assert np.abs(rot - np.asarray(poses.rot)).max() < 1e-5
            assert np.abs(tgt.keypoints() - np.asarray(keypoints(hand, poses))).max() < 1e-5


@pytest.mark.parametrize("hand_fixture", ["shadow", "allegro"])
def test_link_frames_match_fk(hand_fixture: str, request: pytest.FixtureRequest) -> None:
    _check_fk(request.getfixturevalue(hand_fixture))


def test_anchor_shift_and_joint_chains_match_fk(shadow) -> None:
    _check_fk(_twisted(shadow))


def _expected_aabb(g: Geom, pos: np.ndarray, rot: np.ndarray) -> np.ndarray:
    """World AABB (2, 3) of geom ``g`` on a body at (pos, rot) from MuJoCo's size conventions, bounded as
    Bullet does: the rotated local box (r, r, r + half-length) of a capsule, (r, r, half-height) of a
    cylinder; exact for boxes, spheres and hulls."""
    R = rot @ np_quat_to_mat(g.quat)
    c = pos + rot @ g.pos
    r, h = g.size[0], g.size[1]
    if g.type == "mesh":
        v = g.vertices @ R.T + c
        return np.stack([v.min(0), v.max(0)])
    local = {"box": g.size, "sphere": np.full(3, r), "capsule": [r, r, r + h], "cylinder": [r, r, h]}
    local["ellipsoid"] = g.size
    half = np.abs(R) @ np.asarray(local[g.type])
    return np.stack([c - half, c + half])


@pytest.mark.parametrize("hand_fixture", ["shadow", "allegro", "twisted"])
def test_collision_shapes(hand_fixture: str, request: pytest.FixtureRequest) -> None:
    """Every hand geom sits where FK puts it; each geom alone has the AABB its MuJoCo size implies."""
    shadow = request.getfixturevalue("shadow")
    hand = _twisted(shadow) if hand_fixture == "twisted" else request.getfixturevalue(hand_fixture)
    base_rot = Rotation.random(random_state=4).as_matrix()
    q = _random_q(hand, np.random.default_rng(2))
    with PybulletTarget(scene_with(hand, base_rot=base_rot, object_pos=(2.0, 0.0, 0.825))) as tgt:
        pb, kw = tgt.pb, {"physicsClientId": tgt.client}
        tgt.set_state(q)
        pos, rot = tgt.body_poses()
        for b in range(hand.n_bodies):
            geoms = [g for g in hand.collision_geoms() if g.body == b]
            link = int(tgt.body_link[b])
            data = pb.getCollisionShapeData(tgt.hand_id, link, **kw)
            assert len(data) == len(geoms)
            if not geoms:
                continue
            com_p, com_q = pb.getLinkState(tgt.hand_id, link, computeForwardKinematics=1, **kw)[:2]
            for g, d in zip(geoms, data, strict=True):  # child frames are given in the link's inertial frame
                p, o = pb.multiplyTransforms(com_p, com_q, d[5], d[6])
                assert np.abs(np.array(p) - (pos[b] + rot[b] @ g.pos)).max() < 1e-6
                R = np.array(pb.getMatrixFromQuaternion(o)).reshape(3, 3)
                assert np.abs(R - rot[b] @ np_quat_to_mat(g.quat)).max() < 1e-6
        # size conventions: one geom per static body at a known pose, AABB vs MuJoCo sizes
        kinds = set()
        with tempfile.TemporaryDirectory() as d:
            for g in hand.collision_geoms():
                if g.type in kinds:
                    continue
                kinds.add(g.type)
                shape = tgt._shape_array([_geom_shape(g, np.zeros(3))], Path(d))
                body = pb.createMultiBody(0.0, shape, basePosition=[0, 0, 5], **kw)
                tgt._dynamics(body, -1)  # the target's collision margin
                got = np.array(pb.getAABB(body, -1, **kw))
                want = _expected_aabb(g, np.array([0.0, 0.0, 5.0]), np.eye(3))
                # the compound's AABB is padded by its margin; a hull keeps the AABB cached at creation
                # with PyBullet's default 1 mm margin (twice), although contacts use the new margin.
                # An ellipsoid becomes the hull of 200 surface points; hull vertices are single precision.
                hull = g.type in ("mesh", "ellipsoid")
                pad = COLLISION_MARGIN + (2e-3 if hull else 0.0)
                tol = {"mesh": 5e-5, "ellipsoid": 2e-4}.get(g.type, 1e-6)
                assert np.abs(got - want - [[-pad] * 3, [pad] * 3]).max() < tol, (g.name, got, want)
    every = {"box", "capsule", "sphere", "cylinder", "mesh", "ellipsoid"}
    assert kinds >= (every if hand_fixture == "twisted" else {"box"})


def test_pd_tracking_near_gimbal_lock_allegro(allegro) -> None:
    # middle base angle 85 deg: the outer base hinge axes nearly align (implicit damping keeps it stable)
    with PybulletTarget(scene_with(allegro, object_pos=(2.0, 0.0, 0.825))) as tgt:
        q = smooth_targets(allegro, 30, np.array([0.0, 0.0, 1.2]), np.array([0.0, 0.05, 0.0]), 0.8)
        q[:, 3:6] = np.linspace(0, 1, 30)[:, None] * [0.5, np.radians(85), -0.3]
        r = tgt.rollout(q)
        assert np.abs(r.qpos - q).max() < 0.05


def test_object_frame_vs_inertial_frame(shadow) -> None:
    """An object whose centre of mass is off its origin and whose principal axes are tilted."""
    box = box_object((0.08, 0.04, 0.02))
    R = Rotation.from_euler("xyz", [0.3, -0.2, 0.7]).as_matrix()
    com = np.array([0.02, -0.01, 0.03])
    v = box.vertices @ R.T + com
    parts = [(v, box.faces)]
    obj = SimpleNamespace(
        vertices=v,
        faces=box.faces,
        mass=box.mass,
        com=com,
        inertia=R @ box.inertia @ R.T,
        convex_parts=lambda: parts,
    )
    quat0 = Rotation.from_euler("z", 0.4).as_quat()[[3, 0, 1, 2]]
    sc = dataclasses.replace(scene_with(shadow, obj=obj), object_pos0=np.array([0.1, 0.0, 1.0]))
    sc = dataclasses.replace(sc, object_quat0=quat0)
    with PybulletTarget(sc) as tgt:
        pb, kw = tgt.pb, {"physicsClientId": tgt.client}
        p, q = tgt.object_pose()
        assert np.abs(p - sc.object_pos0).max() < 1e-9 and abs(abs(q @ quat0) - 1) < 1e-9
        c_p, c_q = pb.getBasePositionAndOrientation(tgt.obj_id, **kw)  # PyBullet reports the com frame
        assert np.abs(np.array(c_p) - (p + np_quat_to_mat(q) @ com)).max() < 1e-9
        (hull,) = pb.getCollisionShapeData(tgt.obj_id, -1, **kw)  # its frame is given in the com frame...
        h_p, h_q = pb.multiplyTransforms(c_p, c_q, hull[5], hull[6])
        assert np.abs(np.array(h_p) - sc.object_pos0).max() < 1e-6  # ...and is the object frame (float32)
        assert abs(abs(np.dot(h_q, np.r_[quat0[1:], quat0[0]])) - 1) < 1e-6
        mass, _, diag = pb.getDynamicsInfo(tgt.obj_id, -1, **kw)[:3]
        assert mass == pytest.approx(box.mass)
        assert np.allclose(sorted(diag), sorted(np.linalg.eigvalsh(box.inertia)))
        tgt.set_object_pose(np.array([0.3, 0.2, 1.1]), np.array([0.0, 1.0, 0.0, 0.0]))
        p, q = tgt.object_pose()
        assert np.abs(p - [0.3, 0.2, 1.1]).max() < 1e-9 and abs(abs(q[1]) - 1) < 1e-9


def test_no_self_collision(shadow) -> None:
    # adjacent fingers abducted into each other: the capsules overlap, nothing pushes them apart
    sc = scene_with(shadow, obj=box_object(density=200.0), object_pos=(0.0, 0.0, 0.825))
    j = {n: i for i, n in enumerate(shadow.joint_names)}
    lo, hi = shadow.joint_range[:, 0], shadow.joint_range[:, 1]
    goal = shadow.rest_q()
    for name, bound in (("robot0:FFJ3", lo), ("robot0:MFJ3", hi), ("robot0:RFJ3", lo), ("robot0:LFJ3", hi)):
        goal[j[name]] = bound[j[name]]
    q = smooth_targets(shadow, 20, np.array([2.0, 0.0, 1.2]), np.zeros(3), 0.0)
    q[:, 6:] = np.linspace(0, 1, 20)[:, None] * goal
    with PybulletTarget(sc) as tgt:
        r = tgt.rollout(q)
        assert np.isfinite(r.qpos).all() and np.abs(r.qpos[-1, 6:] - goal).max() < 0.02
        a, b = (int(tgt.body_link[shadow.body_names.index(n)]) for n in ("robot0:ffproximal", "robot0:mfproximal"))
        kw = {"physicsClientId": tgt.client}
        close = tgt.pb.getClosestPoints(tgt.hand_id, tgt.hand_id, 0.01, linkIndexA=a, linkIndexB=b, **kw)
        assert min(c[8] for c in close) < -0.01  # 1 cm interpenetration...
        assert tgt.pb.getContactPoints(tgt.hand_id, tgt.hand_id, **kw) == ()  # ...and no contact


def test_hand_pushes_object_at_gimbal_lock(shadow) -> None:
    # the palm sweeps through the box's position at table height, the base's middle angle at 90 deg
    sc = scene_with(shadow, obj=box_object(density=200.0), object_pos=(0.0, 0.0, 0.825))
    q = smooth_targets(shadow, 30, np.array([-0.2, 0.0, 0.84]), np.array([0.3, 0.0, 0.0]), 0.0)
    q[:, 3:6] = [0.0, np.pi / 2, 0.0]
    r = make_target("pybullet", sc).rollout(q)
    assert np.isfinite(r.qpos).all()
    assert np.linalg.norm(r.object_pos[-1, :2] - r.object_pos[0, :2]) > 0.01


def test_window_rollouts_restore_the_saved_state_and_free_it(shadow) -> None:
    """The base class's window loop on PyBullet: ``saveState`` once, ``restoreState`` per candidate and after,
    ``removeState`` at the end (the state id is gone)."""
    sc = scene_with(shadow, object_pos=(0.0, 0.0, 0.86))
    q = smooth_targets(shadow, 4, np.array([0.0, -0.1, 0.95]), np.array([0.0, 0.05, -0.02]), 0.8)
    with PybulletTarget(sc) as tgt:
        tgt.reset(q[0])
        sid = tgt.save_state()
        tgt.release_state(sid)
        pred = tgt.rollout_windows(q[None, :3].repeat(2, axis=0))
        assert pred.n_steps == 2 * 2 * tgt.substeps
        np.testing.assert_array_equal(pred.qpos[0], pred.qpos[1])  # the same window twice, from the same state
        nxt = tgt.save_state()
        assert nxt == sid  # the windows' state was removed again (PyBullet hands out the lowest free id)
