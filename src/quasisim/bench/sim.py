"""``quasisim bench sim``: speed of the quasi-physical simulator (forward, forward + backward) on one
hand-object scene, MuJoCo on the same scene, and the step-size study against the dt = 0.5 ms reference."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from quasisim.data.demo import load_demo
from quasisim.eval.tables import header, peak_rss_mb
from quasisim.method.config import TransferConfig
from quasisim.method.curriculum import load_curriculum
from quasisim.method.problem import Problem, kinematic_problem
from quasisim.optim.trajectory import sim_controls, start_state
from quasisim.sim.step import object_pose, rollout
from quasisim.sim.types import Control, Params, State
from quasisim.targets.mujoco_target import MujocoTarget


@dataclass(frozen=True, eq=False)
class Replay:
    """A clip's kinematic retarget as simulator input: the problem, the stiffest analytical simulator of the
    default curriculum, the start state, the per-frame controls and the retarget's PD targets (T, D)."""

    prob: Problem
    params: Params
    s0: State
    ctrl: Control
    q_kin: np.ndarray


def kinematic_replay(demo_path: Path, hand_name: str, substeps: int, n_candidates: int = 128) -> Replay:
    demo = load_demo(demo_path)
    prob, q = kinematic_problem(demo, hand_name, substeps, n_candidates)
    cur = load_curriculum("default")
    traj = prob.trajectory(q)
    bq = jnp.asarray(prob.base_quat, jnp.float32)
    s0 = start_state(prob.model, traj, bq, *prob.obj0)
    return Replay(prob, prob.params(cur.contact(cur.stiffest)), s0, sim_controls(traj, bq, demo.fps), q)


def _timed(fn: Callable[..., Any], *args: Any, reps: int = 2) -> float:
    """Mean seconds per call of ``fn(*args)`` after one compiling call."""
    jax.block_until_ready(fn(*args))
    t0 = time.perf_counter()
    for _ in range(reps):
        jax.block_until_ready(fn(*args))
    return (time.perf_counter() - t0) / reps


def speed(r: Replay) -> dict[str, Any]:
    """Forward and forward + backward substeps per second, MuJoCo steps per second, peak memory."""
    model, n = r.prob.model, r.prob.model.substeps
    fwd = jax.jit(lambda p, s, c: object_pose(model, rollout(model, p, s, c))[0])
    t_fwd = _timed(fwd, r.params, r.s0, r.ctrl)
    target = jnp.asarray(r.prob.demo.object_pos[1:], jnp.float32)

    def loss(c: Control, p: Params, s: State) -> jax.Array:
        return jnp.mean(jnp.sum((object_pose(model, rollout(model, p, s, c))[0] - target) ** 2, -1))

    t_fb = _timed(jax.jit(jax.value_and_grad(loss)), r.ctrl, r.params, r.s0)
    frames = r.ctrl.root_vel.shape[0]
    mj = MujocoTarget(r.prob.scene).rollout(r.q_kin)
    res: dict[str, Any] = {
        "clip": r.prob.demo.name, "n_points": int(model.n_points), "n_candidates": int(model.n_candidates),
        "dt": float(model.dt), "substeps_per_frame": n, "frames": frames,
        "forward_substeps_per_s": frames * n / t_fwd, "fwd_bwd_substeps_per_s": frames * n / t_fb,
        "rollout60_fwd_bwd_s": t_fb * 59.0 / frames, "rollout60_forward_s": t_fwd * 59.0 / frames,
        "peak_memory_mb": peak_rss_mb(), "mujoco_steps_per_s": (len(r.q_kin) - 1) * mj.substeps / mj.wall_s,
        "mujoco_dt": mj.dt,
    }  # fmt: skip
    res["simulated_seconds_per_wall_second"] = {
        "quasisim_forward": res["forward_substeps_per_s"] * model.dt,
        "mujoco": res["mujoco_steps_per_s"] * mj.dt,
    }
    return res


def dt_study(
    data_dir: Path, clip: str, hand_name: str, substeps: tuple[int, ...], sims: tuple[int, ...] = ()
) -> list[dict[str, Any]]:
    """Object-trajectory deviation of each step size from the 100-substep (0.5 ms at 20 fps) reference,
    with the reference's own sensitivity (200 substeps), in the default curriculum's simulators ``sims``
    (1-based; default: the stiffest analytical one)."""
    cur = load_curriculum("default")
    sims = sims or (cur.stiffest + 1,)
    traj: dict[tuple[int, int], np.ndarray] = {}
    for k in sorted({200, 100, *substeps}, reverse=True):
        r = kinematic_replay(data_dir / f"{clip}.npz", hand_name, k)
        m = r.prob.model
        fwd = jax.jit(lambda p, m=m, r=r: object_pose(m, rollout(m, p, r.s0, r.ctrl))[0])
        for i in sims:
            traj[i, k] = np.asarray(fwd(r.prob.params(cur.contact(i - 1))))
    fps = r.prob.demo.fps
    rows = []
    for i in sims:
        ref = traj[i, 100]
        for k in sorted(k for j, k in traj if j == i and k != 100):
            d = np.linalg.norm(traj[i, k] - ref, axis=-1) * 1e3
            rows.append(
                {"clip": clip, "sim": i, "substeps": k, "dt_ms": 1000.0 / (fps * k), "mean_dev_mm": float(d.mean()),
                 "median_dev_mm": float(np.median(d)), "max_dev_mm": float(d.max()),
                 "object_travel_mm": float(np.linalg.norm(ref - ref[0], axis=-1).max() * 1e3)}
            )  # fmt: skip
    return rows


def run_sim_bench(
    data_dir: Path, clip: str, study_clips: tuple[str, ...], hand_name: str, substeps: int | None,
    substeps_study: tuple[int, ...], as_json: bool, study_sims: tuple[int, ...] = (),
) -> dict[str, Any]:  # fmt: skip
    """Speed on ``clip`` (``substeps`` per frame; default: the ``fast`` budget's) and the step-size study on
    ``study_clips`` in the curriculum's simulators ``study_sims`` (default: the stiffest); prints markdown (or
    JSON) and returns the figures."""
    n = substeps or TransferConfig.from_yaml().budget("fast").substeps
    res = speed(kinematic_replay(data_dir / f"{clip}.npz", hand_name, n))
    study = [row for c in study_clips for row in dt_study(data_dir, c, hand_name, substeps_study, study_sims)]
    res["dt_study_vs_dt_0.5ms"] = study
    if as_json:
        print(json.dumps(res, indent=2))
        return res
    lines = [header("Quasi-physical simulator speed and step size"), "```json", json.dumps({k: v for k, v in res.items() if k != "dt_study_vs_dt_0.5ms"}, indent=2), "```", "",
             "| clip | curriculum sim | substeps/frame | dt (ms) | mean dev (mm) | median (mm) | max (mm) | object travel (mm) |", "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    lines += [
        f"| {r['clip']} | {r['sim']} | {r['substeps']} | {r['dt_ms']:.2f} | {r['mean_dev_mm']:.2f} | {r['median_dev_mm']:.2f} | {r['max_dev_mm']:.2f} | {r['object_travel_mm']:.0f} |"
        for r in study
    ]
    print("\n".join(lines))
    return res
