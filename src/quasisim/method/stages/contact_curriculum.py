"""Stage 2: the contact curriculum, each rigid simulator from soft to stiff (:mod:`quasisim.method.stage2`), with
the touching hand-off between simulators (:mod:`quasisim.method.handoff`)."""

from __future__ import annotations

import json
from typing import Any

from quasisim.method import handoff, stage2
from quasisim.method.checkpoints import trajectory_from
from quasisim.method.curriculum import Curriculum, SimStage
from quasisim.method.stage import Context, Outcome, Plan, RunRecord, Stage
from quasisim.method.stages._common import traj_expect
from quasisim.optim.adam import Progress
from quasisim.optim.objective import TrackingObjective
from quasisim.optim.trajectory import Trajectory
from quasisim.sim.types import Params


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
            if alt is not None and handoff.touches(ctx.cfg.stage2.mode, cur.rigid, cur.rigid[n]):
                alt.update(_touching(ctx, cur.rigid[n - 1], cur.rigid[n], prev))
            return stage2.run_simulator(objective, prev.traj, prev.sysid, p, w2, sb, ctx.progress, label, alt)

        expect = traj_expect(prob, losses=(None,), n_sysid=(), start_losses="str")
        d = ck.get(f"stage2_sim{i + 1:02d}", simulator, expect)
        plan = Plan(*trajectory_from(d, prob.hand_joints))
        _record_simulator(ctx.record, cur, i, d, plan.sysid.describe(prob.obj.mass), ctx.progress)
    _note_residual_stages(ctx)
    return out.replace(plan=plan, q=plan.traj.q_targets, planned=True)


def _touching(ctx: Context, prev: int, nxt: int, plan: Plan) -> dict[str, Trajectory]:
    """The touching start (:mod:`quasisim.method.handoff`) for simulator ``nxt`` after ``prev``, where its
    contact distance is smaller; else none."""
    prob, cur = ctx.prob, ctx.cur
    if cur.stages[nxt].d_c >= cur.stages[prev].d_c:
        return {}
    p = plan.sysid.apply(prob.params(cur.contact(prev)), prob.obj.mass, prob.obj.inertia)
    traj = handoff.touching(
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
    whose start the hand-off mode of ``info`` touches (:func:`quasisim.method.handoff.touches`)."""
    c = info["curriculum_settings"]
    rigid = Curriculum(c["name"], tuple(SimStage(**st) for st in c["stages"]), c["mu"]).rigid
    return any(handoff.touches(info["stage2"]["mode"], rigid, i) for i in rigid if i < sim)


STAGE = Stage(
    name="2", word="stage2", config=("stage2",), s_per_frame=8.0, run=run, budget_parts=("sim",), plans=True,
    uses_simulator=True, scope=scope,
)  # fmt: skip
