"""Stage ``sample``: sampling MPC in the target itself around the PD targets of the stages before it
(:mod:`quasisim.method.sampling`; alone, from the kinematic retarget, it is the ``sample-target`` method)."""

from __future__ import annotations

from typing import Any

import numpy as np

from quasisim.method.sampling import run_sampling
from quasisim.method.stage import Context, Outcome, Stage
from quasisim.method.stages._common import q_expect


def run(ctx: Context, out: Outcome) -> Outcome:
    """Sampling around the last stage's PD targets (the nominal, kept for the selection as ``sampling
    nominal``) and, after a stage that planned (``kinematic_alternative``), around the kinematic retarget too."""
    prob, cfg, spec = ctx.prob, ctx.cfg, ctx.spec
    nominal = out.q
    alternatives = (ctx.kinematic_q,) if cfg.sampling.kinematic_alternative and out.planned else ()

    def sample() -> dict[str, Any]:
        r = run_sampling(
            prob.demo, prob.scene, nominal, cfg.sampling, cfg.weights, spec.target, spec.progress, alternatives
        )
        return {
            "q_targets": r.q_targets, "window_loss": r.window_loss, "wall_s": np.array(r.wall_s),
            "n_physics_steps": np.array(r.n_physics_steps),
        }  # fmt: skip

    d = ctx.ck.get("sample", sample, q_expect(prob))
    ctx.record.seconds["sample"] = float(d["wall_s"])
    ctx.record.curves["sampling window loss per frame"] = [float(x) for x in d["window_loss"]]
    ctx.progress.write(f"sampling in {spec.target} done in {ctx.record.seconds['sample']:.0f} s")
    seen = {**out.seen, "sampling nominal": nominal}
    return out.replace(q=np.asarray(d["q_targets"], np.float64), planned=True, seen=seen)


STAGE = Stage(name="sample", word="sample", config=("sampling",), s_per_frame=0.25, run=run, plans=True)
