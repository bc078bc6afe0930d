"""Settings of the tracking environment (``configs/track_env.yaml``): frozen dataclasses, validated on load."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from quasisim.config import load
from quasisim.errors import InputError
from quasisim.limits import STRICT_CM, STRICT_DEG

TRACK_ENV_PATH = Path(__file__).resolve().parent.parent / "configs" / "track_env.yaml"
TERMINATIONS = ("strict", "unstable")
STARTS = ("first", "random")  # reference state initialisation: the clip's first frame, or a random one


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
