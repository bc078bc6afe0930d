"""Control parameterisation, objective pieces, Adam loop and identification of S (quasisim.optim)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from helpers import STIFF
from quasisim.errors import InputError, QuasisimError
from quasisim.method.curriculum import load_curriculum
from quasisim.optim.adam import adam_steps
from quasisim.optim.sysid import SysID
from quasisim.optim.trajectory import Trajectory, root_quats, sim_controls
from quasisim.rotations import quat_log


def test_quat_log_matches_scipy() -> None:
    rng = np.random.default_rng(0)
    for _ in range(20):
        axis = rng.normal(size=3)
        rv = axis / np.linalg.norm(axis) * rng.uniform(0.0, 3.0)  # shortest arc: angle < pi
        xyzw = Rotation.from_rotvec(rv).as_quat()
        q = np.array([xyzw[3], *xyzw[:3]])
        np.testing.assert_allclose(np.asarray(quat_log(jnp.asarray(q))), rv, atol=1e-5)
        np.testing.assert_allclose(np.asarray(quat_log(jnp.asarray(-q))), rv, atol=1e-5)  # sign-invariant
    np.testing.assert_allclose(np.asarray(quat_log(jnp.array([1.0, 0, 0, 0]))), 0.0, atol=1e-7)
    g = jax.grad(lambda q: jnp.sum(quat_log(q)))(jnp.array([1.0, 0, 0, 0]))
    assert np.all(np.isfinite(np.asarray(g)))


def test_root_quats_match_euler_convention() -> None:
    from quasisim.rotations import euler_xyz_to_mat, np_mat_to_quat, quat_to_mat

    rng = np.random.default_rng(1)
    base_rot = Rotation.random(random_state=2).as_matrix()
    base = np.concatenate([rng.normal(size=(5, 3)), rng.uniform(-1, 1, size=(5, 3))], axis=1)
    q = root_quats(jnp.asarray(base, jnp.float32), jnp.asarray(np_mat_to_quat(base_rot), jnp.float32))
    assert q.shape == (5, 1, 4)  # one hand
    R = np.asarray(quat_to_mat(q[:, 0]))
    R_ref = base_rot @ np.asarray(euler_xyz_to_mat(jnp.asarray(base[:, 3:])))
    np.testing.assert_allclose(R, R_ref, atol=1e-5)


@pytest.mark.parametrize("H", [1, 2])
def test_sim_controls_integrate_back_to_the_targets(H: int) -> None:
    """Integrating each hand's root velocities over a frame lands on the next frame's base targets."""
    from quasisim.rotations import np_mat_to_quat, quat_mul, quat_to_mat

    rng = np.random.default_rng(3)
    T, J, fps = 6, 4, 20.0
    base = np.cumsum(rng.normal(scale=[0.01, 0.01, 0.01, 0.05, 0.05, 0.05] * H, size=(T, 6 * H)), axis=0)
    joints = rng.normal(size=(T, J))
    traj = Trajectory(jnp.asarray(base, jnp.float32), jnp.asarray(joints, jnp.float32), jnp.zeros((T - 1, 2, 3)))
    bq = jnp.asarray(np_mat_to_quat(Rotation.random(H, random_state=4).as_matrix()), jnp.float32)
    c = sim_controls(traj, bq, fps)
    rq = root_quats(traj.base, bq)
    assert c.root_vel.shape == c.root_angvel.shape == (T - 1, H, 3) and rq.shape == (T, H, 4)
    for t in range(T - 1):
        for h in range(H):
            b = base[:, 6 * h : 6 * h + 3]
            np.testing.assert_allclose(b[t] + np.asarray(c.root_vel[t, h]) / fps, b[t + 1], atol=1e-5)
            w = np.asarray(c.root_angvel[t, h]) / fps
            ang = np.linalg.norm(w)
            dq = jnp.asarray([np.cos(ang / 2), *(np.sin(ang / 2) * w / max(ang, 1e-12))], jnp.float32)
            np.testing.assert_allclose(
                np.asarray(quat_to_mat(quat_mul(dq, rq[t, h]))), np.asarray(quat_to_mat(rq[t + 1, h])), atol=1e-5
            )
    np.testing.assert_allclose(np.asarray(c.q_target), joints[1:], atol=1e-6)
    np.testing.assert_allclose(np.asarray(c.qd_target), np.diff(joints, axis=0) * fps, atol=1e-4)


def test_adam_steps_keeps_the_best_iterate_and_stops_early() -> None:
    target = jnp.array([1.0, -2.0])

    def vg(x):
        f = lambda y: (jnp.sum((y - target) ** 2), {"sq": jnp.sum((y - target) ** 2)})  # noqa: E731
        return jax.value_and_grad(f, has_aux=True)(x)

    x, log = adam_steps(vg, jnp.zeros(2), steps=400, lr=0.05, patience=10, min_rel_improvement=1e-3)
    assert log.best < 1e-3 and float(jnp.sum((x - target) ** 2)) == pytest.approx(log.best)
    assert log.best == min(log.losses)
    # a loss that never improves stops after `patience` steps and returns the start
    x2, log2 = adam_steps(lambda x: ((jnp.sum(x) * 0 + 1.0, {}), jnp.ones_like(x)), jnp.zeros(2), 100, 0.1, 5, 1e-3)
    assert log2.stopped_early and len(log2.losses) == 6 and np.allclose(np.asarray(x2), 0.0)


def test_sysid_describe_round_trips() -> None:
    s = SysID.init(lin_damp=0.5, ang_damp=0.2)
    d = s.describe(0.1)
    assert d["mass_kg"] == pytest.approx(0.1) and d["inertia_scale"] == pytest.approx(1.0)
    assert d["lin_damp"] == pytest.approx(0.5, rel=1e-4) and d["ang_damp"] == pytest.approx(0.2, rel=1e-4)


@pytest.mark.slow  # > 20 s on 2 cores (make test-fast stays under 2 minutes)
def test_identification_recovers_damping(shadow, tmp_path) -> None:
    """S from a rollout: an object falls with linear damping 3/s while the hand holds still far away;
    identification starting from 0.1/s recovers it through the simulator's gradient."""
    import trimesh

    from quasisim.assets.object import load_object
    from quasisim.sim.build import SimOptions, build_model, default_params
    from quasisim.sim.step import initial_state, object_pose, rollout
    from quasisim.sim.types import Control
    from quasisim.targets.scene import Table

    trimesh.creation.box(extents=(0.04, 0.04, 0.04)).export(tmp_path / "cube.obj")
    cube = load_object(tmp_path / "cube.obj", density=500.0)
    opts = SimOptions(dt=0.005, substeps=10, n_candidates=16, point_spacing=0.02)
    model = build_model(shadow, cube, Table(-0.1, 0.1, -0.1, 0.1, -5.0), opts, offset=np.zeros(3))
    params = default_params(model, cube.mass, cube.inertia, STIFF)
    s0 = initial_state(model, jnp.array([0.0, 0.5, 0.5]), jnp.array([1.0, 0, 0, 0]), shadow.rest_q(),
                       jnp.zeros(3), jnp.array([1.0, 0, 0, 0]))  # fmt: skip
    F, J = 4, shadow.n_joints
    z = jnp.zeros((F, J))
    q = jnp.broadcast_to(jnp.asarray(shadow.rest_q(), jnp.float32), (F, J))
    ctrl = Control(jnp.zeros((F, 1, 3)), jnp.zeros((F, 1, 3)), z, q, z, jnp.zeros((F, model.n_points, 3)))

    def traj(sid: SysID) -> jax.Array:
        return object_pose(model, rollout(model, sid.apply(params, cube.mass, cube.inertia), s0, ctrl))[0]

    ref = traj(SysID.init(lin_damp=3.0))
    loss = jax.jit(jax.value_and_grad(lambda sid: (jnp.mean(jnp.sum((traj(sid) - ref) ** 2, -1)) * 1e4, {})[0]))

    def value_and_grad(s: SysID) -> tuple[tuple[jax.Array, dict], SysID]:
        v, g = loss(s)  # one evaluation per step
        return (v, {}), g

    sid, log = adam_steps(value_and_grad, SysID.init(lin_damp=0.1), 150, 0.1, 30, 1e-4)
    assert sid.describe(cube.mass)["lin_damp"] == pytest.approx(3.0, rel=0.05), sid.describe(cube.mass)
    assert log.best < 1e-3 * log.losses[0]


def test_curricula_are_the_papers_tables() -> None:
    d = load_curriculum("default")
    assert [s.d_c for s in d.stages] == [0.1, 0.1, 0.05, 0.03, 0.025, 0.02, 0.015, 0.01, 0.0, 0.0]
    assert [s.k_n for s in d.stages] == [4e4, 4e4, 8e4, 1e5, 2e5, 3e5, 3.5e5, 4e5, 4e6, 4e6]
    assert [s.alpha for s in d.stages] == [0.1] + [0.0] * 9
    assert [s.residual for s in d.stages] == [False] * 9 + [True]
    c2 = load_curriculum("curriculum2")
    assert [s.d_c for s in c2.stages] == [0.1, 0.1, 0.05, 0.02, 0.01, 0.0, 0.0]
    assert [s.d_c for s in load_curriculum("none").stages] == [0.0, 0.0]
    with pytest.raises(QuasisimError, match="curriculum2, default, lean, none"):
        load_curriculum("soft")


def test_transfer_config_validation(tmp_path) -> None:
    from quasisim.method.config import TransferConfig
    from quasisim.method.spec import parse_stages

    cfg = TransferConfig.from_yaml(overrides={"budgets.fast.sim.control_steps": 3})
    assert cfg.budget("fast").sim.control_steps == 3 and cfg.budget("paper").sim.sysid_steps == 1000
    with pytest.raises(QuasisimError, match="valid options: fast, paper"):
        cfg.budget("slow")
    with pytest.raises(InputError, match=r"budgets\.fast\.sim"):
        TransferConfig.from_yaml(overrides={"budgets.fast.sim.control_lr": -1.0})
    with pytest.raises(InputError, match=r"weights\.obj_pos"):
        TransferConfig.from_yaml(overrides={"weights.obj_pos": "heavy"})
    bad = tmp_path / "t.yaml"
    bad.write_text("weights: {obj_pos: 1.0}\nbudgets: {}\nfoo: 1\n")
    with pytest.raises(InputError, match="foo"):
        TransferConfig.from_yaml(bad)
    assert parse_stages("2,1") == ("1", "2")
    with pytest.raises(QuasisimError, match="valid stages: quick, 1, 2, 3, neural, control_vae, mpc, sample"):
        parse_stages("1,4")


def test_restart_guard_skips_diverged_and_repeated_starts_and_stage_2_goes_on() -> None:
    """A start whose loss is not finite loses to any finite one, equal starts are evaluated once; a simulator
    whose first evaluation diverged (no loss recorded, measured on a real clip) is reported and the run goes
    on with its start."""
    from quasisim.method.curriculum import load_curriculum
    from quasisim.method.stage import RunRecord
    from quasisim.method.stages.contact_curriculum import _record_simulator, restart_guard
    from quasisim.optim.adam import Progress

    calls = []

    def value(t, *_):
        calls.append(t)
        return t, None

    best, losses = restart_guard(value, {"previous": jnp.nan, "kinematic": 0.3, "stage_start": 0.5}, None, None, {})
    assert best == "kinematic" and losses["previous"] == float("inf")
    # a start equal to an earlier one (the stage's start is often the kinematic retarget) is evaluated once
    calls.clear()
    best, losses = restart_guard(value, {"previous": 0.4, "kinematic": 0.3, "stage_start": 0.3}, None, None, {})
    assert best == "kinematic" and losses["stage_start"] == 0.3 and calls == [0.4, 0.3]
    record, cur = RunRecord(), load_curriculum("default")
    record.seconds["stage2"] = 0.0
    d = {"losses": np.zeros(0), "wall_s": np.array(1.0), "start_losses": np.array("{}")}
    _record_simulator(record, cur, 2, d, {"mass_kg": 0.1}, Progress(False))
    assert record.simulators[0]["steps"] == 0 and record.curves["sim 3"] == []


@pytest.mark.parametrize("sysid_steps", [0, 3])
def test_stage2_reads_back_where_identification_ended_instead_of_evaluating_it_again(sysid_steps: int) -> None:
    """One simulator of stage 2 on a toy objective coupling the controls x and S: the control optimisation's
    first evaluation, at (x, best S), is identification's own, so the objective runs once fewer than the two
    optimisations' loss evaluations (none fewer without identification), and the result is exactly that of
    running both optimisations with their own evaluations."""
    from quasisim.method.stages.contact_curriculum import one_simulator
    from quasisim.method.stages.point_dynamics import pick_grad
    from quasisim.optim.adam import Progress, StepBudget, minimise

    target = jnp.array([0.3, -0.2])

    @jax.jit
    def vg(x, s, params, w):
        def f(x, s):
            loss = jnp.sum((x - target * (1.0 + s.log_mass)) ** 2) + 0.1 * (s.log_mass - 0.5) ** 2
            return loss, {"loss": loss}

        return jax.value_and_grad(f, argnums=(0, 1), has_aux=True)(x, s)

    calls = {"n": 0}

    def counted(*a):
        calls["n"] += 1
        return vg(*a)

    sb = StepBudget(control_steps=4, sysid_steps=sysid_steps, control_lr=0.05, sysid_lr=0.05, patience=5,
                    min_rel_improvement=0.0)  # fmt: skip
    x0, s0 = jnp.zeros(2), SysID.init()
    x, s, log_s, log_c = one_simulator(counted, x0, s0, None, {}, sb, Progress(False), "toy")
    assert calls["n"] == len(log_s.losses) + len(log_c.losses) - (sysid_steps > 0)
    # the same as both optimisations run in full
    s_ref, log_s_ref = (minimise(lambda v: pick_grad(vg(x0, v, None, {}), 1), s0, sysid_steps, 0.05, sb,
                                 Progress(False), "s") if sysid_steps else (s0, None))  # fmt: skip
    x_ref, log_c_ref = minimise(lambda v: pick_grad(vg(v, s_ref, None, {}), 0), x0, 4, 0.05, sb, Progress(False), "c")
    np.testing.assert_array_equal(x, x_ref)
    np.testing.assert_array_equal(s.log_mass, s_ref.log_mass)
    assert log_c.losses == log_c_ref.losses and (log_s_ref is None or log_s.losses == log_s_ref.losses)
