"""Stage ``mpc``: closed-loop MPC in the target with the quasi-physical simulator as its model
(:mod:`quasisim.method.mpc`; methods ``mpc-base``, ``mpc-soften``)."""

from __future__ import annotations

from typing import Any

import numpy as np

from quasisim.method.mpc import run_mpc
from quasisim.method.stage import Context, Outcome, Stage
from quasisim.method.stages._common import q_expect
from quasisim.optim.trajectory import Trajectory


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
