"""Transfer of a demonstration to a robot hand through the physics curriculum (stages 1 and 2).

Stage 1 (point dynamics, the curriculum's relaxed simulators, alpha > 0):
  a. a dynamic human hand built from the demo's own keypoints (:mod:`quasisim.human_hand`) follows the
     demo: its kinematic fit drives it in the quasi-physical simulator;
  b. its point-set controls (PD targets + a free force per point) are optimised so that the object follows
     the demo (softest contact);
  c. the robot hand is retargeted kinematically (:mod:`quasisim.retarget`);
  d. the robot point set's controls are optimised to track the human point set (nearest-neighbour
     correspondences from human to robot points) and the object.
Stage 2 (alpha = 0): in each simulator of the curriculum, soft to stiff, identify S (object mass,
  inertia scale, velocity damping) with the controls fixed, then optimise the controls with S fixed.

Every finished piece writes a checkpoint atomically (``OUT/checkpoints``); ``resume=True`` continues after
the last one. The result's PD targets are the optimised trajectory itself (direct conversion: the
quasi-physical hand is driven by the same PD targets as the target simulators).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from quasisim.config import apply_overrides, build, read_yaml
from quasisim.controls import Controls
from quasisim.curriculum import Curriculum, load_curriculum
from quasisim.demo import Demo, load_demo
from quasisim.errors import InputError, QuasisimError, choice_error
from quasisim.io import save_json_atomic, save_npz_atomic
from quasisim.mpc import MPCOptions, mpc_params, run_mpc
from quasisim.optimize import (
    Reference,
    StepBudget,
    StepLog,
    SysID,
    Trajectory,
    Weights,
    adam_steps,
    hand_point_positions,
    make_objective,
    simulate,
)

CONFIG_PATH = Path(__file__).parent / "configs" / "transfer.yaml"
STAGES = ("1", "2", "mpc")
METHODS = ("ours", "mpc-base", "mpc-soften", "kinematic")


@dataclass(frozen=True)
class Budget:
    """Optimisation budget: simulator discretisation and the steps of each optimisation."""

    substeps: int
    human: StepBudget
    robot_points: StepBudget
    sim: StepBudget
    n_candidates: int = 128


@dataclass(frozen=True)
class TransferConfig:
    """Objective weights and named budgets (``configs/transfer.yaml``)."""

    weights: Weights
    budgets: dict[str, Budget]
    mpc: MPCOptions = field(default_factory=MPCOptions)
    soften_samples: int = 4
    path: str = ""

    @classmethod
    def from_yaml(cls, path: str | Path = CONFIG_PATH, overrides: dict[str, Any] | None = None) -> TransferConfig:
        path = Path(path)
        data = apply_overrides(read_yaml(path), overrides)
        data["path"] = str(path)
        cfg = build(cls, data, path)
        for name, b in cfg.budgets.items():
            if b.substeps < 1:
                raise InputError(path, f"budgets.{name}.substeps", "a positive integer", str(b.substeps))
            for part in ("human", "robot_points", "sim"):
                sb: StepBudget = getattr(b, part)
                if min(sb.control_steps, sb.sysid_steps, sb.patience) < 0 or sb.control_lr < 0 or sb.sysid_lr < 0:
                    raise InputError(path, f"budgets.{name}.{part}", "non-negative steps and learning rates", str(sb))
        return cfg

    def budget(self, name: str) -> Budget:
        if name not in self.budgets:
            raise choice_error("budget", name, list(self.budgets))
        return self.budgets[name]


def parse_stages(text: str) -> tuple[str, ...]:
    """``"1,2"`` -> ("1", "2"); only the stages this module implements are accepted."""
    stages = tuple(s.strip() for s in text.split(",") if s.strip())
    bad = [s for s in stages if s not in STAGES]
    if bad or not stages:
        raise QuasisimError(
            f"unknown stage(s) {', '.join(bad) or '(none given)'}; valid stages: {', '.join(STAGES)} "
            "(stage 3, fitting residual physics to the target, is not implemented yet)"
        )
    return tuple(s for s in STAGES if s in stages)


# ---- checkpoints ---------------------------------------------------------------------------------


class Checkpoints:
    """One ``.npz`` per finished piece of work in ``folder``, plus ``run.json`` naming the run's settings."""

    def __init__(self, folder: Path, run_info: dict[str, Any], resume: bool) -> None:
        self.folder = folder
        info_path = folder / "run.json"
        existing = sorted(folder.glob("*.npz")) if folder.is_dir() else []
        if existing and not resume:
            raise QuasisimError(
                f"{folder} holds checkpoints of an earlier run ({len(existing)} files); pass --resume to continue "
                "it or choose another --out"
            )
        if resume and info_path.is_file():
            old = json.loads(info_path.read_text())
            for k, v in run_info.items():
                if k in old and old[k] != v:  # keys an older version did not write are not compared
                    raise InputError(info_path, k, f"{old.get(k)!r} to resume this run (or a new --out)", repr(v))
        save_json_atomic(info_path, run_info)

    def load(self, name: str) -> dict[str, np.ndarray] | None:
        p = self.folder / f"{name}.npz"
        if not p.is_file():
            return None
        with np.load(p, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}

    def save(self, name: str, **arrays: Any) -> None:
        save_npz_atomic(self.folder / f"{name}.npz", **arrays)


def _traj_arrays(traj: Trajectory, sysid: SysID, log: StepLog | None, wall_s: float) -> dict[str, Any]:
    out: dict[str, Any] = {
        "base": np.asarray(traj.base),
        "joints": np.asarray(traj.joints),
        "point_force": np.asarray(traj.point_force),
        "sysid": np.array(
            [float(x) for x in (sysid.log_mass, sysid.log_inertia, sysid.lin_damp_raw, sysid.ang_damp_raw)]
        ),
        "wall_s": np.array(wall_s),
    }
    if log is not None:
        out["losses"] = np.asarray(log.losses, np.float64)
    return out


def _traj_from(d: dict[str, np.ndarray]) -> tuple[Trajectory, SysID]:
    t = Trajectory(jnp.asarray(d["base"]), jnp.asarray(d["joints"]), jnp.asarray(d["point_force"]))
    s = SysID(*(jnp.asarray(x, jnp.float32) for x in d["sysid"]))
    return t, s


# ---- the run -------------------------------------------------------------------------------------


@dataclass
class TransferResult:
    """What :func:`run_transfer` produced."""

    controls: Controls
    metrics: dict[str, Any]
    kinematic_metrics: dict[str, Any]
    curves: dict[str, list[float]]
    stage_seconds: dict[str, float]
    sim_summary: list[dict[str, Any]]
    out: Path
    extras: dict[str, Any] = field(default_factory=dict)


def _file_digest(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]


def motion_onset(demo: Demo, pos_tol: float = 0.005, deg_tol: float = 5.0) -> int:
    """First frame at which the object is ``pos_tol`` m or ``deg_tol`` deg away from its first pose
    (the middle frame when it never moves)."""
    from quasisim.rotations import quat_angle_deg

    d = np.linalg.norm(demo.object_pos - demo.object_pos[0], axis=1)
    a = quat_angle_deg(np.broadcast_to(demo.object_quat[0], demo.object_quat.shape), demo.object_quat)
    moved = np.flatnonzero((d >= pos_tol) | (a >= deg_tol))
    return int(moved[0]) if len(moved) else demo.n_frames // 2


class _Bar:
    """A tqdm bar per optimisation (stage, simulator, step, loss)."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled

    def run(self, desc: str, total: int) -> tuple[Callable[[int, float], None], Callable[[], None]]:
        if not self.enabled:
            return (lambda k, loss: None), (lambda: None)
        from tqdm import tqdm

        bar = tqdm(total=total + 1, desc=desc, unit="step", leave=False, dynamic_ncols=True)

        def step(k: int, loss: float) -> None:
            bar.update(1)
            bar.set_postfix(loss=f"{loss:.5f}")

        return step, bar.close

    def optimise(
        self, desc: str, value_and_grad: Callable[[Any], Any], x0: Any, steps: int, lr: float, sb: StepBudget
    ) -> tuple[Any, StepLog]:
        """:func:`adam_steps` with a progress bar and ``sb``'s early-termination settings."""
        step, close = self.run(desc, steps)
        try:
            return adam_steps(value_and_grad, x0, steps, lr, sb.patience, sb.min_rel_improvement, on_step=step)
        finally:
            close()

    def write(self, text: str) -> None:
        if self.enabled:
            from tqdm import tqdm

            tqdm.write(text)


def run_transfer(
    demo_path: str | Path,
    out: str | Path,
    hand_ref: str = "shadow",
    target: str = "mujoco",
    curriculum: str | Curriculum = "default",
    stages: tuple[str, ...] = STAGES,
    budget: str = "fast",
    resume: bool = False,
    config: TransferConfig | None = None,
    render: bool = True,
    progress: bool = True,
    method: str = "ours",
) -> TransferResult:
    """Stages 1 and/or 2 on one demonstration; writes ``OUT/controls.npz``, ``OUT/metrics.json`` (judged in
    ``target``), ``OUT/report.html`` and ``OUT/summary.json``. See the module docstring."""
    from quasisim.assets.hand import load_hand
    from quasisim.evaluate import evaluate_controls, load_object_for, scene_for
    from quasisim.retarget import retarget
    from quasisim.sim.build import SimOptions, build_model, default_params
    from quasisim.targets import TARGETS
    from quasisim.targets.scene import size_table

    if target not in TARGETS:
        raise choice_error("target", target, TARGETS)
    if method not in METHODS:
        raise choice_error("method", method, METHODS)
    if method == "kinematic":
        stages = ()
    elif method in ("mpc-base", "mpc-soften"):
        stages = ("mpc",)
    if "mpc" in stages and target != "mujoco":
        raise QuasisimError(
            f"closed-loop MPC runs in MuJoCo only (target {target!r}); use --target mujoco or leave out the mpc stage"
        )
    out = Path(out)
    cfg = config or TransferConfig.from_yaml()
    bud = cfg.budget(budget)
    cur = curriculum if isinstance(curriculum, Curriculum) else load_curriculum(curriculum)
    demo = load_demo(demo_path)
    hand = load_hand(hand_ref)
    bar = _Bar(progress)
    run_info = {
        "demo": demo.name, "demo_sha256": _file_digest(Path(demo_path)), "hand": str(hand_ref),
        "curriculum": cur.name, "stages": list(stages), "budget": budget, "method": method,
        "mpc": dataclasses.asdict(cfg.mpc), "budget_settings": dataclasses.asdict(bud), "weights": dataclasses.asdict(cfg.weights),
    }  # fmt: skip
    ck = Checkpoints(out / "checkpoints", run_info, resume)
    seconds: dict[str, float] = {}
    curves: dict[str, list[float]] = {}
    sim_summary: list[dict[str, Any]] = []

    # ---- kinematic retarget (stage 1c, and the initial trajectory of every later stage) ----
    t0 = time.perf_counter()
    kin = ck.load("kinematic")
    if kin is None:
        rt = retarget(hand, demo, progress=progress)
        kin = {"q": rt.q, "base_rot": rt.base_rot, "wall_s": np.array(time.perf_counter() - t0)}
        ck.save("kinematic", **kin)
    base_rot = np.asarray(kin["base_rot"], np.float64)
    seconds["retarget"] = float(kin["wall_s"])
    from quasisim.rotations import np_mat_to_quat

    base_quat = np_mat_to_quat(base_rot)
    obj = load_object_for(demo)
    table, _ = size_table(demo, obj)
    opts = SimOptions.for_fps(demo.fps, bud.substeps, n_candidates=bud.n_candidates)
    model = build_model(hand, obj, table, opts, demo.object_pos[0])
    params0 = default_params(model, obj.mass, obj.inertia)
    obj0 = (demo.object_pos[0], demo.object_quat[0])
    metric = np.flatnonzero(hand.kp_metric)
    traj = kin_traj = Trajectory.from_q(kin["q"], model.n_points)
    sysid = SysID.init()
    relaxed = [i for i, s in enumerate(cur.stages) if s.alpha > 0 and not s.residual]
    rigid = [i for i, s in enumerate(cur.stages) if s.alpha == 0 and not s.residual]

    # ---- stage 1: point dynamics ----
    human_points = point_index = None
    if "1" in stages and relaxed:
        i1 = relaxed[0]
        p1 = params0.replace(**cur.params_overrides(i1))
        hp = ck.load("stage1_human")
        if hp is None:
            hp = _stage1_human(demo, obj, table, opts, p1, cur, i1, cfg.weights, bud.human, bar)
            ck.save("stage1_human", **hp)
        human_points = np.asarray(hp["points"], np.float32)
        curves["1b human point set"] = list(hp.get("losses", []))
        seconds["stage1_human"] = float(hp["wall_s"])
        # correspondences: each human point -> the nearest robot point at the object's motion onset
        onset = motion_onset(demo)
        from quasisim.kinematics import fk_full

        poses = fk_full(hand, jnp.asarray(base_rot, jnp.float32), jnp.asarray(kin["q"][onset], jnp.float32))
        rp = np.asarray(
            poses.pos[model.point_body] + jnp.einsum("nij,nj->ni", poses.rot[model.point_body], model.point_local)
        )
        from scipy.spatial import cKDTree

        _, point_index = cKDTree(rp).query(human_points[onset])
        ref = _reference(demo, hand, metric, human_points, point_index)
        objective = make_objective(model, ref, base_quat, demo.fps, obj0, obj.mass, obj.inertia)
        vg = jax.jit(jax.value_and_grad(objective, argnums=(0, 1), has_aux=True))
        rp_ck = ck.load("stage1_robot")
        if rp_ck is None:
            w = cfg.weights.arrays()
            rb = bud.robot_points
            traj, log = bar.optimise(
                f"stage 1d robot point set (sim {i1 + 1})", lambda x: _pick(vg(x, sysid, p1, w), 0), traj,
                rb.control_steps, rb.control_lr, rb,
            )  # fmt: skip
            rp_ck = _traj_arrays(traj, sysid, log, log.wall_s)
            ck.save("stage1_robot", **rp_ck)
        traj, sysid = _traj_from(rp_ck)
        curves[f"1d robot point set (sim {i1 + 1})"] = list(rp_ck.get("losses", []))
        seconds["stage1_robot"] = float(rp_ck["wall_s"])
        seconds["stage1"] = seconds["stage1_human"] + seconds["stage1_robot"]
        bar.write(
            f"stage 1 done: human {seconds['stage1_human']:.0f} s, robot point set {seconds['stage1_robot']:.0f} s"
        )
    else:
        ref = _reference(demo, hand, metric, None, None)
        objective = make_objective(model, ref, base_quat, demo.fps, obj0, obj.mass, obj.inertia)
        vg = jax.jit(jax.value_and_grad(objective, argnums=(0, 1), has_aux=True))

    # ---- stage 2: the contact curriculum, alpha = 0 ----
    p_final = params0
    if "2" in stages:
        w2 = cfg.weights.arrays(points=0.0)
        sb = bud.sim
        seconds["stage2"] = 0.0
        start = traj  # the stage's initial trajectory (stage 1's result or the kinematic retarget)
        for n, i in enumerate(rigid):
            p = params0.replace(**cur.params_overrides(i))
            p_final = p
            name = f"stage2_sim{i + 1:02d}"
            d = ck.load(name)
            if d is None:
                t2 = time.perf_counter()
                label = f"stage 2 sim {i + 1} ({n + 1}/{len(rigid)})"
                start_losses: dict[str, float] = {}
                if n > 0:
                    # restart guard: in this simulator, continue from the best of the previous simulator's
                    # result, the stage's start (stage 1's result) and the kinematic retarget
                    cands = {"previous": traj, "stage_start": start, "kinematic": kin_traj}
                    start_losses = {k: float(vg(t, sysid, p, w2)[0][0]) for k, t in cands.items()}
                    best = min(start_losses, key=start_losses.__getitem__)
                    if best != "previous":
                        bar.write(
                            f"sim {i + 1}: restarting from {best} "
                            f"({start_losses[best]:.5f} < previous {start_losses['previous']:.5f})"
                        )
                        traj = cands[best]
                log_s = StepLog()
                if sb.sysid_steps > 0:
                    sysid, log_s = bar.optimise(
                        f"{label} identify S", lambda s, traj=traj, p=p: _pick(vg(traj, s, p, w2), 1), sysid,
                        sb.sysid_steps, sb.sysid_lr, sb,
                    )  # fmt: skip
                traj, log_c = bar.optimise(
                    f"{label} controls", lambda x, sysid=sysid, p=p: _pick(vg(x, sysid, p, w2), 0), traj,
                    sb.control_steps, sb.control_lr, sb,
                )  # fmt: skip
                d = _traj_arrays(traj, sysid, None, time.perf_counter() - t2)
                d["losses"] = np.asarray(log_s.losses + log_c.losses, np.float64)
                d["n_sysid"] = np.array(len(log_s.losses))
                d["terms"] = np.array(json.dumps(log_c.terms[-1] if log_c.terms else {}))
                d["start_losses"] = np.array(json.dumps(start_losses))
                ck.save(name, **d)
            traj, sysid = _traj_from(d)
            losses = [float(x) for x in d["losses"]]
            curves[f"sim {i + 1}"] = losses
            seconds["stage2"] += float(d["wall_s"])
            s_desc = sysid.describe(obj.mass)
            sim_summary.append(
                {"sim": i + 1, **{k: float(v) for k, v in cur.params_overrides(i).items()}, "steps": len(losses),
                 "loss_first": losses[0] if losses else None, "loss_best": min(losses) if losses else None,
                 "wall_s": float(d["wall_s"]), **s_desc,
                 "start_losses": json.loads(str(d["start_losses"])) if "start_losses" in d else None}
            )  # fmt: skip
            bar.write(
                f"sim {i + 1}: loss {losses[0]:.5f} -> {min(losses):.5f} in {len(losses)} steps, "
                f"{float(d['wall_s']):.0f} s; mass {s_desc['mass_kg'] * 1e3:.0f} g"
            )

    # ---- closed-loop MPC in the target ----
    p_out = sysid.apply(p_final, obj.mass, obj.inertia)
    q_out = traj.q_targets
    scene = scene_for(demo, hand, base_rot, obj)
    extras: dict[str, Any] = {"kinematic_q": np.asarray(kin["q"])}
    if "mpc" in stages:
        d = ck.load("mpc")
        if d is None:
            opts = dataclasses.replace(cfg.mpc, soften=cfg.soften_samples if method == "mpc-soften" else 0)
            p_mpc = p_out if method == "ours" else mpc_params(params0, None, obj.mass, obj.inertia)
            r = run_mpc(demo, scene, model, p_mpc, q_out, opts, cfg.weights, progress=progress)
            d = {"q_targets": r.q_targets, "window_loss": r.window_loss, "wall_s": np.array(r.wall_s)}
            ck.save("mpc", **d)
        seconds["mpc"] = float(d["wall_s"])
        extras["plan_q"] = q_out
        q_out = np.asarray(d["q_targets"], np.float64)
        curves["mpc window loss per frame"] = [float(x) for x in d["window_loss"]]
        bar.write(f"mpc done in {seconds['mpc']:.0f} s")

    # ---- outputs ----
    if stages:
        states = jax.jit(lambda pp, tt: simulate(model, pp, tt, base_quat, demo.fps, obj0))(p_out, traj)
        extras["sim_qpos"] = _sim_qpos(model, states, traj, base_rot)
    label = "kinematic" if method == "kinematic" else method if method != "ours" else "transfer"
    controls = Controls(
        hand=str(hand_ref), demo=demo.name, method=f"{label}[{cur.name};stages {','.join(stages)};{budget}]",
        fps=demo.fps, base_rot=base_rot, q_targets=q_out, joint_names=hand.joint_names, extras=extras,
    )  # fmt: skip
    controls.save(out / "controls.npz")
    kin_ev = evaluate_controls(
        demo, dataclasses.replace(controls, q_targets=np.asarray(kin["q"]), method="kinematic"), target,
        None, render=False, scene=scene,
    )  # fmt: skip
    summary = {
        "demo": demo.name, "hand": hand.name, "target": target, "curriculum": cur.name, "stages": list(stages),
        "budget": budget, "method": method, "seconds": seconds, "simulators": sim_summary,
        "kinematic_metrics": kin_ev.metrics, "sysid": sysid.describe(obj.mass),
    }  # fmt: skip
    from quasisim.report import loss_plot

    images = {"optimisation loss per simulator of the curriculum": loss_plot(curves)} if curves else {}
    km = kin_ev.metrics
    ev = evaluate_controls(
        demo, controls, target, out, render=render, scene=scene,
        title=f"{demo.name}: {label} ({cur.name} curriculum, stages {','.join(stages) or 'none'}) in {target}",
        extra_info={
            "kinematic replay in the same target": f"R_err {km['R_err_deg']:.1f} deg, T_err {km['T_err_cm']:.2f} cm, "
            f"MPJPE {km['MPJPE_mm']:.1f} mm, success {km['success']}",
            "budget": f"{budget} (simulator dt {model.dt * 1e3:g} ms)",
            "seconds per stage": ", ".join(f"{k} {v:.0f}" for k, v in seconds.items()),
            "identified S": ", ".join(f"{k} {v:.4g}" for k, v in sysid.describe(obj.mass).items()),
        },
        extra_images=images, progress=progress,
    )  # fmt: skip
    summary["metrics"] = ev.metrics
    save_json_atomic(out / "summary.json", summary)
    return TransferResult(controls, ev.metrics, kin_ev.metrics, curves, seconds, sim_summary, out)


def _pick(res: tuple[tuple[Any, Any], tuple[Any, Any]], i: int) -> tuple[tuple[Any, Any], Any]:
    (loss, terms), grads = res
    return (loss, terms), grads[i]


def _reference(
    demo: Demo, hand: Any, metric: np.ndarray, points: np.ndarray | None, point_index: np.ndarray | None
) -> Reference:
    return Reference(
        obj_pos=demo.object_pos[1:], obj_quat=demo.object_quat[1:],
        keypoints=demo.right_joints[1:, hand.kp_human[metric]], kp_index=metric,
        points=None if points is None else points[1:], point_index=point_index,
    )  # fmt: skip


def _sim_qpos(model: Any, states: Any, traj: Trajectory, base_rot: np.ndarray) -> np.ndarray:
    """(T, 6 + J) hand trajectory of the quasi-physical rollout in base coordinates (frame 0: the start)."""
    from quasisim.rotations import np_mat_to_euler_xyz, np_quat_to_mat

    root = np.asarray(model.to_world(states.root_pos), np.float64)
    R = np_quat_to_mat(np.asarray(states.root_quat))
    eul = np.unwrap(np_mat_to_euler_xyz(np.einsum("ji,tjk->tik", base_rot, R)), axis=0)
    q = np.concatenate([root, eul, np.asarray(states.q, np.float64)], axis=1)
    return np.concatenate([np.asarray(traj.q_targets[:1]), q], axis=0)


def _stage1_human(
    demo: Demo, obj: Any, table: Any, opts: Any, p1: Any, cur: Curriculum, i1: int, weights: Weights,
    sb: StepBudget, bar: _Bar,
) -> dict[str, Any]:  # fmt: skip
    """Stages 1a and 1b: the dynamic human hand's point set moves the object like the demo.
    Returns the human point set per frame (T, P, 3) and the loss history."""
    from quasisim.human_hand import build_human_hand, human_hand_trajectory
    from quasisim.rotations import np_mat_to_quat
    from quasisim.sim.build import build_model, default_params

    t0 = time.perf_counter()
    human = build_human_hand(demo.right_joints)
    fit = human_hand_trajectory(human, demo)
    model = build_model(human, obj, table, opts, demo.object_pos[0])
    params = default_params(model, obj.mass, obj.inertia).replace(**cur.params_overrides(i1))
    bq = np_mat_to_quat(fit.base_rot)
    all_kp = np.arange(len(human.kp_human))
    ref = Reference(
        obj_pos=demo.object_pos[1:], obj_quat=demo.object_quat[1:],
        keypoints=demo.right_joints[1:, human.kp_human], kp_index=all_kp,
    )  # fmt: skip
    obj0 = (demo.object_pos[0], demo.object_quat[0])
    objective = make_objective(model, ref, bq, demo.fps, obj0, obj.mass, obj.inertia)
    vg = jax.jit(jax.value_and_grad(objective, argnums=0, has_aux=True))
    sysid = SysID.init()
    w = weights.arrays(points=0.0)
    traj = Trajectory.from_q(fit.q, model.n_points)
    traj, log = bar.optimise(
        f"stage 1b human point set (sim {i1 + 1})", lambda x: vg(x, sysid, params, w), traj, sb.control_steps,
        sb.control_lr, sb,
    )  # fmt: skip

    @jax.jit
    def points_of(tt: Trajectory) -> jax.Array:
        states = simulate(model, params, tt, bq, demo.fps, obj0)
        idx = np.arange(model.n_points)
        p = hand_point_positions(model, params, states, idx)
        from quasisim.kinematics import fk_full

        poses = fk_full(human, jnp.asarray(fit.base_rot, jnp.float32), jnp.concatenate([tt.base[0], tt.joints[0]]))
        p0 = poses.pos[model.point_body] + jnp.einsum("nij,nj->ni", poses.rot[model.point_body], model.point_local)
        return jnp.concatenate([p0[None], p], axis=0)

    pts = np.asarray(points_of(traj), np.float32)
    return {
        "points": pts,
        "losses": np.asarray(log.losses, np.float64),
        "human_fit_error_mm": np.array(float(fit.mean_metric_error_mm)),
        "wall_s": np.array(time.perf_counter() - t0),
    }
