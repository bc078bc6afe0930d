"""Stage ``sample``: sampling MPC in the target itself around the PD targets of the stages before it
(:mod:`quasisim.method.sampling`; alone, from the kinematic retarget, it is the ``sample-target`` method)."""

from __future__ import annotations

import sys
from typing import Any

import numpy as np

from quasisim.data.demo import content_hash
from quasisim.method.sampling import Transitions, run_sampling
from quasisim.method.stage import Context, Outcome, Stage
from quasisim.method.stages._common import q_expect


def run(ctx: Context, out: Outcome) -> Outcome:
    """Sampling around the last stage's PD targets (the nominal, kept for the selection as ``sampling
    nominal``) and, after a stage that planned (``kinematic_alternative``), around the kinematic retarget too."""
    prob, cfg, spec = ctx.prob, ctx.cfg, ctx.spec
    nominal = out.q
    alternatives = (ctx.kinematic_q,) if cfg.sampling.kinematic_alternative and out.planned else ()

    kept = Transitions() if ctx.transitions is not None else None

    def sample() -> dict[str, Any]:
        r = run_sampling(
            prob.demo, prob.scene, nominal, cfg.sampling, cfg.weights, spec.target, spec.progress, alternatives, kept
        )
        return {
            "q_targets": r.q_targets, "window_loss": r.window_loss, "wall_s": np.array(r.wall_s),
            "n_physics_steps": np.array(r.n_physics_steps), "backups": np.array(r.backups),
            "backup_frames": r.backup_frames,
        }  # fmt: skip

    d = ctx.ck.get("sample", sample, q_expect(prob))
    if kept is not None:
        _save_transitions(ctx, kept)
    ctx.record.seconds["sample"] = float(d["wall_s"])
    ctx.record.curves["sampling window loss per frame"] = [float(x) for x in d["window_loss"]]
    backups = f", {int(d['backups'])} back-ups" if "backups" in d and int(d["backups"]) else ""
    ctx.progress.write(f"sampling in {spec.target} done in {ctx.record.seconds['sample']:.0f} s{backups}")
    seen = {**out.seen, "sampling nominal": nominal}
    return out.replace(q=np.asarray(d["q_targets"], np.float64), planned=True, seen=seen)


def _save_transitions(ctx: Context, kept: Transitions) -> None:
    """``TRANSITIONS/<demo>.<method>.npz`` (said on the progress output); nothing when the sampling stage's
    checkpoint was reused (it did not run), said in one line on stderr."""
    assert ctx.transitions is not None
    demo, spec = ctx.prob.demo, ctx.spec
    path = ctx.transitions / f"{demo.name}.{spec.method}.npz"
    if not kept.run:
        print(
            f"warning: {path}: not written: the sampling stage was read back from its checkpoint (start the run "
            "afresh to record what it rolls out)",
            file=sys.stderr,
        )
        return
    sc = ctx.prob.scene
    meta = {
        "demo": demo.name, "demo_content": content_hash(demo), "hands": " + ".join(h.name for h in sc.hands),
        "hand_dofs": np.array([6 + h.n_joints for h in sc.hands]), "target": spec.target, "method": spec.method,
        "fps": demo.fps, "horizon": ctx.cfg.sampling.horizon, "base_rots": np.stack(sc.base_rots),
        "object": sc.obj.name, "object_mass": sc.obj.mass, "object_com": np.asarray(sc.obj.com),
        "object_inertia": np.asarray(sc.obj.inertia), "kp_metric_index": np.flatnonzero(sc.kp_metric),
        "kp_human": sc.kp_human,
        "table": np.array([sc.table.xmin, sc.table.xmax, sc.table.ymin, sc.table.ymax, sc.table.top]),
    }  # fmt: skip
    kept.save(path, meta)
    ctx.progress.write(f"recorded {len(kept.steps)} sampling steps in {path}")


# s_per_frame: 0.27 s per frame measured on 60-frame GRAB clips, 0.13-0.15 on the long examples (bench long)
STAGE = Stage(
    name="sample", word="sample", config=("sampling",), s_per_frame=0.19, run=run, plans=True, uses_target=True
)
