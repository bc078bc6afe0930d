"""A neural model of the target alone: an MLP of one control frame's transition, no analytical simulator
(the paper's ablation "w/o analytical sim"; the world model of its Control-VAE baseline, appendix).

State ``x`` (S = 2 D + 13): the hands' joints ``qpos`` (D; bases then fingers, the target's layout) and their
velocities ``qvel`` (D), the object's position ``p`` (3, m), orientation ``r`` (4, w x y z, w >= 0), velocity
``v`` (3, m/s) and angular velocity ``w`` (3, rad/s), as a target observes them. One control frame from PD
targets ``qa`` to ``qb`` (D each; :meth:`~quasisim.targets.base.Target.advance`):

    d = MLP((x - mu_x) / sigma_x, (qb - qpos) / sigma_u, (qb - qa) / sigma_u) * sigma_d + mu_d
    qpos' = qpos + d_q,  qvel' = qvel + d_qd,  p' = p + d_p,  r' = exp(d_r) r,  v' = v + d_v,  w' = w + d_w

with ``d_r`` a world-frame rotation vector. The normalisation (mu, sigma) is taken from the first replay buffer
the model is fitted to and kept. The fit minimises the error of ``H``-frame rollouts of the model on its own
predictions against recorded target rollouts (:func:`fit`), each component in units of its typical per-frame
change (:func:`state_error`). Controls are optimised through :func:`rollout` with the tracking objective, the
robot keypoints from the hand's forward kinematics (:func:`keypoints_of`: the hand's kinematics, not its
dynamics).
"""

from __future__ import annotations

import functools
import itertools
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from quasisim.method.replay import ReplayBuffer
from quasisim.optim.adam import minibatch_adam
from quasisim.optim.objective import smoothness, tracking_errors, weighted_sum
from quasisim.optim.trajectory import root_positions, root_quats, split_q
from quasisim.rotations import quat_mul, quat_to_mat
from quasisim.sim.kinematics import forward_kinematics, keypoints
from quasisim.sim.types import Model, pytree, static

Array = jax.Array
F32 = jnp.float32


def state_size(n_dof: int) -> int:
    """S of a scene with ``n_dof`` (D) hand degrees of freedom."""
    return 2 * n_dof + 13


def pack(qpos: Any, qvel: Any, obj_pos: Any, obj_quat: Any, obj_vel: Any, obj_angvel: Any) -> np.ndarray:
    """The state vectors (..., S) of observed arrays (leading axes shared); quaternions with w >= 0."""
    quat = np.asarray(obj_quat, np.float64)
    quat = np.where(quat[..., :1] < 0.0, -quat, quat)
    return np.concatenate([qpos, qvel, obj_pos, quat, obj_vel, obj_angvel], axis=-1).astype(np.float32)


def buffer_states(buf: ReplayBuffer) -> np.ndarray:
    """(R, T, S) the state of every recorded frame of ``buf``."""
    return pack(buf.qpos, buf.qvel, buf.obj_pos, buf.obj_quat, buf.obj_vel, buf.obj_angvel)


def observation_state(obs: dict[str, np.ndarray]) -> np.ndarray:
    """(S,) the state of one target observation."""
    return pack(*(obs[k] for k in ("qpos", "qvel", "obj_pos", "obj_quat", "obj_vel", "obj_angvel")))


def _split(x: Array, D: int) -> tuple[Array, Array, Array, Array, Array, Array]:
    return x[..., :D], x[..., D : 2 * D], x[..., 2 * D : 2 * D + 3], x[..., 2 * D + 3 : 2 * D + 7], \
        x[..., 2 * D + 7 : 2 * D + 10], x[..., 2 * D + 10 :]  # fmt: skip


def _quat_exp(v: Array) -> Array:
    """The unit quaternion of rotation vector ``v`` (..., 3)."""
    a = jnp.sqrt(jnp.sum(v * v, -1, keepdims=True) + 1e-12)
    return jnp.concatenate([jnp.cos(0.5 * a), jnp.sin(0.5 * a) * v / a], -1)


def _quat_log(q: Array) -> Array:
    """The rotation vector (..., 3) of unit quaternion ``q`` (the shorter way round)."""
    q = jnp.where(q[..., :1] < 0.0, -q, q)
    s = jnp.sqrt(jnp.sum(q[..., 1:] ** 2, -1, keepdims=True) + 1e-12)
    return 2.0 * jnp.arctan2(s, q[..., :1]) * q[..., 1:] / s


def difference(xb: Array, xa: Array, D: int) -> Array:
    """The change (..., S - 1) from state ``xa`` to ``xb``: plain differences, the object's rotation as the
    world-frame rotation vector of ``rb ra^-1``."""
    qa, qda, pa, ra, va, wa = _split(xa, D)
    qb, qdb, pb, rb, vb, wb = _split(xb, D)
    conj = ra * jnp.asarray([1.0, -1.0, -1.0, -1.0], F32)
    return jnp.concatenate([qb - qa, qdb - qda, pb - pa, _quat_log(quat_mul(rb, conj)), vb - va, wb - wa], -1)


def advance(x: Array, d: Array, D: int) -> Array:
    """State ``x`` moved by the change ``d`` (inverse of :func:`difference`)."""
    q, qd, p, r, v, w = _split(x, D)
    dq, dqd, dp, dr, dv, dw = d[..., :D], d[..., D : 2 * D], d[..., 2 * D : 2 * D + 3], \
        d[..., 2 * D + 3 : 2 * D + 6], d[..., 2 * D + 6 : 2 * D + 9], d[..., 2 * D + 9 :]  # fmt: skip
    r2 = quat_mul(_quat_exp(dr), r)
    r2 = r2 / jnp.linalg.norm(r2, axis=-1, keepdims=True)
    return jnp.concatenate([q + dq, qd + dqd, p + dp, r2, v + dv, w + dw], -1)


@pytree
class Norm:
    """The model's fixed normalisation: state ``x_mean``, ``x_std`` (S,), control ``u_std`` (D,) and per-frame
    change ``d_mean``, ``d_std`` (S - 1,)."""

    x_mean: Array
    x_std: Array
    u_std: Array
    d_mean: Array
    d_std: Array
    n_dof: int = static()

    @staticmethod
    def of(buf: ReplayBuffer) -> Norm:
        """The statistics of every recorded frame of ``buf`` (standard deviations floored, so that a
        component that never moved does not blow up)."""
        x = jnp.asarray(buffer_states(buf))
        D = buf.qpos.shape[-1]
        d = difference(x[:, 1:], x[:, :-1], D).reshape(-1, x.shape[-1] - 1)
        u = jnp.asarray(np.diff(buf.q_targets, axis=1).reshape(-1, D), F32)
        std = lambda a, floor: jnp.maximum(jnp.std(a, 0), floor)  # noqa: E731
        flat = x.reshape(-1, x.shape[-1])
        return Norm(jnp.mean(flat, 0), std(flat, 1e-3), std(u, 1e-4), jnp.mean(d, 0), std(d, 1e-5), D)


Layers = list[tuple[Array, Array]]  # (W (n_out, n_in), b (n_out,)) per layer, the output layer last


def init_layers(n_dof: int, widths: tuple[int, ...], seed: int) -> Layers:
    """The MLP's weights (He-uniform, biases zero) for a scene of ``n_dof`` hand dofs; the output layer is
    zero, so that the untrained model predicts the mean change."""
    S = state_size(n_dof)
    sizes = [S + 2 * n_dof, *widths, S - 1]
    keys = jax.random.split(jax.random.PRNGKey(seed), len(sizes) - 1)
    layers = []
    for k, (a, b) in enumerate(itertools.pairwise(sizes)):
        lim = float(np.sqrt(6.0 / a)) if k < len(sizes) - 2 else 0.0
        layers.append((jax.random.uniform(keys[k], (b, a), F32, -lim, lim), jnp.zeros(b, F32)))
    return layers


def step(layers: Layers, norm: Norm, x: Array, qa: Array, qb: Array) -> Array:
    """The state one control frame after ``x`` (S,) with PD targets from ``qa`` to ``qb`` (D,)."""
    D = norm.n_dof
    h = jnp.concatenate([(x - norm.x_mean) / norm.x_std, (qb - x[:D]) / norm.u_std, (qb - qa) / norm.u_std])
    for W, b in layers[:-1]:
        h = jax.nn.relu(W @ h + b)
    W, b = layers[-1]
    return advance(x, (W @ h + b) * norm.d_std + norm.d_mean, D)


def rollout(layers: Layers, norm: Norm, x0: Array, q: Array) -> Array:
    """(F, S) the states after each of the F control frames of PD targets ``q`` (F + 1, D), from ``x0``."""

    def one(x: Array, qab: tuple[Array, Array]) -> tuple[Array, Array]:
        x2 = step(layers, norm, x, *qab)
        return x2, x2

    return jax.lax.scan(one, x0, (q[:-1], q[1:]))[1]


def state_error(pred: Array, true: Array, norm: Norm) -> Array:
    """Mean squared error of predicted states against recorded ones, each component of :func:`difference`
    in units of its per-frame standard deviation."""
    return jnp.mean((difference(pred, true, norm.n_dof) / norm.d_std) ** 2)


@pytree
class Segments:
    """``B`` recorded segments of ``H`` frames: start states ``x0`` (B, S), PD targets ``q`` (B, H + 1, D)
    and the states that followed ``x`` (B, H, S)."""

    x0: Array
    q: Array
    x: Array

    def __len__(self) -> int:
        return len(self.x0)

    def take(self, idx: Array) -> Segments:
        return jax.tree_util.tree_map(lambda a: a[idx], self)


def segments(buf: ReplayBuffer, horizon: int) -> Segments:
    """Every ``horizon``-frame segment of every rollout of ``buf``."""
    x = buffer_states(buf)
    R, T = x.shape[:2]
    H = min(horizon, T - 1)
    starts = [(r, t) for r in range(R) for t in range(T - H)]
    q = np.asarray(buf.q_targets, np.float32)
    return Segments(
        jnp.asarray(np.stack([x[r, t] for r, t in starts])),
        jnp.asarray(np.stack([q[r, t : t + H + 1] for r, t in starts])),
        jnp.asarray(np.stack([x[r, t + 1 : t + H + 1] for r, t in starts])),
    )


@jax.jit
def segment_loss_and_grad(layers: Layers, norm: Norm, batch: Segments) -> tuple[Array, Layers]:
    """Value and gradient (w.r.t. ``layers``) of the mean :func:`state_error` of the model's rollouts of a
    ``batch`` of segments."""

    def loss(ls: Layers) -> Array:
        pred = jax.vmap(lambda x0, q: rollout(ls, norm, x0, q))(batch.x0, batch.q)
        return state_error(pred, batch.x, norm)

    return jax.value_and_grad(loss)(layers)


@dataclass(frozen=True, eq=False)
class WorldModel:
    """A fitted model: the MLP's ``layers`` and its normalisation ``norm``."""

    layers: Layers
    norm: Norm

    def rollout(self, x0: Array, q: Array) -> Array:
        return rollout(self.layers, self.norm, x0, q)


def fit(model: WorldModel, buf: ReplayBuffer, horizon: int, steps: int, lr: float, batch: int, seed: int) -> tuple[
    WorldModel, list[float]
]:  # fmt: skip
    """``steps`` minibatch Adam steps on the ``horizon``-frame segments of ``buf`` from ``model``'s weights (its
    normalisation kept); returns the model with the best weights by the loss on a fixed check subset, and the
    minibatch losses."""
    segs = segments(buf, horizon)
    vg = functools.partial(_vg, model.norm)
    layers, losses = minibatch_adam(vg, model.layers, segs, steps, lr, batch, seed, desc="neural model fit")
    return WorldModel(layers, model.norm), losses


def _vg(norm: Norm, layers: Layers, batch: Segments) -> tuple[Array, Layers]:
    return segment_loss_and_grad(layers, norm, batch)


def keypoints_of(model: Model, qpos: Array, base_quat: Array) -> Array:
    """(F, K, 3) world positions of the robot keypoints of hand configurations ``qpos`` (F, D) (the
    quasi-physical model's forward kinematics; its point set and contact are not used)."""
    base, joints = split_q(qpos, model.hand.hand_joints)
    rq, rp = root_quats(base, base_quat), root_positions(base)

    def one(p: Array, r: Array, j: Array) -> Array:
        poses = forward_kinematics(model.hand, model.to_sim(p), quat_to_mat(r), j, model.hand_geom)
        return model.to_world(keypoints(model.hand, poses, model.hand_geom))

    return jax.vmap(one)(rp, rq, joints)


def tracking_cost(
    wm: WorldModel, model: Model, base_quat: Array, x0: Array, q: Array, ref: tuple[Array, ...],
    weights: dict[str, Array],
) -> tuple[Array, dict[str, Array]]:  # fmt: skip
    """The tracking objective (object, hand, smoothness terms) of PD targets ``q`` (F + 1, D) rolled out in the
    model from ``x0``, against ``ref``: object positions (F, 3), quaternions (F, 4), human keypoints (F, K', 3),
    the robot keypoints that follow them (K',) and per-frame weights (F,)."""
    ref_pos, ref_quat, ref_kp, kp_index, frame_w = ref
    xs = wm.rollout(x0, q)
    qpos, _, pos, quat, _, _ = _split(xs, wm.norm.n_dof)
    kp = keypoints_of(model, qpos, base_quat)[:, kp_index]
    terms = tracking_errors(pos, quat, kp, ref_pos, ref_quat, ref_kp, frame_w)
    base, joints = split_q(q, model.hand.hand_joints)
    terms["smooth"] = smoothness(base, joints, frame_w)
    return weighted_sum(terms, {k: weights[k] for k in terms}), terms


@jax.jit
def _cost_vg(wm_layers: Layers, norm: Norm, model: Model, base_quat: Array, x0: Array, q: Array,
             ref: tuple[Array, ...], weights: dict[str, Array]) -> Any:  # fmt: skip
    wm = WorldModel(wm_layers, norm)
    return jax.value_and_grad(lambda qq: tracking_cost(wm, model, base_quat, x0, qq, ref, weights), has_aux=True)(q)


def cost_value_and_grad(wm: WorldModel, model: Model, base_quat: Array, x0: Array, ref: tuple[Array, ...],
                        weights: dict[str, Array]) -> Any:  # fmt: skip
    """``q -> ((cost, terms), d cost / d q)`` of :func:`tracking_cost`, compiled (one program per length of ``q``)."""
    return lambda q: _cost_vg(wm.layers, wm.norm, model, base_quat, x0, q, ref, weights)
