"""Stage 1: transfer through point dynamics in the curriculum's first relaxed simulator (:mod:`quasisim.method.stage1`):
the human point set tracks the demo (1a-b), then the robot point set tracks it (1d)."""

from __future__ import annotations

from typing import Any

import numpy as np

from quasisim.method import stage1
from quasisim.method.checkpoints import trajectory_arrays, trajectory_from
from quasisim.method.stage import Context, Outcome, Plan, Stage
from quasisim.method.stages._common import traj_expect


def run(ctx: Context, out: Outcome) -> Outcome:
    """The robot point set's plan, and the objective whose reference holds the human points. A curriculum
    without a relaxed simulator has no stage 1: the outcome is returned unchanged."""
    prob, cur, cfg, ck, progress, record = ctx.prob, ctx.cur, ctx.cfg, ctx.ck, ctx.progress, ctx.record
    if not cur.relaxed:
        return out
    bud, i1 = cfg.budget(ctx.spec.budget), cur.relaxed[0]
    contact, label = cur.contact(i1), f"sim {i1 + 1}"
    hp = ck.get(
        "stage1_human",
        lambda: stage1.human_point_set(
            prob.demo,
            prob.obj,
            bud.soft,
            bud.n_candidates,
            contact,
            cfg.weights,
            bud.human,
            progress,
            label,
            cfg.stage1.human_point_seed,
        ),
        {"points": (prob.demo.n_frames, None, 3), "losses": (None,), "wall_s": ()},
    )
    human_points = np.asarray(hp["points"], np.float32)
    record.curves["1b human point set"] = list(hp.get("losses", []))
    point_index = stage1.correspondences(prob, ctx.kinematic_q, human_points, hp.get("point_hand"))
    objective = prob.objective(prob.reference(human_points, point_index))
    p1, plan = prob.params(contact), out.plan

    def robot() -> dict[str, Any]:
        traj, log = stage1.robot_point_set(
            objective.with_substeps(bud.soft).value_and_grad,
            plan.traj,
            plan.sysid,
            p1,
            cfg.weights,
            bud.robot_points,
            progress,
            label,
        )
        return trajectory_arrays(traj, plan.sysid, log, log.wall_s)

    rp = ck.get("stage1_robot", robot, traj_expect(prob, losses=(None,)))
    traj, sysid = trajectory_from(rp, prob.hand_joints)
    record.curves[f"1d robot point set ({label})"] = list(rp.get("losses", []))
    record.seconds["stage1_human"], record.seconds["stage1_robot"] = float(hp["wall_s"]), float(rp["wall_s"])
    record.seconds["stage1"] = record.seconds["stage1_human"] + record.seconds["stage1_robot"]
    progress.write(f"stage 1 done: human {float(hp['wall_s']):.0f} s, robot point set {float(rp['wall_s']):.0f} s")
    return out.replace(plan=Plan(traj, sysid), objective=objective, q=traj.q_targets, planned=True)


STAGE = Stage(
    name="1", word="stage1", config=("stage1",), s_per_frame=2.9, run=run, budget_parts=("human", "robot_points"),
    plans=True, uses_simulator=True,
)  # fmt: skip
