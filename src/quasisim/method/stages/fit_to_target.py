"""Stage 3: fit the quasi-physical simulator to the target (:mod:`quasisim.method.stage3`), then the world-model
rounds: optimise the plan in the fitted simulator, judge and collect in the target, refit."""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import numpy as np

from quasisim.method import stage2, stage3
from quasisim.method.stage import Context, Outcome, Plan, Stage
from quasisim.optim.trajectory import Trajectory
from quasisim.sim.types import Params
from quasisim.targets import make_target


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
        d, model, p, f, buf = stage3.fit_to_target(
            prob, params, plan.traj.q_targets, plan.sysid, o, cfg.sampling, w, nets, progress
        )
        b, a = d["held_out_before"], d["held_out_after"]
        progress.write(
            f"stage 3: held-out {o.horizon}-frame error {b[0]:.2f} cm / {b[1]:.1f} deg -> {a[0]:.2f} cm / {a[1]:.1f} deg"
        )
        vg = dataclasses.replace(out.objective, model=model).value_and_grad  # the objective in the fitted simulator

        def improve(traj: Trajectory, f: stage3.SimFit, p: Params) -> Trajectory:
            budget = dataclasses.replace(sb, sysid_steps=0)
            return stage2.one_simulator(
                vg, traj, f.sysid, f.apply_constants(p), w2, budget, progress, "stage 3 (fitted simulator)"
            )[0]

        cost = lambda q: target.judge(prob.demo, q, cfg.weights)  # noqa: E731
        rounds, p = stage3.world_model_rounds(
            prob, model, p, plan.traj, f, buf, o, cfg.sampling, w, improve, cost, progress
        )
        return {**d, **rounds, "net_weights": stage3.network_vector(p), "wall_s": np.array(time.perf_counter() - t0)}

    expect = {"fit": (8,), "losses": (None,), "held_out_before": (3,), "held_out_after": (3,), "round_fit": (8,),
              "round_costs": (o.rounds + 1,), "round_errors": (o.rounds, 3), "best_round": (), "buffer_rollouts": (),
              "q_targets": (prob.demo.n_frames, prob.scene.n_dof), "net_weights": (None,)}  # fmt: skip
    with make_target(spec.target, prob.scene) as target:  # judges the world-model rounds
        d = ctx.ck.get("stage3", fit, expect)
    model, p = stage3.network_template(prob.model, params, nets, o.seed) if nets else (prob.model, params)
    p = stage3.from_network_vector(p, d["net_weights"]) if nets else p
    f = stage3.SimFit.from_array(d["round_fit"])
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
