"""Realistic target simulators (MuJoCo, PyBullet): PD targets per frame in, per-frame states out.

Both targets build the same :class:`~quasisim.targets.scene.Scene` and implement one interface,
:class:`~quasisim.targets.base.Target` (reset, observe, save/restore the state, advance one frame with the
shared PD schedule, roll a clip or candidate windows out, judge a clip); :func:`make_target` builds one.
Importing this package loads no simulator (and no JAX): each backend loads when it is asked for.
"""

from __future__ import annotations

import importlib
from typing import Any

from quasisim.errors import choice_error
from quasisim.targets.base import (
    MAX_HAND_SPEED,
    MAX_OBJECT_SPEED,
    OBS_KEYS,
    Observation,
    PDGains,
    Prediction,
    Prune,
    Target,
    TargetRollout,
    feed_forward,
    pd_gains,
    pd_schedule,
)

# target name -> "module:class" of its Target; adding a target is one module and one line here (docs/stages.md)
BACKENDS: dict[str, str] = {
    "mujoco": "quasisim.targets.mujoco_target:MujocoTarget",
    "pybullet": "quasisim.targets.pybullet_target:PybulletTarget",
}
TARGETS = tuple(BACKENDS)

__all__ = [
    "BACKENDS", "MAX_HAND_SPEED", "MAX_OBJECT_SPEED", "OBS_KEYS", "TARGETS", "Observation", "PDGains", "Prediction", "Prune", "Target",
    "TargetRollout", "feed_forward", "make_target", "pd_gains", "pd_schedule",
]  # fmt: skip


def make_target(name: str, scene: Any, threads: int = 1) -> Target:
    """Build target simulator ``name`` (one of :data:`TARGETS`) for ``scene`` (each target's module, with
    its simulator, loads only when it is asked for); ``threads``: threads for
    :meth:`~quasisim.targets.base.Target.rollout_windows` where the backend has them (MuJoCo; PyBullet runs
    one client, one thread). Every backend's class takes ``(scene, threads=...)``."""
    if name not in BACKENDS:
        raise choice_error("target", name, TARGETS)
    module, cls = BACKENDS[name].split(":")
    return getattr(importlib.import_module(module), cls)(scene, threads=threads)
