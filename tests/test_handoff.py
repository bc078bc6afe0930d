"""Stage 2's touching hand-off (quasisim.method.stages.contact_curriculum): contacts move the asked distance
closer to the object, nothing else moves, and the stage-2 restart guard sees the touching start."""

from __future__ import annotations

from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from quasisim.method.options import HandoffOptions


@pytest.fixture(scope="module")
def soft_grasp(tmp_path_factory: pytest.TempPathFactory):
    """The synthetic cube lift's kinematic retarget rolled out in a soft simulator (d_c = 1 cm)."""
    from quasisim.assets.hand import load_hand
    from quasisim.data.demo import load_demo
    from quasisim.data.synthetic import write_example
    from quasisim.method.problem import make_problem
    from quasisim.method.retarget import retarget
    from quasisim.optim.trajectory import Trajectory
    from quasisim.targets.scene import Placement

    demo = load_demo(write_example("cube_lift", tmp_path_factory.mktemp("demo"), n_frames=16))
    hand = load_hand("shadow")
    rt = retarget(hand, demo)
    prob = make_problem(demo, (Placement(hand, rt.base_rot),), 5, 64)
    soft = {"alpha": 0.0, "d_c": 0.01, "k_n": 4.0e5, "k_f": 1.0e6, "k_d": 1.0e3, "mu": 10.0}
    return prob, prob.params(soft), Trajectory.from_q(rt.q, prob.model.n_points)


def test_touching_moves_each_contact_so_that_it_pushes_as_before(soft_grasp) -> None:
    from helpers import STIFF
    from quasisim.method.stages.contact_curriculum import force_keeping_shift, state_depths, target_depths, touching
    from quasisim.optim.trajectory import simulate_jit

    prob, params, traj = soft_grasp
    stiff = prob.params(STIFF)
    opts = HandoffOptions(mode="every", iterations=10, damping=1.0e-5)
    new = touching(prob.model, params, stiff, traj, prob.base_quat, prob.base_rots, prob.demo.fps, prob.obj0, opts)
    states = simulate_jit(prob.model, params, traj, jnp.asarray(prob.base_quat, jnp.float32), prob.demo.fps, prob.obj0)
    contact = np.asarray(states.in_contact) > 0
    assert contact.sum() >= 10, "the retarget's grasp should touch the cube in the soft simulator"

    # closed form of the shift: a point hovering at d_c moves d_c (1 cm); one at the surface moves
    # (k_n / k_n') d_c = 1 mm; one pressing 5 mm in moves 3.5 mm out
    k = params.k_n / stiff.k_n
    shift = force_keeping_shift(jnp.array([0.01, 0.0, -0.005]), params.d_c, stiff.d_c, k)
    np.testing.assert_allclose(np.asarray(shift), [0.01, 0.001, -0.0035], atol=1e-7)

    phi = np.asarray(state_depths(prob.model, states))
    want = np.asarray(force_keeping_shift(phi, params.d_c, stiff.d_c, k))[contact]
    br = jnp.asarray(prob.base_rots, jnp.float32)
    before = np.asarray(target_depths(prob.model, br, traj.base[1:], traj.joints[1:], states))
    after = np.asarray(target_depths(prob.model, br, new.base[1:], new.joints[1:], states))
    moved = (before - after)[contact]
    assert np.abs(want).mean() > 1e-3, want  # the test asks for a real move
    # the least-squares goal: each contact moves its own shift; fingers are chains, so most of it
    assert np.median(np.abs(moved - want)) < 0.3 * np.abs(want).mean(), (moved, want)
    assert np.abs(moved - want).mean() < 0.5 * np.abs(want).mean()

    # the base targets, the start pose and every frame without a contact are untouched; limits hold
    np.testing.assert_array_equal(np.asarray(new.base), np.asarray(traj.base))
    np.testing.assert_array_equal(np.asarray(new.joints[0]), np.asarray(traj.joints[0]))
    idle = ~contact.any(axis=1)
    np.testing.assert_allclose(np.asarray(new.joints[1:])[idle], np.asarray(traj.joints[1:])[idle], atol=1e-6)
    assert idle.any() and not idle.all()
    hand = prob.placements[0].hand
    q, lo, hi = np.asarray(new.joints), hand.joint_range[:, 0], hand.joint_range[:, 1]
    assert np.all(~hand.joint_limited | ((q >= lo - 1e-6) & (q <= hi + 1e-6)))


def test_handoff_mode_is_validated(tmp_path: Path) -> None:
    from quasisim.errors import InputError
    from quasisim.method.config import TransferConfig

    with pytest.raises(InputError, match=r"stage2\.mode.*stiffest, every, none"):
        TransferConfig.from_yaml(overrides={"stage2.mode": "teleport"})
    assert TransferConfig.from_yaml(overrides={"stage2.mode": "none"}).stage2.mode == "none"


def test_checkpoints_before_the_handoff_are_shared_with_runs_without_it() -> None:
    """Changing the hand-off recomputes stage 2 from the first simulator it touches on, not before; mode
    ``none`` is stage 2 as it was before the option existed (same identities, so older runs stay valid)."""
    import dataclasses

    from quasisim.method.config import TransferConfig
    from quasisim.method.curriculum import load_curriculum
    from quasisim.method.stage import declared_stages
    from quasisim.pipeline import piece_scope as _piece_scope

    cur = load_curriculum("default")
    cur_settings = {k: v for k, v in dataclasses.asdict(cur).items() if k != "path"}

    def info(mode: str) -> dict:
        cfg = TransferConfig.from_yaml(overrides={"stage2.mode": mode})
        stages = ("1", "2", "sample", "select")
        return {
            "demo": "d",
            "curriculum_settings": cur_settings,
            "stages": list(stages),
            **cfg.identity("fast", declared_stages(stages)),
        }

    none, every, stiffest = info("none"), info("every"), info("stiffest")
    assert none["stage2"]["mode"] == "none" and stiffest["stage2"]["mode"] == "stiffest"
    assert cur.stiffest + 1 == 9 and cur.rigid[0] + 1 == 2
    for name, same_every, same_stiffest in [
        ("stage1_robot", True, True), ("stage2_sim02", True, True), ("stage2_sim03", False, True),
        ("stage2_sim08", False, True), ("stage2_sim09", False, False), ("sample", False, False),
    ]:  # fmt: skip
        assert (_piece_scope(every, name) == _piece_scope(none, name)) is same_every, name
        assert (_piece_scope(stiffest, name) == _piece_scope(none, name)) is same_stiffest, name
