"""The method, end to end (paper section "Method" and appendix "Evaluation process").

:func:`run_transfer` reads like the method: kinematic retargeting gives the first trajectory; stage 1
transfers the demo through point dynamics in the curriculum's relaxed simulator; stage 2 follows the
contact curriculum from soft to stiff; closed-loop MPC then tracks the result in the target, with the
quasi-physical simulator as its model (``mpc``) or the target itself (``sample``). Every
finished piece is checkpointed (``OUT/checkpoints``) and ``resume=True`` continues after the last one.
The result's PD targets are the optimised trajectory itself (the quasi-physical hand is driven by the
same PD targets as the target simulators).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from quasisim.assets.hand import load_hand
from quasisim.data.controls import Controls
from quasisim.data.demo import Demo, content_hash, load_demo, warn_long_clip
from quasisim.errors import InputError
from quasisim.files import MANIFEST, check_out_dir, existing_outputs, remove_orphans
from quasisim.method import handoff, outputs, stage1, stage2, stage3
from quasisim.method.checkpoints import Checkpoints, Expect, trajectory_arrays, trajectory_expect, trajectory_from
from quasisim.method.config import TransferConfig
from quasisim.method.curriculum import Curriculum, SimStage, load_curriculum
from quasisim.method.mpc import run_mpc
from quasisim.method.outputs import RunRecord, TransferResult, sim_qpos, write_outputs
from quasisim.method.problem import Problem, make_problem
from quasisim.method.retarget import retarget_hands
from quasisim.method.sample_target import run_sample_target
from quasisim.method.select import best_in_target, clip_cost
from quasisim.method.spec import STAGES, TransferSpec
from quasisim.optim.adam import Progress
from quasisim.optim.objective import TrackingObjective
from quasisim.optim.sysid import SysID
from quasisim.optim.trajectory import Trajectory
from quasisim.sim.types import Model, Params
from quasisim.targets import make_target
from quasisim.targets.build import demo_hands
from quasisim.targets.scene import place_hands


@dataclass
class Plan:
    """The current solution: the trajectory and the identified S."""

    traj: Trajectory
    sysid: SysID


def run_transfer(
    demo_path: str | Path, out: str | Path, spec: TransferSpec | None = None, config: TransferConfig | None = None,
    resume: bool = False, overwrite: bool = False,
) -> TransferResult:  # fmt: skip
    """Transfer one demonstration (see the module docstring); writes ``OUT/controls.npz``,
    ``OUT/metrics.json`` (judged in ``spec.target``), ``OUT/report.html`` and ``OUT/summary.json``.
    An ``out`` holding another run is refused unless ``resume`` (continue it) or ``overwrite`` (start afresh)."""
    spec = (spec or TransferSpec()).checked()
    cfg = config or TransferConfig.from_yaml()
    bud, cur, out = cfg.budget(spec.budget), load_curriculum(spec.curriculum), Path(out)
    demo = load_demo(demo_path)
    hands = demo_hands(spec.hand, demo.sides)
    hand = hands[0]
    _check_run_dir(out, resume, overwrite)
    warn_long_clip(demo, *_cost_per_frame(cfg, spec), f"transfer ({spec.budget} budget)")
    info = _identity(demo_path, demo, spec, cur, cfg)
    ck = Checkpoints(out / "checkpoints", info, resume, overwrite, lambda name: _piece_scope(info, name))
    progress, record = Progress(spec.progress), RunRecord()

    T, D = demo.n_frames, sum(6 + h.n_joints for h in hands)
    kin_expect = {"q": (T, D), "base_rot": (3, 3), **({"left_base_rot": (3, 3)} if len(hands) > 1 else {})}
    kin = _timed(ck, "kinematic", lambda: _kinematic(hands, demo, progress), kin_expect)
    record.seconds["retarget"] = float(kin["wall_s"])
    rots = [kin[k] for k in ("base_rot", "left_base_rot")[: len(hands)]]
    prob = make_problem(demo, place_hands(hands, rots), bud.substeps, bud.n_candidates)
    plan = Plan(prob.trajectory(kin["q"]), SysID.init())
    objective = prob.objective(prob.reference())
    if "1" in spec.stages and cur.relaxed:
        plan, objective = _stage1(prob, cur, cfg, spec, ck, plan, kin["q"], progress, record)
    if "2" in spec.stages:
        plan = _stage2(prob, cur, cfg, spec, ck, plan, objective, kin["q"], progress, record)
        _note_residual_stages(cur, spec, progress, record)
    stiffest = prob.params(cur.contact(cur.stiffest))  # the model of stage 3 and MPC
    model, model_params = prob.model, plan.sysid.apply(stiffest, prob.obj.mass, prob.obj.inertia)
    if "3" in spec.stages:
        model, model_params, plan = _stage3(prob, cfg, spec, ck, plan, stiffest, objective, progress, record)
    q_out, extras = plan.traj.q_targets, {"kinematic_q": np.asarray(kin["q"])}
    if "mpc" in spec.stages:
        extras["plan_q"] = q_out
        q_out = _closed_loop(prob, cfg, spec, ck, plan.traj, model, model_params, progress, record)
    if "sample" in spec.stages:
        extras["sample_nominal_q"] = q_out
        q_out = _sample_in_target(prob, cfg, spec, ck, q_out, extras["kinematic_q"], progress, record)
    if "select" in spec.stages:
        q_out = _select_in_target(prob, cfg, spec, q_out, plan, extras, progress, record)
    if {"1", "2", "3", "mpc"} & set(spec.stages):
        extras["sim_qpos"] = sim_qpos(prob, model_params, plan.traj, model)
    label = {"ours": "transfer"}.get(spec.method, spec.method)
    controls = Controls(
        hand=spec.hand, demo=demo.name, method=f"{label}[{cur.name};stages {','.join(spec.stages)};{spec.budget}]",
        fps=demo.fps, base_rots=prob.scene.base_rots, q_targets=q_out, joint_names=hand.joint_names, extras=extras,
        demo_hash=content_hash(demo),
    )  # fmt: skip
    settings = {
        "label": label,
        "curriculum": cur.name,
        "stages": spec.stages,
        "budget": spec.budget,
        "method": spec.method,
    }
    return write_outputs(
        prob, controls, kin["q"], record, plan.sysid, settings, spec.target, out, spec.render, spec.progress
    )


def _stage1(
    prob: Problem, cur: Curriculum, cfg: TransferConfig, spec: TransferSpec, ck: Checkpoints, plan: Plan,
    kinematic_q: np.ndarray, progress: Progress, record: RunRecord,
) -> tuple[Plan, TrackingObjective]:  # fmt: skip
    """Stage 1 (point dynamics) in the curriculum's first relaxed simulator: the human point set, then the
    robot point set tracking it. Returns the plan and the objective whose reference holds the human points."""
    bud, i1 = cfg.budget(spec.budget), cur.relaxed[0]
    contact, label = cur.contact(i1), f"sim {i1 + 1}"
    hp = ck.get(
        "stage1_human",
        lambda: stage1.human_point_set(
            prob.demo, prob.obj, bud.substeps, bud.n_candidates, contact, cfg.weights, bud.human, progress, label
        ),
        {"points": (prob.demo.n_frames, None, 3), "losses": (None,), "wall_s": ()},
    )
    human_points = np.asarray(hp["points"], np.float32)
    record.curves["1b human point set"] = list(hp.get("losses", []))
    point_index = stage1.correspondences(prob, kinematic_q, human_points, hp.get("point_hand"))
    objective = prob.objective(prob.reference(human_points, point_index))
    vg = objective.value_and_grad
    p1 = prob.params(contact)

    def robot() -> dict[str, Any]:
        traj, log = stage1.robot_point_set(
            vg, plan.traj, plan.sysid, p1, cfg.weights, bud.robot_points, progress, label
        )
        return trajectory_arrays(traj, plan.sysid, log, log.wall_s)

    rp = ck.get("stage1_robot", robot, _traj_expect(prob, losses=(None,)))
    traj, sysid = trajectory_from(rp, prob.hand_joints)
    record.curves[f"1d robot point set ({label})"] = list(rp.get("losses", []))
    record.seconds["stage1_human"], record.seconds["stage1_robot"] = float(hp["wall_s"]), float(rp["wall_s"])
    record.seconds["stage1"] = record.seconds["stage1_human"] + record.seconds["stage1_robot"]
    progress.write(f"stage 1 done: human {float(hp['wall_s']):.0f} s, robot point set {float(rp['wall_s']):.0f} s")
    return Plan(traj, sysid), objective


def _stage2(
    prob: Problem, cur: Curriculum, cfg: TransferConfig, spec: TransferSpec, ck: Checkpoints, plan: Plan,
    objective: TrackingObjective, kinematic_q: np.ndarray, progress: Progress, record: RunRecord,
) -> Plan:  # fmt: skip
    """Stage 2: each rigid simulator of the curriculum, soft to stiff (:mod:`quasisim.method.stage2`)."""
    vg = objective.value_and_grad
    w2, sb = cfg.weights.arrays(points=0.0), cfg.budget(spec.budget).sim
    start, kin_traj = plan.traj, prob.trajectory(kinematic_q)
    record.seconds["stage2"] = 0.0
    for n, i in enumerate(cur.rigid):
        p = prob.params(cur.contact(i))
        label = f"stage 2 sim {i + 1} ({n + 1}/{len(cur.rigid)})"

        def run(p: Params = p, label: str = label, n: int = n, prev: Plan = plan) -> dict[str, Any]:
            alt = {"stage_start": start, "kinematic": kin_traj} if n > 0 else None
            if alt is not None and handoff.touches(cfg.stage2.mode, cur.rigid, cur.rigid[n]):
                alt.update(_touching(prob, cur, cur.rigid[n - 1], cur.rigid[n], prev, cfg.stage2))
            return stage2.run_simulator(vg, prev.traj, prev.sysid, p, w2, sb, progress, label, alt)

        d = ck.get(f"stage2_sim{i + 1:02d}", run, _traj_expect(prob, losses=(None,), n_sysid=(), start_losses="str"))
        plan = Plan(*trajectory_from(d, prob.hand_joints))
        _record_simulator(record, cur, i, d, plan.sysid.describe(prob.obj.mass), progress)
    return plan


def _touching(
    prob: Problem, cur: Curriculum, prev: int, nxt: int, plan: Plan, opts: handoff.HandoffOptions
) -> dict[str, Trajectory]:  # fmt: skip
    """The touching start (:mod:`quasisim.method.handoff`) for simulator ``nxt`` after ``prev``, where its
    contact distance is smaller; else none."""
    if cur.stages[nxt].d_c >= cur.stages[prev].d_c:
        return {}
    p = plan.sysid.apply(prob.params(cur.contact(prev)), prob.obj.mass, prob.obj.inertia)
    traj = handoff.touching(
        prob.model, p, prob.params(cur.contact(nxt)), plan.traj, prob.base_quat, prob.base_rots, prob.demo.fps,
        prob.obj0, opts,
    )  # fmt: skip
    return {"touching": traj}


def _note_residual_stages(cur: Curriculum, spec: TransferSpec, progress: Progress, record: RunRecord) -> None:
    """Say what happens to the curriculum's simulators with residual physics (they are stage 3's)."""
    res = [i + 1 for i, s in enumerate(cur.stages) if s.residual]
    if not res:
        return
    nets = ", ".join(spec.networks) or "no networks"
    how = (
        f"stage 3 fits S, the contact/joint constants and the networks ({nets}) to MuJoCo"
        if "3" in spec.stages
        else "not run: add stage 3 (--stages ...,3) to fit the simulator to the target"
    )
    record.notes.append(f"simulator(s) {', '.join(map(str, res))} with residual physics: {how}")
    progress.write(record.notes[-1])


def _record_simulator(
    record: RunRecord, cur: Curriculum, i: int, d: dict[str, Any], s_desc: dict[str, float], progress: Progress
) -> None:
    """One row of the summary's ``simulators`` table and its loss curve."""
    losses = [float(x) for x in d["losses"]]
    record.curves[f"sim {i + 1}"] = losses
    record.seconds["stage2"] += float(d["wall_s"])
    record.simulators.append(
        {"sim": i + 1, **{k: float(v) for k, v in cur.contact(i).items()}, "steps": len(losses),
         "loss_first": losses[0] if losses else None, "loss_best": min(losses) if losses else None,
         "wall_s": float(d["wall_s"]), **s_desc,
         "start_losses": _json(d["start_losses"]) if "start_losses" in d else None}
    )  # fmt: skip
    if not losses:  # the first evaluation diverged: the trajectory is the simulator's start, unchanged
        progress.write(f"sim {i + 1}: no finite loss (the simulation diverged from its start); kept the start")
        return
    progress.write(
        f"sim {i + 1}: loss {losses[0]:.5f} -> {min(losses):.5f} in {len(losses)} steps, "
        f"{float(d['wall_s']):.0f} s; mass {s_desc['mass_kg'] * 1e3:.0f} g"
    )


def _stage3(
    prob: Problem, cfg: TransferConfig, spec: TransferSpec, ck: Checkpoints, plan: Plan, params: Params,
    objective: TrackingObjective, progress: Progress, record: RunRecord,
) -> tuple[Model, Params, Plan]:  # fmt: skip
    """Stage 3: fit the stiffest simulator (S from stage 2) to MuJoCo rollouts of the plan and its variants (S,
    constants, then ``spec.networks``), then the world-model rounds (optimise in the fitted simulator, judge
    and collect in MuJoCo, refit). Returns the fitted simulator (model and params with S applied: the model
    of the MPC that follows) and the best plan judged in MuJoCo."""
    o, sb, w2 = cfg.stage3, cfg.budget(spec.budget).sim, cfg.weights.arrays(points=0.0)
    nets = spec.networks if o.residual_steps > 0 else ()
    judge, mass, inertia = make_target(spec.target, prob.scene), prob.obj.mass, prob.obj.inertia

    def run() -> dict[str, Any]:
        t0 = time.perf_counter()
        w = cfg.weights.arrays()
        d, model, p, f, buf = stage3.fit_to_target(
            prob, params, plan.traj.q_targets, plan.sysid, o, cfg.sample_target, w, nets, progress
        )
        b, a = d["held_out_before"], d["held_out_after"]
        progress.write(
            f"stage 3: held-out {o.horizon}-frame error {b[0]:.2f} cm / {b[1]:.1f} deg -> {a[0]:.2f} cm / {a[1]:.1f} deg"
        )
        vg = dataclasses.replace(objective, model=model).value_and_grad  # the objective in the fitted simulator

        def improve(traj: Trajectory, f: stage3.SimFit, p: Params) -> Trajectory:
            budget = dataclasses.replace(sb, sysid_steps=0)
            return stage2.one_simulator(
                vg, traj, f.sysid, f.apply_constants(p), w2, budget, progress, "stage 3 (fitted simulator)"
            )[0]

        cost = lambda q: clip_cost(prob.demo, judge.rollout(q), cfg.weights)  # noqa: E731
        rounds, p = stage3.world_model_rounds(
            prob, model, p, plan.traj, f, buf, o, cfg.sample_target, w, improve, cost, progress
        )
        return {**d, **rounds, "net_weights": stage3.network_vector(p), "wall_s": np.array(time.perf_counter() - t0)}

    expect = {"fit": (8,), "losses": (None,), "held_out_before": (3,), "held_out_after": (3,), "round_fit": (8,),
              "round_costs": (o.rounds + 1,), "round_errors": (o.rounds, 3), "best_round": (), "buffer_rollouts": (),
              "q_targets": (prob.demo.n_frames, prob.scene.n_dof), "net_weights": (None,)}  # fmt: skip
    d = ck.get("stage3", run, expect)
    model, p = stage3.network_template(prob.model, params, nets, o.seed) if nets else (prob.model, params)
    p = stage3.from_network_vector(p, d["net_weights"]) if nets else p
    f = stage3.SimFit.from_array(d["round_fit"])
    record.seconds["stage3"] = float(d["wall_s"])
    record.curves["stage 3 fit (minibatch loss)"] = [float(x) for x in d["losses"]]
    b, a = d["held_out_before"], d["held_out_after"]
    record.fit = {
        "fitted": f.describe(mass), "networks": list(nets), "held_out_before": b.tolist(), "held_out_after": a.tolist(),
        "round_costs": d["round_costs"].tolist(), "round_errors": d["round_errors"].tolist(),
        "best_round": int(d["best_round"]), "buffer_rollouts": int(d["buffer_rollouts"]),
    }  # fmt: skip
    progress.write(f"stage 3 done in {record.seconds['stage3']:.0f} s; kept round {int(d['best_round'])}'s controls")
    if int(d["best_round"]) > 0:  # a round's controls did better in the target than the stage's start
        plan = Plan(prob.trajectory(d["q_targets"]), plan.sysid)
    return model, f.apply(p, mass, inertia), plan


def _closed_loop(
    prob: Problem, cfg: TransferConfig, spec: TransferSpec, ck: Checkpoints, traj: Trajectory, model: Model,
    params: Params, progress: Progress, record: RunRecord,
) -> np.ndarray:  # fmt: skip
    """Closed-loop MPC in MuJoCo from ``traj``, with the simulator ``model``, ``params`` (S applied) as the model."""

    def mpc() -> dict[str, Any]:
        opts = dataclasses.replace(cfg.mpc, soften=cfg.soften_samples if spec.method == "mpc-soften" else 0)
        r = run_mpc(prob.demo, prob.scene, model, params, traj.q_targets, opts, cfg.weights, spec.progress)
        return {"q_targets": r.q_targets, "window_loss": r.window_loss, "wall_s": np.array(r.wall_s)}

    d = ck.get("mpc", mpc, _q_expect(prob))
    record.seconds["mpc"] = float(d["wall_s"])
    record.curves["mpc window loss per frame"] = [float(x) for x in d["window_loss"]]
    progress.write(f"mpc done in {record.seconds['mpc']:.0f} s")
    return np.asarray(d["q_targets"], np.float64)


def _sample_in_target(
    prob: Problem, cfg: TransferConfig, spec: TransferSpec, ck: Checkpoints, nominal: np.ndarray,
    alternative: np.ndarray, progress: Progress, record: RunRecord,
) -> np.ndarray:  # fmt: skip
    """Sampling MPC in the target itself around the ``nominal`` PD targets (the result of the stages before
    it; the kinematic retarget for the ``sample-target`` baseline) and, with ``kinematic_alternative``,
    around the kinematic retarget ``alternative`` too."""

    planned = bool({"1", "2", "mpc"} & set(spec.stages))  # else the nominal is the kinematic retarget itself
    kin = alternative if cfg.sample_target.kinematic_alternative and planned else None

    def sample() -> dict[str, Any]:
        r = run_sample_target(
            prob.demo, prob.scene, nominal, cfg.sample_target, cfg.weights, spec.target, spec.progress,
            () if kin is None else (kin,),
        )  # fmt: skip
        return {
            "q_targets": r.q_targets, "window_loss": r.window_loss, "wall_s": np.array(r.wall_s),
            "n_physics_steps": np.array(r.n_physics_steps),
        }  # fmt: skip

    d = ck.get("sample", sample, _q_expect(prob))
    record.seconds["sample"] = float(d["wall_s"])
    record.curves["sampling window loss per frame"] = [float(x) for x in d["window_loss"]]
    progress.write(f"sampling in {spec.target} done in {record.seconds['sample']:.0f} s")
    return np.asarray(d["q_targets"], np.float64)


def _select_in_target(
    prob: Problem, cfg: TransferConfig, spec: TransferSpec, q_out: np.ndarray, plan: Plan, extras: dict[str, Any],
    progress: Progress, record: RunRecord,
) -> np.ndarray:  # fmt: skip
    """The best trajectory seen, judged in the target (:mod:`quasisim.method.select`): the last stage's,
    the curriculum's plan, the MPC's nominal and the kinematic retarget."""
    t0 = time.perf_counter()
    seen = {"last stage": q_out, "sampling nominal": extras.get("sample_nominal_q"), "plan": extras.get("plan_q"),
            "curriculum": np.asarray(plan.traj.q_targets), "kinematic": extras["kinematic_q"]}  # fmt: skip
    candidates = {k: np.asarray(v, np.float64) for k, v in seen.items() if v is not None}
    best, costs = best_in_target(prob.demo, prob.scene, spec.target, candidates, cfg.weights)
    extras["selected"], extras["selection_costs"] = np.array(best), np.array(json.dumps(costs))
    record.seconds["select"] = time.perf_counter() - t0
    record.notes.append(
        f"kept '{best}' (objective in {spec.target}: " + ", ".join(f"{k} {v:.4f}" for k, v in costs.items()) + ")"
    )
    progress.write(record.notes[-1])
    return candidates[best]


def _kinematic(hands: tuple[Any, ...], demo: Any, progress: Progress) -> dict[str, Any]:
    """Stage 1c, the kinematic retarget: the first trajectory of every later stage; with two hands, each
    retargeted to its own keypoints, their targets concatenated (right, left)."""
    rt = retarget_hands(hands, demo, progress=progress.enabled)
    out = {"q": np.concatenate([r.q for r in rt], axis=1), "base_rot": rt[0].base_rot}
    return out if len(rt) == 1 else {**out, "left_base_rot": rt[1].base_rot}


def _timed(ck: Checkpoints, name: str, fn: Callable[[], dict[str, Any]], expect: Expect) -> dict[str, Any]:
    """``ck.get(name, fn, expect)`` recording ``fn``'s wall time as ``wall_s``."""

    def run() -> dict[str, Any]:
        t0 = time.perf_counter()
        d = fn()
        return {**d, "wall_s": np.array(time.perf_counter() - t0)}

    return ck.get(name, run, {**expect, "wall_s": ()})


def _traj_expect(prob: Problem, **more: Any) -> Expect:
    return trajectory_expect(
        prob.demo.n_frames, prob.model.n_joints, prob.model.n_points, prob.model.hand.n_hands, **more
    )


def _q_expect(prob: Problem) -> Expect:
    return {"q_targets": (prob.demo.n_frames, prob.scene.n_dof), "window_loss": (None,), "wall_s": ()}


# Seconds per frame of each stage with the fast budget (BENCHMARKS.md: 60-frame clips, default curriculum, 2 CPU
# cores) and memory per frame (a 10,000-frame clip took about 4 GB): the clip-length warning's estimate.
STAGE_S_PER_FRAME = {"retarget": 0.05, "1": 2.9, "2": 8.0, "3": 2.0, "mpc": 1.5, "sample": 0.25, "select": 0.1}
MB_PER_FRAME = 0.4


def _cost_per_frame(cfg: TransferConfig, spec: TransferSpec) -> tuple[float, float]:
    """(seconds, MB) per frame of ``spec``'s run: the fast budget's figures scaled by substeps and Adam steps."""
    b = cfg.budget(spec.budget)
    f = cfg.budgets.get("fast", b)
    sub = b.substeps / f.substeps
    steps = {
        "1": (b.human.control_steps + b.robot_points.control_steps)
        / max(1, f.human.control_steps + f.robot_points.control_steps),
        "2": (b.sim.control_steps + b.sim.sysid_steps) / max(1, f.sim.control_steps + f.sim.sysid_steps),
    }
    s = STAGE_S_PER_FRAME["retarget"] + sum(
        STAGE_S_PER_FRAME[st] * (sub * steps[st] if st in steps else 1.0) for st in spec.stages
    )
    return s, MB_PER_FRAME * sub


def _check_run_dir(out: Path, resume: bool, overwrite: bool) -> None:
    """Refuse an output folder that cannot be written, or one holding the outputs of a run whose checkpoints
    are gone (they would be replaced without a trace) unless ``resume`` or ``overwrite``."""
    check_out_dir(out)
    remove_orphans(out)
    found = existing_outputs(out, (*outputs.OUTPUTS, MANIFEST))
    has_checkpoints = any((out / "checkpoints").glob("*.npz")) if (out / "checkpoints").is_dir() else False
    if found and not has_checkpoints and not (resume or overwrite):
        raise InputError(
            out, "--out", "a folder without the outputs of an earlier run (pass --overwrite to replace them)",
            ", ".join(found),
        )  # fmt: skip


# the run settings that concern single stages (the rest, e.g. demo, hand, curriculum, budget, concern every piece)
_STAGE_KEYS = {
    "stages": None, "method": None, "stage2": "2", "mpc": "mpc", "stage3": "3", "networks": "3", "sample_target": "sample",
}  # fmt: skip


def _piece_scope(info: dict[str, Any], name: str) -> dict[str, Any]:
    """What determines checkpoint ``name``: the settings every piece shares, the stages that run before its
    stage, their settings and its stage's own (a ``+mpc`` run reuses the stage-1/2 checkpoints of its
    curriculum's; a change to stage 2's settings recomputes stage 2 and what comes after it, not stage 1)."""
    stage = {"kinematic": "", "stage1": "1", "stage2": "2", "stage3": "3", "mpc": "mpc", "sample": "sample"}[
        name.split("_")[0]
    ]
    shared = {k: v for k, v in info.items() if k not in _STAGE_KEYS}
    if not stage:
        return shared
    before = [s for s in info["stages"] if STAGES.index(s) < STAGES.index(stage)]
    own = {k: info[k] for k, st in _STAGE_KEYS.items() if st in (stage, *before) and k in info}
    if stage == "mpc":
        own["method"] = info["method"]  # mpc-soften samples softened simulators
    if stage == "2" and "stage2" in own and not _after_handoff(info, int(name.removeprefix("stage2_sim"))):
        own.pop("stage2")  # a simulator before the first touching hand-off is computed as without it
    return {**shared, "stage": stage, "before": before, **own}


def _after_handoff(info: dict[str, Any], sim: int) -> bool:
    """Whether stage 2's simulator ``sim`` (1-based, as in the checkpoint names) comes at or after the first
    simulator whose start the hand-off mode of ``info`` touches (:func:`quasisim.method.handoff.touches`)."""
    c = info["curriculum_settings"]
    rigid = Curriculum(c["name"], tuple(SimStage(**st) for st in c["stages"]), c["mu"]).rigid
    return any(handoff.touches(info["stage2"]["mode"], rigid, i) for i in rigid if i < sim)


def _identity(
    demo_path: str | Path, demo: Demo, spec: TransferSpec, cur: Curriculum, cfg: TransferConfig
) -> dict[str, Any]:
    """What made the run (recorded in ``checkpoints/run.json`` and, hashed, in every checkpoint; a resumed run
    must match it): the demo (file and content), the hand (config and model files), the settings."""
    cur_settings = {k: v for k, v in dataclasses.asdict(cur).items() if k != "path"}
    hand, hand_files = load_hand(spec.hand), hashlib.sha256()
    for f in (Path(hand.config.path), hand.source):
        hand_files.update(f.read_bytes())
    info = {
        "demo": demo.name, "demo_sha256": hashlib.sha256(Path(demo_path).read_bytes()).hexdigest()[:16],
        "hand": spec.hand, "curriculum": cur.name, "stages": list(spec.stages), "budget": spec.budget,
        "method": spec.method, **cfg.identity(spec.budget, spec.stages),
        **({"networks": list(spec.networks)} if "3" in spec.stages else {}),
        "demo_content": content_hash(demo), "hand_sha256": hand_files.hexdigest()[:16],
        "curriculum_settings": cur_settings,
    }  # fmt: skip
    return json.loads(json.dumps(info))  # as run.json holds it (lists, not tuples)


def _json(x: np.ndarray) -> Any:
    return json.loads(str(x))
