"""Small pieces the stage modules share: timing a checkpointed piece, what a checkpoint must hold."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from quasisim.method.checkpoints import Checkpoints, Expect, trajectory_expect
from quasisim.method.problem import Problem


def timed(ck: Checkpoints, name: str, fn: Callable[[], dict[str, Any]], expect: Expect) -> dict[str, Any]:
    """``ck.get(name, fn, expect)`` recording ``fn``'s wall time as ``wall_s``."""

    def run() -> dict[str, Any]:
        t0 = time.perf_counter()
        d = fn()
        return {**d, "wall_s": np.array(time.perf_counter() - t0)}

    return ck.get(name, run, {**expect, "wall_s": ()})


def traj_expect(prob: Problem, **more: Any) -> Expect:
    """A checkpoint holding a simulator trajectory of ``prob`` (and ``more``)."""
    return trajectory_expect(
        prob.demo.n_frames, prob.model.n_joints, prob.model.n_points, prob.model.hand.n_hands, **more
    )


def q_expect(prob: Problem) -> Expect:
    """A checkpoint holding PD targets (T, D) of ``prob``, a loss per frame and the wall time."""
    return {"q_targets": (prob.demo.n_frames, prob.scene.n_dof), "window_loss": (None,), "wall_s": ()}
