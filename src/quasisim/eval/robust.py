"""Robust success: a run's controls replayed in seeded, perturbed copies of its target, open or closed loop.

A trajectory planned in one simulator meets another world: a slightly heavier object, other friction, an
object a few millimetres off, softer servos, a push. :func:`robust_success` replays the same PD targets in
``n`` perturbed scenes (:func:`perturbed_scene`, ranges in ``configs/robust.yaml``, or the wider
``configs/robust_wide.yaml`` with a push mid-clip) and reports the fraction of replays that pass each success
criterion (:data:`quasisim.eval.metrics.SUCCESS_KEYS`). Open loop, the PD targets are applied as they are;
closed loop, a policy (:class:`Policy`, e.g. :class:`quasisim.method.track.Tracker`) observes each perturbed
world frame by frame and chooses the targets. Both meet the same seeded worlds, so they compare clip by clip.

The perturbations themselves (:class:`~quasisim.targets.perturb.RobustConfig`, :func:`perturbed_scene`,
:func:`push_of` and the metrics keys they name) are :mod:`quasisim.targets.perturb`'s, since the sampling
stage draws them too; they are imported here under the same names.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from quasisim.data.demo import Demo
from quasisim.targets.perturb import CLOSED_LOOP_SUFFIX as CLOSED_LOOP_SUFFIX
from quasisim.targets.perturb import CONFIGS, ROBUST_PATH, RobustConfig, perturbed_scene, push_of
from quasisim.targets.perturb import ROBUST_KEY as ROBUST_KEY
from quasisim.targets.scene import Scene

RANGES = {"default": ROBUST_PATH, "wide": CONFIGS / "robust_wide.yaml"}  # --ranges NAME
# metrics.json key of each shipped perturbation set -> what it perturbs (reports, tables)
ROBUST_SETS = {
    "robust": "object mass, friction, initial object position, PD gains; configs/robust.yaml",
    "robust_wide": "about 2x those ranges and a push on the object mid-clip; configs/robust_wide.yaml",
}


def replays(n: int | None, ranges: str = "default") -> RobustConfig:
    """The shipped settings of ``ranges`` (one of :data:`RANGES`: ``configs/robust.yaml`` or
    ``configs/robust_wide.yaml``) with ``n`` replays where given (``--robust N``)."""
    if ranges not in RANGES:
        from quasisim.errors import choice_error

        raise choice_error("perturbation ranges", ranges, tuple(RANGES))
    return RobustConfig.from_yaml(RANGES[ranges], None if n is None else {"n": n})


class Policy(Protocol):
    """A closed-loop controller (:class:`quasisim.method.track.Tracker`): ``start`` on the world's first
    observation, ``act(t, obs)`` -> the PD targets (D,) for frame ``t + 1``; ``cost()`` what it spent
    (numbers, averaged over replays); ``close()``."""

    def start(self, obs: dict[str, np.ndarray]) -> None: ...
    def act(self, t: int, obs: dict[str, np.ndarray]) -> np.ndarray: ...
    def cost(self) -> dict[str, float]: ...
    def close(self) -> None: ...


def replay(world: Any, q_targets: np.ndarray, policy: Policy | None = None,
           push: tuple[int, np.ndarray] | None = None, qd0: np.ndarray | None = None) -> Any:  # fmt: skip
    """Run a clip in ``world`` (a :class:`~quasisim.targets.base.Target`) as a robust replay does: the hands
    start at ``q_targets[0]`` with the targets' initial velocity (or ``qd0``); open loop (no ``policy``) frame
    ``t + 1``'s targets are ``q_targets[t + 1]``, closed loop ``policy.act(t, observation at t)``; ``push``
    (frame, dv) adds ``dv`` to the object's velocity after that frame. Returns the :class:`TargetRollout`."""
    q = np.asarray(q_targets, np.float64)
    if policy is None and push is None and qd0 is None:
        return world.rollout(q)
    T, fps = len(q), world.scene.fps
    world.reset(q[0], qd0 if qd0 is not None else (q[1] - q[0]) * fps if T > 1 else None)
    t0, frames, prev = time.perf_counter(), [], q[0]
    obs = world.observe()
    if policy is not None:
        policy.start(obs)
    for t in range(T):
        frames.append(obs)
        if t == T - 1:
            break
        nxt = q[t + 1] if policy is None else np.asarray(policy.act(t, obs), np.float64)
        world.advance(prev, nxt)
        prev = nxt
        obs = world.observe()
        if push is not None and t + 1 == push[0]:
            world.sync({**obs, "obj_vel": obs["obj_vel"] + push[1]})
            obs = world.observe()
    return world.recorded(frames, time.perf_counter() - t0)


def robust_success(
    demo: Demo, scene: Scene, q_targets: np.ndarray, target: str, cfg: RobustConfig,
    policy: Callable[[], Policy] | None = None,
) -> dict[str, Any]:  # fmt: skip
    """``{"n", "seed", <success key>: fraction of the n perturbed replays that pass it, "unstable": count}``
    (an unstable replay passes nothing); ``{}`` when ``cfg.n`` is 0. With ``policy`` (a function making a
    fresh :class:`Policy` per replay, built from the nominal ``scene`` only: the perturbed world is never
    handed to it) the replays are closed loop, and the result also holds ``seconds_per_replay`` and the
    policy's mean ``cost()`` per replay (``tracker``)."""
    from quasisim.eval.metrics import SUCCESS_KEYS, evaluate_rollout
    from quasisim.targets import make_target

    if cfg.n == 0:
        return {}
    passed, unstable, costs, wall = dict.fromkeys(SUCCESS_KEYS, 0), 0, [], 0.0
    for i in range(cfg.n):
        ctl = policy() if policy is not None else None
        t0 = time.perf_counter()
        try:
            with make_target(target, perturbed_scene(scene, cfg, i)) as world:
                rollout = replay(world, q_targets, ctl, push_of(cfg, i, len(q_targets)))
        finally:
            if ctl is not None:
                costs.append(ctl.cost())
                ctl.close()
        wall += time.perf_counter() - t0
        if rollout.instability:
            unstable += 1
            continue
        ok = evaluate_rollout(demo, rollout, None)[0]["success"]
        for k in SUCCESS_KEYS:
            passed[k] += bool(ok[k])
    out = {"n": cfg.n, "seed": cfg.seed, **{k: passed[k] / cfg.n for k in SUCCESS_KEYS}, "unstable": unstable}
    if policy is not None:
        out["seconds_per_replay"] = wall / cfg.n
        out["tracker"] = {k: float(np.mean([c[k] for c in costs])) for k in costs[0]}
    return out
