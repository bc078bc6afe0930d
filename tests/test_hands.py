"""The built-in hand variants: the short-thumb Shadow hand and the left Shadow hand in both targets' kinematics."""

from __future__ import annotations

import json

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from helpers import scene_with
from quasisim.assets.hand import builtin_hands, load_hand
from quasisim.sim.kinematics import fk_full, keypoints

THUMB = ("robot0:thbase", "robot0:thproximal", "robot0:thhub", "robot0:thmiddle", "robot0:thdistal")


def _rest_keypoints(hand) -> dict[str, np.ndarray]:
    q = np.concatenate([np.zeros(6), hand.rest_q()]).astype(np.float32)
    kp = np.asarray(keypoints(hand, fk_full(hand, np.eye(3), q)), dtype=np.float64)
    return dict(zip(hand.kp_names, kp, strict=True))


def test_builtin_hands_listed() -> None:
    assert {"shadow", "shadow-left", "shadow-short-thumb", "allegro"} <= set(builtin_hands())


def test_short_thumb_is_the_shadow_hand_with_half_a_thumb(shadow) -> None:
    short = load_hand("shadow-short-thumb")
    assert short.joint_names == shadow.joint_names and short.body_names == shadow.body_names
    np.testing.assert_array_equal(short.joint_range, shadow.joint_range)
    np.testing.assert_array_equal(short.joint_axis, shadow.joint_axis)
    thumb = np.array([n in THUMB for n in shadow.body_names])
    np.testing.assert_allclose(short.body_mass[thumb], shadow.body_mass[thumb] / 8)
    np.testing.assert_allclose(short.body_mass[~thumb], shadow.body_mass[~thumb])
    np.testing.assert_allclose(short.body_inertia[thumb], shadow.body_inertia[thumb] / 32)
    k_short, k_full = _rest_keypoints(short), _rest_keypoints(shadow)
    base = short.body_pos[short.body_names.index("robot0:thbase")]  # where the thumb sits on the palm
    np.testing.assert_allclose(base, shadow.body_pos[shadow.body_names.index("robot0:thbase")])
    for name in ("thumb_mcp", "thumb_ip", "thumb_tip"):
        np.testing.assert_allclose(k_short[name] - base, (k_full[name] - base) / 2, atol=1e-6)
    for name in ("index_tip", "middle_tip", "ring_tip", "little_tip", "wrist"):
        np.testing.assert_allclose(k_short[name], k_full[name], atol=1e-6)
    g_short = {g.name: g for g in short.geoms}
    for g in shadow.geoms:
        if g.body in np.flatnonzero(thumb) and g.vertices is not None:
            span = np.ptp(g.vertices, axis=0)
            np.testing.assert_allclose(np.ptp(g_short[g.name].vertices, axis=0), span / 2, atol=1e-6)


@pytest.mark.parametrize("name", ["shadow-left", "shadow-short-thumb"])
def test_fk_matches_mujoco_target(name: str) -> None:
    """The JAX kinematics and the MuJoCo target built from the edited hand agree (as for the shipped hands)."""
    import mujoco

    from quasisim.targets.mujoco_target import MujocoModel

    hand = load_hand(name)
    rng = np.random.default_rng(0)
    base_rot = Rotation.random(random_state=3).as_matrix()
    mm = MujocoModel(scene_with(hand, base_rot=base_rot), visual=False)
    d = mujoco.MjData(mm.model)
    lo, hi = hand.joint_range[:, 0], hand.joint_range[:, 1]
    for _ in range(5):
        q = np.concatenate([rng.uniform(-1, 1, 3), rng.uniform(-1.4, 1.4, 3), rng.uniform(lo, hi)])
        mm.set_state(d, q, np.array([2.0, 0, 0]), np.array([1.0, 0, 0, 0]))
        poses = fk_full(hand, jnp.asarray(base_rot), jnp.asarray(q))
        assert np.abs(np.asarray(poses.pos) - d.xpos[mm.hand_body]).max() < 1e-5
        assert np.abs(np.asarray(keypoints(hand, poses)) - d.site_xpos[mm.kp_site]).max() < 1e-5


@pytest.mark.parametrize("name", ["shadow-left", "shadow-short-thumb"])
def test_pybullet_link_frames_match_fk(name: str) -> None:
    """PyBullet's hand, assembled from the edited hand model, has the links where the JAX kinematics puts them."""
    pytest.importorskip("pybullet")
    from test_pybullet_target import _check_fk

    _check_fk(load_hand(name))


@pytest.mark.slow
# the short thumb is the Shadow hand with edited thumb links (its kinematics: the FK tests above); its whole
# transfer runs in make test-all
@pytest.mark.parametrize("name", ["allegro", pytest.param("shadow-short-thumb", marks=pytest.mark.extended)])
def test_transfer_runs_with_other_hands(name: str, tmp_path, request: pytest.FixtureRequest) -> None:
    """The whole method with another hand: stages 1 and 2 (tiny budget and curriculum) and sample-target
    on a short synthetic clip; outputs in that hand's joints, judged in MuJoCo, reproducible by replay; ours
    does better in MuJoCo than the kinematic replay of the clip."""
    from quasisim.data.controls import load_controls
    from quasisim.data.demo import load_demo
    from quasisim.data.synthetic import write_example
    from quasisim.eval.evaluate import evaluate_controls
    from quasisim.method.config import TransferConfig
    from quasisim.method.spec import TransferSpec
    from quasisim.pipeline import run_transfer
    from test_transfer import CURRICULUM, TINY

    if name == "allegro":
        request.getfixturevalue("allegro")  # skips when the URDF is absent
    hand = load_hand(name)
    demo = write_example("cube_lift", tmp_path / "demo", n_frames=16)
    (tmp_path / "tiny.yaml").write_text(CURRICULUM)
    cfg = TransferConfig.from_yaml(overrides={**TINY, "sampling.samples": 6, "sampling.horizon": 3})
    for method in ("ours", "sample-target"):  # ours: the default stages 1, 2, sample, select
        spec = TransferSpec(
            hand=name, method=method, curriculum=str(tmp_path / "tiny.yaml"), render=False, progress=False
        )
        res = run_transfer(demo, tmp_path / method, spec, cfg)
        c = load_controls(tmp_path / method / "controls.npz")
        assert c.hand == name and c.joint_names == hand.joint_names and c.q_targets.shape == (16, 6 + hand.n_joints)
        assert np.isfinite([res.metrics["R_err_deg"], res.metrics["T_err_cm"], res.metrics["MPJPE_mm"]]).all()
        assert evaluate_controls(load_demo(demo), c, "mujoco", None, render=False).metrics == res.metrics
        summary = json.loads((tmp_path / method / "summary.json").read_text())
        m, km = summary["metrics"], summary["kinematic_metrics"]  # the run and the kinematic replay, in MuJoCo
        assert m == res.metrics and km == res.kinematic_metrics
        if method == "ours":
            _beats_the_kinematic_replay(name, c, m, km)
        # sample-target (6 samples, horizon 3) does not beat the kinematic replay on this clip: measured with
        # Allegro T_err 3.280 vs 3.278 cm, R_err 1.10 vs 0.84 deg; with the short thumb it is the replay itself


def _beats_the_kinematic_replay(name: str, c, m: dict, km: dict) -> None:
    """Ours against the kinematic replay of the clip, both judged in MuJoCo. Measured (16-frame cube lift):
    Allegro lifts the cube 9.0 cm of the demo's 12 (the replay 0.4): T_err 1.62 vs 3.28 cm, whole-clip
    objective 0.0369 vs 0.0495, but R_err 6.4 vs 0.8 deg; without the sampling stage's back-ups the short
    thumb moves the cube in neither (T_err 3.27 cm and R_err 0 in both) and tracks the hand closer: MPJPE
    9.19 vs 9.68 mm, objective 0.04405 vs 0.04458; with them it pushes the cube closer to the demo's path:
    T_err 2.16 vs 3.27 cm, R_err 2.6 vs 0 deg; with them and the kinematic pre-screen (both the default since
    2026-11-27, 6 of 12 drawn windows rolled out) it moves the cube in neither again and tracks the hand
    closer: MPJPE 9.52 vs 9.68 mm, objective 0.04443 vs 0.04458. So: a trajectory cheaper than the replay's."""
    costs = json.loads(str(c.extras["selection_costs"]))
    selected = str(c.extras["selected"])
    assert selected != "kinematic" and costs[selected] < costs["kinematic"], costs
    assert m["T_err_cm"] <= km["T_err_cm"] + 1e-3, (m, km)  # never further from the demo's object path
    if name == "allegro":
        assert m["T_err_cm"] < 0.75 * km["T_err_cm"] and costs[selected] < 0.85 * costs["kinematic"], (m, km, costs)
        assert m["object_motion"]["lift_cm"] > km["object_motion"]["lift_cm"] + 5.0
    elif m["T_err_cm"] > km["T_err_cm"] - 0.1:  # a tie in T_err and R_err: the hand's own tracking decides
        assert m["R_err_deg"] <= km["R_err_deg"] + 1e-3 and m["MPJPE_mm"] < km["MPJPE_mm"] - 0.1, (m, km)
