"""A trained policy as a closed-loop controller, and its validation during training.

:class:`LearnedPolicy` is the controller protocol of robust success (:class:`quasisim.eval.robust.Policy`): it
observes each frame of the world, never the world's parameters, and chooses the next PD targets with the
policy's mean action (deterministic). :func:`validate` replays it as the evaluation does (:func:`replay`) in the
nominal world and in validation worlds: training worlds (seed ``world_seed``), never the evaluation's (seed 0).
"""

from __future__ import annotations

import time
from typing import Any, NamedTuple

import numpy as np

from quasisim.envs.task import TrackTask

VALIDATION_WORLD0 = 2**31  # validation world k is training world VALIDATION_WORLD0 + k (resets draw below 2**31)


class LearnedPolicy:
    """A trained policy as a closed-loop controller of :mod:`quasisim.eval.robust` (one replay)."""

    def __init__(self, task: TrackTask, model: Any) -> None:
        self.task, self.model = task, model
        self.applied: list[np.ndarray] = []
        self.seconds = 0.0

    def start(self, obs: dict[str, np.ndarray]) -> None:
        self.applied = [self.task.reference[0].copy()]

    def act(self, t: int, obs: dict[str, np.ndarray]) -> np.ndarray:
        t0 = time.perf_counter()
        a, _ = self.model.predict(self.task.observation(t, obs), deterministic=True)
        q = self.task.targets(t, a, obs)
        self.seconds += time.perf_counter() - t0
        self.applied.append(q)
        return q

    def schedule_from(self, prev: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Where each frame's PD schedule starts, as in training (:meth:`TrackTask.schedule_from`)."""
        return self.task.schedule_from(prev, q)

    def cost(self) -> dict[str, float]:
        return {"policy_seconds": self.seconds, "steps": float(len(self.applied) - 1)}

    def close(self) -> None:
        return None


class Score(NamedTuple):
    """A policy's validation, compared in this order (higher is better): strict success in the nominal world,
    the share of validation worlds with strict success, the mean share of frames before a world first left
    the strict limits."""

    nominal: bool
    worlds: float
    frames: float


def _strict(task: TrackTask, rollout: Any) -> tuple[bool, float]:
    """Strict success of a replay (an unstable one fails) and the share of its frames before the first one
    outside the strict limits."""
    from quasisim.limits import STRICT_CM, STRICT_DEG, object_errors, strict_success

    d = task.demo
    if rollout.instability:
        return False, 0.0
    rot, trans = object_errors(d.object_pos, d.object_quat, rollout.object_pos, rollout.object_quat)
    out = np.flatnonzero((trans > STRICT_CM) | (rot > STRICT_DEG))
    share = (out[0] if len(out) else len(trans)) / len(trans)
    return strict_success(d.object_pos, d.object_quat, rollout.object_pos, rollout.object_quat), float(share)


def validate(task: TrackTask, model: Any, target: str, worlds: int, world_seed: int, ranges: Any) -> Score:
    """The :class:`Score` of ``model`` replayed in the nominal world and ``worlds`` validation worlds."""
    import dataclasses

    from quasisim.eval.robust import replay
    from quasisim.targets import make_target
    from quasisim.targets.perturb import perturbed_scene

    cfg = dataclasses.replace(ranges, seed=world_seed)
    results = []
    for k in range(-1, worlds):
        scene = task.scene if k < 0 else perturbed_scene(task.scene, cfg, VALIDATION_WORLD0 + k)
        with make_target(target, scene) as world:
            results.append(_strict(task, replay(world, task.reference, LearnedPolicy(task, model))))
    rest = results[1:] or [results[0]]
    return Score(results[0][0], float(np.mean([r[0] for r in rest])), float(np.mean([r[1] for r in rest])))
