"""Stage ``quick``: the cascade's first step. Sampling MPC in the target from the kinematic retarget, as the
``sample-target`` method does, stopping at the first frame that stays outside the strict limits (the clip can
no longer pass strict success there); a result that ran to the end is replayed in the target, and where it
passes strict success the run ends with it. Otherwise the stages after it run (the curriculum and sampling
around its plan), and a result that ran to the end stays a candidate of the selection (``sample-target``).

With ``robust_select.worlds`` > 0 the gate asks the question robust success asks: a result that passes strict
nominally ends the run only where it also passes strict **closed loop** in at least ``robust_select.gate`` of
the training worlds (:func:`~quasisim.method.stages.selection.closed_loop_success`); otherwise the curriculum runs
and the result stays a candidate of the selection."""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import numpy as np

from quasisim.method.stage import Context, Outcome, Stage
from quasisim.method.stages._common import q_expect
from quasisim.method.stages.sampling import run_sampling
from quasisim.method.stages.selection import closed_loop_success, passes_strict


def run(ctx: Context, out: Outcome) -> Outcome:
    """Sample from the kinematic retarget; end the run where the result passes strict success in the target."""
    prob, cfg, spec = ctx.prob, ctx.cfg, ctx.spec
    opts, ro = dataclasses.replace(cfg.sampling, stop_when_lost=True), cfg.robust_select

    def sample() -> dict[str, Any]:
        r = run_sampling(prob.demo, prob.scene, ctx.kinematic_q, opts, cfg.weights, spec.target, spec.progress)
        passed = r.stopped_at is None and passes_strict(prob, spec.target, r.q_targets)
        t0 = time.perf_counter()
        closed = closed_loop_success(prob, spec.target, r.q_targets, ro, cfg.weights) if passed else None
        return {
            "q_targets": r.q_targets, "window_loss": r.window_loss, "wall_s": np.array(r.wall_s),
            "n_physics_steps": np.array(r.n_physics_steps), "backups": np.array(r.backups),
            "stopped_at": np.array(-1 if r.stopped_at is None else r.stopped_at), "passed": np.array(passed),
            "closed_strict": np.array(-1.0 if closed is None else closed), "gate_s": np.array(time.perf_counter() - t0),
        }  # fmt: skip

    expect = {**q_expect(prob), "stopped_at": (), "passed": (), "closed_strict": (), "gate_s": ()}
    d = ctx.ck.get("quick", sample, expect)
    ctx.record.seconds["quick"] = float(d["wall_s"]) + float(d["gate_s"])
    ctx.record.curves["quick sampling window loss per frame"] = [float(x) for x in d["window_loss"]]
    q, stopped, passed = np.asarray(d["q_targets"], np.float64), int(d["stopped_at"]), bool(d["passed"])
    closed = float(d["closed_strict"])
    if passed and ro.worlds and closed < ro.gate:
        passed = False
        note = (
            f"passes strict success in the target, but closed loop in only {100 * closed:.0f} % of {ro.worlds} "
            f"training worlds (gate {100 * ro.gate:.0f} %): the curriculum runs"
        )
    elif passed:
        note = (
            "passes strict success in the target"
            + (f" (closed loop in {100 * closed:.0f} % of {ro.worlds} training worlds)" if ro.worlds else "")
            + ": the run ends with it"
        )
    elif stopped >= 0:
        note = f"frame {stopped} stayed outside the strict limits: stopped there; the curriculum runs"
    else:
        note = "ran to the end but fails strict success in the target: the curriculum runs"
    ctx.record.notes.append(f"sampling in {spec.target} from the kinematic retarget {note}")
    ctx.progress.write(f"{ctx.record.notes[-1]} ({ctx.record.seconds['quick']:.0f} s)")
    if passed:
        return out.replace(q=q, planned=True, done=True)
    return out if stopped >= 0 else out.replace(seen={**out.seen, "sample-target": q})


# s_per_frame: the sampling stage's from the kinematic retarget (stage sample's figure)
STAGE = Stage(
    name="quick",
    word="quick",
    config=("sampling", "robust_select"),
    s_per_frame=0.19,
    run=run,
    plans=True,
    uses_target=True,
)
