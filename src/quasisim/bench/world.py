"""``quasisim bench world``: how well a fitted world model predicts the target on clips it never saw.

For every held-out clip of the model (or ``--clips``) with recorded transitions, three sets of windows
(:mod:`quasisim.method.transitions`): the final trajectory's windows of 6 and of 10 frames and the sampled
candidates (6 frames). Each is predicted open loop from the target's start state by the nominal stiffest
simulator, by the world model (the same simulator + its learned correction) and by zero motion (the object
stays where it is), and compared with what the target did: object position and rotation error and metric
keypoint error after the window's last frame (and after each frame). One JSON per clip is kept in
``OUT/clips/`` (resumable: reused only for the same model file and transitions file, by their sha256).
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from quasisim.errors import QuasisimError
from quasisim.eval.tables import header, publish
from quasisim.files import file_sha256, save_json_atomic
from quasisim.method.transitions import HELD_OUT, ClipWindows, clip_problem, load_clip, read_meta, transition_files
from quasisim.method.world_fit import SIMULATOR, stiffest_params
from quasisim.method.world_model import WorldModel, WorldModelConfig, batch, predict
from quasisim.rotations import quat_angle_deg
from quasisim.runtime import free_compiled_programs
from quasisim.sim.build import SIMULATOR_REVISION
from quasisim.sim.types import Params

HORIZONS = (6, 10)  # frames of the final trajectories' windows (the sampled ones have the recorded horizon)
PREDICTORS = ("zero motion", "nominal", "world model")
# variants (--decompose: all of them): the nominal simulator with one group of constants changed at a time
# (which error each moves)
VARIANTS: dict[str, Callable[[Params], Params]] = {
    "normal force x3": lambda p: p.replace(contact_scale=p.contact_scale * 3.0),
    "normal force x1/3": lambda p: p.replace(contact_scale=p.contact_scale / 3.0),
    "friction x2": lambda p: p.replace(mu=p.mu * 2.0),
    "friction x1/2": lambda p: p.replace(mu=p.mu * 0.5),
    "object surface +2 mm": lambda p: p.replace(d_c=p.d_c + 0.002),
    "mass and inertia x2": lambda p: p.replace(obj_mass=p.obj_mass * 2.0, obj_inertia=p.obj_inertia * 2.0),
    "hand gains x2": lambda p: p.replace(joint_kp=p.joint_kp * 2.0, joint_kv=p.joint_kv * 2.0),
}
# variants: the nominal simulator built another way (SimOptions), by its settings
MODEL_VARIANTS = {"table on mesh samples": {"table_points": "surface"}}


def window_errors(w: ClipWindows, pred: dict[str, np.ndarray] | None) -> dict[str, list[float]]:
    """Mean errors after each frame h = 1..H over the windows: object position (cm), rotation (deg) and
    keypoints (mm), and the median position and rotation errors after the last frame; ``pred`` None: zero
    motion (keypoints not predicted)."""
    H = w.horizon
    if pred is None:
        pred = {"obj_pos": np.repeat(w.obj_pos[:, :1], H, 1), "obj_quat": np.repeat(w.obj_quat[:, :1], H, 1)}
    pos_w = np.linalg.norm(pred["obj_pos"] - w.obj_pos[:, 1:], axis=-1) * 100.0
    rot_w = quat_angle_deg(pred["obj_quat"], w.obj_quat[:, 1:])
    pos, rot = pos_w.mean(0), rot_w.mean(0)
    kp = (
        np.linalg.norm(pred["keypoints"] - w.keypoints[:, 1:], axis=-1).mean((0, 2)) * 1000.0
        if "keypoints" in pred
        else np.full(H, np.nan)
    )
    med = {"pos_cm_med": float(np.median(pos_w[:, -1])), "rot_deg_med": float(np.median(rot_w[:, -1]))}
    return {"pos_cm": pos.tolist(), "rot_deg": rot.tolist(), "kp_mm": kp.tolist(), **med}


def clip_rows(
    path: Path, data_dir: Path, model: WorldModel | None, variants: tuple[str, ...] = (),
    horizons: tuple[int, ...] = HORIZONS,
) -> list[dict[str, Any]]:  # fmt: skip
    """Every set of windows x predictor of one clip (module docstring; without ``model`` zero motion and the
    nominal simulator); ``variants``: also these of the :data:`VARIANTS` and :data:`MODEL_VARIANTS` of the
    nominal simulator, on the shortest final windows and the sampled ones."""
    prob = clip_problem(path, data_dir, SIMULATOR["substeps"], SIMULATOR["n_candidates"])
    params = stiffest_params(prob)
    cfg = model.cfg if model is not None else WorldModelConfig()
    variant_probs = {
        name: clip_problem(path, data_dir, SIMULATOR["substeps"], SIMULATOR["n_candidates"], **opts)
        for name, opts in MODEL_VARIANTS.items()
        if name in variants
    }
    rows = []
    for kind, H in [*(("final", h) for h in horizons), ("sampled", 0)]:
        w = load_clip(path, prob, kind, horizon=H, per_step=cfg.per_step, seed=cfg.seed + 1)
        predictors = PREDICTORS if model is not None else PREDICTORS[:2]
        names = [*predictors, *(variants if kind == "sampled" or H == min(horizons) else ())]
        prepared = batch(w)  # the simulator's inputs, shared by every predictor of these windows
        for name in names:
            t0 = time.perf_counter()
            par = VARIANTS[name](params) if name in VARIANTS else params
            net = model.net if name == "world model" and model is not None else None
            wv = dataclasses.replace(w, prob=variant_probs[name]) if name in variant_probs else w
            prep = batch(wv) if name in variant_probs else prepared
            pred = None if name == "zero motion" else predict(par, net, wv, cfg, prepared=prep)
            e = window_errors(w, pred)
            rows.append({
                "clip": w.demo, "windows": f"{kind} {w.horizon}", "n": len(w), "predictor": name, **e,
                "pos_cm_H": e["pos_cm"][-1], "rot_deg_H": e["rot_deg"][-1], "kp_mm_H": e["kp_mm"][-1],
                "wall_s": round(time.perf_counter() - t0, 2),
            })  # fmt: skip
    return rows


def run_world_bench(
    folder: Path,
    data_dir: Path,
    model_path: Path | None,
    out: Path,
    clip_names: tuple[str, ...] = (),
    variants: tuple[str, ...] = (),
    horizons: tuple[int, ...] = HORIZONS,
) -> str:
    """The table of the module docstring for ``clip_names`` (default: the model's held-out clips, or
    :data:`~quasisim.method.transitions.HELD_OUT` without a model)."""
    model, names, files = held_out_files(folder, model_path, clip_names)
    trained = sorted(set(names) & set(model.info["trained_on"])) if model is not None else []
    key = {
        "model_sha256": file_sha256(model_path) if model_path is not None else None,
        "horizons": list(horizons), "simulator_revision": SIMULATOR_REVISION,
    }  # fmt: skip
    rows = rows_per_clip(
        names, files, out, key, lambda path: clip_rows(path, data_dir, model, variants, horizons), variants
    )
    return publish(out, "world", rows, _markdown(rows, model, model_path, trained))


def held_out_files(
    folder: Path, model_path: Path | None, clip_names: tuple[str, ...]
) -> tuple[WorldModel | None, tuple[str, ...], dict[str, Path]]:
    """The world model of ``model_path`` (or None), the clips to measure (``clip_names``, default: the
    model's held-out clips, or :data:`~quasisim.method.transitions.HELD_OUT` without a model) and the
    transitions file of every clip under ``folder``; an error names the clips without one."""
    model = WorldModel.load(model_path) if model_path is not None else None
    names = clip_names or (tuple(model.info["held_out"]) if model is not None else HELD_OUT)
    files = {read_meta(f)[0]: f for f in transition_files(folder)}
    missing = [n for n in names if n not in files]
    if missing:
        raise QuasisimError(f"{folder}: no recorded transitions of {', '.join(missing)}")
    return model, names, files


def rows_per_clip(
    names: tuple[str, ...], files: dict[str, Path], out: Path, key: dict[str, Any],
    compute: Callable[[Path], list[dict[str, Any]]], variants: tuple[str, ...] = (),
) -> list[dict[str, Any]]:  # fmt: skip
    """Every clip's rows, in order: kept in ``OUT/clips/<clip>.json`` with ``key`` and the transitions file's
    sha256, and reused from there by a later run with the same (and ``variants`` among its predictors), else
    ``compute(transitions file)``."""
    per_clip = out / "clips"
    per_clip.mkdir(parents=True, exist_ok=True)
    rows: list[dict[str, Any]] = []
    for name in tqdm(names, desc="clips", unit="clip"):
        clip_key = {**key, "transitions_sha256": file_sha256(files[name])}
        cached = _cached(per_clip / f"{name}.json", clip_key, variants)
        if cached is None:
            free_compiled_programs()
            cached = compute(files[name])
            save_json_atomic(per_clip / f"{name}.json", {**clip_key, "rows": cached})
        rows += cached
    return rows


def _cached(path: Path, key: dict[str, Any], variants: tuple[str, ...]) -> list[dict[str, Any]] | None:
    """A clip's rows from an earlier run of the same model on the same transitions (with ``variants``
    among them), else None."""
    try:
        d = json.loads(path.read_text())
        ok = all(d.get(k) == v for k, v in key.items())
        rows = d["rows"] if ok else None
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None
    if rows is None or not set(variants) <= {r["predictor"] for r in rows}:
        return None
    return rows


def _markdown(rows: list[dict[str, Any]], model: WorldModel | None, path: Path | None, trained: list[str]) -> list[str]:
    about = (
        f"Model `{path.name}`: trained on {len(model.info['trained_on'])} clips ({model.info['n_pairs']} frames); "
        f"clips here that it was trained on: {', '.join(trained) or 'none'}."
        if model is not None and path is not None
        else "No world model: the nominal simulator and zero motion."
    )
    lines = [
        header(f"World model prediction against MuJoCo ({model.info['hand'] if model is not None else 'nominal'})"),
        f"{about} Simulator revision {SIMULATOR_REVISION}. Errors after the window's last "
        "frame, mean over windows; zero motion: the object stays where it was.",
        "",
        "| clip | windows | n | predictor | object pos (cm) | object rot (deg) | keypoints (mm) | median pos (cm) | "
        "median rot (deg) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['clip']} | {r['windows']} | {r['n']} | {r['predictor']} | {r['pos_cm_H']:.2f} | "
            f"{r['rot_deg_H']:.2f} | {r['kp_mm_H']:.1f} | {r['pos_cm_med']:.2f} | {r['rot_deg_med']:.2f} |"
        )
    lines += ["", "Summary (mean over clips):", "", "| windows | predictor | object pos (cm) | object rot (deg) | "
              "keypoints (mm) | pos / nominal | rot / nominal | median pos (cm) | median rot (deg) |",
              "|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for label in dict.fromkeys(r["windows"] for r in rows):
        sel = [r for r in rows if r["windows"] == label]
        preds = list(dict.fromkeys(r["predictor"] for r in sel))
        mean = {p: {k: float(np.mean([r[k] for r in sel if r["predictor"] == p])) for k in ("pos_cm_H", "rot_deg_H", "kp_mm_H", "pos_cm_med", "rot_deg_med")}
                for p in preds}  # fmt: skip
        for p in preds:
            m, n = mean[p], mean["nominal"]
            lines.append(
                f"| {label} | {p} | {m['pos_cm_H']:.2f} | {m['rot_deg_H']:.2f} | {m['kp_mm_H']:.1f} | "
                f"{m['pos_cm_H'] / n['pos_cm_H']:.2f} | {m['rot_deg_H'] / n['rot_deg_H']:.2f} | "
                f"{m['pos_cm_med']:.2f} | {m['rot_deg_med']:.2f} |"
            )
    return lines


def run_window_speed(path: Path, data_dir: Path, n: int, chunks: tuple[int, ...], out: Path) -> str:
    """Open-loop prediction speed of the nominal stiffest simulator on ``n`` sampled windows of one
    transitions file, in batches (``chunks``: windows per compiled call), on JAX's default device: the first
    pass (compiling) and a second one (compiled), windows per second."""
    import jax

    from quasisim.method.world_model import WorldModelConfig

    prob = clip_problem(path, data_dir, SIMULATOR["substeps"], SIMULATOR["n_candidates"])
    params = stiffest_params(prob)
    w = load_clip(path, prob, "sampled", per_step=10**6)
    n = min(n, len(w))
    w = w.first(n)
    device = str(jax.devices()[0])
    rows = []
    for c in tqdm(chunks, desc="batch sizes", unit="size"):
        times = []
        for _ in range(2):
            t0 = time.perf_counter()
            predict(params, None, w, WorldModelConfig(), chunk=c)
            times.append(time.perf_counter() - t0)
        rows.append({"clip": w.demo, "device": device, "windows": n, "horizon": w.horizon, "batch": c,
                     "first_s": times[0], "second_s": times[1], "windows_per_s": n / times[1]})  # fmt: skip
    lines = [
        header(f"Quasi-physical window prediction speed ({w.horizon}-frame windows, {device})"),
        f"{n} sampled windows of `{w.demo}` predicted open loop by the stiffest simulator ({SIMULATOR['substeps']} "
        "substeps per frame), in compiled batches of the given size; first pass includes compiling.",
        "",
        "| batch | first pass (s) | second pass (s) | windows / s | ms per window |",
        "|---|---|---|---|---|",
    ]
    lines += [f"| {r['batch']} | {r['first_s']:.1f} | {r['second_s']:.2f} | {r['windows_per_s']:.1f} | "
              f"{1000.0 / r['windows_per_s']:.1f} |" for r in rows]  # fmt: skip
    return publish(out, "windows", rows, lines)
