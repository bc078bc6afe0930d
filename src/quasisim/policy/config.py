"""PPO settings of ``quasisim policy train`` (``configs/ppo.yaml``): a frozen dataclass, validated on load."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from quasisim.config import load
from quasisim.errors import InputError

PPO_PATH = Path(__file__).resolve().parent.parent / "configs" / "ppo.yaml"


@dataclass(frozen=True)
class PPOConfig:
    """stable-baselines3 PPO's settings (their names) and ours: ``n_envs`` processes, ``checkpoint_every``
    env steps (each checkpoint validated in the nominal world and ``validate_worlds`` training worlds), ``net_arch`` and the initial exploration noise ``log_std_init`` (``log_std_init_residual`` for
    a residual policy) of the policy; ``dgrasp-tracking-curriculum`` trains ``curriculum_stage_steps`` env steps in
    each analytical simulator of ``curriculum`` (``configs/curricula``), then the rest in the target."""

    n_envs: int = 2
    n_steps: int = 512
    batch_size: int = 256
    n_epochs: int = 5
    learning_rate: float = 3e-4
    gamma: float = 0.98
    gae_lambda: float = 0.95
    clip_range: float = 0.2
    ent_coef: float = 0.0
    max_grad_norm: float = 0.5
    log_std_init: float = -1.0
    log_std_init_residual: float = -2.5
    net_arch: tuple[int, ...] = (256, 256)
    checkpoint_every: int = 10000
    validate_worlds: int = 8
    curriculum: str = "default"
    curriculum_stage_steps: int = 24576
    path: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        where = self.path or None
        if self.validate_worlds < 0:
            raise InputError(where, "validate_worlds", "a count >= 0", str(self.validate_worlds))
        for name in ("n_envs", "n_steps", "batch_size", "n_epochs", "checkpoint_every", "curriculum_stage_steps"):
            if getattr(self, name) < 1:
                raise InputError(where, name, "an integer >= 1", str(getattr(self, name)))
        if (self.n_envs * self.n_steps) % self.batch_size:
            raise InputError(where, "batch_size", f"a divisor of n_envs * n_steps = {self.n_envs * self.n_steps}",
                             str(self.batch_size))  # fmt: skip
        if not 0 < self.gamma <= 1 or not 0 < self.gae_lambda <= 1:
            raise InputError(where, "gamma", "gamma and gae_lambda in (0, 1]", f"{self.gamma}, {self.gae_lambda}")
        if self.learning_rate <= 0 or not self.net_arch or min(self.net_arch) < 1:
            raise InputError(where, "learning_rate", "a rate > 0 and layers of >= 1 units", repr(self))

    @classmethod
    def from_yaml(cls, path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> PPOConfig:
        return load(cls, Path(path or PPO_PATH), overrides)

    def ppo_kwargs(self, residual: bool) -> dict[str, Any]:
        """The keyword arguments of ``stable_baselines3.PPO`` (for a residual policy or not)."""
        ours = (
            "n_envs",
            "log_std_init",
            "log_std_init_residual",
            "net_arch",
            "checkpoint_every",
            "validate_worlds",
            "curriculum",
            "curriculum_stage_steps",
            "path",
        )
        d = {k: v for k, v in asdict(self).items() if k not in ours}
        arch, std = list(self.net_arch), self.log_std_init_residual if residual else self.log_std_init
        return d | {"policy_kwargs": {"log_std_init": std, "net_arch": {"pi": arch, "vf": arch}}}
