"""Closed-loop model-predictive control in the target simulator with the quasi-physical simulator as model.

At every frame ``t`` (paper appendix "Tracking via closed-loop MPC"):

1. observe the target's state (hand joints and velocities, object pose and twist);
2. put it into the quasi-physical simulator and optimise the PD targets of frames ``t+1 .. t+q`` of the plan
   (a few Adam steps on ``w_o f_O + w_h f_H`` over the window, from the plan's current values);
3. apply the first frame (targets ``t -> t+1``) in the target and keep the rest of the window as the plan.

Methods built on it (``--method``): ``mpc-base`` (the stiffest analytical simulator, the object's nominal S,
planning from the kinematic retarget), ``mpc-soften`` (the same with each gradient averaged over contact
stiffnesses drawn within +-10 %, randomized smoothing as in Bundled Gradients) and ``ours`` (planning from
the stage-2 trajectory with the identified S). Only MuJoCo offers a step-by-step session here.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from quasisim.optimize import SysID, Trajectory, Weights, adam_steps, hand_keypoints, root_quats, sim_controls
from quasisim.sim.step import initial_state, object_pose, rollout
from quasisim.sim.types import Model, Params, State

Array = jax.Array
F32 = jnp.float32


@dataclass(frozen=True)
class MPCOptions:
    """Closed-loop MPC settings.

    Attributes:
        horizon: frames optimised at each step (q).  steps: Adam steps per frame.  lr: Adam step size.
        soften: number of stiffness samples per gradient (0: plain gradient; mpc-soften uses 4).
        soften_range: relative half-width of the stiffness samples (0.1 = +-10 %).  seed: sampling seed.
    """

    horizon: int = 4
    steps: int = 3
    lr: float = 1.0e-3
    soften: int = 0
    soften_range: float = 0.1
    seed: int = 0


@dataclass(frozen=True, eq=False)
class MPCResult:
    q_targets: np.ndarray  # (T, 6 + J) the PD targets applied in the target
    rollout: Any  # quasisim.targets.Rollout of the closed-loop run
    window_loss: np.ndarray  # (T - 1,) best window loss per frame
    wall_s: float


def observed_state(model: Model, obs: dict[str, np.ndarray], base_quat: Array) -> State:
    """The quasi-physical state of a target observation (contacts start fresh)."""
    q = jnp.asarray(obs["qpos"], F32)
    rq = root_quats(q[None, :6], base_quat)[0]
    s = initial_state(model, q[:3], rq, q[6:], obs["obj_pos"], obs["obj_quat"])
    return dataclasses.replace(
        s,
        qd=jnp.asarray(obs["qvel"][6:], F32),
        obj_vel=jnp.asarray(obs["obj_vel"], F32),
        obj_angvel=jnp.asarray(obs["obj_angvel"], F32),
    )


def make_window_objective(model: Model, base_quat: np.ndarray, fps: float, kp_index: np.ndarray) -> Any:
    """``f(win, s0, params, ref_pos, ref_quat, ref_kp, frame_w, weights) -> (loss, terms)`` over one window:
    ``win`` (q + 1 frames of PD targets, the first being the targets the step starts from) rolled out from
    the observed state ``s0``; references (q, ...) for the window's frames, ``frame_w`` (q,) masks frames
    past the clip's end."""
    bq = jnp.asarray(base_quat, F32)

    def f(
        win: Trajectory, s0: State, params: Params, ref_pos: Array, ref_quat: Array, ref_kp: Array, frame_w: Array,
        weights: dict[str, Array],
    ) -> tuple[Array, dict[str, Array]]:  # fmt: skip
        states = rollout(model, params, s0, sim_controls(win, bq, fps))
        pos, quat = object_pose(model, states)
        n = jnp.maximum(jnp.sum(frame_w), 1.0)
        t_err = jnp.sqrt(jnp.sum((pos - ref_pos) ** 2, -1) + 1e-12)
        r_err = 1.0 - jnp.abs(jnp.sum(quat * ref_quat, -1))
        kp = hand_keypoints(model, states)[:, kp_index]
        h_err = jnp.mean(jnp.sqrt(jnp.sum((kp - ref_kp) ** 2, -1) + 1e-12), -1)
        terms = {
            "obj_pos": jnp.sum(frame_w * t_err) / n,
            "obj_rot": jnp.sum(frame_w * r_err) / n,
            "hand": jnp.sum(frame_w * h_err) / n,
            "smooth": jnp.mean(jnp.diff(win.base, 2, axis=0) ** 2) + jnp.mean(jnp.diff(win.joints, 2, axis=0) ** 2),
        }
        return sum(weights[k] * v for k, v in terms.items()), terms

    return f


def run_mpc(
    demo: Any,
    scene: Any,
    model: Model,
    params: Params,
    plan: np.ndarray,
    opts: MPCOptions,
    weights: Weights | None = None,
    progress: bool = True,
) -> MPCResult:
    """Closed-loop MPC in MuJoCo from the PD-target plan ``plan`` (T, 6 + J); ``params`` is the model
    (with S already applied). See the module docstring."""
    from quasisim.rotations import np_mat_to_quat
    from quasisim.targets.mujoco_target import MujocoTarget

    hand = model.hand
    T, q = len(plan), opts.horizon
    kp_index = np.flatnonzero(hand.kp_metric)
    bq = np_mat_to_quat(scene.base_rot)
    f = make_window_objective(model, bq, demo.fps, kp_index)
    w = (weights or Weights()).arrays()
    rng = np.random.default_rng(opts.seed)

    def vg_plain(win: Trajectory, s0: State, p: Params, *ref: Array) -> Any:
        return jax.value_and_grad(f, has_aux=True)(win, s0, p, *ref, w)

    if opts.soften > 0:

        def vg_soft(win: Trajectory, s0: State, p: Params, scales: Array, *ref: Array) -> Any:
            def one(sc: Array) -> Any:
                ps = dataclasses.replace(p, k_n=p.k_n * sc[0], k_f=p.k_f * sc[1], k_d=p.k_d * sc[2])
                return vg_plain(win, s0, ps, *ref)

            (loss, terms), g = jax.vmap(one)(scales)
            mean = lambda x: jnp.mean(x, axis=0)  # noqa: E731
            return (mean(loss), jax.tree_util.tree_map(mean, terms)), jax.tree_util.tree_map(mean, g)

        vg = jax.jit(vg_soft)
    else:
        vg = jax.jit(vg_plain)

    def mask(g: Trajectory) -> Trajectory:  # frame 0 of the window is the target the step starts from
        return dataclasses.replace(g, base=g.base.at[0].set(0.0), joints=g.joints.at[0].set(0.0))

    ref_pos = np.concatenate([demo.object_pos, np.repeat(demo.object_pos[-1:], q, 0)])
    ref_quat = np.concatenate([demo.object_quat, np.repeat(demo.object_quat[-1:], q, 0)])
    ref_kp_all = demo.right_joints[:, hand.kp_human[kp_index]]
    ref_kp = np.concatenate([ref_kp_all, np.repeat(ref_kp_all[-1:], q, 0)])
    plan = np.concatenate([np.asarray(plan, np.float64), np.repeat(plan[-1:], q, 0)])
    applied = plan.copy()
    target = MujocoTarget(scene)
    sess = target.session(plan[0], (plan[1] - plan[0]) * demo.fps)
    bqj = jnp.asarray(bq, F32)
    losses = []
    t0 = time.perf_counter()
    from tqdm import tqdm

    for t in tqdm(range(T), desc="mpc", unit="frame", disable=not progress, leave=False):
        sess.record()
        if t == T - 1:
            break
        s0 = observed_state(model, sess.observe(), bqj)
        win0 = Trajectory.from_q(plan[t : t + q + 1], model.n_points)
        fw = (np.arange(t + 1, t + q + 1) < T).astype(np.float32)
        ref = (*(jnp.asarray(x[t + 1 : t + q + 1], F32) for x in (ref_pos, ref_quat, ref_kp)), jnp.asarray(fw))
        if opts.soften > 0:
            scales = jnp.asarray(1.0 + rng.uniform(-opts.soften_range, opts.soften_range, (opts.soften, 3)), F32)
            fn = lambda x, s0=s0, ref=ref, scales=scales: vg(x, s0, params, scales, *ref)  # noqa: E731
        else:
            fn = lambda x, s0=s0, ref=ref: vg(x, s0, params, *ref)  # noqa: E731
        win, log = adam_steps(fn, win0, opts.steps, opts.lr, opts.steps + 1, 0.0, mask=mask)
        losses.append(log.best)
        plan[t : t + q + 1] = win.q_targets
        applied[t + 1] = plan[t + 1]
        if t == 0:  # start over with the hand velocity of the applied targets, as a replay of them does
            sess = target.session(applied[0], (applied[1] - applied[0]) * demo.fps)
            sess.record()
        sess.advance(applied[t], applied[t + 1])
    wall = time.perf_counter() - t0
    return MPCResult(applied[:T], sess.result(wall), np.asarray(losses), wall)


def mpc_params(params: Params, sysid: SysID | None, mass0: float, inertia0: np.ndarray) -> Params:
    """The MPC model's parameters: ``params`` with S from ``sysid`` (nominal S when None)."""
    return (sysid or SysID.init()).apply(params, mass0, inertia0)
