"""What a transfer run is asked to do (light: no JAX or MuJoCo, so the CLI can use it for its defaults)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from quasisim.errors import QuasisimError, choice_error
from quasisim.method import registry
from quasisim.targets import TARGETS

STAGES = tuple(registry.STAGES)  # the stages' names, in run order (checks read the registry itself)
METHODS = tuple(registry.METHODS)  # the named methods (presets of stages and settings)
NETWORKS = (
    "local",
    "global",
    "control",
)  # stage 3's networks: residual physics (local, global), control transformation


FULL_STAGES = ("1", "2", "sample", "select")  # method ours with no stages given: the full method (BENCHMARKS.md)
DEFAULT_METHOD = "cascade"  # the sampling in the target first, the curriculum where that fails strict success

JUDGING_ONLY = (
    "progress",
    "robust",
    "closed_loop",
    "ranges",
    "robust_set",
)  # TransferSpec fields outside a run's identity


@dataclass(frozen=True)
class TransferSpec:
    """What to run (the CLI's options of ``quasisim transfer``; their defaults are these).

    Attributes:
        hand: built-in hand name or hand YAML path.  target: simulator that judges the result.
        curriculum: built-in curriculum name or YAML path.  stages: of :data:`STAGES`, for method ``ours``
            (None: :data:`FULL_STAGES`; stages given without a method mean ``ours``).
        budget: a budget of the transfer config.  method: of :data:`METHODS`
            (:data:`quasisim.method.registry.METHODS`; None: ``cascade``, or ``ours`` where ``stages`` are
            given. ``cascade`` runs stage ``quick`` and,
            where it fails strict success, stages 1, 2, sample, select; ``ours`` runs ``stages``;
            ``mpc-base``/``mpc-soften`` only the MPC stage, ``sample-target`` only the sampling stage,
            ``kinematic`` no stage).
        render: render the report's video.  progress: show progress bars.
        networks: what stage 3 trains on top of S and the constants, of :data:`NETWORKS` (``local`` and
            ``global`` residual networks, ``control`` transformation); the ablation flags remove them.
        robust: perturbed replays of the result for robust success (None: ``n`` of ``configs/robust.yaml``;
            0: none). Judging only: not part of the run's identity.
        closed_loop: also replay the perturbed worlds closed loop (:mod:`quasisim.method.track`).
        ranges: the perturbation sets of robust success (:data:`quasisim.eval.robust.RANGES`, or paths of YAML
            files of the user's own). Judging only.
        robust_set: (key, value) overrides of every set of ``ranges`` (``--robust-set seed=7``). Judging only.
    """

    hand: str = "shadow"
    target: str = "mujoco"
    # 4 analytical simulators; "default" is the paper's 8 (BENCHMARKS.md, "A shorter curriculum")
    curriculum: str = "short"
    stages: tuple[str, ...] | None = None  # None: the method's (ours: FULL_STAGES)
    budget: str = "fast"
    method: str | None = None  # None: cascade, or ours where stages are given
    render: bool = True
    progress: bool = True
    networks: tuple[str, ...] = ("local", "global", "control")
    robust: int | None = None
    closed_loop: bool = False
    ranges: tuple[str, ...] = ("default",)
    robust_set: tuple[tuple[str, Any], ...] = ()

    def robust_configs(self) -> list[Any]:
        """The :class:`~quasisim.targets.perturb.RobustConfig` of each set of ``ranges``, with ``robust``
        replays and the ``robust_set`` overrides."""
        from quasisim.targets.perturb import replays

        return [replays(self.robust, r, dict(self.robust_set)) for r in self.ranges]

    def checked(self) -> TransferSpec:
        """Validated, with the method (None: ``cascade``, or ``ours`` where stages are given) and the stages it
        implies; stages given to a method that has its own are refused."""
        if self.target not in TARGETS:
            raise choice_error("target", self.target, TARGETS)
        method = self.method or ("ours" if self.stages is not None else DEFAULT_METHOD)
        if method not in registry.METHODS:
            raise choice_error("method", method, list(registry.METHODS))
        preset = registry.METHODS[method].stages
        if preset is not None and self.stages is not None and registry.order(self.stages) != preset:
            raise QuasisimError(
                f"stages {','.join(self.stages)} given with method {method}, which runs its own "
                f"({','.join(preset) or 'none'}): use method ours to run the stages given, or leave the stages out"
            )
        stages = (FULL_STAGES if self.stages is None else self.stages) if preset is None else preset
        bad = [s for s in stages if s not in registry.STAGES]
        if bad:
            raise choice_error("stage", bad[0], list(registry.STAGES))
        bad = [n for n in self.networks if n not in NETWORKS]
        if bad:
            raise choice_error("network", bad[0], NETWORKS)
        if {"3", "mpc"} & set(stages) and self.target != "mujoco":
            raise QuasisimError(
                f"stage 3 and closed-loop MPC run in MuJoCo only (target {self.target!r}); use --target mujoco or "
                "leave out stages 3 and mpc"
            )
        curriculum, nets = _preset_settings(method, self.curriculum, self.networks)
        networks = tuple(n for n in NETWORKS if n in nets)
        return dataclasses.replace(
            self, method=method, stages=registry.order(stages), networks=networks, curriculum=curriculum
        )

    def identity(self) -> dict[str, object]:
        """The fields that determine the run's results (progress and robust replays aside; stage 3's networks
        only with stage 3)."""
        d = {k: v for k, v in dataclasses.asdict(self).items() if k not in JUDGING_ONLY}
        if "3" not in self.stages:
            d.pop("networks")
        return d


def _preset_settings(method: str, curriculum: str, networks: tuple[str, ...]) -> tuple[str, tuple[str, ...]]:
    """The curriculum and stage 3's networks of ``method``: its preset's where it has them (the paper's
    ablations), else those given; a value given that differs from both the default and the preset's is
    refused."""
    m, default = registry.METHODS[method], TransferSpec()
    for what, given, preset, base in (("curriculum", curriculum, m.curriculum, default.curriculum),
                                      ("networks", networks, m.networks, default.networks)):  # fmt: skip
        if preset is not None and given not in (base, preset):
            raise QuasisimError(
                f"method {method} runs {what} {preset!r} of its own, and {given!r} was given: leave that option "
                "out, or use method ours with --stages and the option"
            )
    return m.curriculum or curriculum, m.networks if m.networks is not None else networks


def networks_from_flags(no_residual: bool, no_local_residual: bool, no_control_transform: bool) -> tuple[str, ...]:
    """The networks of stage 3 left by the ablation flags ``--no-residual`` (neither residual network),
    ``--no-local-residual`` and ``--no-control-transform``."""
    drop = {"local", "global"} if no_residual else {"local"} if no_local_residual else set()
    drop |= {"control"} if no_control_transform else set()
    return tuple(n for n in NETWORKS if n not in drop)


def parse_stages(text: str) -> tuple[str, ...]:
    """``"1,2"`` -> ("1", "2"); only the stages this package implements are accepted."""
    stages = tuple(s.strip() for s in text.split(",") if s.strip())
    bad = [s for s in stages if s not in registry.STAGES]
    if bad or not stages:
        raise QuasisimError(
            f"unknown stage(s) {', '.join(bad) or '(none given)'}; valid stages: {', '.join(registry.STAGES)} "
            "(3: fit the simulator to MuJoCo: S, constants, residual networks and control transformation)"
        )
    return registry.order(stages)
