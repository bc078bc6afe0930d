"""Keep the best controls seen in the target, judged there (issue "stage 3": a later stage never makes the
result worse).

Every trajectory of PD targets the method produced (the kinematic retarget, the curriculum's plan, the
closed-loop MPC's and the sampling stage's results) is replayed open loop in the target from the demo's
first frame and scored by the tracking objective the stages optimise, over the whole clip:

    J = w_pos mean_t |t_t - t_ref| + w_rot mean_t (1 - |q_t . q_ref|) + w_hand mean_t,k |x_tk - x_ref|

(the object's translation in m and rotation, the robot's metric keypoints against the human's), with the
stages' weights; an unstable rollout scores infinity. The lowest J wins. The success thresholds are not
used: the choice sees only the objective, as the optimisation does.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from quasisim.data.demo import Demo
from quasisim.optim.objective import Weights, tracking_errors, weighted_sum
from quasisim.targets import TargetRollout, make_target


def clip_cost(demo: Demo, rollout: TargetRollout, weights: Weights) -> float:
    """J of a rollout in the target (frames 1..T-1 against the demo); infinity when it is unstable."""
    if rollout.instability:
        return float("inf")
    ref_kp = demo.human_joints[1:, rollout.kp_human[rollout.kp_metric]]
    terms = tracking_errors(
        rollout.object_pos[1:], rollout.object_quat[1:], rollout.robot_keypoints[1:],
        demo.object_pos[1:], demo.object_quat[1:], ref_kp,
    )  # fmt: skip
    w = {k: np.float32(v) for k, v in weights.arrays().items()}
    return float(weighted_sum({k: terms[k] for k in ("obj_pos", "obj_rot", "hand")}, w))


def best_in_target(
    demo: Demo, scene: Any, target: str, candidates: dict[str, np.ndarray], weights: Weights
) -> tuple[str, dict[str, float]]:
    """The name of the candidate PD-target trajectory (T, 6 + J) with the lowest J in ``target``, and
    every candidate's J (the first of equal ones wins, so list the latest stage first)."""
    tgt = make_target(target, scene)
    costs = {name: clip_cost(demo, tgt.rollout(q), weights) for name, q in candidates.items()}
    return min(costs, key=costs.__getitem__), costs
