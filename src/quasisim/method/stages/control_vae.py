"""Stage ``control_vae``: the paper's Control-VAE baseline adapted to tracking (its supplement: a world model of
the hand and the object, an MLP, and a generative controller trained through it; :mod:`quasisim.method.
control_vae`), judged in the target like every method.

1. **Buffer and world model**: as stage ``neural``'s first step (the current controls, the kinematic retarget, and
   ``neural.variants`` noisy variants rolled out in the target; the MLP of ``neural.widths`` fitted to them).
2. **Rounds** (``rounds`` times): the controller trained through the model (``steps`` minibatch Adam steps on
   ``horizon``-frame windows starting at every recorded frame), then it drives the target closed loop from the
   clip's start (observed states, the posterior's mean); the PD targets it applied are judged there (the best
   kept) and, with noisy variants of them, join the buffer, and the model is refitted.

The result is the PD targets the controller applied in the nominal target: replayed open loop they reproduce that
run, so the row is judged, perturbed worlds included, on them as every row is (the controller itself is not
carried into the perturbed worlds). The controller acts within ``trust`` x the sampling noise std of the
kinematic retarget (as stage ``neural``'s trust region), which it starts from.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from quasisim.data.demo import Demo
from quasisim.errors import InputError, QuasisimError
from quasisim.method.control_vae import (
    Controller,
    act,
    batch_loss_and_grad,
    goal,
    init_controller,
    starts,
)
from quasisim.method.options import ControlVAEOptions
from quasisim.method.replay import ReplayBuffer
from quasisim.method.stage import Context, Outcome, Stage
from quasisim.method.stages._common import timed
from quasisim.method.stages.neural import clip_reference, drive_target, model_rollouts, trust_radius
from quasisim.method.stages.neural import options as neural_options
from quasisim.method.world_model import Norm, WorldModel, buffer_states, fit, init_layers, observation_state
from quasisim.optim.adam import minibatch_adam
from quasisim.targets import Target, make_target

F32 = jnp.float32


def options(ctx: Context) -> ControlVAEOptions:
    """The stage's settings; a config without them is refused."""
    o = ctx.cfg.section("control_vae", "control_vae")
    if not o.widths or min(o.widths) < 1 or o.sigma <= 0:
        raise InputError(ctx.cfg.path or None, "control_vae", "layer widths >= 1 and sigma > 0", str(o))
    return o


def train(ctrl: Controller, wm: WorldModel, ctx: Context, buf: ReplayBuffer, k: np.ndarray, ref: tuple[Any, ...],
          radius: np.ndarray, o: ControlVAEOptions, seed: int) -> tuple[Controller, list[float]]:  # fmt: skip
    """``o.steps`` minibatch Adam steps on the controller through the model ``wm`` (windows from every frame of
    ``buf``); the best iterate on a fixed check subset, and the minibatch losses."""
    prob, w = ctx.prob, ctx.cfg.weights.arrays()
    data = starts(buffer_states(buf), np.asarray(buf.q_targets, np.float32), k, ref, o.horizon, o.latent, seed)
    r, bq = jnp.asarray(radius, F32), jnp.asarray(prob.base_quat, F32)

    def vg(nets: Any, batch: Any) -> Any:
        return batch_loss_and_grad(nets, wm.layers, wm.norm, prob.model, bq, batch, r, o.sigma, o.beta, w)

    nets, losses = minibatch_adam(vg, ctrl.tree(), data, o.steps, o.lr, o.batch, seed, desc="control-vae fit")
    return Controller(*nets), losses


def drive(ctrl: Controller, norm: Norm, demo: Demo, k: np.ndarray, ref: tuple[Any, ...], radius: np.ndarray,
          sigma: float, target: Target) -> np.ndarray:  # fmt: skip
    """The PD targets (T, D) the controller applies in ``target`` from the clip's start, acting on each
    observed state with the posterior's mean."""
    pos, quat = np.asarray(ref[0]), np.asarray(ref[1])
    zeros, r = jnp.zeros(len(ctrl.prior[-1][1]), F32), jnp.asarray(radius, F32)
    policy = jax.jit(lambda x, p, q, kn: act(ctrl.tree(), norm, x, goal(x, p, q, kn, norm), kn, r, zeros, sigma)[0])

    def choose(t: int, obs: dict[str, np.ndarray]) -> np.ndarray:
        x = jnp.asarray(observation_state(obs))
        return np.asarray(policy(x, pos[t + 1], quat[t + 1], jnp.asarray(k[t + 1], F32)), np.float64)

    return drive_target(target, np.array(k[: demo.n_frames], np.float64), demo.fps, choose)


def control_vae_method(ctx: Context, q0: np.ndarray, o: ControlVAEOptions, target: Target) -> dict[str, Any]:
    """Steps 1-2 of the module docstring from controls ``q0`` (T, D); the checkpoint's arrays."""
    prob, cfg, nn = ctx.prob, ctx.cfg, neural_options(ctx)
    demo, scene = prob.demo, prob.scene
    radius = trust_radius(ctx, o.trust)
    ref = tuple(np.asarray(a) for a in clip_reference(demo, prob.model, o.horizon))
    k = np.concatenate([q0, np.repeat(q0[-1:], o.horizon, 0)])

    def rollouts(q: np.ndarray, seed: int) -> ReplayBuffer:
        return model_rollouts(ctx, q, nn, seed, target)

    buf = rollouts(q0, o.seed)
    wm = WorldModel(init_layers(scene.n_dof, nn.widths, nn.seed), Norm.of(buf))
    wm, wm_losses = fit(wm, buf, nn.horizon, nn.steps, nn.lr, nn.batch, o.seed)
    ctrl = init_controller(scene.n_dof, o.widths, o.latent, o.seed)
    best_q, costs, best, losses = q0, [target.judge(demo, q0, cfg.weights)], 0, []
    for rnd in range(1, o.rounds + 1):
        ctrl, more = train(ctrl, wm, ctx, buf, k, ref, radius, o, o.seed + rnd)
        losses += more
        q = drive(ctrl, wm.norm, demo, k, ref, radius, o.sigma, target)
        costs.append(target.judge(demo, q, cfg.weights))
        if costs[-1] < costs[best]:
            best, best_q = rnd, q
        buf = buf.extended(rollouts(q, o.seed + rnd), 10**6)
        wm, more_wm = fit(wm, buf, nn.horizon, nn.steps, nn.lr, nn.batch, o.seed + rnd)
        wm_losses += more_wm
        ctx.progress.write(f"stage control_vae round {rnd}/{o.rounds}: objective in the target {costs[-1]:.4f} "
                           f"(best {costs[best]:.4f})")  # fmt: skip
    return {
        "q_targets": best_q, "round_costs": np.asarray(costs), "best_round": np.array(best),
        "losses": np.asarray(losses, np.float64), "model_losses": np.asarray(wm_losses, np.float64),
        "buffer_rollouts": np.array(buf.n_rollouts),
    }  # fmt: skip


def run(ctx: Context, out: Outcome) -> Outcome:
    """Stage ``control_vae`` from the outcome's controls (module docstring)."""
    prob, o = ctx.prob, options(ctx)
    if prob.demo.n_frames < 3:
        raise QuasisimError(f"stage control_vae: the clip has {prob.demo.n_frames} frames; it needs at least 3")
    T, D = prob.demo.n_frames, prob.scene.n_dof

    def compute() -> dict[str, Any]:
        with make_target(ctx.spec.target, prob.scene) as target:
            return control_vae_method(ctx, np.asarray(out.q, np.float64), o, target)

    expect = {"q_targets": (T, D), "round_costs": (o.rounds + 1,), "best_round": (), "losses": (None,),
              "model_losses": (None,), "buffer_rollouts": ()}  # fmt: skip
    d = timed(ctx.ck, "control_vae", compute, expect)
    rec = ctx.record
    rec.seconds["control_vae"] = float(d["wall_s"])
    rec.curves["stage control_vae controller fit (minibatch loss)"] = [float(x) for x in d["losses"]]
    rec.curves["stage control_vae model fit (minibatch loss)"] = [float(x) for x in d["model_losses"]]
    rec.fit = {"control_vae_round_costs": d["round_costs"].tolist(), "best_round": int(d["best_round"]),
               "buffer_rollouts": int(d["buffer_rollouts"])}  # fmt: skip
    ctx.progress.write(f"stage control_vae done in {rec.seconds['control_vae']:.0f} s; kept round "
                       f"{int(d['best_round'])}")  # fmt: skip
    return out.replace(q=np.asarray(d["q_targets"], np.float64), planned=True)


STAGE = Stage(
    name="control_vae",
    word="control_vae",
    config=("neural", "control_vae"),
    s_per_frame=2.0,
    run=run,
    plans=True,
    uses_target=True,
)
