"""Stage ``select``: keep the best trajectory seen, judged in the target (:mod:`quasisim.method.select`)."""

from __future__ import annotations

import time

import numpy as np

from quasisim.method.select import best_in_target
from quasisim.method.stage import Context, Outcome, Stage


def run(ctx: Context, out: Outcome) -> Outcome:
    """Replay every trajectory the run produced in the target and keep the one with the lowest objective:
    the last stage's, those the later stages started from (``Outcome.seen``: the sampling's nominal, the
    MPC's plan, ...; the latest first), the curriculum's plan and the kinematic retarget. The first of equal
    costs wins, so later stages come first."""
    t0 = time.perf_counter()
    held = [("last stage", out.q), *reversed(out.seen.items()), ("curriculum", out.plan.traj.q_targets)]
    candidates = {k: np.asarray(q, np.float64) for k, q in [*held, ("kinematic", ctx.kinematic_q)]}
    best, costs = best_in_target(ctx.prob.demo, ctx.prob.scene, ctx.spec.target, candidates, ctx.cfg.weights)
    ctx.record.seconds["select"] = time.perf_counter() - t0
    ctx.record.notes.append(
        f"kept '{best}' (objective in {ctx.spec.target}: " + ", ".join(f"{k} {v:.4f}" for k, v in costs.items()) + ")"
    )
    ctx.progress.write(ctx.record.notes[-1])
    return out.replace(q=candidates[best], selected=best, selection_costs=costs)


STAGE = Stage(name="select", word="select", config=(), s_per_frame=0.1, run=run, uses_target=True)
