"""The neural model of the target alone (stage ``neural``, the paper's ablation "w/o analytical sim"): its state
arithmetic, its fit to recorded transitions, and closed-loop MPC with it in MuJoCo."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

from quasisim.method.replay import ReplayBuffer
from quasisim.method.world_model import (
    Norm,
    WorldModel,
    advance,
    buffer_states,
    difference,
    fit,
    init_layers,
    segments,
    state_error,
)

D = 8  # a hand of 2 joints: 6 base coordinates and 2 fingers


def _unit(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def test_advance_undoes_difference_rotations_included() -> None:
    """``advance(xa, difference(xb, xa)) == xb`` (the quaternion up to sign), for rotations up to 180 deg."""
    rng = np.random.default_rng(0)
    n = 64
    xa, xb = (np.concatenate([rng.normal(size=(n, 2 * D + 3)), _unit(rng, n), rng.normal(size=(n, 6))], -1)
              for _ in range(2))  # fmt: skip
    back = np.asarray(advance(jnp.asarray(xa), difference(jnp.asarray(xb), jnp.asarray(xa), D), D))
    q, qb = back[:, 2 * D + 3 : 2 * D + 7], xb[:, 2 * D + 3 : 2 * D + 7]
    np.testing.assert_allclose(np.abs(np.sum(q * qb, -1)), 1.0, atol=1e-5)
    keep = np.r_[0 : 2 * D + 3, 2 * D + 7 : 2 * D + 13]
    np.testing.assert_allclose(back[:, keep], xb[:, keep], atol=1e-5)


def _rollouts(seed: int, n: int = 6, T: int = 30, fps: float = 20.0) -> ReplayBuffer:
    """A known system: the hand moves half way to its PD targets each frame, the object follows the base's
    translation by half and turns about z with the base's last angle."""
    rng = np.random.default_rng(seed)
    q_t = np.cumsum(rng.normal(0.0, 0.05, (n, T, D)), axis=1)
    qpos = np.zeros((n, T, D))
    pos, ang = np.zeros((n, T, 3)), np.zeros((n, T))
    for t in range(1, T):
        qpos[:, t] = qpos[:, t - 1] + 0.5 * (q_t[:, t] - qpos[:, t - 1])
        pos[:, t] = pos[:, t - 1] + 0.5 * (qpos[:, t, :3] - qpos[:, t - 1, :3])
        ang[:, t] = ang[:, t - 1] + (qpos[:, t, 5] - qpos[:, t - 1, 5])
    quat = np.stack([np.cos(ang / 2), 0 * ang, 0 * ang, np.sin(ang / 2)], -1)
    grad = lambda a: np.diff(a, axis=1, prepend=a[:, :1]) * fps  # noqa: E731  (the last frame's change)
    angvel = np.stack([0 * ang, 0 * ang, grad(ang)], -1)
    return ReplayBuffer(q_t, qpos, grad(qpos), pos, quat, grad(pos), angvel, np.zeros((n, T, 1, 3)))


def test_fit_learns_a_known_system_on_rollouts_it_never_saw() -> None:
    """Fitted to rollouts of a known system, the model's 4-frame predictions of other rollouts are at least
    5x better than the untrained model's (which predicts the mean change)."""
    train, test = _rollouts(0), _rollouts(1)
    wm = WorldModel(init_layers(D, (64, 64), 0), Norm.of(train))
    held = segments(test, 4)

    def err(m: WorldModel) -> float:
        import jax

        pred = jax.vmap(m.rollout)(held.x0, held.q)
        return float(state_error(pred, held.x, m.norm))

    fitted, losses = fit(wm, train, 4, 400, 3e-3, 32, 0)
    assert len(losses) == 400 and np.all(np.isfinite(losses))
    assert err(fitted) < 0.2 * err(wm), (err(fitted), err(wm))  # 11x measured; a model blind to its controls: 0.4x


@pytest.fixture(scope="module")
def short_scene(tmp_path_factory: pytest.TempPathFactory):
    from quasisim.data.demo import load_demo
    from quasisim.data.synthetic import write_example
    from quasisim.method.problem import kinematic_problem

    demo = load_demo(write_example("cube_lift", tmp_path_factory.mktemp("wm"), n_frames=12))
    return kinematic_problem(demo, "shadow", 5, 64)


def test_model_mpc_without_steps_applies_the_plan_exactly(short_scene) -> None:
    """MPC with the model and no optimisation steps applies the plan as it is, so the target ends where an
    open-loop replay of the plan ends (its start and every frame advanced as a replay advances it)."""
    from quasisim.method.config import TransferConfig
    from quasisim.method.stages.neural import model_mpc
    from quasisim.targets import make_target

    (prob, plan), cfg = short_scene, TransferConfig.from_yaml()
    with make_target("mujoco", prob.scene) as target:
        buf_state = target.rollout(plan)
        wm = WorldModel(init_layers(prob.scene.n_dof, (8,), 0), _norm_of(prob.scene.n_dof))
        o = dataclasses.replace(cfg.neural, mpc_steps=0, mpc_horizon=2)
        radius = np.full(prob.scene.n_dof, 0.1)
        applied = model_mpc(prob.demo, wm, prob.model, prob.base_quat, plan, o, cfg.weights, target, radius)
        np.testing.assert_allclose(applied, plan, atol=1e-6)
        end = target.observe()
    np.testing.assert_allclose(end["obj_pos"], buf_state.object_pos[-1], atol=1e-6)


def _norm_of(n_dof: int) -> Norm:
    S = 2 * n_dof + 13
    return Norm(jnp.zeros(S), jnp.ones(S), jnp.ones(n_dof), jnp.zeros(S - 1), jnp.ones(S - 1), n_dof)


def test_buffer_states_pack_the_recorded_frames() -> None:
    buf = _rollouts(2, n=2, T=5)
    x = buffer_states(buf)
    assert x.shape == (2, 5, 2 * D + 13)
    np.testing.assert_allclose(x[..., 2 * D + 3 : 2 * D + 7], buf.obj_quat, atol=1e-6)


# ---- Control-VAE (stage control_vae): a generative controller trained through the model ----------------------


def _controller_setup(short_scene, seed: int = 0):
    from quasisim.method.control_vae import init_controller
    from quasisim.method.stages.neural import clip_reference

    prob, plan = short_scene
    H = 3
    ref = tuple(np.asarray(a) for a in clip_reference(prob.demo, prob.model, H))
    k = np.concatenate([plan, np.repeat(plan[-1:], H, 0)])
    ctrl = init_controller(prob.scene.n_dof, (8,), 4, seed)
    return prob, plan, ref, k, ctrl


def test_untrained_controller_drives_the_retarget_exactly(short_scene) -> None:
    """The controller's output layers start at zero: it applies the kinematic retarget as it is (no KL), so
    driving the target with it ends where an open-loop replay of the retarget ends."""
    from quasisim.method.stages.control_vae import drive
    from quasisim.targets import make_target

    prob, plan, ref, k, ctrl = _controller_setup(short_scene)
    radius = np.full(prob.scene.n_dof, 0.1)
    with make_target("mujoco", prob.scene) as target:
        want = target.rollout(plan)
        applied = drive(ctrl, _norm_of(prob.scene.n_dof), prob.demo, k, ref, radius, 0.1, target)
        np.testing.assert_allclose(applied, plan, atol=1e-6)
        np.testing.assert_allclose(target.observe()["obj_pos"], want.object_pos[-1], atol=1e-6)


def test_controller_gradient_matches_central_differences(short_scene) -> None:
    """The gradient of the controller's window loss through the model (tracking terms and KL) against central
    finite differences, along a random direction of every network's weights at a random point."""
    import jax

    from quasisim.method.control_vae import goal_size, window_loss

    prob, plan, ref, k, ctrl = _controller_setup(short_scene)
    D, H = prob.scene.n_dof, 3
    rng = np.random.default_rng(1)
    rand = lambda t: jax.tree_util.tree_map(lambda a: jnp.asarray(rng.normal(0, 0.3, a.shape), jnp.float32), t)  # noqa: E731
    nets, wm = rand(ctrl.tree()), rand(init_layers(D, (8,), 0))
    norm = _norm_of(D)
    x0 = jnp.asarray(np.concatenate([plan[0], np.zeros(D), prob.demo.object_pos[0], prob.demo.object_quat[0],
                                     np.zeros(6)]), jnp.float32)  # fmt: skip
    pos, quat, kp, kp_index = ref
    win = (jnp.asarray(pos[1 : H + 1]), jnp.asarray(quat[1 : H + 1]), jnp.asarray(kp[1 : H + 1]),
           jnp.asarray(kp_index), jnp.ones(H))  # fmt: skip
    eps = jnp.asarray(rng.normal(size=(H, 4)), jnp.float32)
    w = {n: jnp.float32(1.0) for n in ("obj_pos", "obj_rot", "hand")}
    assert goal_size(D) == 7 + D

    def f(n):
        return window_loss(n, wm, norm, prob.model, jnp.asarray(prob.base_quat, jnp.float32), x0,
                           jnp.asarray(plan[0], jnp.float32), jnp.asarray(k[1 : H + 1], jnp.float32), win,
                           jnp.full(D, 0.1, jnp.float32), eps, 0.1, 0.01, w)  # fmt: skip

    g = jax.grad(f)(nets)
    v = rand(nets)
    along = sum(
        float(jnp.sum(a * b)) for a, b in zip(jax.tree_util.tree_leaves(g), jax.tree_util.tree_leaves(v), strict=True)
    )
    h = 1e-3
    shift = lambda s: jax.tree_util.tree_map(lambda a, b: a + s * b, nets, v)  # noqa: E731
    fd = (float(f(shift(h))) - float(f(shift(-h)))) / (2 * h)
    assert abs(along) > 1e-3 and abs(fd - along) <= 0.02 * abs(along), (fd, along)
