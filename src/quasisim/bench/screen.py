"""``quasisim bench screen``: could the quasi-physical simulator pre-screen the sampling stage's candidates?

At every step of the control loop the sampling stage rolls ``N`` candidate windows out in the target and
applies the cheapest (:mod:`quasisim.method.stages.sampling`). Pre-screening (issue "world model", point 4b) would
roll many candidates out in the simulator and send only its ``k`` cheapest to the target. Whether that can
pay is measured here offline, on recorded transitions (``--record-transitions``), step by step:

* every recorded candidate of every step is predicted open loop by a predictor (the nominal stiffest
  simulator; the world model of ``--model``) from the target's state the step started from, and scored with
  the sampling stage's own window cost (:func:`quasisim.method.stages.sampling.window_costs`) against the demo;
* the target's costs are computed again from the recorded rollouts the same way and must equal the recorded
  ones (a check on the frames and references; a mismatch stops the run);
* for ``k`` in ``--top``: the target's cost of the best of the predictor's ``k`` cheapest candidates, as a
  normalised regret ``(c_sel - c_min) / (c_mean - c_min)`` per step (0: the target's best of all ``N``;
  1: a candidate drawn at random), beside the exact expectation for ``k`` candidates drawn at random (what
  sampling only ``k`` in the target gives); the fraction of steps where the target's best is among the
  predictor's ``k``; the rank correlation of the predictor's and the target's costs.
* wall time per window of the predictor (compiled, batches of 64) and of the target (MuJoCo, the sampling
  stage's threads), the same windows, in this process.

So ``k = N/2`` at "regret near 0" would mean half the target rollouts for the same choice, if the
simulator's windows cost less than the target's.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np

from quasisim.bench.tables import header, publish
from quasisim.bench.world import held_out_files, rows_per_clip
from quasisim.errors import QuasisimError
from quasisim.files import file_sha256
from quasisim.method.config import TransferConfig
from quasisim.method.problem import Problem
from quasisim.method.stages.sampling import kinematic_keypoints, window_costs
from quasisim.method.transitions import ClipWindows, Steps, clip_problem, load_candidates
from quasisim.method.world_fit import SIMULATOR, stiffest_params
from quasisim.method.world_model import WorldModel, WorldModelConfig, predict
from quasisim.optim.objective import window_references
from quasisim.sim.build import SIMULATOR_REVISION
from quasisim.targets.base import Prediction

TOP = (1, 3, 6, 12)  # the predictor's k cheapest candidates sent to the target
COST_RTOL = 1e-4  # recomputed against recorded target costs (both float32 objectives of the same inputs)
CHUNK = 64  # windows per compiled call (the fastest of bench windows on 2 cores)


def step_costs(
    w: ClipWindows, steps: Steps, pred: dict[str, np.ndarray], cfg: TransferConfig, object_only: bool = False
) -> np.ndarray:
    """(S, N) the sampling stage's window cost of every candidate of every step, with the object poses and
    keypoints ``pred`` ((S N, H, ...), step by step) in place of the target's; ``object_only``: only its
    object terms (translation and rotation)."""
    prob, H = w.prob, w.horizon
    S, N = steps.costs.shape
    sc = prob.scene
    ref_pos, ref_quat, ref_kp = window_references(prob.demo, sc.kp_human, np.flatnonzero(sc.kp_metric), H)
    wins = w.q_targets.reshape(S, N, *w.q_targets.shape[1:])
    weights = dataclasses.replace(cfg.weights, hand=0.0, smooth=0.0) if object_only else cfg.weights
    strict = (0.0 if object_only else cfg.sampling.strict_weight, cfg.sampling.strict_margin)
    out = np.zeros((S, N))
    for s, t in enumerate(steps.frames):
        rows = slice(s * N, (s + 1) * N)
        p = Prediction(
            qpos=w.qpos[rows, 1:], obj_pos=pred["obj_pos"][rows], obj_quat=pred["obj_quat"][rows],
            keypoints=pred["keypoints"][rows], n_steps=0,
        )  # fmt: skip
        w_ = slice(t + 1, t + H + 1)
        frame_w = (np.arange(t + 1, t + H + 1) < steps.n_frames).astype(np.float64)
        out[s] = window_costs(wins[s], p, ref_pos[w_], ref_quat[w_], ref_kp[w_], frame_w, weights, None, strict)
    return out


def kinematic_prediction(w: ClipWindows) -> dict[str, np.ndarray]:
    """The cheapest predictor, no physics: the hands exactly at their PD targets (the sampling stage's
    pre-screen, :func:`~quasisim.method.stages.sampling.kinematic_keypoints`), the object still at its start pose."""
    return {**object_still(w), "keypoints": kinematic_keypoints(w.prob.scene)(w.q_targets[:, 1:])}


def object_still(w: ClipWindows) -> dict[str, np.ndarray]:
    """The object at its start pose at every frame of every window."""
    H = w.horizon
    return {"obj_pos": np.repeat(w.obj_pos[:, :1], H, 1), "obj_quat": np.repeat(w.obj_quat[:, :1], H, 1)}


def random_regret(c: np.ndarray, k: int) -> float:
    """The expected normalised regret (module docstring) of the best of ``k`` of the costs ``c`` (N,) drawn
    at random without replacement: the i-th cheapest (0-based) is the best of the draw with probability
    C(N - 1 - i, k - 1) / C(N, k)."""
    from math import comb

    c = np.sort(c)
    n, span = len(c), float(np.mean(c) - c[0])
    if span <= 0.0:
        return 0.0
    p = np.array([comb(n - 1 - i, k - 1) for i in range(n)], np.float64) / comb(n, k)
    return float(np.dot(p, c) - c[0]) / span


def rank_correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Mean over rows of Spearman's rank correlation of ``a`` and ``b`` (S, N), over the rows where both vary
    (NaN where none does)."""
    rank = lambda x: np.argsort(np.argsort(x, axis=1), axis=1).astype(np.float64)  # noqa: E731
    live = (np.ptp(a, axis=1) > 0) & (np.ptp(b, axis=1) > 0)
    if not live.any():
        return float("nan")
    ra, rb = rank(a[live]), rank(b[live])
    ra, rb = ra - ra.mean(1, keepdims=True), rb - rb.mean(1, keepdims=True)
    return float(np.mean(np.sum(ra * rb, 1) / np.sqrt(np.sum(ra**2, 1) * np.sum(rb**2, 1))))


def selection(c_target: np.ndarray, c_pred: np.ndarray, top: tuple[int, ...]) -> dict[str, float]:
    """Means over steps of the measures of the module docstring, for costs (S, N) in the target and as
    predicted."""
    S, N = c_target.shape
    out: dict[str, float] = {"spearman": rank_correlation(c_target, c_pred)}
    lo, span = c_target.min(1), c_target.mean(1) - c_target.min(1)
    order = np.argsort(c_pred, axis=1)
    best = np.argmin(c_target, axis=1)
    for k in top:
        if k > N:
            continue
        picked = np.take_along_axis(c_target, order[:, :k], 1).min(1)
        out[f"regret_{k}"] = float(np.mean(np.where(span > 0, (picked - lo) / np.where(span > 0, span, 1.0), 0.0)))
        out[f"random_{k}"] = float(np.mean([random_regret(c, k) for c in c_target]))
        out[f"hit_{k}"] = float(np.mean([best[s] in order[s, :k] for s in range(S)]))
    return out


def target_seconds_per_window(prob: Problem, w: ClipWindows, steps: Steps, n_steps: int, threads: int) -> float:
    """MuJoCo's wall time per window rolling out the candidates of the first ``n_steps`` steps (each from the
    scene's initial state with the step's first PD targets: the cost of a rollout, not its result)."""
    from quasisim.targets import make_target

    N = steps.costs.shape[1]
    wins = w.q_targets.reshape(-1, N, *w.q_targets.shape[1:])[:n_steps]
    with make_target("mujoco", prob.scene, threads=threads) as target:
        t0 = time.perf_counter()
        for win in wins:
            target.reset(win[0, 0])
            target.rollout_windows(win, None)
        return (time.perf_counter() - t0) / (len(wins) * N)


def clip_rows(path: Path, data_dir: Path, model: WorldModel | None, top: tuple[int, ...]) -> list[dict[str, Any]]:
    """One row per predictor of one clip (module docstring)."""
    prob = clip_problem(path, data_dir, SIMULATOR["substeps"], SIMULATOR["n_candidates"])
    cfg = TransferConfig.from_yaml()
    w, steps = load_candidates(path, prob)
    target_pred = {"obj_pos": w.obj_pos[:, 1:], "obj_quat": w.obj_quat[:, 1:], "keypoints": w.keypoints[:, 1:]}
    c_target = step_costs(w, steps, target_pred, cfg)
    o_target = step_costs(w, steps, target_pred, cfg, object_only=True)
    err = float(np.max(np.abs(c_target - steps.costs) / np.maximum(np.abs(steps.costs), 1e-6)))
    if err > COST_RTOL:
        raise QuasisimError(
            f"{path}: the target's window costs computed again differ from the recorded ones by {err:.2e} "
            f"(relative, more than {COST_RTOL:g}): the steps' frames or the settings do not match the recording"
        )
    params = stiffest_params(prob)
    wm_cfg = model.cfg if model is not None else WorldModelConfig()
    mujoco_s = target_seconds_per_window(prob, w, steps, min(5, len(steps.frames)), cfg.sampling.threads)
    preds: dict[str, tuple[dict[str, np.ndarray], float]] = {}
    t0 = time.perf_counter()  # the kinematic predictor's time includes compiling it
    preds["kinematic, object still"] = kinematic_prediction(w), (time.perf_counter() - t0) / len(w)
    for name, net in {"nominal": None, **({"world model": model.net} if model is not None else {})}.items():
        predict(params, net, w.first(CHUNK), wm_cfg, chunk=CHUNK)
        t0 = time.perf_counter()
        preds[name] = predict(params, net, w, wm_cfg, chunk=CHUNK), (time.perf_counter() - t0) / len(w)
        if name == "nominal":  # its hands, the object still: what its object physics adds to the ranking
            preds["nominal hands, object still"] = {**preds[name][0], **object_still(w)}, preds[name][1]
    rows = []
    for name, (pred, sec) in preds.items():
        rows.append({
            "clip": w.demo, "predictor": name, "steps": len(steps.frames), "candidates": steps.costs.shape[1],
            **selection(c_target, step_costs(w, steps, pred, cfg), top),
            "object_rank": rank_correlation(o_target, step_costs(w, steps, pred, cfg, object_only=True)),
            "s_per_window": sec,
            "target_s_per_window": mujoco_s, "cost_check": err,
        })  # fmt: skip
    return rows


def run_screen_bench(
    folder: Path, data_dir: Path, model_path: Path | None, out: Path, clip_names: tuple[str, ...] = (),
    top: tuple[int, ...] = TOP,
) -> str:  # fmt: skip
    """The table of the module docstring for ``clip_names`` (default: the model's held-out clips, or
    :data:`~quasisim.method.transitions.HELD_OUT`); each clip's rows are kept in ``OUT/clips/`` and reused
    for the same model, transitions file and ``top``."""
    model, names, files = held_out_files(folder, model_path, clip_names)
    key: dict[str, Any] = {
        "model_sha256": file_sha256(model_path) if model_path is not None else None, "top": list(top),
        "simulator_revision": SIMULATOR_REVISION,
    }  # fmt: skip
    rows = rows_per_clip(names, files, out, key, lambda path: clip_rows(path, data_dir, model, top))
    return publish(out, "screen", rows, _markdown(rows, top, model_path))


def _markdown(rows: list[dict[str, Any]], top: tuple[int, ...], model_path: Path | None) -> list[str]:
    ks = [k for k in top if f"regret_{k}" in rows[0]]
    n = rows[0]["candidates"]
    cols = " | ".join(f"top {k}: regret / random / best in" for k in ks)
    lines = [
        header("Pre-screening sampled candidates in the simulator (shadow, MuJoCo)"),
        f"{n} candidates per step, simulator revision {SIMULATOR_REVISION}"
        + (f", world model `{model_path.name}`" if model_path is not None else "")
        + ". Regret of the best of the predictor's k cheapest, judged in the target: 0 = the target's best of "
        f"all {n}, 1 = one drawn at random; random: k drawn at random (sampling only k in the target); best in: "
        "steps whose best candidate is among the predictor's k. Rank: Spearman correlation of the costs; object "
        "rank: of their object terms alone (none where the predictor holds the object still). "
        "Time per window: the predictor (compiled, batches of 64) and MuJoCo, in one process.",
        "",
        f"| clip | predictor | steps | rank | object rank | {cols} | ms per window | MuJoCo ms per window |",
        "|---|---|---|---|---|" + "---|" * len(ks) + "---|---|",
    ]

    def line(label: str, pred: str, r: dict[str, float], steps: str) -> str:
        cells = " | ".join(f"{r[f'regret_{k}']:.2f} / {r[f'random_{k}']:.2f} / {100 * r[f'hit_{k}']:.0f} %" for k in ks)
        return (
            f"| {label} | {pred} | {steps} | {r['spearman']:.2f} | {r['object_rank']:.2f} | {cells} | {1000 * r['s_per_window']:.1f} | "
            f"{1000 * r['target_s_per_window']:.1f} |"
        )

    for r in rows:
        lines.append(line(r["clip"], r["predictor"], r, str(r["steps"])))
    for pred in dict.fromkeys(r["predictor"] for r in rows):
        sel = [r for r in rows if r["predictor"] == pred]
        keys = [k for k in sel[0] if isinstance(sel[0][k], float)]
        mean = {k: float(np.nanmean([r[k] for r in sel])) if any(np.isfinite(r[k]) for r in sel) else float("nan")
                for k in keys}  # fmt: skip
        lines.append(line(f"**mean of {len(sel)} clips**", pred, mean, str(sum(r["steps"] for r in sel))))
    return lines
