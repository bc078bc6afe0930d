"""Stage ``select`` (:data:`STAGE`): keep the best controls seen in the target, judged there (issue "stage
3": a later stage never makes the result worse).

Every trajectory of PD targets the method produced (the kinematic retarget, the curriculum's plan, the
closed-loop MPC's and the sampling stage's results) is replayed open loop in the target from the demo's
first frame and scored by the tracking objective the stages optimise, over the whole clip:

    J = w_pos mean_t |t_t - t_ref| + w_rot mean_t (1 - |q_t . q_ref|) + w_hand mean_t,k |x_tk - x_ref|

(the object's translation in m and rotation, the robot's metric keypoints against the human's), with the
stages' weights (:func:`quasisim.optim.objective.clip_cost`, through the target's
:meth:`~quasisim.targets.base.Target.judge`); an unstable rollout scores infinity. The lowest J wins. The success thresholds are not
used: the choice sees only the objective, as the optimisation does.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from quasisim.data.demo import Demo
from quasisim.method.stage import Context, Outcome, Stage
from quasisim.optim.objective import Weights
from quasisim.targets import make_target


def best_in_target(
    demo: Demo, scene: Any, target: str, candidates: dict[str, np.ndarray], weights: Weights
) -> tuple[str, dict[str, float]]:
    """The name of the candidate PD-target trajectory (T, 6 + J) with the lowest J in ``target`` (its
    :meth:`~quasisim.targets.base.Target.judge`), and every candidate's J (the first of equal ones wins, so
    list the latest stage first)."""
    with make_target(target, scene) as tgt:
        costs = {name: tgt.judge(demo, q, weights) for name, q in candidates.items()}
    return min(costs, key=costs.__getitem__), costs


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
