"""Articulated dynamics (mass matrix, bias forces) against MuJoCo's mj_fullM and qfrc_bias."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from helpers import scene_with
from quasisim.sim.articulation import bias_forces, body_jacobians, mass_matrix


@pytest.mark.slow  # > 20 s on 2 cores (make test-fast stays under 2 minutes)
@pytest.mark.parametrize("hand_fixture", ["shadow", "allegro"])
def test_mass_matrix_and_bias_match_mujoco(hand_fixture: str, request: pytest.FixtureRequest) -> None:
    import mujoco

    from quasisim.targets.mujoco_target import MujocoModel

    hand = request.getfixturevalue(hand_fixture)
    R0 = Rotation.random(random_state=2).as_matrix()
    mm = MujocoModel(scene_with(hand, base_rot=R0), visual=False)
    m, d = mm.model, mujoco.MjData(mm.model)
    rng = np.random.default_rng(0)
    arm = np.concatenate([np.zeros(6), np.full(hand.n_joints, hand.config.pd.joint_armature)])
    with jax.enable_x64(True):
        for _ in range(4):
            q = np.concatenate([rng.uniform(-1, 1, 3), rng.uniform(-1.2, 1.2, 3), rng.uniform(*hand.joint_range.T)])
            qd = rng.normal(size=len(q))
            mm.set_state(d, q, np.array([3.0, 0, 0]), np.array([1.0, 0, 0, 0]))
            d.qvel[:] = 0
            d.qvel[mm.hand_dof] = qd
            mujoco.mj_forward(m, d)
            full = np.zeros((m.nv, m.nv))
            mujoco.mj_fullM(m, d, full)
            M_ref = full[np.ix_(mm.hand_dof, mm.hand_dof)]
            bj = body_jacobians(hand, None, None, jnp.asarray(q[6:]), base=jnp.asarray(q[:6]), base_rot=jnp.asarray(R0))
            M = np.asarray(mass_matrix(hand, bj, jnp.asarray(arm)))
            np.testing.assert_allclose(M, M_ref, atol=1e-10)
            b = bias_forces(
                hand,
                jnp.asarray(q),
                jnp.asarray(qd),
                jnp.asarray(arm),
                jnp.array([0.0, 0, -9.81]),
                base_rot=jnp.asarray(R0),
            )
            np.testing.assert_allclose(np.asarray(b), d.qfrc_bias[mm.hand_dof], atol=1e-9)


@pytest.mark.slow  # > 20 s on 2 cores (make test-fast stays under 2 minutes)
def test_point_jacobian_matches_autodiff(shadow) -> None:
    """The geometric Jacobian of a body origin equals d(position)/dq by forward-mode autodiff."""
    from quasisim.sim.kinematics import forward_kinematics

    rng = np.random.default_rng(1)
    q = jnp.asarray(rng.uniform(*shadow.joint_range.T))
    R = jnp.asarray(Rotation.random(random_state=4).as_matrix(), dtype=q.dtype)
    p = jnp.array([0.1, 0.2, 0.3], dtype=q.dtype)
    with jax.enable_x64(True):
        q, R, p = (jnp.asarray(np.asarray(a), dtype=jnp.float64) for a in (q, R, p))
        bj = body_jacobians(shadow, p, R, q)
        auto = jax.jacfwd(lambda qq: forward_kinematics(shadow, p, R, qq).pos)(q)
        np.testing.assert_allclose(np.asarray(bj.jv), np.asarray(auto), atol=1e-8)
