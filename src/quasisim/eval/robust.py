"""Robust success: a run's controls replayed open loop in seeded, perturbed copies of its target.

A trajectory planned in one simulator meets another world: a slightly heavier object, other friction, an
object a few millimetres off, softer servos. :func:`robust_success` replays the same PD targets in
``n`` perturbed scenes (:func:`perturbed_scene`, ranges in ``configs/robust.yaml``) and reports the fraction
of replays that pass each success criterion (:data:`quasisim.eval.metrics.SUCCESS_KEYS`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from quasisim.config import apply_overrides, build, read_yaml
from quasisim.data.demo import Demo
from quasisim.errors import InputError
from quasisim.targets.scene import Scene

ROBUST_PATH = Path(__file__).resolve().parent.parent / "configs" / "robust.yaml"
ROBUST_KEY = "robust"  # metrics.json


@dataclass(frozen=True)
class RobustConfig:
    """Perturbed replays (``configs/robust.yaml``): ``n`` replays seeded with ``(seed, i)``; relative ranges
    ``mass`` (mass and inertia), ``friction``, ``pd_gains`` (kp and kv); ``object_pos`` (m, along x and y)."""

    n: int = 0
    seed: int = 0
    mass: float = 0.15
    friction: float = 0.20
    object_pos: float = 0.003
    pd_gains: float = 0.10
    path: str = ""

    def __post_init__(self) -> None:
        if self.n < 0:
            raise InputError(self.path or None, "n", "a count >= 0 (0: no robust replays)", str(self.n))
        for name in ("mass", "friction", "pd_gains"):
            v = getattr(self, name)
            if not 0 <= v < 1:
                raise InputError(self.path or None, name, "a relative range in [0, 1)", repr(v))
        if not 0 <= self.object_pos <= 0.05:
            raise InputError(self.path or None, "object_pos", "a distance in [0, 0.05] m", repr(self.object_pos))

    @classmethod
    def from_yaml(cls, path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> RobustConfig:
        path = Path(path or ROBUST_PATH)
        data = apply_overrides(read_yaml(path), overrides)
        return build(cls, {**data, "path": str(path)}, path)


def replays(n: int | None) -> RobustConfig:
    """The shipped settings (``configs/robust.yaml``) with ``n`` replays where given (``--robust N``)."""
    return RobustConfig.from_yaml(None, None if n is None else {"n": n})


def perturbed_scene(scene: Scene, cfg: RobustConfig, i: int) -> Scene:
    """Replay ``i``'s copy of ``scene``: every factor drawn uniformly within its range from a generator
    seeded with ``(cfg.seed, i)`` (the same copy on every machine and in every run)."""
    u = np.random.default_rng([cfg.seed, i]).uniform(-1.0, 1.0, size=5)
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


def robust_success(demo: Demo, scene: Scene, q_targets: np.ndarray, target: str, cfg: RobustConfig) -> dict[str, Any]:
    """``{"n", "seed", <success key>: fraction of the n perturbed replays that pass it, "unstable": count}``
    (an unstable replay passes nothing); ``{}`` when ``cfg.n`` is 0."""
    from quasisim.eval.metrics import SUCCESS_KEYS, evaluate_rollout
    from quasisim.targets import make_target

    if cfg.n == 0:
        return {}
    passed, unstable = dict.fromkeys(SUCCESS_KEYS, 0), 0
    for i in range(cfg.n):
        with make_target(target, perturbed_scene(scene, cfg, i)) as tgt:
            rollout = tgt.rollout(q_targets)
        if rollout.instability:
            unstable += 1
            continue
        ok = evaluate_rollout(demo, rollout, None)[0]["success"]
        for k in SUCCESS_KEYS:
            passed[k] += bool(ok[k])
    return {"n": cfg.n, "seed": cfg.seed, **{k: passed[k] / cfg.n for k in SUCCESS_KEYS}, "unstable": unstable}
