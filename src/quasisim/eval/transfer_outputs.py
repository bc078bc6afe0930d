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
from quasisim.method.problem import Problem
from quasisim.method.stage import RunRecord
from quasisim.optim.sysid import SysID
from quasisim.optim.trajectory import Trajectory, join_q, simulate_jit
from quasisim.rotations import np_mat_to_euler_xyz, np_quat_to_mat
from quasisim.sim.types import Model, Params

OUTPUTS = ("controls.npz", *evaluate.OUTPUTS, "summary.json")


@dataclass
class TransferResult:
    """What :func:`~quasisim.pipeline.run_transfer` produced."""

    controls: Controls
    metrics: dict[str, Any]
    kinematic_metrics: dict[str, Any]
    record: RunRecord
    out: Path


def sim_qpos(prob: Problem, params: Params, traj: Trajectory, model: Model | None = None) -> np.ndarray:
    """(T, D) the hands' trajectory of ``traj``'s quasi-physical rollout (in ``model``, default the
    problem's) in base coordinates, laid out as the targets' PD targets."""
    model = model or prob.model
    states = simulate_jit(model, params, traj, prob.base_quat, prob.demo.fps, prob.obj0)
    root = np.asarray(model.to_world(states.root_pos), np.float64)  # (T - 1, H, 3)
    R = np_quat_to_mat(np.asarray(states.root_quat, np.float64))  # (T - 1, H, 3, 3)
    eul = np.unwrap(np_mat_to_euler_xyz(np.einsum("hji,thjk->thik", prob.base_rots, R)), axis=0)
    base = np.concatenate([root, eul], axis=-1).reshape(len(root), -1)
    q = join_q(base, np.asarray(states.q, np.float64), prob.hand_joints)
    return np.concatenate([np.asarray(traj.q_targets[:1]), q], axis=0)


def write_outputs(
    prob: Problem, controls: Controls, kinematic_q: np.ndarray, record: RunRecord, sysid: SysID, settings: dict[str, Any],
    target: str, out: Path, render: bool, progress: bool,
) -> TransferResult:  # fmt: skip
    """Save ``controls``, judge them and the kinematic retarget in ``target``, write the report and summary."""
    demo, scene = prob.demo, prob.scene
    kin = dataclasses.replace(controls, q_targets=np.asarray(kinematic_q), method="kinematic")
    km = evaluate_controls(demo, kin, target, None, render=False, scene=scene).metrics
    s_desc = sysid.describe(prob.obj.mass)
    images = {"optimisation loss per simulator of the curriculum": loss_plot(record.curves)} if record.curves else {}
    ev = evaluate_controls(demo, controls, target, None, render=False, scene=scene)
    title = (
        f"{demo.name}: {settings['label']} ({settings['curriculum']} curriculum, stages "
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
        evaluate.write_outputs(ev, demo, controls, target, stage, render, title, info, images, progress)
        save_json_atomic(stage / "summary.json", summary)
    return TransferResult(controls, ev.metrics, km, record, out)
