"""Robust success: a run's controls replayed in seeded, perturbed copies of its target, open or closed loop.

A trajectory planned in one simulator meets another world: a slightly heavier object, other friction, an
object a few millimetres off, softer servos, a push. :func:`robust_success` replays the same PD targets in
``n`` perturbed scenes (:func:`perturbed_scene`, ranges in ``configs/robust.yaml``, or the wider
``configs/robust_wide.yaml`` with a push mid-clip) and reports the fraction of replays that pass each success
criterion (:data:`quasisim.eval.metrics.SUCCESS_KEYS`). Open loop, the PD targets are applied as they are;
closed loop, a policy (:class:`Policy`, e.g. :class:`quasisim.method.track.Tracker`) observes each perturbed
world frame by frame and chooses the targets. Both meet the same seeded worlds, so they compare clip by clip.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from quasisim.config import apply_overrides, build, read_yaml
from quasisim.data.demo import Demo
from quasisim.errors import InputError
from quasisim.targets.scene import Scene

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
ROBUST_PATH = CONFIGS / "robust.yaml"
RANGES = {"default": ROBUST_PATH, "wide": CONFIGS / "robust_wide.yaml"}  # --ranges NAME
ROBUST_KEY = "robust"  # metrics.json (the default ranges; the wide ones: "robust_wide")
CLOSED_LOOP_SUFFIX = "_closed_loop"  # metrics.json: "robust_closed_loop", "robust_wide_closed_loop"
# metrics.json key of each shipped perturbation set -> what it perturbs (reports, tables)
ROBUST_SETS = {
    "robust": "object mass, friction, initial object position, PD gains; configs/robust.yaml",
    "robust_wide": "about 2x those ranges and a push on the object mid-clip; configs/robust_wide.yaml",
}


@dataclass(frozen=True)
class RobustConfig:
    """Perturbed replays (``configs/robust.yaml``): ``n`` replays seeded with ``(seed, i)``; relative ranges
    ``mass`` (mass and inertia), ``friction``, ``pd_gains`` (kp and kv); ``object_pos`` (m, along x and y);
    ``push`` (m/s) added to the object's velocity, horizontally, at frame ``round(push_at (T - 1))`` (0: none).
    ``name``: the metrics key of the open-loop results (``name + "_closed_loop"`` closed loop)."""

    n: int = 0
    seed: int = 0
    mass: float = 0.15
    friction: float = 0.20
    object_pos: float = 0.003
    pd_gains: float = 0.10
    push: float = 0.0
    push_at: float = 0.5
    name: str = ROBUST_KEY
    path: str = ""

    def __post_init__(self) -> None:
        where = self.path or None
        if self.n < 0:
            raise InputError(where, "n", "a count >= 0 (0: no robust replays)", str(self.n))
        for name in ("mass", "friction", "pd_gains"):
            v = getattr(self, name)
            if not 0 <= v < 1:
                raise InputError(where, name, "a relative range in [0, 1)", repr(v))
        if not 0 <= self.object_pos <= 0.05:
            raise InputError(where, "object_pos", "a distance in [0, 0.05] m", repr(self.object_pos))
        if not 0 <= self.push <= 2.0:
            raise InputError(where, "push", "a speed in [0, 2] m/s", repr(self.push))
        if not 0 <= self.push_at <= 1:
            raise InputError(where, "push_at", "a fraction of the clip in [0, 1]", repr(self.push_at))
        if not self.name.isidentifier():
            raise InputError(where, "name", "a metrics key (letters, digits, _)", repr(self.name))

    @classmethod
    def from_yaml(cls, path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> RobustConfig:
        path = Path(path or ROBUST_PATH)
        data = apply_overrides(read_yaml(path), overrides)
        return build(cls, {**data, "path": str(path)}, path)

    @property
    def closed_loop_key(self) -> str:
        return self.name + CLOSED_LOOP_SUFFIX


def replays(n: int | None, ranges: str = "default") -> RobustConfig:
    """The shipped settings of ``ranges`` (one of :data:`RANGES`: ``configs/robust.yaml`` or
    ``configs/robust_wide.yaml``) with ``n`` replays where given (``--robust N``)."""
    if ranges not in RANGES:
        from quasisim.errors import choice_error

        raise choice_error("perturbation ranges", ranges, tuple(RANGES))
    return RobustConfig.from_yaml(RANGES[ranges], None if n is None else {"n": n})


def _draws(cfg: RobustConfig, i: int) -> np.ndarray:
    """Replay ``i``'s 6 uniform draws in [-1, 1): mass, friction, gains, object x, object y (the first five,
    as they always were), then the push's direction."""
    return np.random.default_rng([cfg.seed, i]).uniform(-1.0, 1.0, size=6)


def perturbed_scene(scene: Scene, cfg: RobustConfig, i: int) -> Scene:
    """Replay ``i``'s copy of ``scene``: every factor drawn uniformly within its range from a generator
    seeded with ``(cfg.seed, i)`` (the same copy on every machine and in every run)."""
    u = _draws(cfg, i)
    obj = dataclasses.replace(scene.obj, mass=scene.obj.mass * (1 + cfg.mass * u[0]),
                              inertia=scene.obj.inertia * (1 + cfg.mass * u[0]))  # fmt: skip
    object.__setattr__(obj, "_memo", scene.obj._memo)  # the mesh, its SDF and convex parts are unchanged
    physics = dataclasses.replace(
        scene.physics,
        friction=scene.physics.friction * (1 + cfg.friction * u[1]),
        gain_scale=scene.physics.gain_scale * (1 + cfg.pd_gains * u[2]),
    )
    pos0 = scene.object_pos0 + cfg.object_pos * np.array([u[3], u[4], 0.0])
    return dataclasses.replace(scene, obj=obj, physics=physics, object_pos0=pos0)


def push_of(cfg: RobustConfig, i: int, n_frames: int) -> tuple[int, np.ndarray] | None:
    """Replay ``i``'s push: the frame after which it acts and the velocity (3,) m/s added to the object's
    centre of mass (horizontal, direction drawn with the replay's generator); None without a push."""
    if cfg.push == 0 or n_frames < 2:
        return None
    a = np.pi * _draws(cfg, i)[5]
    return max(1, round(cfg.push_at * (n_frames - 1))), cfg.push * np.array([np.cos(a), np.sin(a), 0.0])


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
