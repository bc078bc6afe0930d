"""Stage 2: the contact curriculum (alpha = 0), soft to stiff.

In each rigid simulator of the curriculum: a restart guard picks the starting trajectory, then S (object
mass, inertia scale, velocity damping) is identified with the controls fixed, then the controls are
optimised with S fixed (paper appendix "Evaluation process", stage 2). One checkpoint per simulator
(``stage2_simNN``); the stage is :data:`STAGE`.

**The hand-off** to a simulator with a smaller contact distance (:func:`touching`): touch instead of hovering.
A point touches the object when its signed distance is below ``d_c`` (:mod:`quasisim.sim.contact`), so a
grasp found in a simulator with ``d_c = 1 cm`` may hold the object from up to 1 cm away. In the next
simulator, with a smaller ``d_c``, those fingers no longer touch, the object drops, and no gradient brings
them back (an untouched point has no force to differentiate), while ten Adam steps of 1e-3 rad cannot move a
finger a centimetre. Measured on the 25 development clips (BENCHMARKS.md): at the step to ``d_c = 0`` the
previous simulator's solution was the best start on 8 of 25 clips only.

The hand-off moves the grasp instead, so that every contact pushes as it did. A point in contact at the
end of frame ``t`` of the previous simulator's rollout, at signed distance ``phi_a`` (m) from the object,
pushes with ``k_n (d_c - phi_a)`` there; in the next simulator (``d_c'``, ``k_n'``) it pushes as hard at
``phi_a' = d_c' - (k_n / k_n') (d_c - phi_a)``. Its PD target moves as far, ``Delta = phi_a - phi_a'``, along
the object's normal (so the PD spring keeps its stretch too): a point that hovered ``phi_a = 1 cm`` away with
``d_c = 1 cm`` moves 1 cm, one that pressed ``phi_a = -5 mm`` into a simulator ten times softer moves 3.5 mm
out. With ``phi`` the object's signed distance at the previous rollout's object pose, ``x_p(q)`` the point
at joint targets ``q`` (the base targets fixed) and ``c_tp`` 1 for a point in contact:

    min_{q'_t}  sum_p c_tp (phi(x_p(q'_t)) - phi(x_p(q_t)) + Delta_tp)^2  +  lambda |q'_t - q_t|^2

one small least-squares problem per frame, solved by Levenberg-Marquardt steps (frame 0, the rest pose the
rollout starts from, is kept). The result is one more start for stage 2's restart guard, which keeps
whichever start scores best in the new simulator, so the hand-off never makes a simulator's start worse.
"""

from __future__ import annotations

import dataclasses
import json
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from quasisim.method.checkpoints import trajectory_arrays, trajectory_from
from quasisim.method.curriculum import Curriculum, SimStage
from quasisim.method.options import HandoffOptions
from quasisim.method.stage import Context, Outcome, Plan, RunRecord, Stage
from quasisim.method.stages._common import traj_expect
from quasisim.method.stages.point_dynamics import pick_grad
from quasisim.optim.adam import Progress, StepBudget, StepLog, minimise
from quasisim.optim.objective import TrackingObjective
from quasisim.optim.sysid import SysID
from quasisim.optim.trajectory import Trajectory, bucket_frames, first_frames, pad_frames, simulate_jit
from quasisim.rotations import quat_to_mat
from quasisim.sim.kinematics import bases_to_roots, forward_kinematics, points_world
from quasisim.sim.step import object_origin, sdf_lookup
from quasisim.sim.types import Model, Params, State
from quasisim.tracecache import cached_jit

Array = jax.Array


def restart_guard(
    value: Any, candidates: dict[str, Trajectory], sysid: SysID, params: Params, w: dict[str, Any]
) -> tuple[str, dict[str, float]]:
    """The candidate start with the lowest loss in the simulator ``params`` and every candidate's loss;
    ``value(traj, sysid, params, w) -> (loss, terms)`` is the objective's forward pass.

    A trajectory found in a softer simulator can score worse in the next one than the stage's start or the
    kinematic retarget (grasps held from a distance collapse when contact requires touching)."""
    losses: dict[str, float] = {}
    for k, t in candidates.items():
        twin = next((j for j, u in candidates.items() if j in losses and _same(t, u)), None)  # often the same start
        losses[k] = losses[twin] if twin is not None else float(value(t, sysid, params, w)[0])
    losses = {k: v if np.isfinite(v) else float("inf") for k, v in losses.items()}  # a diverged start never wins
    return min(losses, key=losses.__getitem__), losses


def _same(a: Any, b: Any) -> bool:
    """Whether two pytrees hold equal arrays (a simulator's result is often its start unchanged)."""
    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    return len(la) == len(lb) and all(np.array_equal(x, y) for x, y in zip(la, lb, strict=True))


def one_simulator(
    vg: Any, traj: Trajectory, sysid: SysID, params: Params, w: dict[str, Any], sb: StepBudget, progress: Progress,
    label: str,
) -> tuple[Trajectory, SysID, StepLog, StepLog]:  # fmt: skip
    """Identify S with the controls fixed, then optimise the controls with S fixed.

    The control optimisation starts where identification ended, at (controls, best S): identification has
    already evaluated the value and both gradients there, so that first evaluation is read back, not run
    again (the same compiled program on the same arrays: the same numbers, one forward + backward fewer)."""
    log_s = StepLog()
    seen: list[tuple[SysID, Any]] = []  # identification's evaluations: (S, value and gradients)

    def at_sysid(s: SysID) -> Any:
        seen.append((s, vg(traj, s, params, w)))
        return pick_grad(seen[-1][1], 1)

    if sb.sysid_steps > 0:
        sysid, log_s = minimise(
            at_sysid, sysid, sb.sysid_steps, sb.sysid_lr, sb, progress, f"{label} identify S (object mass, inertia, damping)"
        )  # fmt: skip
    start = traj
    known = next((out for s, out in seen if s is sysid), None)  # minimise returns one of the points it evaluated

    def at_controls(x: Trajectory) -> Any:
        return pick_grad(known if x is start and known is not None else vg(x, sysid, params, w), 0)

    traj, log_c = minimise(at_controls, traj, sb.control_steps, sb.control_lr, sb, progress, f"{label} controls")
    return traj, sysid, log_s, log_c


def run_simulator(
    objective: TrackingObjective, traj: Trajectory, sysid: SysID, params: Params, w: dict[str, Any], sb: StepBudget,
    progress: Progress, label: str, restart_from: dict[str, Trajectory] | None,
) -> dict[str, Any]:  # fmt: skip
    """One simulator of stage 2 as checkpoint arrays: the restart guard (when ``restart_from`` names
    alternatives to ``traj``; forward passes only), identification, control optimisation, losses and wall time."""
    t0 = time.perf_counter()
    start_losses: dict[str, float] = {}
    vg = objective.value_and_grad
    if restart_from:
        best, start_losses = restart_guard(objective.value, {"previous": traj, **restart_from}, sysid, params, w)
        if best != "previous":
            progress.write(
                f"{label}: continuing from the {best.replace('_', ' ')} trajectory instead of the previous simulator's "
                f"result (lower loss in this simulator: {start_losses[best]:.5f} < {start_losses['previous']:.5f})"
            )
            traj = restart_from[best]
    traj, sysid, log_s, log_c = one_simulator(vg, traj, sysid, params, w, sb, progress, label)
    d = trajectory_arrays(traj, sysid, None, time.perf_counter() - t0)
    d["losses"] = np.asarray(log_s.losses + log_c.losses, np.float64)
    d["n_sysid"] = np.array(len(log_s.losses))
    d["terms"] = np.array(json.dumps(log_c.terms[-1] if log_c.terms else {}))
    d["start_losses"] = np.array(json.dumps(start_losses))
    return d


def touches(mode: str, rigid: list[int], sim: int) -> bool:
    """Whether ``mode`` adds the touching start at stage 2's simulator ``sim`` (an entry of ``rigid``, the
    curriculum's rigid simulators, soft to stiff; the first has no previous simulator to hand off from)."""
    if sim == rigid[0]:
        return False
    return mode == "every" or (mode == "stiffest" and sim == rigid[-1])


def _depths(model: Model, root_pos: Array, root_rot: Array, q: Array, s: State) -> Array:
    """(N,) signed distances (m) of the hand points at root pose (simulator coordinates) and joints ``q`` to
    the object where state ``s`` holds it."""
    p = points_world(
        forward_kinematics(model.hand, root_pos, root_rot, q, model.hand_geom), model.point_body, model.point_local
    )
    origin, R = object_origin(model, s)
    return sdf_lookup(model, (p - origin) @ R)[0]


def target_depths(model: Model, base_rot: Array, base: Array, joints: Array, states: State) -> Array:
    """(T - 1, N) signed distances of the hand points at the PD targets of frames 1..T-1 (``base`` (T - 1, 6 H),
    ``joints`` (T - 1, J)) to the object where ``states`` (the rollout's T - 1 states) hold it."""

    def one(b: Array, q: Array, s: State) -> Array:
        root_pos, root_rot = bases_to_roots(b, base_rot)
        return _depths(model, model.to_sim(root_pos), root_rot, q, s)

    return jax.vmap(one)(base, joints, states)


def state_depths(model: Model, states: State) -> Array:
    """(T - 1, N) signed distances of the hand points where the rollout's ``states`` put them."""
    return jax.vmap(lambda s: _depths(model, s.root_pos, quat_to_mat(s.root_quat), s.q, s))(states)


def force_keeping_shift(phi: Array, d_c: Array, d_c_next: Array, k_ratio: Array) -> Array:
    """``Delta = phi - phi'`` (m): how far a contact at signed distance ``phi`` moves so that it pushes as
    hard in the next simulator, ``phi' = d_c_next - k_ratio (d_c - phi)``, ``k_ratio = k_n / k_n(next)``."""
    return phi - (d_c_next - k_ratio * (d_c - phi))


@cached_jit(static_argnames=("iterations",))
def touching_joints(
    model: Model, base_rot: Array, base: Array, joints: Array, states: State, shift: Array, damping: Array,
    lo: Array, hi: Array, iterations: int,
) -> Array:  # fmt: skip
    """(T - 1, J) joint targets of frames 1..T-1 whose contact points (``states.in_contact``) sit ``shift``
    (T - 1, N) (m) deeper (module docstring), within the joint range [``lo``, ``hi``]."""
    contact = states.in_contact
    goal = target_depths(model, base_rot, base, joints, states) - shift
    eye = jnp.eye(joints.shape[1], dtype=joints.dtype)

    def frame_step(b: Array, q: Array, mu: Array, q0: Array, s: State, c: Array, g: Array) -> tuple[Array, Array]:
        def residual(qq: Array) -> Array:  # (N,) of the points in contact
            one = jax.tree.map(lambda x: x[None], s)
            return c * (target_depths(model, base_rot, b[None], qq[None], one)[0] - g)

        def cost(qq: Array, r: Array) -> Array:  # r: residual(qq)
            return r @ r + damping * jnp.sum((qq - q0) ** 2)

        r, Jr = residual(q), jax.jacfwd(residual)(q)  # (N,), (N, J)
        grad = Jr.T @ r + damping * (q - q0)
        trial = jnp.clip(q - jnp.linalg.solve(Jr.T @ Jr + (damping + mu) * eye, grad), lo, hi)
        # Levenberg-Marquardt: keep a step only if it lowers the cost
        better = cost(trial, residual(trial)) < cost(q, r)
        return jnp.where(better, trial, q), jnp.where(better, mu / 3.0, mu * 4.0)

    def body(carry: tuple[Array, Array], _: None) -> tuple[tuple[Array, Array], None]:
        q, mu = carry
        return jax.vmap(frame_step)(base, q, mu, joints, states, contact, goal), None

    mu0 = jnp.full(joints.shape[0], 1.0e-4, joints.dtype)  # m^2/rad^2; /3 after a kept step, x4 after a refused one
    return jax.lax.scan(body, (joints, mu0), None, length=iterations)[0][0]


def touching(
    model: Model, params: Params, next_params: Params, traj: Trajectory, base_quat: np.ndarray,
    base_rot: np.ndarray, fps: float, obj0: tuple[np.ndarray, np.ndarray], opts: HandoffOptions,
) -> Trajectory:  # fmt: skip
    """``traj`` (found in the simulator ``params``, S applied) with the joint targets moved so that each of
    its contacts pushes in the simulator ``next_params`` as it did in ``params`` (module docstring, the
    hand-off). Computed on the frames padded to :func:`~quasisim.optim.trajectory.bucket_frames` (one program
    per bucket)."""
    n_frames, traj = traj.base.shape[0], pad_frames(traj, bucket_frames(traj.base.shape[0]))
    states = simulate_jit(model, params, traj, jnp.asarray(base_quat, jnp.float32), fps, obj0)
    shift = force_keeping_shift(state_depths(model, states), params.d_c, next_params.d_c, params.k_n / next_params.k_n)
    hand = model.hand
    lo = np.where(hand.joint_limited, hand.joint_range[:, 0], -np.inf).astype(np.float32)
    hi = np.where(hand.joint_limited, hand.joint_range[:, 1], np.inf).astype(np.float32)
    q = touching_joints(
        model, jnp.asarray(base_rot, jnp.float32), traj.base[1:], traj.joints[1:], states, shift,
        jnp.float32(opts.damping), jnp.asarray(lo), jnp.asarray(hi), opts.iterations,
    )  # fmt: skip
    return first_frames(dataclasses.replace(traj, joints=traj.joints.at[1:].set(q)), n_frames)


def run(ctx: Context, out: Outcome) -> Outcome:
    """The plan after the curriculum's stiffest rigid simulator (one checkpoint per simulator)."""
    prob, cur, ck = ctx.prob, ctx.cur, ctx.ck
    bud = ctx.cfg.budget(ctx.spec.budget)
    w2, sb = ctx.cfg.weights.arrays(points=0.0), bud.sim
    start, kin_traj, plan = out.plan.traj, prob.trajectory(ctx.kinematic_q), out.plan
    ctx.record.seconds["stage2"] = 0.0
    for n, i in enumerate(cur.rigid):
        p = prob.params(cur.contact(i))
        label = f"stage 2 sim {i + 1} ({n + 1}/{len(cur.rigid)})"

        objective = out.objective if i == cur.stiffest else out.objective.with_substeps(bud.soft)

        def simulator(
            p: Params = p, label: str = label, n: int = n, prev: Plan = plan, objective: TrackingObjective = objective
        ) -> dict[str, Any]:
            alt = {"stage_start": start, "kinematic": kin_traj} if n > 0 else None
            if alt is not None and touches(ctx.cfg.stage2.mode, cur.rigid, cur.rigid[n]):
                alt.update(_touching(ctx, cur.rigid[n - 1], cur.rigid[n], prev))
            return run_simulator(objective, prev.traj, prev.sysid, p, w2, sb, ctx.progress, label, alt)

        expect = traj_expect(prob, losses=(None,), n_sysid=(), start_losses="str")
        d = ck.get(f"stage2_sim{i + 1:02d}", simulator, expect)
        plan = Plan(*trajectory_from(d, prob.hand_joints))
        _record_simulator(ctx.record, cur, i, d, plan.sysid.describe(prob.obj.mass), ctx.progress)
    _note_residual_stages(ctx)
    return out.replace(plan=plan, q=plan.traj.q_targets, planned=True)


def _touching(ctx: Context, prev: int, nxt: int, plan: Plan) -> dict[str, Trajectory]:
    """The touching start (:func:`touching`) for simulator ``nxt`` after ``prev``, where its
    contact distance is smaller; else none."""
    prob, cur = ctx.prob, ctx.cur
    if cur.stages[nxt].d_c >= cur.stages[prev].d_c:
        return {}
    p = plan.sysid.apply(prob.params(cur.contact(prev)), prob.obj.mass, prob.obj.inertia)
    traj = touching(
        prob.model, p, prob.params(cur.contact(nxt)), plan.traj, prob.base_quat, prob.base_rots, prob.demo.fps,
        prob.obj0, ctx.cfg.stage2,
    )  # fmt: skip
    return {"touching": traj}


def _note_residual_stages(ctx: Context) -> None:
    """Say what happens to the curriculum's simulators with residual physics (they are stage 3's)."""
    res = [i + 1 for i, s in enumerate(ctx.cur.stages) if s.residual]
    if not res:
        return
    nets = ", ".join(ctx.spec.networks) or "no networks"
    how = (
        f"stage 3 fits S, the contact/joint constants and the networks ({nets}) to MuJoCo"
        if "3" in ctx.spec.stages
        else "not run: add stage 3 (--stages ...,3) to fit the simulator to the target"
    )
    ctx.record.notes.append(f"simulator(s) {', '.join(map(str, res))} with residual physics: {how}")
    ctx.progress.write(ctx.record.notes[-1])


def _record_simulator(
    record: RunRecord, cur: Curriculum, i: int, d: dict[str, Any], s_desc: dict[str, float], progress: Progress
) -> None:
    """One row of the summary's ``simulators`` table and its loss curve."""
    losses = [float(x) for x in d["losses"]]
    record.curves[f"sim {i + 1}"] = losses
    record.seconds["stage2"] += float(d["wall_s"])
    record.simulators.append(
        {"sim": i + 1, **{k: float(v) for k, v in cur.contact(i).items()}, "steps": len(losses),
         "loss_first": losses[0] if losses else None, "loss_best": min(losses) if losses else None,
         "wall_s": float(d["wall_s"]), **s_desc,
         "start_losses": json.loads(str(d["start_losses"])) if "start_losses" in d else None}
    )  # fmt: skip
    if not losses:  # the first evaluation diverged: the trajectory is the simulator's start, unchanged
        progress.write(f"sim {i + 1}: no finite loss (the simulation diverged from its start); kept the start")
        return
    progress.write(
        f"sim {i + 1}: loss {losses[0]:.5f} -> {min(losses):.5f} in {len(losses)} steps, "
        f"{float(d['wall_s']):.0f} s; mass {s_desc['mass_kg'] * 1e3:.0f} g"
    )


def scope(info: dict[str, Any], checkpoint: str, own: dict[str, Any]) -> dict[str, Any]:
    """A simulator before the first touching hand-off is computed as without it: its checkpoint does not
    depend on the hand-off's settings (runs with and without the hand-off share it)."""
    if "stage2" in own and not _after_handoff(info, int(checkpoint.removeprefix("stage2_sim"))):
        own = {k: v for k, v in own.items() if k != "stage2"}
    return own


def _after_handoff(info: dict[str, Any], sim: int) -> bool:
    """Whether simulator ``sim`` (1-based, as in the checkpoint names) comes at or after the first simulator
    whose start the hand-off mode of ``info`` touches (:func:`touches`)."""
    c = info["curriculum_settings"]
    rigid = Curriculum(c["name"], tuple(SimStage(**st) for st in c["stages"]), c["mu"]).rigid
    return any(touches(info["stage2"]["mode"], rigid, i) for i in rigid if i < sim)


STAGE = Stage(
    name="2", word="stage2", config=("stage2",), s_per_frame=8.0, run=run, budget_parts=("sim",), plans=True,
    uses_simulator=True, scope=scope,
)  # fmt: skip
