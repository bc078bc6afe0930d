"""The grasp margin (issue 84, lever 3): friction-cone slack of hand-made contact sets with known answers; the
contacts both targets report (MuJoCo's batched contact sensors against ``mj_contactForce`` of the run itself);
the window cost's term and what it does to a sampled run."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from quasisim.targets.grasp import cone_loads, slack_excess, strongest
from test_sampling import OPTS, W, _inputs


def test_slack_excess_of_hand_made_contact_sets() -> None:
    """A contact at its friction cone's rim carries ``margin`` x its cone beyond the shrunk cone; one well
    inside carries nothing beyond it; loads add over contacts; an empty slot counts nothing."""
    mu, weight = 0.5, 2.0  # N
    rim = [10.0, 3.0, 4.0]  # |f_t| = 5 = mu f_n: sliding
    inside = [10.0, 0.0, 2.0]  # |f_t| = 2 < 0.8 mu f_n = 4
    cones = cone_loads(np.array([rim, inside, [0.0, 0.0, 0.0]]), mu, weight)
    np.testing.assert_allclose(cones, [[2.5, 2.5], [2.5, 1.0], [0.0, 0.0]])  # object weights
    assert slack_excess(cones, 0.0) == pytest.approx(0.0)  # nothing outside the cones themselves
    assert slack_excess(cones, 0.2) == pytest.approx(2.5 - 0.8 * 2.5)  # the rim contact's 0.5 weights
    assert slack_excess(cones, 0.7) == pytest.approx((2.5 - 0.3 * 2.5) + (1.0 - 0.3 * 2.5))  # both now
    # two symmetric fingers pinching a 1 N object with friction 1: each carries half the weight tangentially;
    # pressing with 1 N each, the cones (radius 1 N) hold it with a margin of 1/2; pressing with 0.6 N, only 1/6
    pinch = [[1.0, 0.5, 0.0], [1.0, -0.5, 0.0]]
    assert slack_excess(cone_loads(np.array(pinch), 1.0, 1.0), 0.5) == pytest.approx(0.0)
    light = [[0.6, 0.5, 0.0], [0.6, -0.5, 0.0]]
    assert slack_excess(cone_loads(np.array(light), 1.0, 1.0), 0.5) == pytest.approx(2 * (0.5 - 0.3))
    # the sign of a reported normal force does not matter (a sensor reports the pair's orientation)
    np.testing.assert_allclose(cone_loads(np.array([[-10.0, 3.0, 4.0]]), mu, weight), [[2.5, 2.5]])
    with pytest.raises(ValueError, match="margin"):
        slack_excess(cones, 1.0)
    with pytest.raises(ValueError, match="weight"):
        cone_loads(np.zeros((1, 3)), mu, 0.0)


def test_strongest_keeps_the_largest_forces_and_pads_with_zeros() -> None:
    f = np.array([[1.0, 0.0, 0.0], [3.0, 0.0, 4.0], [2.0, 0.0, 0.0]])
    np.testing.assert_array_equal(strongest(f, 2), [[3.0, 0.0, 4.0], [2.0, 0.0, 0.0]])
    np.testing.assert_array_equal(strongest(f[:1], 3), [[1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    np.testing.assert_array_equal(strongest(np.zeros((0, 3)), 2), np.zeros((2, 3)))


@pytest.fixture(scope="module")
def held(data_dir: Path):
    """12 frames of a real clip from its lift-off (clip frame 30): the hand holds the cube in two contacts."""
    from quasisim.data.demo import load_demo

    return _inputs(load_demo(data_dir / "grab_s1_cubesmall_lift.npz").slice(30, 42))


def test_mujoco_window_rollouts_report_the_contacts_of_the_run(held) -> None:
    """The batched rollouts' contact sensors (each hand's subtree against the object, the forces of each frame's
    last physics step) give what ``mj_contactForce`` reads of the target's own run advanced frame by frame (the
    base class's loop); the cube is held: two contacts pressing ~4 N each, in object weights about 13 cones."""
    from quasisim.targets import Target, make_target

    demo, q, scene = held
    rng = np.random.default_rng(0)
    wins = np.repeat(q[None, 3:8], 3, axis=0)
    wins[1:, 1:] += rng.normal(0.0, 0.01, wins[1:, 1:].shape)
    with make_target("mujoco", scene, threads=2) as tgt:
        tgt.reset(q[0], (q[1] - q[0]) * demo.fps)
        for t in range(3):
            tgt.advance(q[t], q[t + 1])
        fast = tgt.rollout_windows(wins, None, None, contacts=4)
        loop = Target.rollout_windows(tgt, wins, None, None, contacts=4)
        plain = tgt.rollout_windows(wins)
    assert fast.cones is not None and fast.cones.shape == (3, 4, 4, 2) and plain.cones is None
    np.testing.assert_allclose(fast.cones, loop.cones, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(fast.obj_pos, plain.obj_pos)  # sensors do not change the physics
    held_now = fast.cones[0, :, :, 0] > 1.0  # cone radius above one object weight
    assert np.all(held_now.sum(axis=1) >= 2)


def test_pybullet_reports_the_held_cube_as_mujoco_does(held) -> None:
    """PyBullet's contact points of the same held cube: two contacts per frame, each cone within 2x of
    MuJoCo's (two simulators, one grasp), and its window rollouts carry them as advancing by hand reads them."""
    from quasisim.targets import make_target

    demo, q, scene = held
    cones = {}
    for backend in ("mujoco", "pybullet"):
        with make_target(backend, scene) as tgt:
            tgt.reset(q[0], (q[1] - q[0]) * demo.fps)
            tgt.advance(q[0], q[1])
            tgt.advance(q[1], q[2])
            cones[backend] = tgt.contact_cones(4)
            if backend == "pybullet":
                pred = tgt.rollout_windows(q[None, 2:5], None, None, contacts=4)
                tgt.advance(q[2], q[3])
                np.testing.assert_allclose(pred.cones[0, 0], tgt.contact_cones(4), atol=1e-9)
    radius = {b: np.sort(c[:, 0])[::-1][:2] for b, c in cones.items()}
    assert np.all(radius["pybullet"] > 1.0)
    np.testing.assert_allclose(radius["pybullet"], radius["mujoco"], rtol=1.0)


def test_the_grasp_term_is_the_window_mean_of_the_excess() -> None:
    from quasisim.method.stages.sampling import grasp_term

    cones = np.zeros((2, 3, 2, 2))
    cones[0, :, 0] = [1.0, 1.0]  # at the rim: 0.2 beyond the cone shrunk by 0.2, every frame
    cones[1, 2, 0] = [1.0, 1.0]  # only on the last frame, masked out (past the clip's end)
    cones[1, 1, 1] = np.nan  # a frame a pruned candidate never ran
    np.testing.assert_allclose(grasp_term(cones, np.array([1.0, 1.0, 0.0]), 0.2), [0.2, 0.0])


def test_sampling_with_the_grasp_margin_applies_windows_that_hold_inside_the_shrunk_cones(held) -> None:
    """With a weight that outweighs tracking, the sampler chooses windows whose contacts carry less beyond cones
    shrunk by half: measured in MuJoCo by replaying the applied targets, the run's mean excess falls."""
    from quasisim.method.stages.sampling import run_sampling
    from quasisim.targets import make_target

    demo, plan, scene = held

    def excess(q: np.ndarray) -> float:
        with make_target("mujoco", scene) as tgt:
            tgt.reset(q[0], (q[1] - q[0]) * demo.fps)
            out = []
            for t in range(len(q) - 1):
                tgt.advance(q[t], q[t + 1])
                out.append(slack_excess(tgt.contact_cones(8), 0.5))
        return float(np.mean(out))

    plain = run_sampling(demo, scene, plan, OPTS, W, progress=False)
    grasp = dataclasses.replace(OPTS, grasp_weight=1.0, grasp_margin=0.5)
    firm = run_sampling(demo, scene, plan, grasp, W, progress=False)
    assert excess(plain.q_targets) > 0.5  # the fixture's grasp does not hold with that margin
    assert excess(firm.q_targets) < 0.7 * excess(plain.q_targets)


def test_two_hands_report_their_own_contacts() -> None:
    """An ARCTIC clip's kinematic retarget holds the box with both hands: each hand's sensor (its own subtree)
    reports what ``mj_contactForce`` reads of that hand's bodies, the right hand's slots first."""
    from conftest import ARCTIC_CLIP
    from helpers import missing_data
    from quasisim.assets.hand import load_hand
    from quasisim.data.demo import load_demo
    from quasisim.method.retarget import kinematic_controls
    from quasisim.targets import Target, make_target
    from quasisim.targets.build import scene_for
    from quasisim.targets.scene import place_hands

    if not ARCTIC_CLIP.is_file():
        missing_data(f"ARCTIC clip not found at {ARCTIC_CLIP} (set QUASISIM_DATA to the folder that holds arctic/)")
    demo = load_demo(ARCTIC_CLIP)
    hands = (load_hand("shadow"), load_hand("shadow", side="left"))
    c = kinematic_controls(hands, demo, "shadow")
    q, scene = c.q_targets, scene_for(demo, place_hands(hands, c.base_rots))
    with make_target("mujoco", scene, threads=2) as tgt:
        tgt.reset(q[0], (q[1] - q[0]) * demo.fps)
        for t in range(44):
            tgt.advance(q[t], q[t + 1])
        per_hand = tgt.contact_forces(4)
        wins = q[None, 44:48]
        fast = tgt.rollout_windows(wins, None, None, contacts=4)
        loop = Target.rollout_windows(tgt, wins, None, None, contacts=4)
    assert per_hand.shape == (2, 4, 3) and np.all(np.abs(per_hand[:, 0, 0]) > 0)  # both hands touch the box
    np.testing.assert_allclose(fast.cones, loop.cones, rtol=0, atol=1e-9)
    assert fast.cones.shape == (1, 3, 8, 2)
