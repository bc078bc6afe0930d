"""Control-VAE adapted to tracking (the paper's baseline, its supplement): a generative controller trained
through a learned world model (:mod:`quasisim.method.world_model`, the MLP of the target alone).

Per control frame ``t``, from the state ``x_t`` (S) and the reference of frame ``t + 1`` (what to track):

    mu_p = prior(x_t)                                   the prior p(z | x_t) = N(mu_p, sigma^2 I)   (Z,)
    mu_q = mu_p + encoder(x_t, g_t)                     the posterior q(z | x_t, g_t) = N(mu_q, sigma^2 I)
    z    = mu_q + sigma eps,  eps ~ N(0, I)             (training; the mean mu_q when acting)
    q_{t+1} = k_{t+1} + r tanh(decoder(x_t, z))         the PD target, within r of the kinematic retarget k

with ``g_t`` the tracking goal: the reference object position relative to the current one (m), the reference
orientation (w x y z), and ``(k_{t+1} - qpos_t) / sigma_u``. Training rolls the controller out through the world
model for ``H`` frames from recorded states and minimises the tracking objective of the predicted states against
the reference (object, hand keypoints, as stage ``neural`` plans) plus ``beta`` times the KL divergence of the
posterior from the prior, ``|mu_q - mu_p|^2 / (2 sigma^2)`` per frame. Each network is an MLP (ReLU) with a zero
output layer, so that the untrained controller applies the kinematic retarget.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from quasisim.method.world_model import Layers, Norm, _split, keypoints_of, step
from quasisim.optim.objective import tracking_errors, weighted_sum
from quasisim.sim.types import Model

Array = jax.Array
F32 = jnp.float32


def goal_size(n_dof: int) -> int:
    """The size of the tracking goal ``g_t``: 3 + 4 + D."""
    return 7 + n_dof


def _mlp_init(sizes: list[int], key: Array) -> Layers:
    keys = jax.random.split(key, len(sizes) - 1)
    out = []
    for k, (a, b) in enumerate(itertools.pairwise(sizes)):
        lim = float(np.sqrt(6.0 / a)) if k < len(sizes) - 2 else 0.0
        out.append((jax.random.uniform(keys[k], (b, a), F32, -lim, lim), jnp.zeros(b, F32)))
    return out


def _mlp(layers: Layers, h: Array) -> Array:
    for W, b in layers[:-1]:
        h = jax.nn.relu(W @ h + b)
    W, b = layers[-1]
    return W @ h + b


@dataclass(frozen=True, eq=False)
class Controller:
    """The three networks' weights: ``prior`` (S -> Z), ``encoder`` (S + G -> Z), ``decoder`` (S + Z -> D)."""

    prior: Layers
    encoder: Layers
    decoder: Layers

    def tree(self) -> tuple[Layers, Layers, Layers]:
        return self.prior, self.encoder, self.decoder


def init_controller(n_dof: int, widths: tuple[int, ...], latent: int, seed: int) -> Controller:
    """A controller for a scene of ``n_dof`` hand dofs (hidden ``widths``, latent size ``latent``)."""
    S, G = 2 * n_dof + 13, goal_size(n_dof)
    k = jax.random.split(jax.random.PRNGKey(seed), 3)
    return Controller(
        _mlp_init([S, *widths, latent], k[0]), _mlp_init([S + G, *widths, latent], k[1]),
        _mlp_init([S + latent, *widths, n_dof], k[2]),
    )  # fmt: skip


def goal(x: Array, ref_pos: Array, ref_quat: Array, k_next: Array, norm: Norm) -> Array:
    """``g_t`` (G,) of state ``x`` (S,) against the reference object pose of the next frame and the kinematic
    retarget's next PD target ``k_next`` (D,)."""
    D = norm.n_dof
    _, _, p, _, _, _ = _split(x, D)
    return jnp.concatenate([ref_pos - p, ref_quat, (k_next - x[:D]) / norm.u_std])


def act(nets: tuple[Layers, Layers, Layers], norm: Norm, x: Array, g: Array, k_next: Array, radius: Array,
        eps: Array, sigma: float) -> tuple[Array, Array]:  # fmt: skip
    """The PD target of frame ``t + 1`` (D,) and the frame's KL term, from state ``x``, goal ``g``, noise ``eps``
    (Z,; zeros to act with the posterior's mean)."""
    prior, encoder, decoder = nets
    xn = (x - norm.x_mean) / norm.x_std
    mu_p = _mlp(prior, xn)
    off = _mlp(encoder, jnp.concatenate([xn, g]))
    z = mu_p + off + sigma * eps
    q = k_next + radius * jnp.tanh(_mlp(decoder, jnp.concatenate([xn, z])))
    return q, jnp.sum(off**2) / (2.0 * sigma**2)


def window_loss(nets: tuple[Layers, Layers, Layers], wm: Layers, norm: Norm, model: Model, base_quat: Array,
                x0: Array, qa0: Array, k: Array, ref: tuple[Array, ...], radius: Array, eps: Array, sigma: float,
                beta: float, weights: dict[str, Array]) -> Array:  # fmt: skip
    """The controller's loss on one window: from state ``x0`` and the PD target ``qa0`` it was reached with, ``H``
    frames acted through the world model ``wm`` against the kinematic retarget ``k`` (H, D) of those frames and
    the reference ``ref`` (object positions (H, 3), quaternions (H, 4), human keypoints (H, K', 3), keypoint
    indices (K',), frame weights (H,)); ``eps`` (H, Z) the latent noise."""
    ref_pos, ref_quat, ref_kp, kp_index, frame_w = ref

    def one(carry: tuple[Array, Array], inp: tuple[Array, ...]) -> tuple[tuple[Array, Array], tuple[Array, Array]]:
        x, qa = carry
        rp, rq, kn, e = inp
        qb, kl = act(nets, norm, x, goal(x, rp, rq, kn, norm), kn, radius, e, sigma)
        x2 = step(wm, norm, x, qa, qb)
        return (x2, qb), (x2, kl)

    _, (xs, kls) = jax.lax.scan(one, (x0, qa0), (ref_pos, ref_quat, k, eps))
    qpos, _, pos, quat, _, _ = _split(xs, norm.n_dof)
    kp = keypoints_of(model, qpos, base_quat)[:, kp_index]
    terms = tracking_errors(pos, quat, kp, ref_pos, ref_quat, ref_kp, frame_w)
    return weighted_sum(terms, {n: weights[n] for n in terms}) + beta * jnp.mean(kls * frame_w)


@jax.jit
def batch_loss_and_grad(nets: tuple[Layers, Layers, Layers], wm: Layers, norm: Norm, model: Model,
                        base_quat: Array, batch: tuple[Array, ...], radius: Array, sigma: float, beta: float,
                        weights: dict[str, Array]) -> tuple[Array, Any]:  # fmt: skip
    """Value and gradient (w.r.t. the controller) of the mean :func:`window_loss` over a batch of windows
    (:meth:`Starts.take`)."""
    x0, qa0, k, rp, rq, rk, fw, eps, kp_index = batch

    def loss(n: Any) -> Array:
        def one(x: Array, qa: Array, kk: Array, p: Array, q: Array, kp: Array, w: Array, e: Array) -> Array:
            return window_loss(n, wm, norm, model, base_quat, x, qa, kk, (p, q, kp, kp_index, w), radius, e, sigma,
                               beta, weights)  # fmt: skip

        return jnp.mean(jax.vmap(one)(x0, qa0, k, rp, rq, rk, fw, eps))

    return jax.value_and_grad(loss)(nets)


@dataclass(eq=False)
class Starts:
    """Training windows of ``H`` frames from recorded states: start states ``x0`` (N, S), the PD targets they
    were reached with ``qa0`` (N, D), the kinematic retarget ``k`` (N, H, D) and the references ``ref_pos``,
    ``ref_quat``, ``ref_kp``, ``frame_w`` (N, H, ...) of the frames after, the keypoint indices ``kp_index``;
    :meth:`take` draws fresh latent noise (``latent`` wide) for each window it hands out."""

    x0: np.ndarray
    qa0: np.ndarray
    k: np.ndarray
    ref_pos: np.ndarray
    ref_quat: np.ndarray
    ref_kp: np.ndarray
    frame_w: np.ndarray
    kp_index: np.ndarray
    latent: int
    rng: np.random.Generator

    def __len__(self) -> int:
        return len(self.x0)

    def take(self, idx: Any) -> tuple[Array, ...]:
        idx = np.asarray(idx)
        eps = self.rng.standard_normal((len(idx), self.k.shape[1], self.latent)).astype(np.float32)
        parts = (self.x0, self.qa0, self.k, self.ref_pos, self.ref_quat, self.ref_kp, self.frame_w)
        return (*(jnp.asarray(a[idx], F32) for a in parts), jnp.asarray(eps), jnp.asarray(self.kp_index))


def starts(states: np.ndarray, q_targets: np.ndarray, k: np.ndarray, ref: tuple[np.ndarray, ...], horizon: int,
           latent: int, seed: int) -> Starts:  # fmt: skip
    """Every window of ``horizon`` frames of recorded rollouts: ``states`` (R, T, S), ``q_targets`` (R, T, D),
    against the kinematic retarget ``k`` (T + H, D) and the clip's references ``ref`` (object positions,
    quaternions, human keypoints, each padded to T + H frames, and the keypoint indices)."""
    R, T = states.shape[:2]
    H = horizon
    pos, quat, kp, kp_index = ref
    idx = [(r, t) for r in range(R) for t in range(T - 1)]
    fw = np.array([(np.arange(t + 1, t + H + 1) < T) for _, t in idx], np.float32)
    return Starts(
        np.stack([states[r, t] for r, t in idx]), np.stack([q_targets[r, t] for r, t in idx]),
        np.stack([k[t + 1 : t + H + 1] for _, t in idx]), np.stack([pos[t + 1 : t + H + 1] for _, t in idx]),
        np.stack([quat[t + 1 : t + H + 1] for _, t in idx]), np.stack([kp[t + 1 : t + H + 1] for _, t in idx]),
        fw, np.asarray(kp_index), latent, np.random.default_rng(seed),
    )  # fmt: skip
