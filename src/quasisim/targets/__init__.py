"""Realistic target simulators (MuJoCo, PyBullet): PD targets per frame in, per-frame states out.

Both targets build the same :class:`~quasisim.targets.scene.Scene` and implement one interface,
:class:`~quasisim.targets.base.Target` (reset, observe, save/restore the state, advance one frame with the
shared PD schedule, roll a clip or candidate windows out, judge a clip); :func:`make_target` builds one.
Importing this package loads no simulator (and no JAX): each backend loads when it is asked for.
"""

from __future__ import annotations

from typing import Any

from quasisim.errors import choice_error
from quasisim.targets.base import (
    MAX_HAND_SPEED,
    MAX_OBJECT_SPEED,
    OBS_KEYS,
    Observation,
    PDGains,
    Prediction,
    Target,
    TargetRollout,
    feed_forward,
    pd_gains,
    pd_schedule,
)

TARGETS = ("mujoco", "pybullet")

__all__ = [
    "MAX_HAND_SPEED", "MAX_OBJECT_SPEED", "OBS_KEYS", "TARGETS", "Observation", "PDGains", "Prediction", "Target",
    "TargetRollout", "feed_forward", "make_target", "pd_gains", "pd_schedule",
]  # fmt: skip


def make_target(name: str, scene: Any, threads: int = 1) -> Target:
    """Build target simulator ``name`` (one of :data:`TARGETS`) for ``scene`` (each target's module, with
    its simulator, loads only when it is asked for); ``threads``: MuJoCo's threads for
    :meth:`~quasisim.targets.base.Target.rollout_windows` (PyBullet runs one client, one thread)."""
    if name == "mujoco":
        from quasisim.targets.mujoco_target import MujocoTarget

        return MujocoTarget(scene, threads=threads)
    if name == "pybullet":
        from quasisim.targets.pybullet_target import PybulletTarget

        return PybulletTarget(scene)
    raise choice_error("target", name, TARGETS)
