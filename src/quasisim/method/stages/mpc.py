"""Closed-loop model-predictive control in the target simulator with the quasi-physical simulator as model.

At every frame ``t`` (paper appendix "Tracking via closed-loop MPC"):

1. observe the target's state (hand joints and velocities, object pose and twist);
2. put it into the quasi-physical simulator and optimise the PD targets of frames ``t+1 .. t+H`` of the plan
   (a few Adam steps on ``w_o f_O + w_h f_H`` over the window, from the plan's current values);
3. apply the first frame (targets ``t -> t+1``) in the target and keep the rest of the window as the plan.

Methods built on it (``--method``): ``mpc-base`` (the stiffest analytical simulator, the object's nominal S,
planning from the kinematic retarget), ``mpc-soften`` (the same with each gradient averaged over contact
stiffnesses drawn within +-10 %, randomized smoothing as in Bundled Gradients) and ``ours`` (planning from
the stage-2 trajectory with the identified S). The loop drives any :class:`~quasisim.targets.base.Target`
(``reset``, ``observe``, ``advance``); the command line runs it in MuJoCo only (``quasisim.method.spec``).

The stage (``--stages ...,mpc``, :data:`STAGE`, :func:`run`) runs it from the plan with the simulator after
stage 2 (or stage 3's fitted one) as the model; the plan's PD targets stay a candidate of the selection.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from quasisim.data.demo import Demo
from quasisim.method.options import MPCOptions
from quasisim.method.stage import Context, Outcome, Stage
from quasisim.method.stages._common import q_expect
from quasisim.optim.adam import adam_steps
from quasisim.optim.objective import Weights, WindowObjective, make_window_objective, padded, window_references
from quasisim.optim.trajectory import Trajectory, observed_state
from quasisim.sim.types import Model, Params, State
from quasisim.targets import Observation, Target, TargetRollout, make_target
from quasisim.targets.scene import Scene

Array = jax.Array
F32 = jnp.float32


@dataclass(frozen=True, eq=False)
class MPCResult:
    q_targets: np.ndarray  # (T, 6 + J) the PD targets applied in the target
    rollout: TargetRollout  # the closed-loop run in the target
    window_loss: np.ndarray  # (T - 1,) best window loss per frame
    window_loss_start: np.ndarray  # (T - 1,) loss of the plan's window before the frame's Adam steps
    wall_s: float


def _gradient_fn(f: WindowObjective, w: dict[str, Array], opts: MPCOptions) -> Any:
    """Compiled value and gradient of the window objective ``f``: ``vg(win, s0, p, *ref)``; with
    ``opts.soften``, ``vg(win, s0, p, scales, *ref)``, the mean over contact stiffnesses scaled by
    ``scales`` (S, 3): k_n, k_f, k_d."""
    return functools.partial(_vg_soft if opts.soften else _vg_plain, f, w)


@jax.jit
def _vg_plain(f: WindowObjective, w: dict[str, Array], win: Trajectory, s0: State, p: Params, *ref: Array) -> Any:
    return jax.value_and_grad(f, has_aux=True)(win, s0, p, *ref, w)


@jax.jit
def _vg_soft(
    f: WindowObjective, w: dict[str, Array], win: Trajectory, s0: State, p: Params, scales: Array, *ref: Array
) -> Any:
    def one(sc: Array) -> Any:
        ps = dataclasses.replace(p, k_n=p.k_n * sc[0], k_f=p.k_f * sc[1], k_d=p.k_d * sc[2])
        return jax.value_and_grad(f, has_aux=True)(win, s0, ps, *ref, w)

    (loss, terms), g = jax.vmap(one)(scales)
    mean = lambda x: jnp.mean(x, axis=0)  # noqa: E731
    return (mean(loss), jax.tree_util.tree_map(mean, terms)), jax.tree_util.tree_map(mean, g)


def _mask_first_frame(g: Trajectory) -> Trajectory:
    """Frame 0 of a window is the target the step starts from: it is not optimised."""
    return dataclasses.replace(g, base=g.base.at[0].set(0.0), joints=g.joints.at[0].set(0.0))


def run_mpc(
    demo: Demo, scene: Scene, model: Model, params: Params, plan: np.ndarray, opts: MPCOptions, weights: Weights,
    progress: bool = True, target: str | Target = "mujoco",
) -> MPCResult:  # fmt: skip
    """Closed-loop MPC in ``target`` (a name of :data:`~quasisim.targets.TARGETS`, built for ``scene``, or a
    :class:`~quasisim.targets.base.Target`, left open) from the PD-target plan ``plan`` (T, D); ``params`` is
    the model (with S already applied). See the module docstring."""
    if isinstance(target, str):
        with make_target(target, scene) as tgt:
            return _closed_loop(demo, model, params, plan, opts, weights, progress, tgt)
    return _closed_loop(demo, model, params, plan, opts, weights, progress, target)


def _closed_loop(
    demo: Demo, model: Model, params: Params, plan: np.ndarray, opts: MPCOptions, weights: Weights, progress: bool,
    target: Target,
) -> MPCResult:  # fmt: skip
    T, H = len(plan), opts.horizon
    scene = target.scene
    kp_index = np.flatnonzero(model.hand.kp_metric)
    bq = jnp.asarray(scene.base_quat, F32)
    vg = _gradient_fn(make_window_objective(model, bq, demo.fps, kp_index), weights.arrays(), opts)
    rng = np.random.default_rng(opts.seed)
    refs = window_references(demo, model.hand.kp_human, kp_index, H)
    plan = padded(np.asarray(plan, np.float64), H)
    applied = plan.copy()
    target.reset(plan[0], (plan[1] - plan[0]) * demo.fps)
    frames: list[Observation] = []
    losses = []
    t0 = time.perf_counter()
    for t in tqdm(range(T), desc="mpc", unit="frame", disable=not progress, leave=False):
        frames.append(target.observe())
        if t == T - 1:
            break
        s0 = observed_state(model, frames[-1], bq)
        fw = (np.arange(t + 1, t + H + 1) < T).astype(np.float32)
        ref = (*(jnp.asarray(x[t + 1 : t + H + 1], F32) for x in refs), jnp.asarray(fw))
        if opts.soften > 0:
            scales = jnp.asarray(1.0 + rng.uniform(-opts.soften_range, opts.soften_range, (opts.soften, 3)), F32)
            fn = lambda x, s0=s0, ref=ref, scales=scales: vg(x, s0, params, scales, *ref)  # noqa: E731
        else:
            fn = lambda x, s0=s0, ref=ref: vg(x, s0, params, *ref)  # noqa: E731
        win0 = Trajectory.from_q(plan[t : t + H + 1], model.n_points, model.hand.hand_joints)
        win, log = adam_steps(fn, win0, opts.steps, opts.lr, opts.steps + 1, 0.0, mask=_mask_first_frame)
        losses.append((log.best, log.losses[0] if log.losses else np.nan))
        plan[t : t + H + 1] = win.q_targets
        applied[t + 1] = plan[t + 1]
        if t == 0:  # start over with the hand velocity of the applied targets, as a replay of them does
            target.reset(applied[0], (applied[1] - applied[0]) * demo.fps)
            frames = [target.observe()]
        target.advance(applied[t], applied[t + 1])
    wall = time.perf_counter() - t0
    best, start = np.asarray(losses).reshape(-1, 2).T
    return MPCResult(applied[:T], target.recorded(frames, wall), best, start, wall)


def run(ctx: Context, out: Outcome) -> Outcome:
    """MPC from the plan, with the simulator after stage 2 (or stage 3's fitted one) as the model; the plan's
    PD targets are kept for the selection as ``plan``."""
    prob, cfg, spec = ctx.prob, ctx.cfg, ctx.spec
    model, params = out.simulator(ctx)
    traj: Trajectory = out.plan.traj

    def mpc() -> dict[str, Any]:
        r = run_mpc(prob.demo, prob.scene, model, params, traj.q_targets, cfg.mpc, cfg.weights, spec.progress)
        return {"q_targets": r.q_targets, "window_loss": r.window_loss, "wall_s": np.array(r.wall_s)}

    d = ctx.ck.get("mpc", mpc, q_expect(prob))
    ctx.record.seconds["mpc"] = float(d["wall_s"])
    ctx.record.curves["mpc window loss per frame"] = [float(x) for x in d["window_loss"]]
    ctx.progress.write(f"mpc done in {ctx.record.seconds['mpc']:.0f} s")
    seen = {**out.seen, "plan": out.q}
    return out.replace(q=np.asarray(d["q_targets"], np.float64), planned=True, seen=seen)


STAGE = Stage(
    name="mpc",
    word="mpc",
    config=("mpc",),
    s_per_frame=1.5,
    run=run,
    plans=True,
    uses_simulator=True,
    uses_target=True,
)
