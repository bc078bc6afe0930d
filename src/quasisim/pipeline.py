"""The method, end to end (paper section "Method" and appendix "Evaluation process").

:func:`run_transfer` reads like the method: kinematic retargeting gives the first trajectory; then the
run's stages (named in :mod:`quasisim.method.registry`, loaded by
:func:`~quasisim.method.stage.declared_stages`), each a module of :mod:`quasisim.method.stages`, in order:
``quick`` (the default method's first step) samples in the target from the retarget and ends the run where
that passes strict success; stage 1 transfers the demo through point dynamics in the curriculum's relaxed simulator, stage 2 follows the
contact curriculum from soft to stiff, stage 3 fits the simulator to the target, closed-loop MPC tracks
the result in the target with the quasi-physical simulator as its model (``mpc``) or the target itself
(``sample``), and ``select`` keeps the best trajectory seen, judged in the target. Every finished piece is
checkpointed (``OUT/checkpoints``) and ``resume=True`` continues after the last one. The result's PD
targets are the optimised trajectory itself (the quasi-physical hand is driven by the same PD targets as
the target simulators).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from quasisim import runtime
from quasisim.assets.hand import load_hand
from quasisim.data.controls import Controls
from quasisim.data.demo import Demo, content_hash, load_demo, warn_long_clip
from quasisim.errors import InputError, QuasisimError
from quasisim.eval.evaluate import judging_cost
from quasisim.eval.transfer_outputs import OUTPUTS, TransferResult, write_outputs
from quasisim.files import MANIFEST, check_out_dir, existing_outputs, remove_orphans, run_lock
from quasisim.method import registry
from quasisim.method.checkpoints import Checkpoints
from quasisim.method.config import Budget, TransferConfig
from quasisim.method.curriculum import Curriculum, load_curriculum
from quasisim.method.problem import Problem, make_problem
from quasisim.method.retarget import RETARGET_S_PER_FRAME, retarget_hands
from quasisim.method.spec import TransferSpec
from quasisim.method.stage import (
    Context,
    Outcome,
    Plan,
    RunRecord,
    Stage,
    declared_stages,
    identity_stages,
    simulator_identity,
)
from quasisim.method.stages._common import timed
from quasisim.optim.adam import Progress
from quasisim.optim.sysid import SysID
from quasisim.optim.trajectory import Trajectory, join_q, simulate_jit
from quasisim.rotations import np_mat_to_euler_xyz, np_quat_to_mat
from quasisim.sim.types import Model, Params
from quasisim.targets.build import demo_hands
from quasisim.targets.scene import place_hands

# called around every checkpointed piece that is computed (not read back): hook(name, compute) -> arrays
PieceHook = Callable[[str, Callable[[], dict[str, Any]]], dict[str, Any]]


def run_transfer(
    demo_path: str | Path, out: str | Path, spec: TransferSpec | None = None, config: TransferConfig | None = None,
    resume: bool = False, overwrite: bool = False, piece_hook: PieceHook | None = None,
    record_transitions: str | Path | None = None,
) -> TransferResult:  # fmt: skip
    """Transfer one demonstration (see the module docstring); writes ``OUT/controls.npz``,
    ``OUT/metrics.json`` (judged in ``spec.target``), ``OUT/report.html`` and ``OUT/summary.json``.
    An ``out`` holding another run is refused unless ``resume`` (continue it) or ``overwrite`` (start afresh).
    ``piece_hook`` wraps the computation of each checkpointed piece (:class:`quasisim.batch.BatchHooks`: the tests
    kill a batch's worker there);
    ``record_transitions``: a folder where the sampling stage keeps every window it rolls out in the target
    (``<demo>.<method>.npz``; the results are the same with or without it)."""
    spec = (spec or TransferSpec()).checked()
    cfg = registry.METHODS[spec.method].config(config or TransferConfig.from_yaml())
    stages, cur, out = declared_stages(spec.stages), load_curriculum(spec.curriculum), Path(out)
    demo = load_demo(demo_path)
    hands = demo_hands(spec.hand, demo.sides)
    if record_transitions is not None:
        if "sample" not in spec.stages:
            raise QuasisimError(
                f"--record-transitions: expected a run with the sampling stage (stage 'sample'), got stages "
                f"{','.join(spec.stages) or 'none'} (method {spec.method}): nothing would be recorded"
            )
        check_out_dir(Path(record_transitions), "--record-transitions")
    check_out_dir(out)
    with run_lock(out, f"transfer {demo.name}, method {spec.method}"):  # one run per folder
        _check_run_dir(out, resume, overwrite)
        warn_long_clip(
            demo,
            *cost_per_frame(cfg.budget(spec.budget), cfg.budgets.get("fast"), stages, spec),
            f"transfer ({spec.budget} budget)",
        )
        info = identity(demo_path, demo, spec, cur, cfg)
        ck = Checkpoints(out / "checkpoints", info, resume, overwrite, lambda name: piece_scope(info, name), piece_hook)
        progress, record = Progress(spec.progress), RunRecord()

        T, D = demo.n_frames, sum(6 + h.n_joints for h in hands)
        kin_expect = {"q": (T, D), "base_rot": (3, 3), **({"left_base_rot": (3, 3)} if len(hands) > 1 else {})}
        kin = timed(ck, "kinematic", lambda: _kinematic(hands, demo, progress), kin_expect)
        record.seconds["retarget"] = float(kin["wall_s"])
        bud, rots = cfg.budget(spec.budget), [kin[k] for k in ("base_rot", "left_base_rot")[: len(hands)]]
        prob = make_problem(demo, place_hands(hands, rots), bud.substeps, bud.n_candidates)
        transitions = None if record_transitions is None else Path(record_transitions)
        ctx = Context(prob, cur, cfg, spec, ck, progress, record, np.asarray(kin["q"]), transitions)
        plan = Plan(prob.trajectory(kin["q"]), SysID.init())  # its q_targets: the retarget, rounded to float32
        outcome = Outcome(plan, prob.objective(prob.reference()), plan.traj.q_targets)
        ran: list[Stage] = []
        for stage in stages:
            if outcome.done and not stage.after_done:  # a stage ended the run: the cascade's quick step passed
                continue
            outcome = stage.run(ctx, outcome)
            ran.append(stage)
            runtime.free_compiled_programs()  # a long method (paper: stages 1-3) outgrows the mapping limit

        controls = Controls(
            hand=spec.hand, demo=demo.name, method=f"{spec.method}[{cur.name};stages {','.join(spec.stages)};{spec.budget}]",
            fps=demo.fps, base_rots=prob.scene.base_rots, q_targets=np.asarray(outcome.q), joint_names=hands[0].joint_names,
            extras=file_extras(ctx, outcome, tuple(ran)), demo_hash=content_hash(demo),
        )  # fmt: skip
        return write_outputs(ctx, controls, outcome.plan.sysid, out)


def file_extras(ctx: Context, outcome: Outcome, stages: tuple[Stage, ...]) -> dict[str, Any]:
    """What ``controls.npz`` keeps of the run beside its PD targets: the kinematic retarget, the trajectories
    the later stages started from (``plan_q``: MPC's, ``sample_nominal_q``: the sampling's, ``<name>_q`` for
    what another stage keeps in ``Outcome.seen``), the selection, and the plan's quasi-physical rollout
    (``sim_qpos``) when one of the stages that ran, ``stages``, optimised in the simulator."""
    extras: dict[str, Any] = {"kinematic_q": ctx.kinematic_q}
    names = {"plan": "plan_q", "sampling nominal": "sample_nominal_q"}
    extras.update({names.get(k, k.replace(" ", "_") + "_q"): v for k, v in outcome.seen.items()})
    if outcome.selected is not None:
        extras["selected"], extras["selection_costs"] = (
            np.array(outcome.selected),
            np.array(json.dumps(outcome.selection_costs)),
        )
    if any(st.uses_simulator for st in stages):
        model, params = outcome.simulator(ctx)
        extras["sim_qpos"] = sim_qpos(ctx.prob, params, outcome.plan.traj, model)
    return extras


def sim_qpos(prob: Problem, params: Params, traj: Trajectory, model: Model | None = None) -> np.ndarray:
    """(T, D) the hands' trajectory of ``traj``'s quasi-physical rollout (in ``model``, default the
    problem's) in base coordinates, laid out as the targets' PD targets."""
    model = model or prob.model
    states = simulate_jit(model, params, traj, prob.base_quat, prob.demo.fps, prob.obj0)
    root = np.asarray(model.to_world(states.root_pos), np.float64)  # (T - 1, H, 3)
    R = np_quat_to_mat(np.asarray(states.root_quat, np.float64))  # (T - 1, H, 3, 3)
    eul = np.unwrap(np_mat_to_euler_xyz(np.einsum("hji,thjk->thik", prob.base_rots, R)), axis=0)
    base = np.concatenate([root, eul], axis=-1).reshape(len(root), -1)
    q = join_q(base, np.asarray(states.q, np.float64), prob.hand_joints)
    return np.concatenate([np.asarray(traj.q_targets[:1]), q], axis=0)


def _kinematic(hands: tuple[Any, ...], demo: Any, progress: Progress) -> dict[str, Any]:
    """Stage 1c, the kinematic retarget: the first trajectory of every later stage; with two hands, each
    retargeted to its own keypoints, their targets concatenated (right, left)."""
    rt = retarget_hands(hands, demo, progress=progress.enabled)
    out = {"q": np.concatenate([r.q for r in rt], axis=1), "base_rot": rt[0].base_rot}
    return out if len(rt) == 1 else {**out, "left_base_rot": rt[1].base_rot}


# memory per frame of a transfer (0.15-0.2 MB per frame for sample-target, docs/history "Commands on long clips"), with the fast budget
MB_PER_FRAME = 0.2


def cost_per_frame(
    budget: Budget, fast: Budget | None, stages: tuple[Stage, ...], spec: TransferSpec
) -> tuple[float, float]:
    """(seconds, MB) per frame of a run of ``stages`` with ``budget``: the kinematic retarget, each stage's
    figure for the ``fast`` budget scaled by the substeps and the Adam steps of its budget parts against
    ``fast``'s, and judging the result (robust replays, the video)."""
    f = fast or budget
    sub = budget.substeps / f.substeps

    def steps(b: Budget, parts: tuple[str, ...]) -> int:
        return sum(getattr(b, p).control_steps + getattr(b, p).sysid_steps for p in parts)

    def scale(st: Stage) -> float:
        return sub * steps(budget, st.budget_parts) / max(1, steps(f, st.budget_parts)) if st.budget_parts else 1.0

    robust = spec.robust_configs()
    judge_s, judge_mb = judging_cost(spec.render, robust, spec.closed_loop)
    s = RETARGET_S_PER_FRAME + sum(st.s_per_frame * scale(st) for st in stages) + judge_s
    return s, max(MB_PER_FRAME * sub, judge_mb)


def _check_run_dir(out: Path, resume: bool, overwrite: bool) -> None:
    """Refuse an output folder that cannot be written, or one holding the outputs of a run whose checkpoints
    are gone (they would be replaced without a trace) unless ``resume`` or ``overwrite``."""
    check_out_dir(out)
    remove_orphans(out)
    found = existing_outputs(out, (*OUTPUTS, MANIFEST))
    has_checkpoints = any((out / "checkpoints").glob("*.npz")) if (out / "checkpoints").is_dir() else False
    if found and not has_checkpoints and not (resume or overwrite):
        raise InputError(
            out, "--out", "a folder without the outputs of an earlier run (pass --overwrite to replace them)",
            ", ".join(found),
        )  # fmt: skip


def stage_keys() -> set[str]:
    """The run settings that concern single stages (each stage's config keys; the run's stages and method);
    the rest (demo, hand, curriculum, budget, weights) concern every piece."""
    return {"stages", "method", "target", *(k for st in declared_stages() for k in st.config)}


def piece_scope(info: dict[str, Any], name: str) -> dict[str, Any]:
    """What determines checkpoint ``name``: the settings every piece shares, the stages that run before its
    stage, their settings and its stage's own (a ``+mpc`` run reuses the stage-1/2 checkpoints of its
    curriculum's; a change to stage 2's settings recomputes stage 2 and what comes after it, not stage 1)."""
    shared = {k: v for k, v in info.items() if k not in stage_keys()}
    owner = next((st for st in declared_stages() if st.owns(name)), None)
    if owner is None:  # the kinematic retarget
        return shared
    before = [
        st
        for st in declared_stages(info["stages"])
        if list(registry.STAGES).index(st.name) < list(registry.STAGES).index(owner.name)
    ]
    own = {k: info[k] for st in (*before, owner) for k in st.config if k in info}
    if "target" in info and any(st.uses_target for st in (*before, owner)):
        own["target"] = info["target"]
    own = owner.scope(info, name, own) if owner.scope else own
    return {**shared, "stage": owner.name, "before": [st.name for st in before], **own}


def identity(
    demo_path: str | Path, demo: Demo, spec: TransferSpec, cur: Curriculum, cfg: TransferConfig
) -> dict[str, Any]:
    """What made the run (recorded in ``checkpoints/run.json`` and, hashed, in every checkpoint; a resumed run
    must match it): the demo (file and content), the hand (config and model files), the settings (the run's
    and those of its stages)."""
    cur_settings = {k: v for k, v in dataclasses.asdict(cur).items() if k != "path"}
    hand, hand_files = load_hand(spec.hand), hashlib.sha256()
    for f in (Path(hand.config.path), hand.source):
        hand_files.update(f.read_bytes())
    info = {
        "demo": demo.name, "demo_sha256": hashlib.sha256(Path(demo_path).read_bytes()).hexdigest()[:16],
        "hand": spec.hand, "curriculum": cur.name, "stages": identity_stages(spec.stages, cfg), "budget": spec.budget,
        "method": spec.method, **cfg.identity(spec.budget, declared_stages(spec.stages), spec),
        "demo_content": content_hash(demo), "hand_sha256": hand_files.hexdigest()[:16],
        "curriculum_settings": cur_settings, **simulator_identity(spec.stages),
        # the target only where it is not MuJoCo, so that MuJoCo runs keep the identity they had before it
        **({"target": spec.target} if spec.target != "mujoco" else {}),
    }  # fmt: skip
    return json.loads(json.dumps(info))  # as run.json holds it (lists, not tuples)
