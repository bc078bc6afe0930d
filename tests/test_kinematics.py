"""Forward kinematics in JAX against MuJoCo's body and site positions; hand loading errors."""

from __future__ import annotations

from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from helpers import scene_with
from quasisim.assets.hand import HandConfig, load_hand
from quasisim.errors import InputError, QuasisimError
from quasisim.sim.kinematics import fk_full, keypoints


def _random_q(hand, rng: np.random.Generator) -> np.ndarray:
    lo = np.where(hand.joint_limited, hand.joint_range[:, 0], -np.pi)
    hi = np.where(hand.joint_limited, hand.joint_range[:, 1], np.pi)
    return np.concatenate([rng.uniform(-1, 1, 3), rng.uniform(-1.4, 1.4, 3), rng.uniform(lo, hi)])


@pytest.mark.parametrize("hand_fixture", ["shadow", "allegro"])
def test_fk_matches_mujoco(hand_fixture: str, request: pytest.FixtureRequest) -> None:
    import mujoco

    from quasisim.targets.mujoco_target import MujocoModel

    hand = request.getfixturevalue(hand_fixture)
    rng = np.random.default_rng(0)
    base_rot = Rotation.random(random_state=3).as_matrix()
    mm = MujocoModel(scene_with(hand, base_rot=base_rot), visual=False)
    d = mujoco.MjData(mm.model)
    for _ in range(10):
        q = _random_q(hand, rng)
        mm.set_state(d, q, np.array([2.0, 0, 0]), np.array([1.0, 0, 0, 0]))
        poses = fk_full(hand, jnp.asarray(base_rot), jnp.asarray(q))
        assert np.abs(np.asarray(poses.pos) - d.xpos[mm.hand_body]).max() < 1e-5
        assert np.abs(np.asarray(poses.rot) - d.xmat[mm.hand_body].reshape(-1, 3, 3)).max() < 1e-5
        assert np.abs(np.asarray(keypoints(hand, poses)) - d.site_xpos[mm.kp_site]).max() < 1e-5


def test_shadow_model(shadow) -> None:
    assert shadow.n_joints == 22 and shadow.body_names[0] == "robot0:palm"
    assert set(shadow.kp_human[shadow.kp_metric]) == {0, 4, 5, 8, 12, 16, 17, 20}
    assert 0.4 < shadow.total_mass < 1.0
    assert not any("forearm" in n for n in shadow.body_names)


@pytest.mark.slow  # > 20 s on 2 cores (make test-fast stays under 2 minutes)
def test_fk_gradient_matches_finite_differences(shadow) -> None:
    import jax

    q = jnp.asarray(_random_q(shadow, np.random.default_rng(1)), dtype=jnp.float32)
    R0 = jnp.eye(3)

    def f(q):
        return jnp.sum(keypoints(shadow, fk_full(shadow, R0, q))[:, 0])

    g = np.asarray(jax.grad(f)(q))
    eps = 1e-3
    fd = np.array([(f(q.at[i].add(eps)) - f(q.at[i].add(-eps))) / (2 * eps) for i in range(len(q))])
    np.testing.assert_allclose(g, fd, atol=2e-3)


def test_hand_config_errors(tmp_path: Path) -> None:
    good = Path(__file__).resolve().parents[1] / "src/quasisim/assets/hands/shadow.yaml"
    text = good.read_text()
    bad = tmp_path / "bad.yaml"
    bad.write_text(text.replace("root_body: robot0:palm", "root_body: robot0:nope"))
    with pytest.raises(InputError, match="root_body"):
        load_hand(bad)
    bad.write_text(text.replace("human: 20, site: robot0:S_lftip", "human: 21, site: robot0:S_lftip"))
    with pytest.raises(InputError, match=r"keypoints\[20\].human"):
        load_hand(bad)
    bad.write_text(text + "\nunknown_key: 3\n")
    with pytest.raises(InputError, match="unknown_key"):
        HandConfig.from_yaml(bad)
    bad.write_text(text.replace("model: gymnasium_robotics:hand/reach.xml", "model: nowhere/hand.xml"))
    with pytest.raises(InputError, match="QUASISIM_ROBOT_PATH"):
        load_hand(bad)
    with pytest.raises(QuasisimError, match=r"valid options: .*allegro, shadow"):
        load_hand("nohand")


def test_overrides(tmp_path: Path) -> None:
    cfg = HandConfig.from_yaml(
        Path(__file__).resolve().parents[1] / "src/quasisim/assets/hands/shadow.yaml", {"pd.joint.kp": 3.0}
    )
    assert cfg.pd.joint.kp == 3.0
