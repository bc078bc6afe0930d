"""Keep the best controls seen in the target, judged there (issue "stage 3": a later stage never makes the
result worse).

Every trajectory of PD targets the method produced (the kinematic retarget, the curriculum's plan, the
closed-loop MPC's and the sampling stage's results) is replayed open loop in the target from the demo's
first frame and scored by the tracking objective the stages optimise, over the whole clip:

    J = w_pos mean_t |t_t - t_ref| + w_rot mean_t (1 - |q_t . q_ref|) + w_hand mean_t,k |x_tk - x_ref|

(the object's translation in m and rotation, the robot's metric keypoints against the human's), with the
stages' weights (:func:`quasisim.optim.objective.clip_cost`, through the target's
:meth:`~quasisim.targets.base.Target.judge`); an unstable rollout scores infinity. The lowest J wins. The success thresholds are not
used: the choice sees only the objective, as the optimisation does.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from quasisim.data.demo import Demo
from quasisim.optim.objective import Weights
from quasisim.targets import make_target


def best_in_target(
    demo: Demo, scene: Any, target: str, candidates: dict[str, np.ndarray], weights: Weights
) -> tuple[str, dict[str, float]]:
    """The name of the candidate PD-target trajectory (T, 6 + J) with the lowest J in ``target`` (its
    :meth:`~quasisim.targets.base.Target.judge`), and every candidate's J (the first of equal ones wins, so
    list the latest stage first)."""
    with make_target(target, scene) as tgt:
        costs = {name: tgt.judge(demo, q, weights) for name, q in candidates.items()}
    return min(costs, key=costs.__getitem__), costs
