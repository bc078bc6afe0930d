"""The stages of the method and the named methods built from them (light: names only; the stage modules
load when :func:`quasisim.method.stage.declared_stages` asks for them).

:data:`STAGES` lists every stage in the order a run takes them, each by the module that declares it (a
:class:`~quasisim.method.stage.Stage` named ``STAGE``). Adding a stage is one module under
:mod:`quasisim.method.stages` and one line here (``docs/stages.md`` has a worked example).

:data:`METHODS` are named presets: the stages a method runs (None: the stages the user gives, ``--stages``)
and the settings it changes (``--method mpc-soften`` is MPC with softened gradients). The default,
``cascade``, spends the curriculum where it pays: sampling in the target first (stage ``quick``), and the
curriculum with sampling around its plan only where that fails strict success.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from quasisim.method.config import TransferConfig

# stage name (as in --stages) -> the module that declares it (or, added at run time, the Stage itself), in the
# order a run takes them
STAGES: dict[str, Any] = {
    "quick": "quasisim.method.stages.quick",
    "1": "quasisim.method.stages.point_dynamics",
    "2": "quasisim.method.stages.contact_curriculum",
    "3": "quasisim.method.stages.fit_to_target",
    "neural": "quasisim.method.stages.neural",
    "control_vae": "quasisim.method.stages.control_vae",
    "mpc": "quasisim.method.stages.mpc",
    "sample": "quasisim.method.stages.sampling",
    "select": "quasisim.method.stages.selection",
    "margin": "quasisim.method.stages.margin",
}


def order(names: tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """``names`` in run order."""
    return tuple(n for n in STAGES if n in names)


def _soften(cfg: TransferConfig) -> TransferConfig:
    """MPC whose gradients average ``soften_samples`` contact stiffnesses (randomized smoothing)."""
    return dataclasses.replace(cfg, mpc=dataclasses.replace(cfg.mpc, soften=cfg.soften_samples))


@dataclass(frozen=True)
class Method:
    """A named preset of stages and settings.

    Attributes:
        stages: the stages it runs; None: the stages the user asks for (``--stages``).
        configure: the settings it changes (a function of the transfer config), or None.
        summary: one line for ``--help``.
        curriculum: the curriculum it runs (None: the user's, ``--curriculum``).
        networks: stage 3's networks (of :data:`quasisim.method.spec.NETWORKS`; None: the user's, the
            ablation flags).
    """

    stages: tuple[str, ...] | None
    summary: str
    configure: Callable[[Any], Any] | None = None
    curriculum: str | None = None
    networks: tuple[str, ...] | None = None

    def config(self, cfg: TransferConfig) -> TransferConfig:
        return cfg if self.configure is None else self.configure(cfg)


CASCADE = ("quick", "1", "2", "sample", "select", "margin")
PAPER = ("1", "2", "3", "mpc")  # the paper's method: curriculum, fit to the target, MPC in the fitted simulator

METHODS: dict[str, Method] = {
    "cascade": Method(
        CASCADE, "the default: sample in the target first; where that fails strict success, the curriculum "
        "(stages 1, 2) and sampling around its plan, keeping the best judged in the target",
    ),
    "ours": Method(None, "the stages given (--stages; the full method: 1,2,sample,select)"),
    "mpc-base": Method(("mpc",), "gradient MPC in MuJoCo with the stiffest simulator, from the kinematic retarget"),
    "mpc-soften": Method(("mpc",), "mpc-base with gradients averaged over softened contact", _soften),
    "sample-target": Method(("sample",), "sampling MPC with the target itself as the model, from the kinematic retarget"),
    "kinematic": Method((), "the kinematic retarget only"),
    # the paper's method and its ablations (its ablation table; docs/paper_tables.md says where a row differs)
    "paper": Method(
        PAPER, "the paper's method in full: its 8-simulator curriculum (stages 1, 2), the simulator fitted to "
        "MuJoCo with residual physics (stage 3), closed-loop MPC in the fitted simulator", curriculum="default",
    ),
    "paper-no-residual": Method(
        PAPER, "paper without residual physics (stage 3 fits the analytical constants and the control "
        "transformation only)", curriculum="default", networks=("control",),
    ),
    "paper-no-local-force": Method(
        PAPER, "paper without the local force network (the global residual network kept)", curriculum="default",
        networks=("global", "control"),
    ),
    "paper-no-curriculum": Method(
        PAPER, "paper without the curriculum: stages 1 and 2 in the stiffest simulator only", curriculum="none"
    ),
    "paper-no-analytical": Method(
        ("neural",), "paper without the analytical simulator: an MLP of the target alone, fitted to its rollouts, "
        "the controls optimised through it (no curriculum: there is no analytical simulator to relax), then MPC "
        "with it as the model",
    ),
    "paper-curriculum2": Method(PAPER, "paper with the paper's curriculum II (stages left out)",
                                curriculum="curriculum2"),
    "control-vae": Method(
        ("control_vae",), "the paper's Control-VAE baseline for tracking: a generative controller trained through "
        "an MLP of the target (stage neural's world model), driving the target from the clip's start",
    ),
}  # fmt: skip
