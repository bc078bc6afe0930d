"""Stage 3: fit the quasi-physical simulator to the target (paper appendix "Optimizing towards a realistic
physical environment").

1. **Replay buffer** (:class:`~quasisim.method.replay.ReplayBuffer`, :func:`~quasisim.method.replay.collect`):
   PD-target trajectories (the current controls and noisy variants of them) rolled out in the target
   (:func:`~quasisim.targets.make_target`, its ``reset``/``observe``/``advance``); per frame the hand's joints
   and velocities, the object's pose and twist, the robot keypoints and the PD targets.
2. **Windows** (:func:`~quasisim.method.replay.windows`): from a recorded frame ``t`` the target's state is put into the
   quasi-physical simulator (contacts start fresh) and the recorded PD targets of frames ``t+1 .. t+H`` are
   applied; the prediction is compared with what the target did (object position, rotation, keypoints).
3. **Fit** (:func:`fit`): Adam on the mean H-frame prediction error of training windows over
   :class:`SimFit`: S (object mass, inertia, velocity damping) and the contact and joint constants
   (contact stiffness scale, friction coefficient, joint damping, PD gain scale), all in log coordinates;
   then, optionally, the residual networks and the control transformation (:mod:`quasisim.sim.residual`,
   zero at start) on the same loss (:func:`fit_networks`).
4. **Measure** (:func:`quasisim.method.replay.prediction_errors`): the error after ``h = 1..H`` frames on windows the fit never
   saw (the clip's later frames), beside the zero-motion predictor (the object stays where it is).
5. **World-model rounds** (:func:`world_model_rounds`): optimise the controls in the fitted simulator, roll
   them out in the target (kept when the target judges them best: its
   :meth:`~quasisim.targets.base.Target.judge`), add the rollouts to the buffer, refit.

The loss is the tracking objective's terms (:func:`quasisim.optim.objective.tracking_errors`) between the
predicted and the recorded trajectory: object translation (m), ``1 - |q . q_ref|`` and keypoint distance (m).

The stage (``--stages ...,3``, :data:`STAGE`, :func:`run`) fits the curriculum's stiffest simulator, with S
from stage 2, and runs the rounds in one checkpoint (``stage3``); its fitted simulator is the model of the
MPC that follows.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from quasisim.errors import QuasisimError
from quasisim.method import spec
from quasisim.method.options import FitOptions, SamplingOptions
from quasisim.method.replay import ReplayBuffer, Windows, collect, predict, prediction_errors, split_starts, windows
from quasisim.method.stage import Context, Outcome, Plan, Stage
from quasisim.method.stages.contact_curriculum import one_simulator
from quasisim.method.stages.sampling import scene_sampler
from quasisim.optim.adam import Progress, minibatch_adam
from quasisim.optim.objective import tracking_errors, weighted_sum
from quasisim.optim.sysid import SysID
from quasisim.optim.trajectory import Trajectory
from quasisim.sim.build import attach_control_transform, attach_residual
from quasisim.sim.residual import ControlTransform, ResidualConfig, ResidualNets
from quasisim.sim.types import NETWORKS, Model, Params, pytree
from quasisim.targets import make_target
from quasisim.targets.scene import Scene

Array = jax.Array
F32 = jnp.float32


def noisy_variants(plan: np.ndarray, n: int, noise: SamplingOptions, seed: int, scene: Scene) -> list[np.ndarray]:
    """``n`` smooth perturbations of ``plan`` (T, D) with the sampling baseline's noise model (knots every
    ~6 frames, the noise scales cycled), joints kept within the joint ranges of ``scene``'s hands."""
    T = len(plan)
    opts = dataclasses.replace(noise, samples=n + 1, horizon=T - 1, knots=max(2, (T - 1) // 6))
    wins = scene_sampler(opts, scene)(np.random.default_rng(seed), plan)
    return list(wins[1:])


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


def fit(
    model: Model, params: Params, train: Windows, fps: float, base_quat: np.ndarray, mass0: float,
    inertia0: np.ndarray, opts: FitOptions, weights: dict[str, Array], start: SimFit | None = None,
    progress: Progress | None = None,
) -> tuple[SimFit, list[float]]:  # fmt: skip
    """Adam on :class:`SimFit` (from ``start``, default nominal) over random batches of the training
    windows; returns the fit and the losses."""

    const = (model, params, jnp.asarray(mass0, jnp.float32), jnp.asarray(inertia0, jnp.float32))
    vg = functools.partial(_fit_vg, const, jnp.asarray(base_quat, jnp.float32), weights, fps=fps)
    desc = "stage 3 fit S and constants"
    return minibatch_adam(
        vg, start or SimFit.nominal(), train, opts.steps, opts.lr, opts.batch, opts.seed, progress=progress, desc=desc
    )


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


NETWORK_NAMES = spec.NETWORKS  # residual networks (local, global), control transformation: one definition


def fit_networks(
    model: Model, params: Params, train: Windows, fps: float, base_quat: np.ndarray, opts: FitOptions,
    weights: dict[str, Array], cfg: ResidualConfig, networks: tuple[str, ...] = NETWORK_NAMES,
    progress: Progress | None = None,
) -> tuple[Model, Params, list[float]]:  # fmt: skip
    """Train the ``networks`` (of :data:`NETWORK_NAMES`) of the simulator ``params`` together on the training
    windows: those not attached yet are attached first, zero at start (:mod:`quasisim.sim.residual`); attached
    ones continue from their weights. Returns the model, params and losses."""
    bad = set(networks) - set(NETWORK_NAMES)
    if bad:
        raise QuasisimError(f"unknown network {sorted(bad)[0]!r}; valid: {', '.join(NETWORK_NAMES)}")
    m, p0 = model, params
    if {"local", "global"} & set(networks) and params.residual is None:
        nets = ResidualNets(cfg, seed=opts.seed)
        m, p0 = attach_residual(m, p0, nets, "local" in networks, "global" in networks)
    if "control" in networks and params.control_transform is None:
        m, p0 = attach_control_transform(
            m, p0, ControlTransform(cfg, model.hand.n_joints, model.hand.n_hands, seed=opts.seed)
        )
    trained = {k: getattr(p0, k) for k in NETWORKS if getattr(p0, k) is not None}
    if not trained or opts.residual_steps == 0:
        return m, p0, []

    vg = functools.partial(_networks_vg, (m, p0), jnp.asarray(base_quat, jnp.float32), weights, fps=fps)
    desc = f"stage 3 fit networks ({', '.join(networks)})"
    nets, losses = minibatch_adam(vg, trained, train, opts.residual_steps, opts.residual_lr, opts.batch, opts.seed + 1,
                         progress=progress, desc=desc)  # fmt: skip
    return m, p0.replace(**nets), losses


@functools.partial(jax.jit, static_argnames=("fps",))
def _networks_vg(
    const: tuple[Model, Params], base_quat: Array, weights: dict[str, Array], nets: dict[str, Any], batch: Windows,
    fps: float,
) -> tuple[Array, Any]:  # fmt: skip
    """Value and gradient of the window loss of a ``batch`` w.r.t. the network weights ``nets``; ``const``: the
    model and the simulator (with S and the constants applied). Module level, with the model and simulator as
    arguments, so every round of a clip, and every clip of a hand, reuses one compiled program."""
    model, params = const
    return jax.value_and_grad(lambda n: window_loss(model, params.replace(**n), batch, fps, base_quat, weights))(nets)


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
    plans = [plan, *noisy_variants(plan, opts.variants, noise, opts.seed, prob.scene)]
    buf = collect(prob.scene, plans, demo.fps)
    train = windows(m, buf, train_s, opts.horizon, bq)
    test = windows(m, buf, [s for s in test_s if s[0] == 0], opts.horizon, bq)
    return train, test, buf


def fit_to_target(
    prob: Any, params: Params, plan: np.ndarray, sysid: SysID, opts: FitOptions, noise: SamplingOptions,
    weights: dict[str, Array], networks: tuple[str, ...] = (), progress: Progress | None = None,
) -> tuple[dict[str, Any], Model, Params, SimFit, ReplayBuffer]:  # fmt: skip
    """Stage 3's first fit for one plan (T, 6 + J) of a :class:`~quasisim.method.problem.Problem`: a replay
    buffer of the plan and noisy variants in MuJoCo, the fit of :class:`SimFit` from S ``sysid`` on the
    training windows, then the ``networks`` (:func:`fit_networks`), and the held-out ``H``-frame errors
    before and after. Returns the checkpoint arrays, the model and the simulator ``params`` with the networks
    (S and constants not applied), the fit and the buffer."""
    demo, bq, obj = prob.demo, prob.base_quat, prob.obj
    train, test, buf = fit_windows(prob, plan, opts, noise)
    start = SimFit.nominal(sysid)
    # the networks are attached (zero at start, so the simulator is the analytical one) before S is fitted: every
    # fit of S, here and in the rounds, then runs one compiled program, and so do both held-out measurements
    m, p0 = network_template(prob.model, params, networks, opts.seed) if networks else (prob.model, params)
    f, losses = fit(m, p0, train, demo.fps, bq, obj.mass, obj.inertia, opts, weights, start, progress)
    p_fit, net_losses = p0, []
    if networks:
        _, p_n, net_losses = fit_networks(m, f.apply(p0, obj.mass, obj.inertia), train, demo.fps, bq, opts, weights,
                                          ResidualConfig(), networks, progress)  # fmt: skip
        p_fit = with_networks(p0, p_n)
    before = prediction_errors(m, start.apply(p0, obj.mass, obj.inertia), test, demo.fps, bq)
    after = prediction_errors(m, f.apply(p_fit, obj.mass, obj.inertia), test, demo.fps, bq)
    d = {
        "fit": f.as_array(), "losses": np.asarray(losses, np.float64), "network_losses": np.asarray(net_losses, np.float64),
        "held_out_before": np.array([before.obj_pos_cm[-1], before.obj_rot_deg[-1], before.keypoints_mm[-1]]),
        "held_out_after": np.array([after.obj_pos_cm[-1], after.obj_rot_deg[-1], after.keypoints_mm[-1]]),
    }  # fmt: skip
    return d, m, p_fit, f, buf


_NETWORK_FIELDS = (*NETWORKS, "residual_local_on", "residual_global_on")


def with_networks(params: Params, source: Params) -> Params:
    """``params`` with the networks (weights and switches) of ``source``."""
    return params.replace(**{k: getattr(source, k) for k in _NETWORK_FIELDS})


def network_template(model: Model, params: Params, networks: tuple[str, ...], seed: int) -> tuple[Model, Params]:
    """``model`` and ``params`` with freshly initialised ``networks`` attached (the structure a checkpoint's
    :func:`network_vector` is read back into)."""
    opts = FitOptions(horizon=1, held_out=0.5, variants=0, capacity=1, steps=0, lr=0.0, batch=1, residual_steps=0,
                      residual_lr=0.0, rounds=0, seed=seed)  # fmt: skip
    m, p, _ = fit_networks(model, params, None, 0.0, np.zeros(4), opts, {}, ResidualConfig(), networks)  # type: ignore[arg-type]
    return m, p


def network_vector(params: Params) -> np.ndarray:
    """All network weights of ``params`` as one float32 vector (P,) (empty without networks)."""
    leaves = jax.tree_util.tree_leaves([getattr(params, k) for k in NETWORKS])
    return np.concatenate([np.ravel(np.asarray(x, np.float32)) for x in leaves]) if leaves else np.zeros(0, np.float32)


def from_network_vector(params: Params, vec: np.ndarray) -> Params:
    """``params`` (with networks attached) with the weights of :func:`network_vector`'s ``vec``."""
    nets = [getattr(params, k) for k in NETWORKS]
    leaves, tree = jax.tree_util.tree_flatten(nets)
    if sum(x.size for x in leaves) != len(vec):
        raise QuasisimError(
            f"stage 3 checkpoint: {len(vec)} network weights, the networks have {sum(x.size for x in leaves)}"
        )
    out, i = [], 0
    for x in leaves:
        out.append(jnp.asarray(vec[i : i + x.size].reshape(x.shape), x.dtype))
        i += x.size
    return params.replace(**dict(zip(NETWORKS, jax.tree_util.tree_unflatten(tree, out), strict=True)))


def world_model_rounds(
    prob: Any, model: Model, params: Params, traj: Trajectory, f: SimFit, buf: ReplayBuffer, opts: FitOptions,
    noise: SamplingOptions, weights: dict[str, Array], improve: Callable[[Trajectory, SimFit, Params], Trajectory],
    cost: Callable[[np.ndarray], float], progress: Progress | None = None,
) -> tuple[dict[str, Any], Params]:  # fmt: skip
    """The paper's world-model-style loop (appendix "World model-style training"), ``opts.rounds`` times:

    1. ``improve`` the controls in the fitted simulator (``model``, ``params`` with its networks, the fit ``f``);
    2. roll them and ``opts.variants`` noisy variants out in the target and judge them there (``cost``, the
       clip objective: :meth:`~quasisim.targets.base.Target.judge`); the best controls seen are kept, so a
       round never makes the result worse;
    3. measure the fitted simulator's ``H``-frame prediction error on the new controls' rollout (windows from
       every frame: rollouts the fit has not seen);
    4. add the new rollouts to the buffer (the newest ``capacity`` kept) and refit from ``f`` on the windows
       of every rollout and frame: S and the constants, then the networks ``params`` holds.

    Returns the checkpoint arrays (the best controls (T, 6 + J), the last fit, per round the target cost
    (round 0: the stage's starting controls) and the prediction error (cm, deg, mm) before the refit, the
    buffer's size) and the params with the refitted networks."""
    demo, bq, obj = prob.demo, prob.base_quat, prob.obj
    attached = tuple(n for n, on in (("local", params.residual is not None), ("global", params.residual is not None),
                                     ("control", params.control_transform is not None)) if on)  # fmt: skip
    best_q = np.asarray(traj.q_targets, np.float64)
    costs, errors, best = [cost(best_q)], [], 0
    T = demo.n_frames
    for r in range(1, opts.rounds + 1):
        traj = improve(traj, f, params)
        q = np.asarray(traj.q_targets, np.float64)
        costs.append(cost(q))
        if costs[-1] < costs[best]:
            best, best_q = r, q
        variants = noisy_variants(q, opts.variants, noise, opts.seed + r, prob.scene)
        new = collect(prob.scene, [q, *variants], demo.fps)
        fresh = windows(model, new, [(0, t) for t in range(T - opts.horizon)], opts.horizon, bq)
        e = prediction_errors(model, f.apply(params, obj.mass, obj.inertia), fresh, demo.fps, bq)
        errors.append([e.obj_pos_cm[-1], e.obj_rot_deg[-1], e.keypoints_mm[-1]])
        buf = buf.extended(new, opts.capacity)
        every = windows(
            model, buf, [(i, t) for i in range(buf.n_rollouts) for t in range(T - opts.horizon)], opts.horizon, bq
        )
        o_r = dataclasses.replace(opts, seed=opts.seed + r)
        f, _ = fit(model, params, every, demo.fps, bq, obj.mass, obj.inertia, o_r, weights, f, progress)
        if attached:
            _, p_n, _ = fit_networks(model, f.apply(params, obj.mass, obj.inertia), every, demo.fps, bq, o_r, weights,
                                     ResidualConfig(), attached, progress)  # fmt: skip
            params = with_networks(params, p_n)
        if progress is not None:
            progress.write(
                f"stage 3 round {r}/{opts.rounds}: objective in the target {costs[-1]:.4f} (best {costs[best]:.4f}); "
                f"the fitted simulator predicted this round's rollout to {errors[-1][0]:.2f} cm / {errors[-1][1]:.1f} deg "
                f"after {opts.horizon} frames"
            )
    d = {
        "q_targets": best_q, "round_fit": f.as_array(), "round_costs": np.asarray(costs, np.float64),
        "round_errors": np.asarray(errors, np.float64).reshape(-1, 3), "best_round": np.array(best),
        "buffer_rollouts": np.array(buf.n_rollouts),
    }  # fmt: skip
    return d, params


def run(ctx: Context, out: Outcome) -> Outcome:
    """Fit the stiffest simulator (S from stage 2) to target rollouts of the plan and its variants (S,
    constants, then ``spec.networks``), then the world-model rounds. The outcome's ``fitted`` simulator (S
    applied) is the model of the MPC that follows; its plan is the best one judged in the target."""
    prob, cfg, spec, progress = ctx.prob, ctx.cfg, ctx.spec, ctx.progress
    o, sb, w2 = cfg.stage3, cfg.budget(spec.budget).sim, cfg.weights.arrays(points=0.0)
    nets = spec.networks if o.residual_steps > 0 else ()
    mass, inertia = prob.obj.mass, prob.obj.inertia
    params, plan = ctx.stiffest(), out.plan

    def fit() -> dict[str, Any]:
        t0 = time.perf_counter()
        w = cfg.weights.arrays()
        d, model, p, f, buf = fit_to_target(
            prob, params, plan.traj.q_targets, plan.sysid, o, cfg.sampling, w, nets, progress
        )
        b, a = d["held_out_before"], d["held_out_after"]
        progress.write(
            f"stage 3: held-out {o.horizon}-frame error {b[0]:.2f} cm / {b[1]:.1f} deg -> {a[0]:.2f} cm / {a[1]:.1f} deg"
        )
        vg = dataclasses.replace(out.objective, model=model).value_and_grad  # the objective in the fitted simulator

        def improve(traj: Trajectory, f: SimFit, p: Params) -> Trajectory:
            budget = dataclasses.replace(sb, sysid_steps=0)
            return one_simulator(
                vg, traj, f.sysid, f.apply_constants(p), w2, budget, progress, "stage 3 (fitted simulator)"
            )[0]

        cost = lambda q: target.judge(prob.demo, q, cfg.weights)  # noqa: E731
        rounds, p = world_model_rounds(prob, model, p, plan.traj, f, buf, o, cfg.sampling, w, improve, cost, progress)
        return {**d, **rounds, "net_weights": network_vector(p), "wall_s": np.array(time.perf_counter() - t0)}

    expect = {"fit": (8,), "losses": (None,), "held_out_before": (3,), "held_out_after": (3,), "round_fit": (8,),
              "round_costs": (o.rounds + 1,), "round_errors": (o.rounds, 3), "best_round": (), "buffer_rollouts": (),
              "q_targets": (prob.demo.n_frames, prob.scene.n_dof), "net_weights": (None,)}  # fmt: skip
    with make_target(spec.target, prob.scene) as target:  # judges the world-model rounds
        d = ctx.ck.get("stage3", fit, expect)
    model, p = network_template(prob.model, params, nets, o.seed) if nets else (prob.model, params)
    p = from_network_vector(p, d["net_weights"]) if nets else p
    f = SimFit.from_array(d["round_fit"])
    _record(ctx, d, f.describe(mass), nets)
    if int(d["best_round"]) > 0:  # a round's controls did better in the target than the stage's start
        plan = Plan(prob.trajectory(d["q_targets"]), plan.sysid)
    return out.replace(plan=plan, q=plan.traj.q_targets, planned=True, fitted=(model, f.apply(p, mass, inertia)))


def _record(ctx: Context, d: dict[str, Any], fitted: dict[str, float], nets: tuple[str, ...]) -> None:
    """The stage's time, fit curve and summary (``summary.json`` ``stage3``)."""
    record = ctx.record
    record.seconds["stage3"] = float(d["wall_s"])
    record.curves["stage 3 fit (minibatch loss)"] = [float(x) for x in d["losses"]]
    b, a = d["held_out_before"], d["held_out_after"]
    record.fit = {
        "fitted": fitted, "networks": list(nets), "held_out_before": b.tolist(), "held_out_after": a.tolist(),
        "round_costs": d["round_costs"].tolist(), "round_errors": d["round_errors"].tolist(),
        "best_round": int(d["best_round"]), "buffer_rollouts": int(d["buffer_rollouts"]),
    }  # fmt: skip
    ctx.progress.write(
        f"stage 3 done in {record.seconds['stage3']:.0f} s; kept round {int(d['best_round'])}'s controls"
    )


STAGE = Stage(
    name="3",
    word="stage3",
    config=("stage3", "networks"),
    s_per_frame=2.0,
    run=run,
    plans=True,
    uses_simulator=True,
    uses_target=True,
)
