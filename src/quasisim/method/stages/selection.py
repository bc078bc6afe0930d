"""Stage ``select`` (:data:`STAGE`): keep the best controls seen in the target, judged there (issue "stage
3": a later stage never makes the result worse).

Every trajectory of PD targets the method produced (the kinematic retarget, the curriculum's plan, the
closed-loop MPC's and the sampling stage's results) is replayed open loop in the target from the demo's
first frame and scored by the tracking objective the stages optimise, over the whole clip:

    J = w_pos mean_t |t_t - t_ref| + w_rot mean_t (1 - |q_t . q_ref|) + w_hand mean_t,k |x_tk - x_ref|

(the object's translation in m and rotation, the robot's metric keypoints against the human's), with the
stages' weights (:func:`quasisim.optim.objective.clip_cost`, through the target's
:meth:`~quasisim.targets.base.Target.judge`); an unstable rollout scores infinity. The lowest J wins.

With ``robust_select.worlds`` > 0 (:class:`~quasisim.method.options.RobustSelectOptions`) the choice asks
what the result is for: the candidates that pass strict success replayed in the nominal target are tracked
closed loop (:mod:`quasisim.method.track`) in that many perturbed training worlds (:func:`closed_loop_success`;
a stream of their own, never a world robust success judges in), and the one passing strict in the most worlds
wins (ties: the lower J). Where no candidate passes strict nominally, J decides.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from quasisim.data.demo import Demo
from quasisim.limits import strict_success
from quasisim.method.options import RobustSelectOptions
from quasisim.method.problem import Problem
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


def passes_strict(prob: Problem, target: str, q: np.ndarray) -> bool:
    """Whether PD targets ``q`` (T, D), replayed open loop in ``target``, pass strict success against the demo
    (every frame within the strict limits, the object moved as in the demo, a stable rollout)."""
    with make_target(target, prob.scene) as tgt:
        return passes(prob.demo, tgt.rollout(q))


def largest_error(prob: Problem, target: str, q: np.ndarray) -> float:
    """The largest of the object's translation and rotation errors over the clip, as a fraction of the strict
    limits (2 cm, 30 deg), of PD targets ``q`` (T, D) replayed open loop in ``target``; inf where the replay
    fails strict success (:func:`passes`)."""
    from quasisim.method.stages.sampling import strict_fractions

    with make_target(target, prob.scene) as tgt:
        roll = tgt.rollout(q)
    if not passes(prob.demo, roll):
        return math.inf
    demo = prob.demo
    trans, rot = strict_fractions(roll.object_pos, roll.object_quat, demo.object_pos, demo.object_quat)
    return float(max(np.max(trans), np.max(rot)))


def passes(demo: Demo, roll: Any) -> bool:
    """Whether a target's rollout passes strict success against ``demo`` (stable, and the rule of
    :func:`quasisim.limits.strict_success`)."""
    return not roll.instability and strict_success(demo.object_pos, demo.object_quat, roll.object_pos, roll.object_quat)


def closed_loop_success(
    prob: Problem, target: str, q: np.ndarray, opts: RobustSelectOptions, weights: Weights
) -> float | None:
    """The fraction of ``opts.worlds`` training worlds (the ranges of ``configs/robust.yaml`` drawn with
    ``opts.seed``: :class:`~quasisim.targets.perturb.TrainingWorlds`) in which PD targets ``q`` (T, D), tracked
    closed loop by the tracker of ``opts.tracker`` (built from the nominal scene only), pass strict success; None
    without worlds. The same replay as closed-loop robust success, in other worlds."""
    from quasisim.method.track import TrackOptions, closed_loop
    from quasisim.targets.perturb import training_worlds, world_replays

    if opts.worlds == 0:
        return None
    demo, scene = prob.demo, prob.scene
    cfg = training_worlds(opts.seed, opts.worlds)  # the method's stream, never a judging world
    tracker = closed_loop(TrackOptions.preset(opts.tracker), weights)(demo, scene, q, target)
    return sum(passes(demo, roll) for roll, _, _ in world_replays(scene, q, target, cfg, tracker)) / cfg.n


def robust_choice(
    prob: Problem, target: str, candidates: dict[str, np.ndarray], costs: dict[str, float],
    opts: RobustSelectOptions, weights: Weights,
) -> tuple[str | None, dict[str, float]]:  # fmt: skip
    """Among ``candidates`` that pass strict success nominally, the one passing strict closed loop in the most
    training worlds (ties: the lower objective ``costs``), and each one's fraction of worlds
    (:func:`closed_loop_success`); (None, {}) where none passes nominally. Equal trajectories are judged once."""
    scores: dict[str, float] = {}
    by_bytes: dict[bytes, float] = {}
    for name, q in candidates.items():
        key = np.ascontiguousarray(q).tobytes()
        if key not in by_bytes and passes_strict(prob, target, q):
            by_bytes[key] = closed_loop_success(prob, target, q, opts, weights) or 0.0
        if key in by_bytes:
            scores[name] = by_bytes[key]
    if not scores:
        return None, {}
    return max(scores, key=lambda n: (scores[n], -costs[n])), scores


def run(ctx: Context, out: Outcome) -> Outcome:
    """Replay every trajectory the run produced in the target and keep the one with the lowest objective:
    the last stage's, those the later stages started from (``Outcome.seen``: the sampling's nominal, the
    MPC's plan, ...; the latest first), the curriculum's plan and the kinematic retarget. The first of equal
    costs wins, so later stages come first."""
    t0 = time.perf_counter()
    held = [("last stage", out.q), *reversed(out.seen.items()), ("curriculum", out.plan.traj.q_targets)]
    candidates = {k: np.asarray(q, np.float64) for k, q in [*held, ("kinematic", ctx.kinematic_q)]}
    best, costs = best_in_target(ctx.prob.demo, ctx.prob.scene, ctx.spec.target, candidates, ctx.cfg.weights)
    objective = ", ".join(f"{k} {v:.4f}" for k, v in costs.items())
    note = f"kept '{best}' (objective in {ctx.spec.target}: {objective})"
    ro = ctx.cfg.robust_select
    if ro.worlds:
        chosen, scores = robust_choice(ctx.prob, ctx.spec.target, candidates, costs, ro, ctx.cfg.weights)
        if chosen is None:
            note += "; no candidate passes strict nominally, so none was judged closed loop"
        else:
            best = chosen
            strict = ", ".join(f"{k} {100 * v:.0f} %" for k, v in scores.items())
            note = (
                f"kept '{best}' (strict closed loop in {ro.worlds} training worlds: {strict}; objective: {objective})"
            )
    ctx.record.seconds["select"] = time.perf_counter() - t0
    ctx.record.notes.append(note)
    ctx.progress.write(ctx.record.notes[-1])
    return out.replace(q=candidates[best], selected=best, selection_costs=costs)


STAGE = Stage(name="select", word="select", config=("robust_select",), s_per_frame=0.1, run=run, uses_target=True)
