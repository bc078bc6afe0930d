"""What a transfer run leaves behind: ``controls.npz``, ``metrics.json``, ``rollout.npz``, ``report.html``
(judged in the target) and ``summary.json`` (settings, seconds and losses per stage, S, both judgements),
written as one set (:func:`quasisim.files.output_set`: ``manifest.json`` last)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from quasisim.data.controls import Controls
from quasisim.eval import evaluate
from quasisim.eval.evaluate import evaluate_controls
from quasisim.eval.report import loss_plot
from quasisim.files import output_set, save_json_atomic
from quasisim.method.stage import Context, RunRecord
from quasisim.optim.sysid import SysID

OUTPUTS = ("controls.npz", *evaluate.OUTPUTS, "summary.json")


@dataclass
class TransferResult:
    """What :func:`~quasisim.pipeline.run_transfer` produced."""

    controls: Controls
    metrics: dict[str, Any]
    kinematic_metrics: dict[str, Any]
    record: RunRecord
    out: Path


def write_outputs(ctx: Context, controls: Controls, sysid: SysID, out: Path) -> TransferResult:
    """Save ``controls``, judge them and the kinematic retarget in the run's target, write the report and
    the summary (the run's settings and record, ``ctx``; the identified S, ``sysid``)."""
    prob, record, spec, target = ctx.prob, ctx.record, ctx.spec, ctx.spec.target
    demo, scene = prob.demo, prob.scene
    settings = {"curriculum": ctx.cur.name, "stages": spec.stages, "budget": spec.budget, "method": spec.method}
    kin = dataclasses.replace(controls, q_targets=np.asarray(ctx.kinematic_q), method="kinematic")
    km = evaluate_controls(demo, kin, target, None, render=False, scene=scene).metrics
    s_desc = sysid.describe(prob.obj.mass)
    images = {"optimisation loss per simulator of the curriculum": loss_plot(record.curves)} if record.curves else {}
    robust = spec.robust_configs()
    tracker = None
    if spec.closed_loop:
        from quasisim.method.track import closed_loop

        tracker = closed_loop(weights=ctx.cfg.weights)
    ev = evaluate_controls(demo, controls, target, None, render=False, scene=scene, robust=robust, closed_loop=tracker)
    title = (
        f"{demo.name}: {settings['method']} ({settings['curriculum']} curriculum, stages "
        f"{','.join(settings['stages']) or 'none'}) in {target}"
    )
    info = {
        "kinematic replay in the same target": f"R_err {km['R_err_deg']:.1f} deg, T_err {km['T_err_cm']:.2f} cm, "
        f"MPJPE {km['MPJPE_mm']:.1f} mm, success {km['success']}",
        "budget": f"{settings['budget']} (simulator dt {prob.model.dt * 1e3:g} ms)",
        "seconds per stage": ", ".join(f"{k} {v:.0f}" for k, v in record.seconds.items()),
        "identified S": ", ".join(f"{k} {v:.4g}" for k, v in s_desc.items()),
        **({"notes": "; ".join(record.notes)} if record.notes else {}),
    }
    summary = {
        "demo": demo.name, "hand": " + ".join(h.name for h in scene.hands), "target": target, "curriculum": settings["curriculum"],
        "stages": list(settings["stages"]), "budget": settings["budget"], "method": settings["method"],
        "seconds": record.seconds, "simulators": record.simulators, "kinematic_metrics": km, "sysid": s_desc,
        "stage3": record.fit or None, "notes": record.notes, "metrics": ev.metrics,
    }  # fmt: skip
    with output_set(out) as stage:
        controls.save(stage / "controls.npz")
        evaluate.write_outputs(ev, demo, controls, target, stage, spec.render, title, info, images, spec.progress)
        save_json_atomic(stage / "summary.json", summary)
    return TransferResult(controls, ev.metrics, km, record, out)
