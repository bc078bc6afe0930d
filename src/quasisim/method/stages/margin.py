"""Stage ``margin``: plans with margin, the cascade's last step (``robust_select.margin``; 0: off).

A plan that passes strict success in the target with its largest error close to the limits passes in that
world only: a tracker keeps a plan's margin but cannot create it (DESIGN.md 12a: closed loop keeps 81 % of the
replays of plans below 0.8 of the limits strict, 21 % of those riding them). So where the run's plan passes strict
success with its largest error ``e`` (the larger of the object's translation and rotation errors over the clip,
as a fraction of the strict limits, :func:`~quasisim.method.stages.selection.largest_error`) above ``m`` =
``margin``, the sampling stage runs again **from that plan** (:func:`~quasisim.method.stages.sampling.run_sampling`,
its settings, ``stop_when_lost``), backing up wherever the object leaves ``m`` x the limits (``backtrack_limit``
= ``m``) instead of the limits themselves. The new plan replaces the old one only where it passes strict
success with a smaller largest error; otherwise the run keeps its plan. It runs after a stage that ended the
run (the cascade's ``quick``), and costs nothing where the plan already has the margin or fails strict.

Measured (BENCHMARKS.md, "Plans with margin and a tracker that tightens its grasp"): with ``margin`` 0.8 it gave 4
of the 7 riding GRAB plans a smaller largest error without changing closed-loop robust success on the 25 GRAB
clips (60 %; the nominal error is not what decides the perturbed worlds), and took ARCTIC's one riding clip from
0 to 62 %. Off by default.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any

import numpy as np

from quasisim.method.stage import Context, Outcome, Stage
from quasisim.method.stages.selection import largest_error


def polish(ctx: Context, q: np.ndarray, margin: float) -> dict[str, Any]:
    """``q`` (T, D) sampled again from itself with back-ups at ``margin`` x the strict limits where its
    largest error is in (``margin``, 1]; ``{"q_targets", "before", "after", "sampled"}`` (errors as fractions of
    the limits, inf: fails strict; ``after`` is the kept plan's)."""
    prob, cfg, spec = ctx.prob, ctx.cfg, ctx.spec
    before = largest_error(prob, spec.target, q)
    out = {"q_targets": q, "before": np.array(before), "after": np.array(before), "sampled": np.array(False)}
    if not margin < before <= 1:
        return out
    from quasisim.method.stages.sampling import run_sampling

    opts = dataclasses.replace(cfg.sampling, backtrack_limit=margin, stop_when_lost=True)
    r = run_sampling(prob.demo, prob.scene, q, opts, cfg.weights, spec.target, spec.progress)
    after = largest_error(prob, spec.target, r.q_targets) if r.stopped_at is None else math.inf
    out["sampled"] = np.array(True)
    if after < before:
        out.update(q_targets=np.asarray(r.q_targets, np.float64), after=np.array(after))
    return out


def run(ctx: Context, out: Outcome) -> Outcome:
    """Give the run's plan margin where it rides the strict limits (see the module docstring)."""
    m = ctx.cfg.robust_select.margin
    if m == 0:
        return out
    q0 = np.asarray(out.q, np.float64)
    t0 = time.perf_counter()
    expect = {"q_targets": (ctx.prob.demo.n_frames, ctx.prob.scene.n_dof), "before": (), "after": (), "sampled": ()}
    d = ctx.ck.get("margin", lambda: polish(ctx, q0, m), expect)
    ctx.record.seconds["margin"] = time.perf_counter() - t0
    before, after = float(d["before"]), float(d["after"])
    if not bool(d["sampled"]):
        why = "fails strict success" if before > 1 else f"is within {m:g} of the limits ({before:.2f})"
        note = f"margin: the plan {why}: kept as it is"
    elif after < before:
        note = f"margin: sampled again from the plan, largest error {before:.2f} -> {after:.2f} of the limits: kept"
    else:
        note = (
            f"margin: sampled again from the plan (largest error {before:.2f} of the limits), no smaller: the plan kept"
        )
    ctx.record.notes.append(note)
    ctx.progress.write(note)
    if after < before:
        return out.replace(q=np.asarray(d["q_targets"], np.float64), seen={**out.seen, "before margin": q0})
    return out


STAGE = Stage(
    name="margin",
    word="margin",
    config=("sampling", "robust_select"),
    s_per_frame=0.0,  # it samples again only where a plan rides the limits: left out of the long-clip estimate
    run=run,
    plans=True,
    uses_target=True,
    after_done=True,
    idle=lambda cfg: cfg.robust_select.margin == 0,
)
