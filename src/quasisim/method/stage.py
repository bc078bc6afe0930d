"""What a stage of the method is, what it is given and what it hands on, and the stages by name (light: no
JAX or MuJoCo at import).

A transfer runs a sequence of stages (named in :mod:`quasisim.method.registry`, loaded by
:func:`declared_stages`) over one :class:`Outcome`:

    outcome = Outcome.start(context)
    for stage in declared_stages(spec.stages):
        if outcome.done and not stage.after_done:  # a stage ended the run (the cascade's first step passed)
            continue
        outcome = stage.run(context, outcome)

Each stage is a module of :mod:`quasisim.method.stages` that declares one :class:`Stage`: its name (as in
``--stages``), the word naming its checkpoints and its entry in ``summary.json`` ``seconds``, the config
keys it reads, its cost per frame (the long-clip warning), and ``run(context, outcome) -> outcome``.
Everything that used to be a table per stage (the run's identity, checkpoint scopes, cost estimates, batch
timing keys, benchmark run names) is derived from these declarations.
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from quasisim.method import registry

if TYPE_CHECKING:
    from quasisim.method.checkpoints import Checkpoints
    from quasisim.method.config import TransferConfig
    from quasisim.method.curriculum import Curriculum
    from quasisim.method.problem import Problem
    from quasisim.method.spec import TransferSpec
    from quasisim.optim.adam import Progress
    from quasisim.optim.objective import TrackingObjective
    from quasisim.optim.sysid import SysID
    from quasisim.optim.trajectory import Trajectory
    from quasisim.sim.types import Model, Params


@dataclass
class RunRecord:
    """What the stages report as they go: seconds per stage, loss curves, one row per stage-2 simulator."""

    seconds: dict[str, float] = field(default_factory=dict)
    curves: dict[str, list[float]] = field(default_factory=dict)
    simulators: list[dict[str, Any]] = field(default_factory=list)
    fit: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


@dataclass(frozen=True, eq=False)
class Context:
    """What every stage of one run reads: the problem, the curriculum, the settings, the run's checkpoints,
    progress output and record (the record is the one mutable part: stages append to it).

    Attributes:
        prob: the demo set up for transfer (scene and quasi-physical simulator).
        cur: the physics curriculum.  cfg: the transfer config (weights, budgets, stage settings).
        spec: what the run was asked to do.  ck: the run's checkpoints.  progress: bars and messages.
        record: seconds, curves and notes for ``summary.json`` and the report.
        kinematic_q: (T, D) the kinematic retarget's PD targets (every later stage's first trajectory).
        transitions: a folder where the sampling stage keeps every window it rolls out in the target
            (``--record-transitions``), or None.
    """

    prob: Problem
    cur: Curriculum
    cfg: TransferConfig
    spec: TransferSpec
    ck: Checkpoints
    progress: Progress
    record: RunRecord
    kinematic_q: np.ndarray
    transitions: Path | None = None

    def stiffest(self) -> Params:
        """The curriculum's stiffest simulator's parameters (nominal S): the model of stage 3 and MPC."""
        return self.prob.params(self.cur.contact(self.cur.stiffest))


@dataclass(frozen=True, eq=False)
class Plan:
    """A quasi-physical solution: the trajectory (PD targets, free point forces) and the identified S."""

    traj: Trajectory
    sysid: SysID


@dataclass(frozen=True, eq=False)
class Outcome:
    """What the stages hand on (each returns a new one, :meth:`replace`).

    Attributes:
        plan: the quasi-physical plan (stages 1, 2, 3 change it; it starts as the kinematic retarget).
        objective: the tracking objective (stage 1 adds the human point set to its reference).
        q: (T, D) the PD targets of the last stage that produced any (the kinematic retarget at first).
        planned: whether ``q`` came from a stage after the kinematic retarget.
        fitted: the simulator fitted to the target (stage 3): model and parameters with S applied; None
            before stage 3 (:meth:`simulator` then gives the stiffest nominal one with the plan's S).
        seen: PD-target trajectories (T, D) that a stage replaced, by name, for the selection: ``plan``
            (MPC's start) and ``sampling nominal`` (the sampling stage's nominal).
        selected: the name of the trajectory the selection kept, and ``selection_costs`` every candidate's
            objective in the target (stage ``select``).
        done: a stage ended the run: the stages after it do not run (the cascade's first step, stage
            ``quick``, when its result passes strict success in the target).
    """

    plan: Plan
    objective: TrackingObjective
    q: np.ndarray
    planned: bool = False
    fitted: tuple[Model, Params] | None = None
    seen: dict[str, np.ndarray] = field(default_factory=dict)
    selected: str | None = None
    selection_costs: dict[str, float] = field(default_factory=dict)
    done: bool = False

    def replace(self, **changes: Any) -> Outcome:
        return dataclasses.replace(self, **changes)

    def simulator(self, ctx: Context) -> tuple[Model, Params]:
        """The model used after stage 2: the fitted simulator, else the stiffest one with the plan's S."""
        if self.fitted is not None:
            return self.fitted
        p = self.plan.sysid.apply(ctx.stiffest(), ctx.prob.obj.mass, ctx.prob.obj.inertia)
        return ctx.prob.model, p


@dataclass(frozen=True)
class Stage:
    """One stage of the method, as its module declares it.

    Attributes:
        name: as in ``--stages`` (``"quick"``, ``"1"``, ``"2"``, ``"3"``, ``"mpc"``, ``"sample"``, ``"select"``).
        word: names its checkpoints (``word`` or ``word_*``) and its ``seconds`` entry in ``summary.json``.
        config: the config keys (:class:`~quasisim.method.config.TransferConfig` fields) and spec fields
            (``networks``) whose values determine its result.
        s_per_frame: seconds per frame with the ``fast`` budget (60-frame clips, 2 CPU cores): the long-clip
            warning's estimate.  budget_parts: the parts of the budget whose Adam steps (and the budget's
            substeps) scale that estimate; empty: it does not scale.
        plans: whether it produces PD targets (after it the sampling stage also samples around the
            kinematic retarget).  uses_simulator: whether it optimises in the quasi-physical simulator (the
            controls then record the plan's quasi-physical rollout, ``sim_qpos``).  uses_target: whether it
            rolls out or judges in the target, so that its checkpoints (and those of the stages after it)
            depend on which target the run has.
        run: ``run(context, outcome) -> outcome``.
        scope: narrows the settings that determine one of its checkpoints (``scope(info, checkpoint, own)``
            -> own): stage 2 computes its simulators before the first touching hand-off as without it.
        after_done: it runs also after a stage ended the run (``Outcome.done``: the cascade's ``quick``), on the
            plan that ended it (stage ``margin``).
        idle: ``idle(cfg)``: whether it does nothing with the transfer config ``cfg`` (stage ``margin`` at
            ``robust_select.margin`` 0); an idle stage is left out of a run's identity, so that runs made before
            it existed keep theirs (:func:`identity_stages`).
    """

    name: str
    word: str
    config: tuple[str, ...]
    s_per_frame: float
    run: Callable[[Context, Outcome], Outcome]
    budget_parts: tuple[str, ...] = ()
    plans: bool = False
    uses_simulator: bool = False
    uses_target: bool = False
    scope: Callable[[dict[str, Any], str, dict[str, Any]], dict[str, Any]] | None = None
    after_done: bool = False
    idle: Callable[[Any], bool] | None = None

    def owns(self, checkpoint: str) -> bool:
        """Whether ``checkpoint`` (a file name without ``.npz``) is one of this stage's."""
        return checkpoint == self.word or checkpoint.startswith(self.word + "_")


def declared_stage(name: str) -> Stage:
    """The stage called ``name`` (one of :data:`quasisim.method.registry.STAGES`), as its module declares it."""
    entry = registry.STAGES[name]
    st: Stage = importlib.import_module(entry).STAGE if isinstance(entry, str) else entry
    if st.name != name:
        raise RuntimeError(f"registry: {entry} declares stage {st.name!r}, registered as {name!r}")
    return st


def declared_stages(names: tuple[str, ...] | list[str] | None = None) -> tuple[Stage, ...]:
    """The stages ``names`` (default: all) in run order."""
    return tuple(declared_stage(n) for n in registry.STAGES if names is None or n in names)


def identity_stages(names: tuple[str, ...] | list[str], cfg: Any) -> list[str]:
    """The stages ``names`` as a run's identity records them: those idle with the transfer config ``cfg``
    (:attr:`Stage.idle`) left out."""
    return [st.name for st in declared_stages(names) if not (st.idle is not None and st.idle(cfg))]


def simulator_identity(names: tuple[str, ...] | list[str]) -> dict[str, int]:
    """``{"simulator_revision": N}`` for a run with stages ``names`` of which one optimises in the
    quasi-physical simulator, else ``{}`` (runs without it, e.g. sample-target, keep their identity)."""
    from quasisim.sim.build import SIMULATOR_REVISION

    return {"simulator_revision": SIMULATOR_REVISION} if any(st.uses_simulator for st in declared_stages(names)) else {}
