"""Settings of the tracking environment (``configs/track_env.yaml``): frozen dataclasses, validated on load."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from quasisim.config import load
from quasisim.errors import InputError
from quasisim.limits import STRICT_CM, STRICT_DEG

TRACK_ENV_PATH = Path(__file__).resolve().parent.parent / "configs" / "track_env.yaml"
TERMINATIONS = ("strict", "unstable")
STARTS = ("first", "random")  # reference state initialisation: the clip's first frame, or a random one
REWARD_FORMS = ("tracking", "dgrasp")  # the tracking reward (Reward), or DGrasp's terms (DgraspReward)
ACTION_FORMS = ("default", "dgrasp")  # today's residual/delta targets, or DGrasp's (DgraspAction; not residual)


@dataclass(frozen=True)
class DofScale:
    """Action scale per kind of dof: the bases' slides (m), their hinges (rad), the finger joints (rad)."""

    base_pos: float
    base_rot: float
    joints: float


@dataclass(frozen=True)
class Term:
    """One reward term ``weight exp(-error / scale)`` (the error in the term's unit: cm or deg)."""

    weight: float
    scale: float


@dataclass(frozen=True)
class Reward:
    """The terms of the tracking reward (see ``configs/track_env.yaml``)."""

    object_pos: Term
    object_rot: Term
    keypoints: Term
    contact: Term
    action_cost: float = 0.0

    def terms(self) -> dict[str, Term]:
        return {"object_pos": self.object_pos, "object_rot": self.object_rot, "keypoints": self.keypoints,
                "contact": self.contact}  # fmt: skip


@dataclass(frozen=True)
class DgraspReward:
    """DGrasp's reward (``reward_form: dgrasp``): the coefficient of each term and the per-step lower bound, as in
    DGrasp's published configuration (github christsa/dgrasp, ``raisimGymTorch/.../envs/dgrasp/cfgs/cfg.yaml``:
    ``pos_reward`` 2.0, ``pose_reward`` 0.1, ``contact_reward`` 1.0, ``impulse_reward`` 2.0, ``rel_obj_reward_``
    -1.0, ``body_vel_reward_`` -0.5, ``body_qvel_reward_`` -0.5, ``reward_clip`` -2.0). The terms are
    :meth:`quasisim.envs.task.TrackTask.dgrasp_terms`; ``impulse_cap`` bounds the impulse term, in object
    weights ``m g``. ``clip`` is the lower bound DGrasp's configuration names; its published ``runner.py`` computes
    ``reward.clip(min=reward_clip)`` without keeping the result (its training ran unclipped: set it far below)."""

    pos: float = 2.0
    pose: float = 0.1
    contact: float = 1.0
    impulse: float = 2.0
    obj_vel: float = -1.0
    body_vel: float = -0.5
    body_qvel: float = -0.5
    clip: float = -2.0
    impulse_cap: float = 5.0

    def coefficients(self) -> dict[str, float]:
        """Each term's coefficient by the term's name (``r_<name>`` in a step's info)."""
        return {"pos": self.pos, "pose": self.pose, "contact": self.contact, "impulse": self.impulse,
                "obj_vel": self.obj_vel, "body_vel": self.body_vel, "body_qvel": self.body_qvel}  # fmt: skip


@dataclass(frozen=True)
class DgraspAction:
    """DGrasp's action scale (``action_form: dgrasp``): the step per unit action of the finger joints
    (``fingers``, rad), the base hinges (``rot``, rad) and the base slides around the goal wrist position
    (``root``, m), as in DGrasp's published code with its wrist guidance on (github christsa/dgrasp,
    ``raisimGymTorch/.../envs/dgrasp/Environment.hpp``, ``cfgs/cfg.yaml``: ``finger_action_std`` 0.015,
    ``rot_action_std`` 0.01, the root's 0.001 of ``root_guided``). DGrasp's actions are unbounded Gaussians
    scaled by these; ours are clipped to [-1, 1], so each is the largest step a frame's action can take."""

    fingers: float = 0.015
    rot: float = 0.01
    root: float = 0.001

    def scale(self) -> DofScale:
        """As a :class:`DofScale` (base slides, base hinges, finger joints)."""
        return DofScale(base_pos=self.root, base_rot=self.rot, joints=self.fingers)


@dataclass(frozen=True)
class TrackEnvConfig:
    """The environment's settings; see ``configs/track_env.yaml`` for each key."""

    horizon: int
    residual_scale: DofScale
    delta_scale: DofScale
    reward: Reward
    contact_radius: float = 0.01
    terminate: str = "strict"
    randomize: bool = True
    ranges: str = "default"
    world_seed: int = 1000
    start: str = "first"
    limits_start: tuple[float, float] = (2.0, 30.0)
    limits_steps: int = 0
    observe_hand_frame: bool = False
    reward_form: str = "tracking"
    dgrasp_reward: DgraspReward = field(default_factory=DgraspReward)
    action_form: str = "default"
    dgrasp_action: DgraspAction = field(default_factory=DgraspAction)
    path: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        where = self.path or None
        if self.horizon < 1:
            raise InputError(where, "horizon", "frames >= 1", str(self.horizon))
        if self.terminate not in TERMINATIONS:
            raise InputError(where, "terminate", f"one of {', '.join(TERMINATIONS)}", repr(self.terminate))
        if self.ranges not in ("default", "wide"):
            raise InputError(where, "ranges", "default or wide", repr(self.ranges))
        for name, t in self.reward.terms().items():
            if t.weight < 0 or t.scale <= 0:
                raise InputError(where, f"reward.{name}", "weight >= 0 and scale > 0", f"{t.weight}, {t.scale}")
        for kind in ("residual_scale", "delta_scale"):
            s: DofScale = getattr(self, kind)
            if min(s.base_pos, s.base_rot, s.joints) <= 0:
                raise InputError(where, kind, "positive scales", repr(s))
        if self.contact_radius <= 0:
            raise InputError(where, "contact_radius", "a distance > 0 m", repr(self.contact_radius))
        if self.start not in STARTS:
            raise InputError(where, "start", f"one of {', '.join(STARTS)}", repr(self.start))
        cm, deg = self.limits_start
        if not (cm >= STRICT_CM and deg >= STRICT_DEG):  # also refuses NaN
            raise InputError(where, "limits_start", f"[cm, deg] at least the strict limits [{STRICT_CM:g}, "
                             f"{STRICT_DEG:g}]", f"[{cm:g}, {deg:g}]")  # fmt: skip
        if self.limits_steps < 0:
            raise InputError(where, "limits_steps", "a count of env steps >= 0", repr(self.limits_steps))
        if self.reward_form not in REWARD_FORMS:
            raise InputError(where, "reward_form", f"one of {', '.join(REWARD_FORMS)}", repr(self.reward_form))
        for name, value in dataclasses.asdict(self.dgrasp_reward).items():
            if not math.isfinite(value):  # the YAML loader refuses these; a config built in code may not
                raise InputError(where, f"dgrasp_reward.{name}", "a finite number", repr(value))
        if not self.dgrasp_reward.impulse_cap > 0:
            raise InputError(where, "dgrasp_reward.impulse_cap", "object weights > 0",
                             repr(self.dgrasp_reward.impulse_cap))  # fmt: skip
        if self.action_form not in ACTION_FORMS:
            raise InputError(where, "action_form", f"one of {', '.join(ACTION_FORMS)}", repr(self.action_form))
        for name, value in dataclasses.asdict(self.dgrasp_action).items():
            if not (math.isfinite(value) and value > 0):
                raise InputError(where, f"dgrasp_action.{name}", "a finite scale > 0", repr(value))

    def limits(self, steps: int) -> tuple[float, float]:
        """The termination limits (cm, deg) in force after ``steps`` env steps: ``limits_start`` shrinking
        linearly to the strict limits (:data:`quasisim.limits.STRICT_CM`, ``STRICT_DEG``) over the first
        ``limits_steps`` steps, the strict limits from then on (and throughout with ``limits_steps: 0``)."""
        if steps >= self.limits_steps:
            return STRICT_CM, STRICT_DEG
        f, (cm, deg) = steps / self.limits_steps, self.limits_start
        return cm + f * (STRICT_CM - cm), deg + f * (STRICT_DEG - deg)

    @classmethod
    def from_yaml(cls, path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> TrackEnvConfig:
        return load(cls, Path(path or TRACK_ENV_PATH), overrides)
