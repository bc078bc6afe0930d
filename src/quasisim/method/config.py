"""Settings of ``quasisim transfer``: objective weights, step budgets and each stage's settings
(:mod:`quasisim.method.options`), from ``configs/transfer.yaml``.

The shipped YAML is the only source of default values: the settings dataclasses have no defaults of their
own (fields added later excepted: theirs leave results as before), so a key missing from a user's YAML is an
error naming it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from quasisim.config import apply_overrides, build, read_yaml
from quasisim.errors import InputError, choice_error
from quasisim.method.options import (
    HANDOFF_MODES,
    ControlVAEOptions,
    FitOptions,
    HandoffOptions,
    MPCOptions,
    NeuralOptions,
    RobustSelectOptions,
    SamplingOptions,
    Stage1Options,
    tracker_file,
)
from quasisim.optim.adam import StepBudget
from quasisim.optim.objective import Weights

CONFIG_PATH = Path(__file__).parents[1] / "configs" / "transfer.yaml"


@dataclass(frozen=True)
class Budget:
    """Optimisation budget: simulator discretisation and the steps of each optimisation.

    Attributes:
        substeps: simulator substeps per frame (dt = 1 / (fps substeps)).
        n_candidates: hand points examined for contact per frame (broad phase).
        human, robot_points, sim: steps of stage 1b, stage 1d and of each stage-2 simulator.
        soft_step_scale: how many times longer the step of the simulators softer than the curriculum's
            stiffest analytical one is (stage 1's relaxed simulator and stage 2's all but the last; softer
            contact allows a larger step, BENCHMARKS.md): they take :attr:`soft` substeps per frame. The
            stiffest simulator and what uses it after stage 2 (stage 3, MPC) step with ``substeps``.
    """

    substeps: int
    n_candidates: int
    human: StepBudget
    robot_points: StepBudget
    sim: StepBudget
    soft_step_scale: float = 1.0  # the YAML sets it per budget; 1: the step of the stiffest (as before it existed)

    @property
    def soft(self) -> int:
        """Substeps per frame of the simulators softer than the stiffest: ``substeps / soft_step_scale``,
        rounded, at least 1."""
        return max(1, round(self.substeps / self.soft_step_scale))


@dataclass(frozen=True)
class TransferConfig:
    """Objective weights, named budgets, closed-loop MPC and sampling settings (``configs/transfer.yaml``)."""

    weights: Weights
    budgets: dict[str, Budget]
    stage1: Stage1Options
    stage2: HandoffOptions
    mpc: MPCOptions
    soften_samples: int
    sampling: SamplingOptions
    stage3: FitOptions
    robust_select: RobustSelectOptions = dataclasses.field(default_factory=RobustSelectOptions)
    neural: NeuralOptions | None = None  # stage neural's settings (a YAML without them cannot run that stage)
    control_vae: ControlVAEOptions | None = None  # stage control_vae's (the same)
    path: str = ""

    @classmethod
    def from_yaml(cls, path: str | Path = CONFIG_PATH, overrides: dict[str, Any] | None = None) -> TransferConfig:
        """Load and validate; ``overrides`` are dotted keys (``{"budgets.fast.sim.control_steps": 20}``)."""
        path = Path(path)
        data = apply_overrides(read_yaml(path), overrides)
        data["path"] = str(path)
        cfg = build(cls, data, path)
        for name, b in cfg.budgets.items():
            if b.substeps < 1 or b.n_candidates < 1:
                raise InputError(path, f"budgets.{name}", "positive substeps and n_candidates", str(b))
            if not 1.0 <= b.soft_step_scale < float("inf"):
                raise InputError(
                    path, f"budgets.{name}.soft_step_scale", "a finite number >= 1", str(b.soft_step_scale)
                )
            for part in ("human", "robot_points", "sim"):
                sb: StepBudget = getattr(b, part)
                if min(sb.control_steps, sb.sysid_steps, sb.patience) < 0 or sb.control_lr < 0 or sb.sysid_lr < 0:
                    raise InputError(path, f"budgets.{name}.{part}", "non-negative steps and learning rates", str(sb))
        if cfg.mpc.horizon < 1 or cfg.mpc.steps < 0 or cfg.soften_samples < 1 or not cfg.mpc.soften_range < 1:
            raise InputError(
                path, "mpc", "horizon >= 1, steps >= 0, soften_range < 1 and soften_samples >= 1", str(cfg.mpc)
            )
        if cfg.stage2.mode not in HANDOFF_MODES:
            raise InputError(path, "stage2.mode", f"one of {', '.join(HANDOFF_MODES)}", repr(cfg.stage2.mode))
        _check_ranges(cfg, path)
        return cfg

    def budget(self, name: str) -> Budget:
        """The budget ``name``; an error lists the valid names."""
        if name not in self.budgets:
            raise choice_error("budget", name, list(self.budgets))
        return self.budgets[name]

    def section(self, key: str, stage: str) -> Any:
        """The settings section ``key`` that stage ``stage`` needs; :class:`InputError` naming it where the
        user's YAML left an optional section (e.g. ``neural``) out."""
        value = getattr(self, key)
        if value is None:
            raise InputError(self.path or None, key, f"the settings of stage {stage} (see configs/transfer.yaml)",
                             "missing")  # fmt: skip
        return value

    def identity(self, budget: str, stages: Sequence[Any], spec: Any = None) -> dict[str, Any]:
        """The settings that determine the results of a run of ``stages`` (their declarations in run order,
        :func:`quasisim.method.stage.declared_stages`): the budget, the weights, and each stage's own (its
        declared config keys, :attr:`~quasisim.method.stage.Stage.config`; keys that are fields of ``spec``,
        e.g. stage 3's ``networks``, are read from it when it is given)."""
        out: dict[str, Any] = {
            "budget_settings": _settings(self.budget(budget)),
            "weights": dataclasses.asdict(self.weights),
        }
        for st in stages:
            for key in st.config:
                if hasattr(self, key):
                    settings = _settings(self.section(key, st.name))
                    if settings:  # a section added later, at its defaults, leaves the identity as it was
                        out[key] = settings
                elif spec is not None:
                    out[key] = list(getattr(spec, key))
        return out


def _settings(obj: Any) -> dict[str, Any]:
    """A settings dataclass as the identity of a run sees it. Fields added later carry a default that leaves
    results as before (e.g. budgets' soft_step_scale 1, sampling's backtrack 0): at that default they are left
    out, so a run keeps the identity it had before the field existed."""
    added = {f.name: f.default for f in dataclasses.fields(obj) if f.default is not dataclasses.MISSING}
    return {k: v for k, v in dataclasses.asdict(obj).items() if k not in added or v != added[k]}


# settings that must be at least 1 (every other number of the config must be >= 0)
_AT_LEAST_ONE = (
    "stage3.horizon",
    "stage3.capacity",
    "stage3.batch",
    "neural.horizon",
    "neural.batch",
    "neural.mpc_horizon",
    "control_vae.latent",
    "control_vae.horizon",
    "control_vae.batch",
)


def _check_ranges(cfg: TransferConfig, path: Path) -> None:
    """No negative number anywhere in the config (weights, steps, learning rates, noise, ...), the counts of
    :data:`_AT_LEAST_ONE` at least 1 and stage 3's held-out fraction in (0, 1)."""

    def walk(x: Any, key: str) -> None:
        if dataclasses.is_dataclass(x):
            for f in dataclasses.fields(x):
                walk(getattr(x, f.name), f"{key}.{f.name}" if key else f.name)
        elif isinstance(x, dict):
            for k, v in x.items():
                walk(v, f"{key}.{k}")
        elif isinstance(x, tuple):
            for i, v in enumerate(x):
                walk(v, f"{key}[{i}]")
        elif isinstance(x, int | float) and not isinstance(x, bool):
            low = 1 if key in _AT_LEAST_ONE else 0
            if x < low:
                raise InputError(path, key, f"a number >= {low}", repr(x))

    walk(cfg, "")
    if not 0.0 < cfg.stage3.held_out < 1.0:
        raise InputError(path, "stage3.held_out", "a fraction in (0, 1)", repr(cfg.stage3.held_out))
    ro = cfg.robust_select
    if not isinstance(ro.worlds, int) or not 0 <= ro.worlds <= 64:
        raise InputError(path, "robust_select.worlds", "a count of training worlds in [0, 64]", repr(ro.worlds))
    if isinstance(ro.seed, bool) or not isinstance(ro.seed, int) or not 0 <= ro.seed < 2**32:
        raise InputError(path, "robust_select.seed", "a training-world seed in [0, 2**32)", repr(ro.seed))
    if not 0 <= ro.gate <= 1:
        raise InputError(path, "robust_select.gate", "a fraction in [0, 1]", repr(ro.gate))
    if isinstance(ro.margin, bool) or not isinstance(ro.margin, int | float) or not 0 <= ro.margin < 1:
        raise InputError(path, "robust_select.margin", "a fraction of the strict limits in [0, 1)", repr(ro.margin))
    try:
        tracker_file(ro.tracker)  # the tracker's settings exist
    except InputError as e:
        raise InputError(path, "robust_select.tracker", e.expected, e.got) from None
