"""Stage 2: the contact curriculum (alpha = 0), soft to stiff.

In each rigid simulator of the curriculum: a restart guard picks the starting trajectory, then S (object
mass, inertia scale, velocity damping) is identified with the controls fixed, then the controls are
optimised with S fixed (paper appendix "Evaluation process", stage 2).
"""

from __future__ import annotations

import json
import time
from typing import Any

import jax
import numpy as np

from quasisim.method.checkpoints import trajectory_arrays
from quasisim.method.stage1 import pick_grad
from quasisim.optim.adam import Progress, StepBudget, StepLog, minimise
from quasisim.optim.objective import TrackingObjective
from quasisim.optim.sysid import SysID
from quasisim.optim.trajectory import Trajectory
from quasisim.sim.types import Params


def restart_guard(
    value: Any, candidates: dict[str, Trajectory], sysid: SysID, params: Params, w: dict[str, Any]
) -> tuple[str, dict[str, float]]:
    """The candidate start with the lowest loss in the simulator ``params`` and every candidate's loss;
    ``value(traj, sysid, params, w) -> (loss, terms)`` is the objective's forward pass.

    A trajectory found in a softer simulator can score worse in the next one than the stage's start or the
    kinematic retarget (grasps held from a distance collapse when contact requires touching)."""
    losses: dict[str, float] = {}
    for k, t in candidates.items():
        twin = next((j for j, u in candidates.items() if j in losses and _same(t, u)), None)  # often the same start
        losses[k] = losses[twin] if twin is not None else float(value(t, sysid, params, w)[0])
    losses = {k: v if np.isfinite(v) else float("inf") for k, v in losses.items()}  # a diverged start never wins
    return min(losses, key=losses.__getitem__), losses


def _same(a: Any, b: Any) -> bool:
    """Whether two pytrees hold equal arrays (a simulator's result is often its start unchanged)."""
    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    return len(la) == len(lb) and all(np.array_equal(x, y) for x, y in zip(la, lb, strict=True))


def one_simulator(
    vg: Any, traj: Trajectory, sysid: SysID, params: Params, w: dict[str, Any], sb: StepBudget, progress: Progress,
    label: str,
) -> tuple[Trajectory, SysID, StepLog, StepLog]:  # fmt: skip
    """Identify S with the controls fixed, then optimise the controls with S fixed.

    The control optimisation starts where identification ended, at (controls, best S): identification has
    already evaluated the value and both gradients there, so that first evaluation is read back, not run
    again (the same compiled program on the same arrays: the same numbers, one forward + backward fewer)."""
    log_s = StepLog()
    seen: list[tuple[SysID, Any]] = []  # identification's evaluations: (S, value and gradients)

    def at_sysid(s: SysID) -> Any:
        seen.append((s, vg(traj, s, params, w)))
        return pick_grad(seen[-1][1], 1)

    if sb.sysid_steps > 0:
        sysid, log_s = minimise(
            at_sysid, sysid, sb.sysid_steps, sb.sysid_lr, sb, progress, f"{label} identify S (object mass, inertia, damping)"
        )  # fmt: skip
    start = traj
    known = next((out for s, out in seen if s is sysid), None)  # minimise returns one of the points it evaluated

    def at_controls(x: Trajectory) -> Any:
        return pick_grad(known if x is start and known is not None else vg(x, sysid, params, w), 0)

    traj, log_c = minimise(at_controls, traj, sb.control_steps, sb.control_lr, sb, progress, f"{label} controls")
    return traj, sysid, log_s, log_c


def run_simulator(
    objective: TrackingObjective, traj: Trajectory, sysid: SysID, params: Params, w: dict[str, Any], sb: StepBudget,
    progress: Progress, label: str, restart_from: dict[str, Trajectory] | None,
) -> dict[str, Any]:  # fmt: skip
    """One simulator of stage 2 as checkpoint arrays: the restart guard (when ``restart_from`` names
    alternatives to ``traj``; forward passes only), identification, control optimisation, losses and wall time."""
    t0 = time.perf_counter()
    start_losses: dict[str, float] = {}
    vg = objective.value_and_grad
    if restart_from:
        best, start_losses = restart_guard(objective.value, {"previous": traj, **restart_from}, sysid, params, w)
        if best != "previous":
            progress.write(
                f"{label}: continuing from the {best.replace('_', ' ')} trajectory instead of the previous simulator's "
                f"result (lower loss in this simulator: {start_losses[best]:.5f} < {start_losses['previous']:.5f})"
            )
            traj = restart_from[best]
    traj, sysid, log_s, log_c = one_simulator(vg, traj, sysid, params, w, sb, progress, label)
    d = trajectory_arrays(traj, sysid, None, time.perf_counter() - t0)
    d["losses"] = np.asarray(log_s.losses + log_c.losses, np.float64)
    d["n_sysid"] = np.array(len(log_s.losses))
    d["terms"] = np.array(json.dumps(log_c.terms[-1] if log_c.terms else {}))
    d["start_losses"] = np.array(json.dumps(start_losses))
    return d
