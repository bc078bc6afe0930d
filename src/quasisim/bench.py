"""Benchmarks that print markdown for BENCHMARKS.md (date, machine, command, table)."""

from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from quasisim.io import save_json_atomic, save_text_atomic
from quasisim.metrics import SUCCESS_KEYS


def machine_line() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{platform.system()} {platform.machine()}, {cpu}, {os.cpu_count()} logical CPUs, Python {platform.python_version()}"


def header(title: str) -> str:
    now = _dt.datetime.now().strftime("%Y-%m-%d %H:%M")
    cmd = (
        "quasisim " + " ".join(sys.argv[1:])
        if sys.argv and "quasisim" in Path(sys.argv[0]).name
        else " ".join(sys.argv)
    )
    return f"### {title}\n\n- date: {now}\n- machine: {machine_line()}\n- command: `{cmd}`\n"


def clips(data_dir: Path, pattern: str) -> list[Path]:
    paths = sorted(data_dir.glob(pattern))
    if "_long" not in pattern:
        paths = [p for p in paths if not p.stem.endswith("_long")]
    return paths


def summary_rows(rows: list[dict[str, Any]], group: str) -> list[str]:
    out = []
    for g in sorted({r[group] for r in rows}):
        rs = [r for r in rows if r[group] == g]
        m = {k: np.mean([r[k] for r in rs]) for k in ("R_err_deg", "T_err_cm", "MPJPE_mm", "CD_mm")}
        s = {k: 100.0 * np.mean([r["success"][k] for r in rs]) for k in SUCCESS_KEYS}
        out.append(
            f"| {g} | {len(rs)} | {m['R_err_deg']:.1f} | {m['T_err_cm']:.2f} | {m['MPJPE_mm']:.1f} | {m['CD_mm']:.1f} | "
            + " | ".join(f"{s[k]:.0f}" for k in SUCCESS_KEYS)
            + f" | {np.mean([r['wall_s'] for r in rs]):.2f} |"
        )
    return out


SUMMARY_HEAD = (
    "| {g} | clips | R_err (deg) | T_err (cm) | MPJPE (mm) | CD (mm) | succ 10 (%) | succ 15 (%) | succ 20 (%) | strict (%) | wall s/clip |\n"
    "|---|---|---|---|---|---|---|---|---|---|---|"
)
CLIP_HEAD = (
    "| clip | {g} | R_err | T_err | MPJPE | CD | 10 | 15 | 20 | strict | lifted | wall s |\n"
    "|---|---|---|---|---|---|---|---|---|---|---|---|"
)


def clip_row(r: dict[str, Any], group: str) -> str:
    s = r["success"]
    yn = lambda b: "y" if b else "-"  # noqa: E731
    return (
        f"| {r['clip']} | {r[group]} | {r['R_err_deg']:.1f} | {r['T_err_cm']:.2f} | {r['MPJPE_mm']:.1f} | {r['CD_mm']:.1f} | "
        + " | ".join(yn(s[k]) for k in SUCCESS_KEYS)
        + f" | {yn(r['lifted'])} | {r['wall_s']:.2f} |"
    )


def lifted(demo: Any, rollout: Any, min_lift: float = 0.03) -> bool:
    """Did the simulated object rise >= 3 cm (or half the demo's lift, if smaller) above its start?"""
    demo_lift = float(demo.object_pos[:, 2].max() - demo.object_pos[0, 2])
    need = min(min_lift, 0.5 * demo_lift)
    return bool(rollout.object_pos[:, 2].max() - rollout.object_pos[0, 2] >= need) and demo_lift > 0.01


def run_baseline(
    data_dir: Path, hand_name: str, targets: tuple[str, ...], out: Path, pattern: str, render: bool
) -> str:
    """Kinematic retargeting replayed with PD control in each target, on every clip."""
    from tqdm import tqdm

    from quasisim.assets.hand import load_hand
    from quasisim.demo import load_demo
    from quasisim.evaluate import evaluate_controls, load_object_for, scene_for
    from quasisim.retarget import kinematic_controls

    hand = load_hand(hand_name)
    rows: list[dict[str, Any]] = []
    paths = clips(data_dir, pattern)
    for p in tqdm(paths, desc="clips", unit="clip"):
        demo = load_demo(p)
        t0 = time.perf_counter()
        controls = kinematic_controls(hand, demo, hand_name)
        t_ret = time.perf_counter() - t0
        obj = load_object_for(demo)
        scene = scene_for(demo, hand, controls.base_rot, obj)
        for tgt in targets:
            t1 = time.perf_counter()
            ev = evaluate_controls(demo, controls, tgt, out / demo.name / tgt if render else None, render, scene=scene)
            rows.append(
                {
                    "clip": demo.name,
                    "target": tgt,
                    **ev.metrics,
                    "lifted": lifted(demo, ev.rollout),
                    "retarget_s": t_ret,
                    "rollout_s": ev.rollout.wall_s,
                    "wall_s": t_ret + time.perf_counter() - t1,
                }
            )
    lines = [
        header(f"Kinematic-replay baseline ({hand_name})"),
        SUMMARY_HEAD.format(g="target"),
        *summary_rows(rows, "target"),
    ]
    for tgt in targets:
        n_lift = sum(r["lifted"] for r in rows if r["target"] == tgt)
        n = sum(1 for r in rows if r["target"] == tgt)
        lines.append(f"\n{tgt}: object lifted (>= 3 cm or half the demo's lift) in {n_lift} of {n} clips.")
    lines += ["", CLIP_HEAD.format(g="target"), *[clip_row(r, "target") for r in rows]]
    return _publish(out, "baseline", rows, lines)


def _publish(out: Path, name: str, rows: list[dict[str, Any]], lines: list[str]) -> str:
    """Write ``out/name.json`` (rows) and ``out/name.md`` (the markdown), print the markdown."""
    text = "\n".join(lines) + "\n"
    out.mkdir(parents=True, exist_ok=True)
    save_json_atomic(out / f"{name}.json", rows)
    save_text_atomic(out / f"{name}.md", text)
    print(text)
    return text


def dump(obj: Any) -> str:
    return json.dumps(obj, indent=2)


def _peak_rss_mb() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def sim_setup(demo_path: Path, hand_name: str, substeps: int | None = None, n_candidates: int = 128) -> dict[str, Any]:
    """Model, stiffest params, initial state and kinematic-replay controls for one clip."""
    import jax.numpy as jnp

    from quasisim.assets.hand import load_hand
    from quasisim.demo import load_demo
    from quasisim.evaluate import load_object_for
    from quasisim.kinematics import base_to_root
    from quasisim.retarget import retarget
    from quasisim.rotations import np_mat_to_quat
    from quasisim.sim.build import SimOptions, build_model, controls_from_trajectory, default_params
    from quasisim.sim.step import initial_state
    from quasisim.targets.scene import size_table

    demo = load_demo(demo_path)
    hand = load_hand(hand_name)
    obj = load_object_for(demo)
    table, _ = size_table(demo, obj)
    rt = retarget(hand, demo)
    roots = [base_to_root(jnp.asarray(q[:6]), jnp.asarray(rt.base_rot)) for q in rt.q]
    root_pos = np.array([np.asarray(p) for p, _ in roots])
    root_rot = np.array([np.asarray(R) for _, R in roots])
    model = build_model(
        hand, obj, table, SimOptions.for_fps(demo.fps, substeps, n_candidates=n_candidates), demo.object_pos[0]
    )
    params = default_params(model, obj.mass, obj.inertia)
    s0 = initial_state(
        model, root_pos[0], np_mat_to_quat(root_rot[0]), rt.q[0, 6:], demo.object_pos[0], demo.object_quat[0]
    )
    ctrl = controls_from_trajectory(model, root_pos, root_rot, rt.q[:, 6:], demo.fps)
    return {"demo": demo, "hand": hand, "obj": obj, "model": model, "params": params, "s0": s0, "ctrl": ctrl, "rt": rt}


def run_sim_bench(
    data_dir: Path,
    clip: str,
    study_clips: tuple[str, ...],
    hand_name: str,
    substeps: int | None,
    dt_study: tuple[int, ...],
    as_json: bool,
) -> dict:
    """Speed of the quasi-physical simulator on one hand-object scene (stiffest analytical setting,
    kinematic-replay controls), MuJoCo on the same scene, and the object-trajectory deviation of larger
    steps from the dt = 5e-4 s reference on several clips (with the reference's own sensitivity: dt = 2.5e-4)."""
    import jax
    import jax.numpy as jnp

    from quasisim.sim.step import object_pose, rollout
    from quasisim.targets.mujoco_target import MujocoTarget
    from quasisim.targets.scene import make_scene

    def timed(fn: Any, *args: Any, reps: int = 2) -> tuple[Any, float]:
        out = jax.block_until_ready(fn(*args))  # compile
        t0 = time.perf_counter()
        for _ in range(reps):
            out = jax.block_until_ready(fn(*args))
        return out, (time.perf_counter() - t0) / reps

    st = sim_setup(data_dir / f"{clip}.npz", hand_name, substeps)
    model, params, s0, ctrl, demo = st["model"], st["params"], st["s0"], st["ctrl"], st["demo"]
    n = model.substeps
    fwd = jax.jit(lambda p, s, c: object_pose(model, rollout(model, p, s, c))[0])
    _, t_fwd = timed(fwd, params, s0, ctrl)
    target = jnp.asarray(demo.object_pos[1:], jnp.float32)

    def loss(c: Any, p: Any, s: Any) -> Any:
        return jnp.mean(jnp.sum((object_pose(model, rollout(model, p, s, c))[0] - target) ** 2, -1))

    _, t_fb = timed(jax.jit(jax.value_and_grad(loss)), ctrl, params, s0)
    frames = ctrl.root_vel.shape[0]
    mj = MujocoTarget(make_scene(demo, st["hand"], st["rt"].base_rot, st["obj"]))
    r = mj.rollout(st["rt"].q)
    res: dict[str, Any] = {
        "clip": demo.name,
        "n_points": int(model.n_points),
        "n_candidates": int(model.n_candidates),
        "dt": float(model.dt),
        "substeps_per_frame": n,
        "frames": frames,
        "forward_substeps_per_s": frames * n / t_fwd,
        "fwd_bwd_substeps_per_s": frames * n / t_fb,
        "rollout60_fwd_bwd_s": t_fb * 59.0 / frames,
        "rollout60_forward_s": t_fwd * 59.0 / frames,
        "peak_memory_mb": _peak_rss_mb(),
        "mujoco_steps_per_s": (len(st["rt"].q) - 1) * r.substeps / r.wall_s,
        "mujoco_dt": r.dt,
    }
    res["simulated_seconds_per_wall_second"] = {
        "quasisim_forward": res["forward_substeps_per_s"] * model.dt,
        "mujoco": res["mujoco_steps_per_s"] * r.dt,
    }
    study: list[dict[str, Any]] = []
    for c in study_clips:
        traj: dict[int, np.ndarray] = {}
        for k in sorted({200, 100, *dt_study}, reverse=True):
            s_ = sim_setup(data_dir / f"{c}.npz", hand_name, k)
            m_, p_, x_, c_ = s_["model"], s_["params"], s_["s0"], s_["ctrl"]
            traj[k] = np.asarray(jax.jit(lambda p, m_=m_, x_=x_, c_=c_: object_pose(m_, rollout(m_, p, x_, c_))[0])(p_))
        for k in sorted(traj):
            if k == 100:
                continue
            d = np.linalg.norm(traj[k] - traj[100], axis=-1) * 1e3
            study.append(
                {"clip": c, "substeps": k, "dt_ms": 1000.0 / (demo.fps * k), "mean_dev_mm": float(d.mean()),
                 "median_dev_mm": float(np.median(d)), "max_dev_mm": float(d.max()),
                 "object_travel_mm": float(np.linalg.norm(traj[100] - traj[100][0], axis=-1).max() * 1e3)}
            )  # fmt: skip
    res["dt_study_vs_dt_0.5ms"] = study
    if as_json:
        print(json.dumps(res, indent=2))
    else:
        lines = [header("Quasi-physical simulator speed and step size"), "```json", json.dumps({k: v for k, v in res.items() if k != "dt_study_vs_dt_0.5ms"}, indent=2), "```", "",
                 "| clip | substeps/frame | dt (ms) | mean dev (mm) | median (mm) | max (mm) | object travel (mm) |", "|---|---|---|---|---|---|---|"]  # fmt: skip
        lines += [
            f"| {r_['clip']} | {r_['substeps']} | {r_['dt_ms']:.2f} | {r_['mean_dev_mm']:.2f} | {r_['median_dev_mm']:.2f} | {r_['max_dev_mm']:.2f} | {r_['object_travel_mm']:.0f} |"
            for r_ in study
        ]
        print("\n".join(lines))
    return res


RUN_KINDS = "CURRICULUM (stages 1,2), CURRICULUM+mpc (stages 1,2,mpc), mpc-base, mpc-soften"


def _run_spec(run: str, stages: tuple[str, ...]) -> tuple[str, str, tuple[str, ...]]:
    """A benchmark run name -> (method, curriculum, stages): ``default``, ``none+mpc``, ``mpc-base``..."""
    from quasisim.curriculum import load_curriculum

    if run in ("mpc-base", "mpc-soften"):
        return run, "none", ("mpc",)
    cur, _, extra = run.partition("+")
    if extra not in ("", "mpc"):
        from quasisim.errors import QuasisimError

        raise QuasisimError(f"unknown benchmark run {run!r}; valid forms: {RUN_KINDS}")
    load_curriculum(cur)
    return "ours", cur, (*stages, "mpc") if extra else stages


def run_transfer_bench(
    data_dir: Path,
    clip_names: tuple[str, ...],
    pattern: str,
    runs: tuple[str, ...],
    stages: tuple[str, ...],
    budget: str,
    target: str,
    hand_name: str,
    out: Path,
    report_only: bool = False,
    judge: str | None = None,
) -> str:
    """Transfer runs on clips beside the kinematic replay (same target): ``runs`` name curricula (stages 1-2),
    ``CURRICULUM+mpc`` (then closed-loop MPC) and the MPC baselines ``mpc-base``, ``mpc-soften``.
    With ``judge`` (another simulator), the table judges each run's controls and the kinematic retarget
    open loop in that simulator instead (cached as ``metrics_<judge>.json`` beside each run).

    Each run writes into ``out/<clip>/<run>`` and is resumed from its checkpoints, so an interrupted
    benchmark continues where it stopped; finished runs (``summary.json`` present) are read back
    (``report_only``: only those, nothing is run). A
    ``CURRICULUM+mpc`` run starts from the stage-1/2 checkpoints of the ``CURRICULUM`` run when present."""
    import shutil

    from tqdm import tqdm

    from quasisim.transfer import run_transfer

    specs = {r: _run_spec(r, stages) for r in runs}
    paths = [data_dir / f"{c}.npz" for c in clip_names] if clip_names else clips(data_dir, pattern)
    missing = [str(p) for p in paths if not p.is_file()]
    if missing:
        from quasisim.errors import QuasisimError

        raise QuasisimError(f"clips not found: {', '.join(missing)}")
    rows: list[dict[str, Any]] = []
    for p in tqdm(paths, desc="clips", unit="clip"):
        for run, (method, cur, st) in specs.items():
            d = out / p.stem / run
            summ = d / "summary.json"
            if not summ.is_file() and report_only:
                continue
            if not summ.is_file():
                for stale in d.glob("metrics_*.json"):  # judgements of an earlier, unfinished or redone run
                    stale.unlink()
                base_ck = out / p.stem / cur / "checkpoints"
                if "+" in run and base_ck.is_dir() and not (d / "checkpoints").is_dir():
                    (d / "checkpoints").mkdir(parents=True)
                    for f in base_ck.glob("*.npz"):
                        shutil.copy2(f, d / "checkpoints" / f.name)
                    json_info = json.loads((base_ck / "run.json").read_text())
                    from quasisim.transfer import TransferConfig

                    mpc_opts = dataclasses.asdict(TransferConfig.from_yaml().mpc)
                    json_info.update(stages=list(st), method=method, mpc=mpc_opts)
                    save_json_atomic(d / "checkpoints" / "run.json", json_info)
                t0 = time.perf_counter()
                run_transfer(
                    p, d, hand_ref=hand_name, target=target, curriculum=cur, stages=st, budget=budget,
                    resume=(d / "checkpoints").is_dir(), render=False, progress=True, method=method,
                )  # fmt: skip
                s = json.loads(summ.read_text())
                s["bench_wall_s"] = time.perf_counter() - t0
                save_json_atomic(summ, s)
            s = json.loads(summ.read_text())
            if judge and judge != target:
                s["metrics"], s["kinematic_metrics"] = _judged(p, d, judge)
            k = s["kinematic_metrics"]
            if not any(r["clip"] == p.stem and r["method"] == "kinematic" for r in rows):
                rows.append(
                    {
                        "clip": p.stem,
                        "method": "kinematic",
                        **k,
                        "wall_s": float(s["seconds"].get("retarget", 0.0)),
                        "seconds": {},
                    }
                )
            rows.append(
                {"clip": p.stem, "method": run, **s["metrics"], "seconds": s["seconds"],
                 "wall_s": float(s.get("bench_wall_s", sum(s["seconds"].values()))),
                 "better": bool(s["metrics"]["T_err_cm"] < k["T_err_cm"] and s["metrics"]["R_err_deg"] < k["R_err_deg"])}
            )  # fmt: skip
    for r in rows:
        r["lifted"] = False  # not recomputed here (see the baseline benchmark)
    judged_in = judge or target
    lines = [
        header(f"Transfer ({hand_name}, optimised for {target}, judged in {judged_in}, budget {budget})"),
        SUMMARY_HEAD.format(g="method"),
        *summary_rows(rows, "method"),
        "",
    ]
    for run in runs:
        rs = [r for r in rows if r["method"] == run]
        n_better = sum(r["better"] for r in rs)
        st_ = [r["seconds"] for r in rs]
        per_stage = {k: np.mean([s_.get(k, 0.0) for s_ in st_]) for k in sorted({k for s_ in st_ for k in s_})}
        lines.append(
            f"- {run}: lower T_err and lower R_err than the kinematic replay on {n_better} of {len(rs)} clips; "
            "mean seconds per stage: " + ", ".join(f"{k} {v:.0f}" for k, v in per_stage.items())
        )
    lines += [
        "",
        "| clip | method | R_err | T_err | MPJPE | CD | 10 | 15 | 20 | strict | wall s |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    yn = lambda b: "y" if b else "-"  # noqa: E731
    for r in rows:
        s_ = r["success"]
        lines.append(
            f"| {r['clip']} | {r['method']} | {r['R_err_deg']:.1f} | {r['T_err_cm']:.2f} | {r['MPJPE_mm']:.1f} | "
            f"{r['CD_mm']:.1f} | " + " | ".join(yn(s_[k]) for k in SUCCESS_KEYS) + f" | {r['wall_s']:.0f} |"
        )
    return _publish(out, "transfer" if judged_in == target else f"transfer_{judged_in}", rows, lines)


def _judged(demo_path: Path, run_dir: Path, judge: str) -> tuple[dict[str, Any], dict[str, Any]]:
    """Metrics of a finished run's controls and of its kinematic retarget, replayed open loop in ``judge``."""
    cache = run_dir / f"metrics_{judge}.json"
    if cache.is_file():
        d = json.loads(cache.read_text())
        return d["metrics"], d["kinematic_metrics"]
    from quasisim.controls import load_controls
    from quasisim.demo import load_demo
    from quasisim.evaluate import evaluate_controls

    demo = load_demo(demo_path)
    c = load_controls(run_dir / "controls.npz")
    kin = dataclasses.replace(c, q_targets=np.asarray(c.extras["kinematic_q"]), method="kinematic")
    d = {
        "metrics": evaluate_controls(demo, c, judge, None, render=False).metrics,
        "kinematic_metrics": evaluate_controls(demo, kin, judge, None, render=False).metrics,
    }
    save_json_atomic(cache, d)
    return d["metrics"], d["kinematic_metrics"]


def run_predict_bench(
    data_dir: Path, clip_names: tuple[str, ...], pattern: str, horizon: int, curriculum: str, hand_name: str,
    out: Path, sims: tuple[int, ...] = (), mus: tuple[float, ...] = (),
) -> str:  # fmt: skip
    """Open-loop ``horizon``-frame prediction error of the quasi-physical simulator against MuJoCo (no
    residual physics, nominal S) under the kinematic retarget's PD targets, for each rigid simulator of
    ``curriculum`` (or those numbered in ``sims``, 1-based), beside the zero-motion predictor; with ``mus``,
    each simulator once per friction coefficient instead of the curriculum's. See :mod:`quasisim.fit`."""
    import jax.numpy as jnp
    from tqdm import tqdm

    from quasisim.assets.hand import load_hand
    from quasisim.curriculum import load_curriculum
    from quasisim.demo import load_demo
    from quasisim.errors import QuasisimError
    from quasisim.evaluate import load_object_for, scene_for
    from quasisim.fit import prediction_error, record_target
    from quasisim.retarget import retarget
    from quasisim.rotations import np_mat_to_quat
    from quasisim.sim.build import SimOptions, build_model, default_params
    from quasisim.targets.scene import size_table

    cur = load_curriculum(curriculum)
    rigid = [i for i, s in enumerate(cur.stages) if s.alpha == 0 and not s.residual]
    if sims:
        bad = [n for n in sims if n - 1 not in rigid]
        if bad:
            raise QuasisimError(
                f"--sim {bad[0]}: not a rigid simulator of curriculum {cur.name!r}; valid: {', '.join(str(i + 1) for i in rigid)}"
            )
        rigid = [n - 1 for n in sims]
    if any(not (np.isfinite(m) and m > 0) for m in mus):
        raise QuasisimError(f"--mu: friction coefficients must be positive numbers, got {list(mus)}")
    paths = [data_dir / f"{c}.npz" for c in clip_names] if clip_names else clips(data_dir, pattern)
    hand = load_hand(hand_name)
    rows: list[dict[str, Any]] = []
    for p in tqdm(paths, desc="clips", unit="clip"):
        demo = load_demo(p)
        rt = retarget(hand, demo)
        obj = load_object_for(demo)
        table, _ = size_table(demo, obj)
        model = build_model(hand, obj, table, SimOptions.for_fps(demo.fps), demo.object_pos[0])
        p0 = default_params(model, obj.mass, obj.inertia)
        params = {
            f"sim {i + 1} (d_c {100 * cur.stages[i].d_c:g} cm{f', mu {m:g}' if mus else ''})": p0.replace(
                **{**cur.params_overrides(i), "mu": m}
            )
            for i in rigid
            for m in (mus or (cur.mu,))
        }
        scene = scene_for(demo, hand, rt.base_rot, obj)
        t0 = time.perf_counter()
        obs, ro = record_target(scene, rt.q, demo.fps)
        errs = prediction_error(
            model, params, np_mat_to_quat(rt.base_rot), demo.fps, jnp.asarray(rt.q), obs, ro, horizon
        )
        wall = time.perf_counter() - t0
        for name, e in errs.items():
            rows.append({"clip": p.stem, "simulator": name, **e.summary(), "wall_s": wall})
    lines = [
        header(f"{horizon}-frame prediction error against MuJoCo ({hand_name}, kinematic retarget's PD targets)"),
        f"Mean over clips and start frames, after {horizon} frames; zero-motion: the object stays where it was; "
        "diverged: windows whose prediction became non-finite (left out of the means).",
        "",
        "| simulator | clips | object pos (cm) | object rot (deg) | keypoints (mm) | zero-motion pos (cm) | zero-motion rot (deg) | diverged |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for sim in dict.fromkeys(r["simulator"] for r in rows):
        rs = [r for r in rows if r["simulator"] == sim]
        mean = lambda k, rs=rs: float(np.nanmean([r[k] for r in rs]))  # noqa: E731
        lines.append(
            f"| {sim} | {len(rs)} | {mean('obj_pos_cm'):.2f} | {mean('obj_rot_deg'):.1f} | {mean('keypoints_mm'):.1f} | "
            f"{mean('static_pos_cm'):.2f} | {mean('static_rot_deg'):.1f} | "
            f"{sum(r['n_diverged'] for r in rs)} of {sum(r['n_windows'] for r in rs)} |"
        )
    return _publish(out, "predict", rows, lines)
