"""Perturbed copies of a scene: the worlds of robust success (:mod:`quasisim.eval.robust`) and of the sampling
stage's robust scoring (:mod:`quasisim.method.stages.sampling`, step 7).

:class:`RobustConfig` holds the ranges (``configs/robust.yaml``, or the wider ``configs/robust_wide.yaml``
with a push mid-clip); :func:`perturbed_scene` draws replay ``i``'s copy of a scene (object mass and
inertia, friction, PD gains, the object's initial position) and :func:`push_of` its push, each from a
generator seeded with ``(seed, i)``, the same on every machine and in every run.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from quasisim.config import load
from quasisim.errors import InputError
from quasisim.targets.scene import Scene

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
ROBUST_PATH = CONFIGS / "robust.yaml"
ROBUST_KEY = "robust"  # metrics.json (the default ranges; the wide ones: "robust_wide")
CLOSED_LOOP_SUFFIX = "_closed_loop"  # metrics.json: "robust_closed_loop", "robust_wide_closed_loop"


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
        return load(cls, Path(path or ROBUST_PATH), overrides)

    @property
    def closed_loop_key(self) -> str:
        return self.name + CLOSED_LOOP_SUFFIX


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
