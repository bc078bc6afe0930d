"""Stage 1: transfer via point dynamics (paper appendix "Evaluation process", stage 1).

a. a dynamic human hand built from the demo's own keypoints (:mod:`quasisim.assets.human_hand`) is fitted
   to the demo kinematically;
b. its point-set controls are optimised in the curriculum's first (relaxed, alpha > 0) simulator so that
   the object follows the demo: :func:`human_point_set`;
c. the robot hand is retargeted kinematically (:mod:`quasisim.method.retarget`, run by the pipeline);
d. the robot point set's controls are optimised to track the human point set (nearest-neighbour
   correspondences from human to robot points at the object's motion onset) and the object:
   :func:`robot_point_set`.

The stage (``--stages 1``, :data:`STAGE`) runs b and d in the curriculum's first relaxed simulator, each
checkpointed (``stage1_human``, ``stage1_robot``); a curriculum without a relaxed simulator has no stage 1.
"""

from __future__ import annotations

import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial import cKDTree

from quasisim.assets.hand import HandModel
from quasisim.assets.human_hand import RETARGET_SETTINGS, build_human_hand
from quasisim.assets.object import ObjectAsset
from quasisim.data.demo import Demo
from quasisim.method.checkpoints import trajectory_arrays, trajectory_from
from quasisim.method.problem import Problem, fitted_problem
from quasisim.method.retarget import RetargetOptions, RetargetResult, retarget
from quasisim.method.stage import Context, Outcome, Plan, Stage
from quasisim.method.stages._common import traj_expect
from quasisim.optim.adam import Progress, StepBudget, StepLog, minimise
from quasisim.optim.objective import Reference, Weights, hand_point_positions
from quasisim.optim.sysid import SysID
from quasisim.optim.trajectory import Trajectory, bucket_frames, pad_frames, simulate
from quasisim.rotations import quat_angle_deg
from quasisim.sim.kinematics import fk_full, points_world
from quasisim.sim.types import Model, Params
from quasisim.tracecache import cached_jit


def motion_onset(demo: Demo, pos_tol: float = 0.005, deg_tol: float = 5.0) -> int:
    """First frame at which the object is ``pos_tol`` m or ``deg_tol`` deg away from its first pose
    (the middle frame when it never moves)."""
    d = np.linalg.norm(demo.object_pos - demo.object_pos[0], axis=1)
    a = quat_angle_deg(np.broadcast_to(demo.object_quat[0], demo.object_quat.shape), demo.object_quat)
    moved = np.flatnonzero((d >= pos_tol) | (a >= deg_tol))
    return int(moved[0]) if len(moved) else demo.n_frames // 2


def fit_human_hand(human: HandModel, demo: Demo, side: str = "right") -> RetargetResult:
    """Stage 1a: per-frame keypoint IK of the dynamic human hand to the demo's ``side`` keypoints (tight
    settings: the human hand can reach every demo pose). ``q`` (T, 6 + J), the base frame and the errors."""
    return retarget(human, demo, RetargetOptions(**RETARGET_SETTINGS), side=side)


def human_problem(
    demo: Demo, obj: ObjectAsset, substeps: int, n_candidates: int, point_seed: int
) -> tuple[Problem, np.ndarray, float]:
    """Stage 1a for each of the demo's hands: the dynamic human hands (built from each side's own keypoints,
    point sets drawn with ``point_seed``) fitted to the demo, as a problem (one hand set for two hands); their
    PD targets (T, D) and mean metric keypoint error (mm)."""
    hands = tuple(
        build_human_hand(demo.joints_of(s), name="human" if s == "right" else f"human-{s}", point_seed=point_seed)
        for s in demo.sides
    )
    fits = tuple(fit_human_hand(h, demo, s) for h, s in zip(hands, demo.sides, strict=True))
    prob, q = fitted_problem(demo, hands, fits, substeps, n_candidates, obj)
    return prob, q, float(np.mean([f.mean_metric_error_mm for f in fits]))


def human_point_set(
    demo: Demo, obj: ObjectAsset, substeps: int, n_candidates: int, contact: dict[str, float], weights: Weights,
    sb: StepBudget, progress: Progress, label: str, point_seed: int,
) -> dict[str, Any]:  # fmt: skip
    """Stages 1a and 1b (the human point set drawn with ``point_seed``). Returns ``points``: the human point
    set per frame (T, P, 3) m, ``point_hand`` (P,) the hand of each point (0 right, 1 left), ``losses``, the
    human hands' kinematic fit error and the wall time."""
    t0 = time.perf_counter()
    prob, q, fit_error_mm = human_problem(demo, obj, substeps, n_candidates, point_seed)
    params = prob.params(contact)
    human = prob.model.hand
    ref = Reference.from_demo(demo, human.kp_human, np.arange(len(human.kp_human)))
    vg = prob.objective(ref).value_and_grad
    sysid, w = SysID.init(), weights.arrays(points=0.0)
    traj, log = minimise(
        lambda x: pick_grad(vg(x, sysid, params, w), 0), prob.trajectory(q), sb.control_steps,
        sb.control_lr, sb, progress, f"stage 1b human point set ({label})",
    )  # fmt: skip
    return {
        "points": np.asarray(_point_set(prob, params, traj), np.float32),
        "point_hand": prob.point_hand.astype(np.int32),
        "losses": np.asarray(log.losses, np.float64),
        "human_fit_error_mm": np.array(fit_error_mm),
        "wall_s": np.array(time.perf_counter() - t0),
    }


def _point_set(prob: Problem, params: Params, traj: Trajectory) -> jax.Array:
    """(T, P, 3): all hand points at frame 0 and along the rollout of ``traj`` (compiled for its frames
    padded to :func:`~quasisim.optim.trajectory.bucket_frames`)."""
    base_rot = jnp.asarray(prob.base_rots, jnp.float32)
    n = traj.base.shape[0]
    padded = pad_frames(traj, bucket_frames(n))
    return _points_over_time(prob.model, params, padded, prob.base_quat, base_rot, prob.obj0, prob.demo.fps)[:n]


@cached_jit(static_argnames=("fps",))
def _points_over_time(
    model: Model, params: Params, traj: Trajectory, base_quat: jax.Array, base_rot: jax.Array,
    obj0: tuple[jax.Array, jax.Array], fps: float,
) -> jax.Array:  # fmt: skip
    """(T, P, 3): all hand points at frame 0 and along the rollout of ``traj``."""
    p = hand_point_positions(
        model, params, simulate(model, params, traj, base_quat, fps, obj0), jnp.arange(model.n_points)
    )
    q0 = jnp.concatenate([traj.base[0], traj.joints[0]])
    poses = fk_full(model.hand, base_rot, q0, model.hand_geom)
    return jnp.concatenate([points_world(poses, model.point_body, model.point_local)[None], p], axis=0)


def correspondences(
    prob: Problem, kinematic_q: np.ndarray, human_points: np.ndarray, human_hand: np.ndarray | None = None
) -> np.ndarray:
    """(P,) for each human point the nearest robot point of the same hand (``human_hand`` (P,), the hand
    of each human point; None: one hand), both at the object's motion onset."""
    onset = motion_onset(prob.demo)
    robot, robot_hand = prob.points_at(kinematic_q[onset]), prob.point_hand
    human_hand = np.zeros(human_points.shape[1], int) if human_hand is None else np.asarray(human_hand)
    index = np.zeros(human_points.shape[1], int)
    for h in np.unique(human_hand):
        mine = np.flatnonzero(robot_hand == h)
        _, nearest = cKDTree(robot[mine]).query(human_points[onset, human_hand == h])
        index[human_hand == h] = mine[nearest]
    return index


def robot_point_set(
    vg: Any, traj: Trajectory, sysid: SysID, params: Params, weights: Weights, sb: StepBudget, progress: Progress,
    label: str,
) -> tuple[Trajectory, StepLog]:  # fmt: skip
    """Stage 1d: optimise the robot's controls in the relaxed simulator ``params``; ``vg`` is the jitted
    value and gradient (w.r.t. trajectory and S) of an objective whose reference holds the human points."""
    w = weights.arrays()
    return minimise(
        lambda x: pick_grad(vg(x, sysid, params, w), 0), traj, sb.control_steps, sb.control_lr, sb, progress,
        f"stage 1d robot point set ({label})",
    )  # fmt: skip


def pick_grad(res: tuple[tuple[Any, Any], tuple[Any, Any]], i: int) -> tuple[tuple[Any, Any], Any]:
    """``((loss, terms), grads)`` -> ``((loss, terms), grads[i])`` (one compiled program, two uses)."""
    (loss, terms), grads = res
    return (loss, terms), grads[i]


def run(ctx: Context, out: Outcome) -> Outcome:
    """The robot point set's plan, and the objective whose reference holds the human points. A curriculum
    without a relaxed simulator has no stage 1: the outcome is returned unchanged."""
    prob, cur, cfg, ck, progress, record = ctx.prob, ctx.cur, ctx.cfg, ctx.ck, ctx.progress, ctx.record
    if not cur.relaxed:
        return out
    bud, i1 = cfg.budget(ctx.spec.budget), cur.relaxed[0]
    contact, label = cur.contact(i1), f"sim {i1 + 1}"
    hp = ck.get(
        "stage1_human",
        lambda: human_point_set(
            prob.demo,
            prob.obj,
            bud.soft,
            bud.n_candidates,
            contact,
            cfg.weights,
            bud.human,
            progress,
            label,
            cfg.stage1.human_point_seed,
        ),
        {"points": (prob.demo.n_frames, None, 3), "losses": (None,), "wall_s": ()},
    )
    human_points = np.asarray(hp["points"], np.float32)
    record.curves["1b human point set"] = list(hp.get("losses", []))
    point_index = correspondences(prob, ctx.kinematic_q, human_points, hp.get("point_hand"))
    objective = prob.objective(prob.reference(human_points, point_index))
    p1, plan = prob.params(contact), out.plan

    def robot() -> dict[str, Any]:
        traj, log = robot_point_set(
            objective.with_substeps(bud.soft).value_and_grad,
            plan.traj,
            plan.sysid,
            p1,
            cfg.weights,
            bud.robot_points,
            progress,
            label,
        )
        return trajectory_arrays(traj, plan.sysid, log, log.wall_s)

    rp = ck.get("stage1_robot", robot, traj_expect(prob, losses=(None,)))
    traj, sysid = trajectory_from(rp, prob.hand_joints)
    record.curves[f"1d robot point set ({label})"] = list(rp.get("losses", []))
    record.seconds["stage1_human"], record.seconds["stage1_robot"] = float(hp["wall_s"]), float(rp["wall_s"])
    record.seconds["stage1"] = record.seconds["stage1_human"] + record.seconds["stage1_robot"]
    progress.write(f"stage 1 done: human {float(hp['wall_s']):.0f} s, robot point set {float(rp['wall_s']):.0f} s")
    return out.replace(plan=Plan(traj, sysid), objective=objective, q=traj.q_targets, planned=True)


STAGE = Stage(
    name="1", word="stage1", config=("stage1",), s_per_frame=2.9, run=run, budget_parts=("human", "robot_points"),
    plans=True, uses_simulator=True,
)  # fmt: skip
