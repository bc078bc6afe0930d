"""Realistic target simulators (MuJoCo, PyBullet): PD targets per frame in, per-frame states out.

Both targets build the same :class:`~quasisim.targets.scene.Scene` and share :class:`TargetRollout`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from quasisim.errors import choice_error
from quasisim.files import save_npz_atomic

TARGETS = ("mujoco", "pybullet")
# A rollout faster than this is a numerical blow-up, not a manipulation (a dropped object reaches ~4 m/s).
MAX_OBJECT_SPEED = 10.0  # m/s, object origin between two frames
MAX_HAND_SPEED = 30.0  # m/s, any robot keypoint between two frames


@dataclass(frozen=True, eq=False)
class TargetRollout:
    """What a target simulator produced, sampled at the control frames (T frames).

    Attributes:
        target: ``"mujoco"`` or ``"pybullet"``.
        qpos: (T, D) measured hand generalized positions (base coordinates + joints; D = 6 + J per hand,
            the hands concatenated, right then left).
        object_pos: (T, 3) m.  object_quat: (T, 4) w x y z.
        keypoints: (T, K, 3) all robot keypoints of every hand (m).
        kp_human: (K,) index of each robot keypoint into the human keypoints of all hands
            (``Demo.human_joints``: the left hand's are 21..41).  kp_metric: (K,) used in MPJPE.
        dt: physics step (s); substeps: physics steps per control frame; wall_s: wall time of the rollout.
        extras: ``sim_warnings`` (name -> count) where the simulator reports numerical trouble (MuJoCo).
    """

    target: str
    qpos: np.ndarray
    object_pos: np.ndarray
    object_quat: np.ndarray
    keypoints: np.ndarray
    kp_human: np.ndarray
    kp_metric: np.ndarray
    dt: float
    substeps: int
    wall_s: float
    extras: dict[str, Any] = field(default_factory=dict)

    @property
    def robot_keypoints(self) -> np.ndarray:
        """(T, K_metric, 3) the keypoints used by the metrics."""
        return self.keypoints[:, self.kp_metric]

    @property
    def human_keypoint_index(self) -> np.ndarray:
        return self.kp_human[self.kp_metric]

    @property
    def instability(self) -> str:
        """Why this rollout is numerically unstable (the simulator's warnings, NaN or inf, an energy blow-up:
        speeds no hand or held object reaches), or "" when it is not."""
        warned = {k: int(n) for k, n in self.extras.get("sim_warnings", {}).items() if n}
        if warned:
            return f"{self.target} warned: " + ", ".join(f"{k} x{n}" for k, n in warned.items())
        for name, a in (("hand qpos", self.qpos), ("object pose", self.object_pos), ("keypoints", self.keypoints)):
            if not np.isfinite(a).all():
                return f"NaN or inf in the {name} from frame {int(np.argwhere(~np.isfinite(a))[0][0])}"
        frame_dt = self.dt * self.substeps
        v_obj = np.linalg.norm(np.diff(self.object_pos, axis=0), axis=-1) / frame_dt
        v_kp = np.linalg.norm(np.diff(self.keypoints, axis=0), axis=-1).max(axis=-1, initial=0.0) / frame_dt
        for what, v, vmax in (("object", v_obj, MAX_OBJECT_SPEED), ("hand keypoint", v_kp, MAX_HAND_SPEED)):
            if len(v) and v.max() > vmax:
                t = int(np.argmax(v > vmax))
                return f"energy blow-up: {what} speed {v[t]:.3g} m/s (limit {vmax:g}) at frame {t + 1}"
        return ""

    def save(self, path: str | Path) -> Path:
        """``rollout.npz``: object_pos, object_quat, robot_keypoints, human_keypoint_index (+ full state)."""
        return save_npz_atomic(
            path,
            target=np.array(self.target),
            object_pos=self.object_pos.astype(np.float64),
            object_quat=self.object_quat.astype(np.float64),
            robot_keypoints=self.robot_keypoints.astype(np.float64),
            human_keypoint_index=self.human_keypoint_index.astype(np.int64),
            qpos=self.qpos.astype(np.float64),
            all_keypoints=self.keypoints.astype(np.float64),
            all_human_keypoint_index=self.kp_human.astype(np.int64),
            dt=np.array(self.dt),
            substeps=np.array(self.substeps),
            instability=np.array(self.instability),
        )


class Target(Protocol):
    name: str

    def rollout(self, q_targets: np.ndarray) -> TargetRollout: ...


def make_target(name: str, scene: Any) -> Target:
    """Build target simulator ``name`` (one of :data:`TARGETS`) for ``scene`` (each target's module, with
    its simulator, loads only when it is asked for)."""
    if name == "mujoco":
        from quasisim.targets.mujoco_target import MujocoTarget

        return MujocoTarget(scene)
    if name == "pybullet":
        from quasisim.targets.pybullet_target import PybulletTarget

        return PybulletTarget(scene)
    raise choice_error("target", name, TARGETS)
