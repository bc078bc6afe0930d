"""Two-handed demos: the two-hand MuJoCo scene (layout, keypoints as the retarget computes them, the left
hand the mirror image of the right), controls, the whole method with two hands."""

from __future__ import annotations

import numpy as np
import pytest

from helpers import box_object, scene_with

M = np.diag([-1.0, 1.0, 1.0])  # Shadow's mirror_axis is x; base frames chosen so the root frame's x is world x


@pytest.fixture(scope="module")
def two_hand_scene(shadow):
    from quasisim.assets.hand import load_hand
    from quasisim.targets.scene import place_hands

    left = load_hand("shadow", side="left")
    sc = scene_with(shadow, box_object(), object_pos=(2.0, 0.0, 0.825))
    B = _rot(0.3, -0.2, 0.5)
    return sc.__class__(**{**sc.__dict__, "placements": place_hands((shadow, left), (B, M @ B @ M))})


def _rot(a: float, b: float, c: float) -> np.ndarray:
    from quasisim.rotations import euler_xyz_to_mat

    return np.asarray(euler_xyz_to_mat(np.array([a, b, c])), np.float64)


def _retarget_kp(hand, base_rot: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Keypoints (K, 3) as the kinematic retarget computes them (its forward kinematics)."""
    import jax.numpy as jnp

    from quasisim.rotations import euler_xyz_to_mat
    from quasisim.sim.kinematics import forward_kinematics, keypoints

    q = jnp.asarray(q)
    R = jnp.asarray(base_rot) @ euler_xyz_to_mat(q[3:6])
    return np.asarray(keypoints(hand, forward_kinematics(hand, q[:3], R, q[6:])), np.float64)


def _random_q(hand, rng: np.random.Generator) -> np.ndarray:
    lo, hi = hand.joint_range[:, 0], hand.joint_range[:, 1]
    return np.r_[rng.uniform(-0.3, 0.3, 3) + np.array([0, 0, 1.2]), rng.uniform(-0.5, 0.5, 3), rng.uniform(lo, hi)]


def test_two_hand_scene_layout(two_hand_scene, shadow) -> None:
    import mujoco

    from quasisim.targets.mujoco_target import MujocoModel

    sc = two_hand_scene
    J = shadow.n_joints
    assert sc.prefixes == ("rhand/", "lhand/") and sc.n_dof == 2 * (6 + J)
    assert sc.dof_slices == (slice(0, 6 + J), slice(6 + J, 12 + 2 * J))
    K = len(shadow.kp_names)
    np.testing.assert_array_equal(sc.kp_human, np.r_[shadow.kp_human, shadow.kp_human + 21])
    mm = MujocoModel(sc, visual=False)
    m = mm.model
    assert m.nq == 2 * (6 + J) + 7 and m.nu == 2 * 2 * (6 + J) and len(mm.kp_site) == 2 * K
    names = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(m.njnt)]
    assert names[0] == "rhand/base_tx" and names[6 + J] == "lhand/base_tx" and names[-1] == "object_free"
    np.testing.assert_array_equal(mm.hand_qpos, np.arange(2 * (6 + J)))  # [right (6 + J), left (6 + J)]


def test_keypoints_match_the_retarget_and_left_is_the_mirror_image(two_hand_scene) -> None:
    import mujoco

    from quasisim.targets.mujoco_target import MujocoModel

    sc = two_hand_scene
    mm = MujocoModel(sc, visual=False)
    d = mujoco.MjData(mm.model)
    rng = np.random.default_rng(0)
    right, left = sc.hands
    q_r = _random_q(right, rng)
    # the mirrored pose: base position reflected, base angles (a, b, c) -> (a, -b, -c), the same joint angles
    q_l = np.r_[M @ q_r[:3], q_r[3], -q_r[4], -q_r[5], q_r[6:]]
    mm.set_state(d, np.r_[q_r, q_l], sc.object_pos0, sc.object_quat0)
    kp = d.site_xpos[mm.kp_site]
    K = len(right.kp_names)
    np.testing.assert_allclose(kp[:K], _retarget_kp(right, sc.base_rots[0], q_r), atol=2e-5)
    np.testing.assert_allclose(kp[K:], _retarget_kp(left, sc.base_rots[1], q_l), atol=2e-5)
    np.testing.assert_allclose(kp[K:], kp[:K] @ M.T, atol=1e-9)  # the left hand is the reflection
    assert np.abs(kp[K:] - kp[:K]).max() > 0.05  # and not the same hand


def test_two_hand_rollout_records_both_hands(two_hand_scene) -> None:
    from quasisim.targets import make_target

    sc = two_hand_scene
    q = np.tile(np.r_[_random_q(sc.hands[0], np.random.default_rng(1))], (5, 1))
    q = np.concatenate([q, q * np.r_[-1, np.ones(sc.n_dof // 2 - 1)]], axis=1)  # left hand at mirrored x
    r = make_target("mujoco", sc).rollout(q)
    K = len(sc.hands[0].kp_names)
    assert r.qpos.shape == (5, sc.n_dof) and r.keypoints.shape == (5, 2 * K, 3)
    assert r.human_keypoint_index.max() > 21 and r.human_keypoint_index.min() < 21
    with pytest.raises(ValueError, match=str(sc.n_dof)):
        make_target("mujoco", sc).rollout(q[:, : sc.n_dof // 2])


def test_pybullet_two_hands_match_mujoco(two_hand_scene) -> None:
    """PyBullet builds both hands (one multibody each): the same keypoints as MuJoCo at the same state, and
    each hand tracks its own PD targets."""
    from quasisim.targets import make_target

    sc = two_hand_scene
    rng = np.random.default_rng(2)
    q0 = np.r_[_random_q(sc.hands[0], rng), _random_q(sc.hands[1], rng)]
    q0[sc.dof_slices[1].start] -= 0.5  # the hands apart
    q = np.tile(q0, (4, 1))
    q[:, sc.dof_slices[1].start + 2] += np.linspace(0.0, 0.03, 4)  # the left hand rises 3 cm
    mj = make_target("mujoco", sc).rollout(q)
    with make_target("pybullet", sc) as tgt:
        assert len(tgt.parts) == 2
        pb = tgt.rollout(q)
    np.testing.assert_allclose(pb.keypoints[0], mj.keypoints[0], atol=1e-6)  # both hands, frame 0
    assert pb.qpos.shape == (4, sc.n_dof) and np.array_equal(pb.kp_human, mj.kp_human)
    np.testing.assert_allclose(pb.qpos[:, :3], q[:, :3], atol=0.003)  # the right hand stays
    np.testing.assert_allclose(pb.qpos[:, sc.dof_slices[1]][:, :3], q[:, sc.dof_slices[1]][:, :3], atol=0.003)


def test_sampling_over_both_hands() -> None:
    """Noise and bounds per column of both hands; the smoothness term averages both bases, then all joints."""
    import dataclasses

    from quasisim.method.config import TransferConfig
    from quasisim.method.options import SamplingOptions
    from quasisim.method.stages.sampling import Prediction, noise_std, sample_windows, window_costs

    opts = SamplingOptions(
        samples=300, horizon=3, knots=2, noise_base_pos=0.004, noise_base_rot=0.04, noise_joints=0.5,
        noise_scales=(1.0,), mode="predictive", temperature=0.003, seed=0, threads=1, kinematic_alternative=False,
    )  # fmt: skip
    std = noise_std(opts, (2, 2))
    np.testing.assert_allclose(std, [0.004] * 3 + [0.04] * 3 + [0.5] * 2 + [0.004] * 3 + [0.04] * 3 + [0.5] * 2)
    lo = np.r_[np.full(6, -np.inf), -1.0, -1.0, np.full(6, -np.inf), 0.0, 0.0]
    hi = -lo
    hi[14:] = 0.2  # the left hand's joints within [0, 0.2]
    w = sample_windows(np.random.default_rng(0), np.zeros((4, 16)), opts, lo, hi, std)
    assert w[:, :, 14:].min() == 0.0 and w[:, :, 14:].max() == 0.2 and w[:, :, 6:8].min() == -1.0
    assert np.abs(w[:, :, 8:11]).max() < 0.05  # the left base position gets base noise, not the joints'
    # smoothness: a second difference 0.1 in the left hand's base x (column 8) counts as a base column
    wins = np.zeros((1, 4, 16))
    wins[0, 2, 8] = 0.1
    pred = Prediction(np.zeros((1, 3, 16)), np.zeros((1, 3, 3)), np.tile([1.0, 0, 0, 0], (1, 3, 1)),
                      np.zeros((1, 3, 2, 3)), 0)  # fmt: skip
    W = dataclasses.replace(TransferConfig.from_yaml().weights, smooth=1.0)
    ref = (np.zeros((3, 3)), np.tile([1.0, 0, 0, 0], (3, 1)), np.zeros((3, 2, 3)), np.ones(3))
    c = window_costs(wins, pred, *ref, W, base_cols=np.r_[0:6, 8:14])
    c0 = window_costs(np.zeros_like(wins), pred, *ref, W, base_cols=np.r_[0:6, 8:14])  # the tracking terms
    np.testing.assert_allclose(c - c0, [(0.01 + 0.04) / (2 * 12)], rtol=1e-5)  # mean over the 12 base columns


# ---- the command line: a synthetic two-hand clip, refusals ---------------------------------------------


@pytest.fixture(scope="module")
def two_hand_clip(tmp_path_factory):
    from quasisim.data.synthetic import write_example

    return write_example("cube_lift", tmp_path_factory.mktemp("two"), n_frames=12, two_hands=True)


def _cli(*args: str):
    from click.testing import CliRunner

    from quasisim.cli import main

    return CliRunner().invoke(main, list(args))


OURS = ("1", "2", "sample", "select")


@pytest.mark.slow
@pytest.mark.parametrize(
    "stages", [OURS, pytest.param(("1", "2", "3", "mpc", "sample", "select"), marks=pytest.mark.extended)]
)
def test_ours_two_hands_end_to_end(two_hand_clip, tmp_path, stages: tuple[str, ...]) -> None:
    """The default method (stages 1 and 2 with both hands in the quasi-physical simulator, sampling and the
    selection in MuJoCo) and, as an extended test, every stage (with 3 fitting the simulator to MuJoCo with
    its networks, and MPC) on the synthetic two-hand clip, with tiny budgets: the controls drive both hands,
    stage 1's human points pair with robot points of their own hand, and the result, judged in MuJoCo, beats
    the kinematic replay of the clip there."""
    import json

    from quasisim.data.controls import load_controls
    from quasisim.data.demo import load_demo
    from quasisim.eval.evaluate import evaluate_controls
    from quasisim.method.config import TransferConfig
    from quasisim.method.spec import TransferSpec
    from quasisim.pipeline import run_transfer
    from test_transfer import CURRICULUM, TINY

    (tmp_path / "tiny.yaml").write_text(CURRICULUM)
    more = {"sampling.samples": 4, "sampling.horizon": 3, "mpc.steps": 1, "mpc.horizon": 2,
            "stage3.steps": 2, "stage3.variants": 1, "stage3.horizon": 3, "stage3.batch": 4, "stage3.rounds": 1,
            "stage3.residual_steps": 2}  # fmt: skip
    cfg = TransferConfig.from_yaml(overrides={**TINY, **more})
    spec = TransferSpec(
        curriculum=str(tmp_path / "tiny.yaml"), stages=stages, render=False,
        progress=False, robust=2,
    )  # fmt: skip
    out = tmp_path / "ours"
    res = run_transfer(two_hand_clip, out, spec, cfg)
    c = load_controls(out / "controls.npz")
    J = 22
    assert c.sides == ("right", "left") and c.q_targets.shape == (12, 2 * (6 + J))
    if "mpc" in stages:  # the quasi-physical rollout put each hand where its own PD targets are (bases within 2 cm)
        assert c.extras["sim_qpos"].shape == c.extras["plan_q"].shape == (12, 2 * (6 + J))
        plan, sim = c.extras["plan_q"], c.extras["sim_qpos"]
        for sl in (slice(0, 3), slice(6 + J, 9 + J)):
            assert np.abs(sim[:, sl] - plan[:, sl]).max() < 0.02
    hp = np.load(out / "checkpoints" / "stage1_human.npz")
    assert set(np.unique(hp["point_hand"]).tolist()) == {0, 1}
    summary = json.loads((out / "summary.json").read_text())
    assert summary["hand"] == "shadow + shadow-left" and len(summary["simulators"]) == 2  # the rigid ones
    if "3" in stages:
        assert np.all(np.isfinite(summary["stage3"]["held_out_after"])) and summary["stage3"]["networks"] == [
            "local", "global", "control"
        ]  # fmt: skip
    from quasisim.eval.robust import replays

    m = res.metrics
    assert m["robust"]["n"] == 2
    assert np.isfinite([m["R_err_deg"], m["T_err_cm"], m["MPJPE_mm"]]).all()
    again = evaluate_controls(load_demo(two_hand_clip), c, "mujoco", None, render=False, robust=replays(2))
    assert again.metrics == m  # robust success too: the perturbed replays are seeded
    # the result beats the kinematic replay of the clip, both judged in MuJoCo (summary.json); measured:
    # R_err 0.96 vs 21.4 deg, T_err 0.51 vs 0.85 cm, whole-clip objective 0.011 vs 0.080
    assert summary["metrics"] == m
    km = summary["kinematic_metrics"]
    assert m["R_err_deg"] < 0.5 * km["R_err_deg"] and m["T_err_cm"] < km["T_err_cm"], (m, km)
    costs = json.loads(str(c.extras["selection_costs"]))
    assert str(c.extras["selected"]) != "kinematic" and costs[str(c.extras["selected"])] < 0.5 * costs["kinematic"]


def test_kinematic_two_hands_end_to_end(two_hand_clip, tmp_path) -> None:
    """retarget -> evaluate (MuJoCo) of the synthetic two-hand clip; one-hand controls refused for it."""
    from quasisim.data.controls import load_controls

    r = _cli("retarget", str(two_hand_clip), "--out", str(tmp_path / "rt"))
    assert r.exit_code == 0, r.output
    c = load_controls(tmp_path / "rt" / "kinematic.npz")
    assert c.sides == ("right", "left") and c.q_targets.shape == (12, 2 * (6 + 22))
    r = _cli("evaluate", str(two_hand_clip), str(tmp_path / "rt" / "kinematic.npz"), "--out", str(tmp_path / "ev"),
             "--no-render")  # fmt: skip
    assert r.exit_code == 0, r.output
    z = np.load(tmp_path / "ev" / "rollout.npz")
    idx = z["human_keypoint_index"]
    assert z["robot_keypoints"].shape == (12, len(idx), 3) and len(idx) == 16
    np.testing.assert_array_equal(idx[8:], idx[:8] + 21)  # the left hand's: 21..41
    import json

    m = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    assert np.isfinite([m["R_err_deg"], m["T_err_cm"], m["MPJPE_mm"], m["CD_mm"]]).all()
    assert m["MPJPE_mm"] < 30.0  # both hands retargeted to their own keypoints (the mirrored one too)
    r = _cli("evaluate", str(two_hand_clip), str(tmp_path / "rt" / "kinematic.npz"), "--out", str(tmp_path / "pb"),
             "--target", "pybullet", "--no-render", "--robust", "0")  # fmt: skip
    assert r.exit_code == 0, r.output
    m_pb = json.loads((tmp_path / "pb" / "metrics.json").read_text())
    assert np.isfinite(m_pb["MPJPE_mm"]) and len(np.load(tmp_path / "pb" / "rollout.npz")["human_keypoint_index"]) == 16
    one = c.__class__(**{**c.__dict__, "base_rots": c.base_rots[:1], "q_targets": c.q_targets[:, :28]})
    one.save(tmp_path / "one.npz")
    r = _cli("evaluate", str(two_hand_clip), str(tmp_path / "one.npz"), "--out", str(tmp_path / "o1"))
    assert r.exit_code == 2 and "field 'left_base_rot'" in r.output and "controls for 2 hand(s)" in r.output


# ---- a real bimanual clip (ARCTIC, research-only: read from $QUASISIM_DATA/arctic, never copied) ---------


@pytest.fixture(scope="module")
def arctic_clip():
    from conftest import ARCTIC_CLIP as p
    from helpers import missing_data

    if not p.is_file():
        missing_data(f"ARCTIC clip not found at {p} (set QUASISIM_DATA to the folder that holds arctic/)")
    return p


@pytest.mark.slow
@pytest.mark.parametrize("method", ["kinematic", "sample-target"])
def test_arctic_transfer_end_to_end(arctic_clip, tmp_path, method) -> None:
    """`transfer` on a real two-hand clip: both hands' keypoints judged; the kinematic method's result is the
    kinematic replay, and sample-target's does better than it in MuJoCo."""
    import json

    out = tmp_path / method
    more = ("--set", "sampling.samples=4") if method == "sample-target" else ()
    r = _cli("transfer", str(arctic_clip), "--method", method, "--out", str(out), "--no-render", *more)
    assert r.exit_code == 0, r.output
    for f in ("controls.npz", "metrics.json", "rollout.npz", "report.html", "summary.json", "manifest.json"):
        assert (out / f).is_file(), f
    z = np.load(out / "rollout.npz")
    idx = z["human_keypoint_index"]
    assert idx.min() < 21 <= idx.max() <= 41 and z["robot_keypoints"].shape == (60, len(idx), 3)
    assert set(idx.tolist()) == set((idx[idx < 21]).tolist()) | set((idx[idx < 21] + 21).tolist())
    m = json.loads((out / "metrics.json").read_text())
    assert np.isfinite([m["R_err_deg"], m["T_err_cm"], m["MPJPE_mm"], m["CD_mm"]]).all() and not m["unstable"]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["hand"] == "shadow + shadow-left" and summary["metrics"] == m
    km = summary["kinematic_metrics"]  # the kinematic replay of the clip, judged in the same MuJoCo scene
    if method == "kinematic":  # the run is that replay
        assert m == km
    else:  # sampling in MuJoCo beats the replay; measured: T_err 0.43 vs 0.89 cm, R_err 1.70 vs 2.52 deg
        assert m["T_err_cm"] < 0.75 * km["T_err_cm"] and m["R_err_deg"] < 0.85 * km["R_err_deg"], (m, km)


@pytest.mark.slow
def test_the_simulator_follows_mujoco_with_two_hands(two_hand_clip) -> None:
    """The quasi-physical simulator (the stiffest of the default curriculum, the fast budget's step), put into
    each window's MuJoCo state, follows the kinematic retarget's PD targets as MuJoCo does with both hands:
    keypoints within a few mm after 2 frames, no window diverges, the object errors finite."""
    from quasisim.data.demo import load_demo
    from quasisim.method.config import TransferConfig
    from quasisim.method.curriculum import load_curriculum
    from quasisim.method.problem import kinematic_problem
    from quasisim.method.replay import collect, prediction_errors, windows

    demo = load_demo(two_hand_clip)
    bud, cur = TransferConfig.from_yaml().budget("fast"), load_curriculum("default")
    prob, q_kin = kinematic_problem(demo, "shadow", bud.substeps, bud.n_candidates)
    assert q_kin.shape == (12, 2 * (6 + 22))
    buf = collect(prob.scene, [q_kin], demo.fps)
    w = windows(prob.model, buf, [(0, t) for t in range(demo.n_frames - 2)], 2, prob.base_quat)
    e = prediction_errors(prob.model, prob.params(cur.contact(cur.stiffest)), w, demo.fps, prob.base_quat)
    assert e.n_windows == 12 - 2 and e.n_diverged == 0
    assert e.keypoints_mm[-1] < 10.0 and np.isfinite([e.obj_pos_cm[-1], e.obj_rot_deg[-1]]).all()
