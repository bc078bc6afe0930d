"""Stage ``neural``: the method with a neural model of the target in place of the quasi-physical simulator (the
paper's ablation "Ours w/o Analytical Sim.": "we ablate the analytical model and use neural networks to
approximate physics in Bullet directly"; here MuJoCo).

1. **Buffer and first fit**: the current controls (the kinematic retarget) and ``variants`` noisy variants are
   rolled out in the target; the MLP of :mod:`quasisim.method.world_model` is fitted to their ``horizon``-frame
   segments.
2. **Rounds** (``rounds`` times, the world-model loop of stage 3 without its analytical part): Adam on the
   controls through the model (the tracking objective, the start observed in the target); the result and
   noisy variants of it are rolled out in the target, judged there (the best controls seen are kept), the
   model's prediction error on them measured before they join the buffer, and the model refitted.
3. **MPC**: closed loop in the target from the best controls, the model as MPC's model (at every frame the
   observed state, ``mpc_steps`` Adam steps on the next ``mpc_horizon`` frames, the first applied).

Every optimisation through the model stays in a trust region, ``q0 + r tanh(z)`` with ``r`` = ``trust`` x the
sampling stage's noise std per column around where it starts (the model is right only near its data; the
paper does not say how it kept its optimisation there). There is no curriculum: the curriculum relaxes the
analytical simulator, which this ablation leaves out.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from quasisim.data.demo import Demo
from quasisim.errors import InputError, QuasisimError
from quasisim.method.options import NeuralOptions
from quasisim.method.replay import ReplayBuffer, collect
from quasisim.method.stage import Context, Outcome, Stage
from quasisim.method.stages._common import timed
from quasisim.method.stages.fit_to_target import noisy_variants
from quasisim.method.stages.sampling import noise_std
from quasisim.method.world_model import (
    Norm,
    WorldModel,
    buffer_states,
    cost_value_and_grad,
    fit,
    init_layers,
    observation_state,
)
from quasisim.optim.adam import adam_steps
from quasisim.optim.objective import Weights, window_references
from quasisim.rotations import quat_angle_deg
from quasisim.sim.types import Model
from quasisim.targets import Target, make_target

F32 = jnp.float32


def options(ctx: Context) -> NeuralOptions:
    """The stage's settings; a config without them (or with an empty layer) is refused."""
    o = ctx.cfg.section("neural", "neural")
    if not o.widths or min(o.widths) < 1:
        raise InputError(ctx.cfg.path or None, "neural.widths", "one or more layer widths >= 1", repr(o.widths))
    return o


def _first_frame_fixed(g: jax.Array) -> jax.Array:
    """Frame 0 of the controls is where the hand starts: not optimised."""
    return g.at[0].set(0.0)


def plan_through(wm: WorldModel, model: Model, base_quat: np.ndarray, x0: np.ndarray, q: np.ndarray,
                 ref: tuple[Any, ...], weights: dict[str, Any], steps: int, lr: float,
                 radius: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
    """Controls after ``steps`` Adam steps through the model from the observed start ``x0`` (the best iterate by
    the model's objective), within the trust region ``q + radius tanh(z)`` around ``q`` (T, D) (radius (D,)),
    from ``start`` (in that region; default ``q``)."""
    vg = cost_value_and_grad(wm, model, jnp.asarray(base_quat, F32), jnp.asarray(x0), ref, weights)
    q0, r = jnp.asarray(q, F32), jnp.asarray(radius, F32)
    z0 = np.zeros(q.shape) if start is None else np.arctanh(np.clip((start - q) / radius, -0.99, 0.99))

    def vg_z(z: Any) -> Any:
        th = jnp.tanh(z)
        out, g = vg(q0 + r * th)
        return out, g * r * (1.0 - th**2)

    best, _ = adam_steps(vg_z, jnp.asarray(z0, F32), steps, lr, steps + 1, 0.0, mask=_first_frame_fixed)
    return np.asarray(q0 + r * jnp.tanh(best), np.float64)


def trust_radius(ctx: Context, trust: float) -> np.ndarray:
    """(D,) how far an optimisation through the model may move each column: ``trust`` x the sampling noise
    std (m for base positions, rad otherwise)."""
    counts = tuple(h.n_joints for h in ctx.prob.scene.hands)
    return trust * noise_std(ctx.cfg.sampling, counts)


def clip_reference(demo: Demo, model: Model, horizon: int = 0) -> tuple[Any, ...]:
    """The objective's reference of frames 1.. (padded by ``horizon`` frames): object positions, quaternions,
    the human keypoints the robot's metric keypoints follow, their indices."""
    kp_index = np.flatnonzero(model.hand.kp_metric)
    pos, quat, kp = window_references(demo, model.hand.kp_human, kp_index, horizon)
    return jnp.asarray(pos, F32), jnp.asarray(quat, F32), jnp.asarray(kp, F32), jnp.asarray(kp_index, jnp.int32)


def prediction_error(wm: WorldModel, buf: ReplayBuffer, horizon: int) -> tuple[float, float]:
    """The model's mean object error (cm, deg) ``horizon`` frames after every frame of ``buf``'s rollouts,
    rolled out on its own predictions with the recorded controls."""
    x, q = buffer_states(buf), np.asarray(buf.q_targets, np.float32)
    T, H = x.shape[1], min(horizon, x.shape[1] - 1)
    starts = [(r, t) for r in range(len(x)) for t in range(T - H)]
    pred = np.asarray(jax.vmap(wm.rollout)(jnp.asarray([x[r, t] for r, t in starts]),
                                           jnp.asarray([q[r, t : t + H + 1] for r, t in starts]))[:, -1])  # fmt: skip
    true = np.stack([x[r, t + H] for r, t in starts])
    D = wm.norm.n_dof
    pos = np.linalg.norm(pred[:, 2 * D : 2 * D + 3] - true[:, 2 * D : 2 * D + 3], axis=-1) * 100.0
    rot = quat_angle_deg(pred[:, 2 * D + 3 : 2 * D + 7], true[:, 2 * D + 3 : 2 * D + 7])
    return float(np.mean(pos)), float(np.mean(rot))


def model_mpc(demo: Demo, wm: WorldModel, model: Model, base_quat: np.ndarray, plan: np.ndarray, o: NeuralOptions,
              weights: Weights, target: Target, radius: np.ndarray) -> np.ndarray:  # fmt: skip
    """Closed-loop MPC in ``target`` with the model (module docstring, step 3), each window within ``radius``
    (D,) of the plan; returns the PD targets applied (T, D)."""
    T, H = len(plan), o.mpc_horizon
    ref = clip_reference(demo, model, H)
    w = weights.arrays()
    plan = np.concatenate([plan, np.repeat(plan[-1:], H, 0)])
    anchor = plan.copy()

    def choose(t: int, obs: dict[str, np.ndarray]) -> np.ndarray:
        fw = jnp.asarray((np.arange(t + 1, t + H + 1) < T).astype(np.float32))
        win_ref = (*(r[t + 1 : t + H + 1] for r in ref[:3]), ref[3], fw)
        win = slice(t, t + H + 1)
        plan[win] = plan_through(wm, model, base_quat, observation_state(obs), anchor[win], win_ref, w, o.mpc_steps,
                                 o.mpc_lr, radius, plan[win])  # fmt: skip
        return plan[t + 1]

    return drive_target(target, plan[:T].copy(), demo.fps, choose)


def drive_target(target: Target, applied: np.ndarray, fps: float, choose: Any) -> np.ndarray:
    """Closed loop in ``target`` from ``applied`` (T, D; its frames 0 and 1 set the start and its velocity):
    at every frame ``t`` the PD target of frame ``t + 1`` is ``choose(t, observation)``; returns the PD targets
    applied. After frame 0's choice the target starts over with the hand velocity of the applied targets, as an
    open-loop replay of them does, so that the replay reproduces the run."""
    fps = float(fps)
    target.reset(applied[0], (applied[1] - applied[0]) * fps)
    for t in range(len(applied) - 1):
        applied[t + 1] = choose(t, target.observe())
        if t == 0:
            target.reset(applied[0], (applied[1] - applied[0]) * fps)
        target.advance(applied[t], applied[t + 1])
    return applied


def model_rollouts(ctx: Context, q: np.ndarray, o: NeuralOptions, seed: int, target: Target) -> ReplayBuffer:
    """Controls ``q`` (T, D) and ``o.variants`` noisy variants of them (``seed``) rolled out in ``target``."""
    scene, cfg = ctx.prob.scene, ctx.cfg
    return collect(scene, [q, *noisy_variants(q, o.variants, cfg.sampling, seed, scene)], ctx.prob.demo.fps,
                   target.name)  # fmt: skip


def neural_method(ctx: Context, q0: np.ndarray, o: NeuralOptions, target: Target) -> dict[str, Any]:
    """Steps 1-3 of the module docstring from controls ``q0`` (T, D); the checkpoint's arrays."""
    prob, cfg, progress, radius = ctx.prob, ctx.cfg, ctx.progress, trust_radius(ctx, o.trust)
    demo, scene, model, bq = prob.demo, prob.scene, prob.model, prob.base_quat
    w, T = cfg.weights.arrays(), demo.n_frames
    pos, quat, kp, kp_index = clip_reference(demo, model)
    ref = (pos[1:], quat[1:], kp[1:], kp_index, jnp.ones(T - 1, F32))

    def rollouts(q: np.ndarray, seed: int) -> ReplayBuffer:
        return model_rollouts(ctx, q, o, seed, target)

    def refit(wm: WorldModel, buf: ReplayBuffer, seed: int) -> tuple[WorldModel, list[float]]:
        return fit(wm, buf, o.horizon, o.steps, o.lr, o.batch, seed)

    buf = rollouts(q0, o.seed)
    wm = WorldModel(init_layers(scene.n_dof, o.widths, o.seed), Norm.of(buf))
    wm, losses = refit(wm, buf, o.seed)
    best_q, q, x0 = q0, q0, buffer_states(buf)[0, 0]
    costs, errors, best = [target.judge(demo, q0, cfg.weights)], [], 0
    for r in range(1, o.rounds + 1):
        q = plan_through(wm, model, bq, x0, q, ref, w, o.plan_steps, o.plan_lr, radius)
        costs.append(target.judge(demo, q, cfg.weights))
        if costs[-1] < costs[best]:
            best, best_q = r, q
        new = rollouts(q, o.seed + r)
        errors.append(prediction_error(wm, new, o.horizon))
        buf, x0 = buf.extended(new, 10**6), buffer_states(new)[0, 0]
        wm, more = refit(wm, buf, o.seed + r)
        losses += more
        progress.write(
            f"stage neural round {r}/{o.rounds}: objective in the target {costs[-1]:.4f} (best {costs[best]:.4f}); "
            f"the model predicted this round's rollouts to {errors[-1][0]:.2f} cm / {errors[-1][1]:.1f} deg after "
            f"{o.horizon} frames"
        )
    q_mpc = model_mpc(demo, wm, model, bq, best_q, o, cfg.weights, target, radius) if o.mpc_steps > 0 else best_q
    return {
        "q_targets": q_mpc, "plan_q": best_q, "round_costs": np.asarray(costs), "best_round": np.array(best),
        "round_errors": np.asarray(errors, np.float64).reshape(-1, 2), "losses": np.asarray(losses, np.float64),
        "buffer_rollouts": np.array(buf.n_rollouts),
    }  # fmt: skip


def run(ctx: Context, out: Outcome) -> Outcome:
    """Stage ``neural`` from the outcome's controls (module docstring); the result's PD targets are MPC's, the
    rounds' best stays a candidate (``plan``)."""
    prob, o = ctx.prob, options(ctx)
    if prob.demo.n_frames < 3:
        raise QuasisimError(f"stage neural: the clip has {prob.demo.n_frames} frames; it needs at least 3")
    T, D = prob.demo.n_frames, prob.scene.n_dof

    def compute() -> dict[str, Any]:
        with make_target(ctx.spec.target, prob.scene) as target:
            return neural_method(ctx, np.asarray(out.q, np.float64), o, target)

    expect = {"q_targets": (T, D), "plan_q": (T, D), "round_costs": (o.rounds + 1,), "best_round": (),
              "round_errors": (o.rounds, 2), "losses": (None,), "buffer_rollouts": ()}  # fmt: skip
    d = timed(ctx.ck, "neural", compute, expect)
    rec = ctx.record
    rec.seconds["neural"] = float(d["wall_s"])
    rec.curves["stage neural model fit (minibatch loss)"] = [float(x) for x in d["losses"]]
    rec.fit = {"neural_round_costs": d["round_costs"].tolist(), "neural_round_errors": d["round_errors"].tolist(),
               "best_round": int(d["best_round"]), "buffer_rollouts": int(d["buffer_rollouts"])}  # fmt: skip
    ctx.progress.write(f"stage neural done in {rec.seconds['neural']:.0f} s; kept round {int(d['best_round'])}")
    seen = {**out.seen, "plan": np.asarray(d["plan_q"], np.float64)}
    return out.replace(q=np.asarray(d["q_targets"], np.float64), planned=True, seen=seen)


STAGE = Stage(
    name="neural",
    word="neural",
    config=("neural",),
    s_per_frame=2.0,
    run=run,
    plans=True,
    uses_target=True,
)
