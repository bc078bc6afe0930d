"""Stage 3: fit the quasi-physical simulator to the target (paper appendix "Optimizing towards a realistic
physical environment").

1. **Replay buffer** (:class:`~quasisim.eval.predict.ReplayBuffer`, :func:`~quasisim.eval.predict.collect`): PD-target trajectories (the current controls
   and noisy variants of them) rolled out in the target; per frame the hand's joints and velocities, the
   object's pose and twist, the robot keypoints and the PD targets.
2. **Windows** (:func:`~quasisim.eval.predict.windows`): from a recorded frame ``t`` the target's state is put into the
   quasi-physical simulator (contacts start fresh) and the recorded PD targets of frames ``t+1 .. t+H`` are
   applied; the prediction is compared with what the target did (object position, rotation, keypoints).
3. **Fit** (:func:`fit`): Adam on the mean H-frame prediction error of training windows over
   :class:`SimFit`: S (object mass, inertia, velocity damping) and the contact and joint constants
   (contact stiffness scale, friction coefficient, joint damping, PD gain scale), all in log coordinates;
   then, optionally, the residual networks (:mod:`quasisim.sim.residual`, zero at start) on the same loss.
4. **Measure** (:func:`quasisim.eval.predict.prediction_errors`): the error after ``h = 1..H`` frames on windows the fit never
   saw (the clip's later frames), beside the zero-motion predictor (the object stays where it is).
5. **World-model rounds** (:func:`world_model_rounds`): optimise the controls in the fitted simulator, roll
   them out in the target (kept when the target judges them best), add the rollouts to the buffer, refit.

The loss is the tracking objective's terms (:func:`quasisim.optim.objective.tracking_errors`) between the
predicted and the recorded trajectory: object translation (m), ``1 - |q . q_ref|`` and keypoint distance (m).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from quasisim.errors import QuasisimError
from quasisim.eval.predict import ReplayBuffer, Windows, collect, predict, prediction_errors, split_starts, windows
from quasisim.method.sample_target import SamplingOptions, sample_windows
from quasisim.optim.objective import tracking_errors, weighted_sum
from quasisim.optim.sysid import SysID
from quasisim.optim.trajectory import Trajectory
from quasisim.sim.build import attach_residual
from quasisim.sim.residual import ResidualConfig, ResidualNets
from quasisim.sim.types import Model, Params, pytree

Array = jax.Array
F32 = jnp.float32
OBS_KEYS = ("qpos", "qvel", "obj_pos", "obj_quat", "obj_vel", "obj_angvel", "keypoints")


def noisy_variants(
    plan: np.ndarray, n: int, noise: SamplingOptions, seed: int, joint_range: np.ndarray
) -> list[np.ndarray]:
    """``n`` smooth perturbations of ``plan`` (T, 6 + J) with the sampling baseline's noise model (knots
    every ~6 frames, the noise scales cycled), joints kept within ``joint_range`` (J, 2)."""
    T = len(plan)
    opts = dataclasses.replace(noise, samples=n + 1, horizon=T - 1, knots=max(2, (T - 1) // 6))
    wins = sample_windows(np.random.default_rng(seed), plan, opts, joint_range[:, 0], joint_range[:, 1])
    return [w for w in wins[1:]]


@pytree
class SimFit:
    """The fitted simulator parameters in unconstrained (log) coordinates; zeros are the nominal simulator.

    Attributes:
        sysid: S (object mass, inertia, velocity damping).
        log_contact: contact stiffness, friction stiffness and damping scale (multiplies ``contact_scale``).
        log_mu: friction coefficient scale.  log_joint_damping: joint damping scale.
        log_gain: joint PD gain scale (kp and kv).
    """

    sysid: SysID
    log_contact: Array
    log_mu: Array
    log_joint_damping: Array
    log_gain: Array

    @staticmethod
    def nominal(sysid: SysID | None = None) -> SimFit:
        """The nominal constants with S ``sysid`` (default: the object's nominal S)."""
        z = jnp.zeros((), F32)
        return SimFit(sysid or SysID.init(), z, z, z, z)

    def as_array(self) -> np.ndarray:
        """(8,) S then the four log scales (for checkpoints)."""
        rest = [float(x) for x in (self.log_contact, self.log_mu, self.log_joint_damping, self.log_gain)]
        return np.concatenate([self.sysid.as_array(), rest])

    @staticmethod
    def from_array(x: np.ndarray) -> SimFit:
        """Inverse of :meth:`as_array`."""
        return SimFit(SysID.from_array(x[:4]), *(jnp.asarray(v, F32) for v in np.asarray(x)[4:]))

    def apply(self, params: Params, mass0: float, inertia0: np.ndarray) -> Params:
        """``params`` with the fitted values (differentiable in ``self``)."""
        return self.sysid.apply(self.apply_constants(params), mass0, inertia0)

    def apply_constants(self, params: Params) -> Params:
        """``params`` with the fitted contact and joint constants, S left as it is (the tracking objective
        applies S itself)."""
        p, g = params, jnp.exp(self.log_gain)
        return dataclasses.replace(
            p,
            contact_scale=p.contact_scale * jnp.exp(self.log_contact),
            mu=p.mu * jnp.exp(self.log_mu),
            joint_damping=p.joint_damping * jnp.exp(self.log_joint_damping),
            joint_kp=p.joint_kp * g,
            joint_kv=p.joint_kv * g,
        )

    def describe(self, mass0: float) -> dict[str, float]:
        """The fitted values as scales of the nominal ones (S in physical units)."""
        scales = {
            k: float(np.exp(float(getattr(self, f"log_{k}")))) for k in ("contact", "mu", "joint_damping", "gain")
        }
        return {**self.sysid.describe(mass0), **{f"{k}_scale": v for k, v in scales.items()}}


def window_loss(
    model: Model, params: Params, w: Windows, fps: float, base_quat: np.ndarray, weights: dict[str, Array]
) -> Array:
    """Mean over windows of the weighted prediction terms (object translation, rotation, keypoints)."""
    pos, quat, kp = predict(model, params, w, fps, base_quat)

    def one(p: Array, q: Array, k: Array, rp: Array, rq: Array, rk: Array) -> Array:
        return weighted_sum(tracking_errors(p, q, k, rp, rq, rk), weights)

    return jnp.mean(jax.vmap(one)(pos, quat, kp, w.obj_pos, w.obj_quat, w.keypoints))


@dataclass(frozen=True)
class FitOptions:
    """Settings of the fit (values: ``configs/transfer.yaml``, ``stage3``).

    Attributes:
        horizon: frames per window (H).  held_out: fraction of the clip's last frames left out of the fit.
        variants: noisy rollouts added to the buffer beside the current controls.  capacity: rollouts kept.
        steps, lr: Adam steps and step size of the constants.  batch: windows per step.
        residual_steps, residual_lr: the same for the residual networks (0 steps: no residual).
        rounds: world-model rounds after the first fit (:func:`world_model_rounds`; 0: fit only).
        seed: window sampling and variant noise.
    """

    horizon: int
    held_out: float
    variants: int
    capacity: int
    steps: int
    lr: float
    batch: int
    residual_steps: int
    residual_lr: float
    rounds: int
    seed: int


def fit(
    model: Model, params: Params, train: Windows, fps: float, base_quat: np.ndarray, mass0: float,
    inertia0: np.ndarray, opts: FitOptions, weights: dict[str, Array], start: SimFit | None = None,
) -> tuple[SimFit, list[float]]:  # fmt: skip
    """Adam on :class:`SimFit` (from ``start``, default nominal) over random batches of the training
    windows; returns the fit and the losses."""

    const = (model, params, jnp.asarray(mass0, jnp.float32), jnp.asarray(inertia0, jnp.float32))
    vg = functools.partial(_fit_vg, const, jnp.asarray(base_quat, jnp.float32), weights, fps=fps)
    return _adam(vg, start or SimFit.nominal(), train, opts.steps, opts.lr, opts.batch, opts.seed)


@functools.partial(jax.jit, static_argnames=("fps",))
def _fit_vg(
    const: tuple[Model, Params, Array, Array], base_quat: Array, weights: dict[str, Array], f: SimFit,
    batch: Windows, fps: float,
) -> tuple[Array, SimFit]:  # fmt: skip
    """Value and gradient of the window loss of a ``batch`` of windows w.r.t. the fit ``f``; ``const``: the
    model, the simulator and the object's nominal mass and inertia."""
    model, params, mass0, inertia0 = const
    return jax.value_and_grad(
        lambda f: window_loss(model, f.apply(params, mass0, inertia0), batch, fps, base_quat, weights)
    )(f)


def fit_residual(
    model: Model, params: Params, train: Windows, fps: float, base_quat: np.ndarray, opts: FitOptions,
    weights: dict[str, Array], cfg: ResidualConfig, local: bool = True, glob: bool = True,
) -> tuple[Model, Params, list[float]]:  # fmt: skip
    """Attach residual networks (zero at start) to the simulator ``params`` and train their weights on the
    training windows; ``local`` / ``glob`` switch the two networks. Returns the model, params and losses."""
    model, p0 = attach_residual(model, params, ResidualNets(cfg, seed=opts.seed), local, glob)

    @jax.jit
    def vg(res: Any, batch: Windows) -> tuple[Array, Any]:
        loss = lambda r: window_loss(model, p0.replace(residual=r), batch, fps, base_quat, weights)  # noqa: E731
        return jax.value_and_grad(loss)(res)

    res, losses = _adam(vg, p0.residual, train, opts.residual_steps, opts.residual_lr, opts.batch, opts.seed + 1)
    return model, p0.replace(residual=res), losses


def _adam(
    vg: Any, x0: Any, train: Windows, steps: int, lr: float, batch: int, seed: int, check_every: int = 10
) -> tuple[Any, list[float]]:
    """Minibatch Adam (``batch`` random training windows per step; ``vg(x, windows)``). Every ``check_every``
    steps the loss on a fixed subset of ``2 batch`` training windows is measured and the best iterate by it
    is returned, so a fit never ends worse on that subset than it started. Returns the iterate and the
    minibatch losses. Batches are taken here, so ``vg`` is compiled for the batch's size alone, whatever
    the number of training windows."""
    rng, n = np.random.default_rng(seed), len(train)
    b = min(batch, n)
    check = rng.choice(n, size=min(2 * batch, n), replace=False)
    # the check subset in batches of the step's own size: one compiled program serves both
    chunks = [train.take(jnp.asarray(check[i : i + b])) for i in range(0, len(check) - b + 1, b)]

    def check_loss(x: Any) -> float:
        return float(np.mean([float(vg(x, c)[0]) for c in chunks]))

    tx = optax.adam(lr)
    x, st = x0, tx.init(eqx.filter(x0, eqx.is_array))
    best, best_x = check_loss(x), x
    losses: list[float] = []
    for k in range(1, steps + 1):
        idx = jnp.asarray(rng.choice(n, size=b, replace=False))
        loss, g = vg(x, train.take(idx))
        if not np.isfinite(float(loss)):
            break
        losses.append(float(loss))
        upd, st = tx.update(g, st, x)
        x = optax.apply_updates(x, upd)
        if k % check_every == 0 or k == steps:
            c = check_loss(x)
            if c < best:
                best, best_x = c, x
    return best_x, losses


def fit_windows(
    prob: Any, plan: np.ndarray, opts: FitOptions, noise: SamplingOptions
) -> tuple[Windows, Windows, ReplayBuffer]:
    """The training and held-out windows of stage 3 for a plan (T, 6 + J): the plan and ``opts.variants``
    noisy variants rolled out in MuJoCo; training windows end before the last ``held_out`` fraction of the
    clip, the held-out ones are those of the plan's own rollout. Refuses clips too short for both."""
    demo, m, bq = prob.demo, prob.model, prob.base_quat
    train_s, test_s = split_starts(1 + opts.variants, demo.n_frames, opts.horizon, opts.held_out)
    if not train_s or not test_s:
        raise QuasisimError(
            f"stage 3: the clip's {demo.n_frames} frames are too few for {opts.horizon}-frame windows with the last "
            f"{100 * opts.held_out:.0f} % held out; lower stage3.horizon or stage3.held_out (--set), or leave out stage 3"
        )
    plans = [plan, *noisy_variants(plan, opts.variants, noise, opts.seed, prob.hand.joint_range)]
    buf = collect(prob.scene, plans, demo.fps)
    train = windows(m, buf, train_s, opts.horizon, bq)
    test = windows(m, buf, [s for s in test_s if s[0] == 0], opts.horizon, bq)
    return train, test, buf


def fit_to_target(
    prob: Any, params: Params, plan: np.ndarray, sysid: SysID, opts: FitOptions, noise: SamplingOptions,
    weights: dict[str, Array],
) -> tuple[dict[str, Any], SimFit, ReplayBuffer]:  # fmt: skip
    """Stage 3's first fit for one plan (T, 6 + J) of a :class:`~quasisim.method.problem.Problem`: a replay
    buffer of the plan and noisy variants in MuJoCo, the fit of :class:`SimFit` from S ``sysid`` on the
    training windows, and the held-out ``H``-frame errors before and after. Returns the checkpoint arrays,
    the fit and the buffer."""
    demo, m, bq, obj = prob.demo, prob.model, prob.base_quat, prob.obj
    train, test, buf = fit_windows(prob, plan, opts, noise)
    start = SimFit.nominal(sysid)
    f, losses = fit(m, params, train, demo.fps, bq, obj.mass, obj.inertia, opts, weights, start)
    before = prediction_errors(m, start.apply(params, obj.mass, obj.inertia), test, demo.fps, bq)
    after = prediction_errors(m, f.apply(params, obj.mass, obj.inertia), test, demo.fps, bq)
    d = {
        "fit": f.as_array(), "losses": np.asarray(losses, np.float64),
        "held_out_before": np.array([before.obj_pos_cm[-1], before.obj_rot_deg[-1], before.keypoints_mm[-1]]),
        "held_out_after": np.array([after.obj_pos_cm[-1], after.obj_rot_deg[-1], after.keypoints_mm[-1]]),
    }  # fmt: skip
    return d, f, buf


def world_model_rounds(
    prob: Any, params: Params, traj: Trajectory, f: SimFit, buf: ReplayBuffer, opts: FitOptions,
    noise: SamplingOptions, weights: dict[str, Array], improve: Callable[[Trajectory, SimFit], Trajectory],
    cost: Callable[[np.ndarray], float], progress: Any = None,
) -> dict[str, Any]:  # fmt: skip
    """The paper's world-model-style loop (appendix "World model-style training"), ``opts.rounds`` times:

    1. ``improve`` the controls in the fitted simulator (``params`` with the fit ``f``);
    2. roll them and ``opts.variants`` noisy variants out in the target and judge them there (``cost``, the
       clip objective of :mod:`quasisim.method.select`); the best controls seen are kept, so a round never
       makes the result worse;
    3. measure the fitted simulator's ``H``-frame prediction error on the new controls' rollout (windows from
       every frame: rollouts the fit has not seen);
    4. add the new rollouts to the buffer (the newest ``capacity`` kept) and refit from ``f`` on the windows
       of every rollout and frame.

    Returns the best controls (T, 6 + J), the last fit, per round the target cost (round 0: the stage's
    starting controls) and the prediction error (cm, deg, mm) before the refit, and the buffer's size, as
    checkpoint arrays."""
    demo, m, bq, obj = prob.demo, prob.model, prob.base_quat, prob.obj
    best_q = np.asarray(traj.q_targets, np.float64)
    costs, errors, best = [cost(best_q)], [], 0
    for r in range(1, opts.rounds + 1):
        traj = improve(traj, f)
        q = np.asarray(traj.q_targets, np.float64)
        costs.append(cost(q))
        if costs[-1] < costs[best]:
            best, best_q = r, q
        new = collect(
            prob.scene, [q, *noisy_variants(q, opts.variants, noise, opts.seed + r, prob.hand.joint_range)], demo.fps
        )
        T = demo.n_frames
        e = prediction_errors(
            m,
            f.apply(params, obj.mass, obj.inertia),
            windows(m, new, [(0, t) for t in range(T - opts.horizon)], opts.horizon, bq),
            demo.fps,
            bq,
        )
        errors.append([e.obj_pos_cm[-1], e.obj_rot_deg[-1], e.keypoints_mm[-1]])
        buf = buf.extended(new, opts.capacity)
        every = [(i, t) for i in range(buf.n_rollouts) for t in range(T - opts.horizon)]
        f, _ = fit(m, params, windows(m, buf, every, opts.horizon, bq), demo.fps, bq, obj.mass, obj.inertia,
                   dataclasses.replace(opts, seed=opts.seed + r), weights, f)  # fmt: skip
        if progress is not None:
            progress.write(
                f"stage 3 round {r}/{opts.rounds}: objective in the target {costs[-1]:.4f} (best {costs[best]:.4f}); "
                f"the fitted simulator predicted this round's rollout to {errors[-1][0]:.2f} cm / {errors[-1][1]:.1f} deg "
                f"after {opts.horizon} frames"
            )
    return {
        "q_targets": best_q, "round_fit": f.as_array(), "round_costs": np.asarray(costs, np.float64),
        "round_errors": np.asarray(errors, np.float64).reshape(-1, 3), "best_round": np.array(best),
        "buffer_rollouts": np.array(buf.n_rollouts),
    }  # fmt: skip
