"""Gymnasium environments on quasisim's clips and targets; importing this module registers them.

* ``quasisim/Track-v0`` (:class:`~quasisim.envs.track.TrackEnv`): track one demonstration in MuJoCo or
  PyBullet, optionally as a residual on one of our results (docs/policies.md).
"""

from __future__ import annotations

import gymnasium as gym

TRACK_ID = "quasisim/Track-v0"

if TRACK_ID not in gym.registry:
    gym.register(TRACK_ID, entry_point="quasisim.envs.track:TrackEnv")

__all__ = ["TRACK_ID"]
