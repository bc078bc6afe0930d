"""A stage of one's own: smooth the PD targets of the stage before it (a moving average of the finger joints).

A stage is a module declaring a :class:`~quasisim.method.stage.Stage` (its name, the word naming its
checkpoint and its time in ``summary.json``, the config keys it reads, its cost per frame) and a function
``run(context, outcome) -> outcome``. Built-in stages live in ``src/quasisim/method/stages/`` and are listed
in ``quasisim.method.registry.STAGES`` (one line each); this script adds one at run time instead, then
transfers the bundled example with it alone (after the kinematic retarget) and judges it in MuJoCo beside the
kinematic replay (``docs/stages.md`` walks through it).

Run: python examples/custom_stage.py [OUT_DIR]
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np

from quasisim.method import registry
from quasisim.method.stage import Context, Outcome, Stage

WIDTH = 5  # frames in the moving average


def smooth_joints(q: np.ndarray, hand_columns: list[slice], width: int = WIDTH) -> np.ndarray:
    """``q`` (T, D) with each hand's joint columns (after its 6 base columns) averaged over ``width`` frames
    (a centred window, shortened at the clip's ends); the bases are kept."""
    out = np.array(q, np.float64)
    kernel = np.ones(width) / width
    for sl in hand_columns:
        for c in range(sl.start + 6, sl.stop):
            padded = np.pad(out[:, c], width // 2, mode="edge")
            out[:, c] = np.convolve(padded, kernel, mode="valid")
    return out


def run(ctx: Context, out: Outcome) -> Outcome:
    """The outcome's PD targets smoothed (checkpointed as ``smooth.npz``, timed as ``seconds.smooth``)."""

    def compute() -> dict[str, Any]:
        return {"q_targets": smooth_joints(out.q, list(ctx.prob.scene.dof_slices))}

    d = ctx.ck.get("smooth", compute, {"q_targets": (ctx.prob.demo.n_frames, ctx.prob.scene.n_dof)})
    ctx.record.seconds["smooth"] = 0.0
    ctx.progress.write(f"smoothed the finger targets over {WIDTH} frames")
    # the targets before smoothing stay a candidate of the selection (and are kept in controls.npz)
    seen = {**out.seen, "before smoothing": out.q}
    return out.replace(q=np.asarray(d["q_targets"], np.float64), planned=True, seen=seen)


STAGE = Stage(name="smooth", word="smooth", config=(), s_per_frame=0.001, run=run, plans=True)


def main(out: Path) -> dict[str, Any]:
    from quasisim.data.synthetic import write_example
    from quasisim.method.spec import TransferSpec
    from quasisim.pipeline import run_transfer

    registry.STAGES["smooth"] = STAGE  # a built-in stage would be one line here: "smooth": "module.path"
    try:
        demo = write_example("cube_lift", out / "demo")
        spec = TransferSpec(stages=("smooth",), render=False, progress=False)
        res = run_transfer(demo, out / "smooth", spec)
    finally:
        del registry.STAGES["smooth"]
    print("smoothed kinematic retarget:", res.metrics["R_err_deg"], "deg,", res.metrics["T_err_cm"], "cm")
    print(
        "kinematic replay:           ",
        res.kinematic_metrics["R_err_deg"],
        "deg,",
        res.kinematic_metrics["T_err_cm"],
        "cm",
    )
    return {"metrics": res.metrics, "kinematic": res.kinematic_metrics, "controls": res.controls}


if __name__ == "__main__":
    from quasisim.runtime import configure

    configure()
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "out/custom_stage"))
