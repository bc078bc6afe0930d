"""``quasisim bench fit``: how well the fitted quasi-physical simulator predicts MuJoCo on windows the fit
never saw (stage 3's measure), per clip and in summary: the analytical nominal simulator, + S and the
contact/joint constants, + residual networks (local only, global only, both), + the control
transformation (alone, and with both residual networks), beside zero motion.
Resumable: each finished clip's rows are kept in ``OUT/clips/<clip>.json``."""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Any

from tqdm import tqdm

from quasisim.data.demo import load_demo
from quasisim.eval.tables import clips, header, prediction_summary, publish
from quasisim.files import save_json_atomic
from quasisim.method import replay
from quasisim.method.config import TransferConfig
from quasisim.method.curriculum import load_curriculum
from quasisim.method.problem import kinematic_problem
from quasisim.method.stages import fit_to_target
from quasisim.runtime import free_compiled_programs
from quasisim.sim.residual import ResidualConfig

# row name -> the networks trained on top of S and the constants
NETWORK_ROWS = {
    "+residual local": ("local",), "+residual global": ("global",), "+residual both": ("local", "global"),
    "+control transformation": ("control",), "+residual both, control transformation": ("local", "global", "control"),
}  # fmt: skip
VARIANTS = ("nominal", "+S, constants", *NETWORK_ROWS)


def fit_clip(demo_path: Path, hand_name: str, cfg: TransferConfig, residual: bool) -> list[dict[str, Any]]:
    """Rows (one per simulator variant) of one clip: held-out H-frame errors, fit losses, seconds."""
    o, bud = cfg.stage3, cfg.budget("fast")
    demo = load_demo(demo_path)
    prob, q_kin = kinematic_problem(demo, hand_name, bud.substeps, bud.n_candidates)
    cur = load_curriculum("default")
    p0 = prob.params(cur.contact(cur.stiffest))
    t0 = time.perf_counter()
    train, test, _ = fit_to_target.fit_windows(prob, q_kin, o, cfg.sampling)
    w = cfg.weights.arrays()
    args = (demo.fps, prob.base_quat)
    t_collect = time.perf_counter() - t0
    sim_fit, losses = fit_to_target.fit(prob.model, p0, train, *args, prob.obj.mass, prob.obj.inertia, o, w)
    p_fit = sim_fit.apply(p0, prob.obj.mass, prob.obj.inertia)
    t_fit = time.perf_counter() - t0 - t_collect
    variants: dict[str, tuple[Any, Any, list[float], float]] = {
        "nominal": (prob.model, p0, [], 0.0), "+S, constants": (prob.model, p_fit, losses, t_fit),
    }  # fmt: skip
    if residual and o.residual_steps > 0:
        for name, nets in NETWORK_ROWS.items():
            t1 = time.perf_counter()
            m, p, ls = fit_to_target.fit_networks(prob.model, p_fit, train, *args, o, w, ResidualConfig(), nets)
            variants[name] = (m, p, ls, time.perf_counter() - t1)
    rows = []
    for name, (m, p, ls, secs) in variants.items():
        e = replay.prediction_errors(m, p, test, *args)
        rows.append(
            {"clip": demo.name, "simulator": name, "obj_pos_cm": float(e.obj_pos_cm[-1]),
             "obj_rot_deg": float(e.obj_rot_deg[-1]), "keypoints_mm": float(e.keypoints_mm[-1]),
             "static_pos_cm": float(e.static_pos_cm[-1]), "static_rot_deg": float(e.static_rot_deg[-1]),
             "n_windows": e.n_windows, "n_diverged": e.n_diverged, "n_train": len(train),
             "loss_first": ls[0] if ls else None, "loss_last": ls[-1] if ls else None, "fit_s": secs,
             "collect_s": t_collect, "fitted": sim_fit.describe(prob.obj.mass) if name != "nominal" else None}
        )  # fmt: skip
    return rows


def run_fit_bench(
    data_dir: Path, clip_names: tuple[str, ...], pattern: str, hand_name: str, out: Path, residual: bool,
    overrides: dict[str, Any] | None = None,
) -> str:  # fmt: skip
    """:func:`fit_clip` on every clip; prints and writes the markdown table (per clip, then the summary)."""
    paths = clips(data_dir, pattern, clip_names)
    cfg = TransferConfig.from_yaml(overrides=overrides)
    settings = {"stage3": dataclasses.asdict(cfg.stage3), "residual": residual, "hand": hand_name}
    rows: list[dict[str, Any]] = []
    for p in tqdm(paths, desc="clips", unit="clip"):
        free_compiled_programs()
        done = out / "clips" / f"{p.stem}.json"  # a finished clip is read back (same settings), never redone
        cached = json.loads(done.read_text()) if done.is_file() else None
        if cached is None or cached["settings"] != settings:
            cached = {"settings": settings, "rows": fit_clip(p, hand_name, cfg, residual)}
            save_json_atomic(done, cached)
        rows += cached["rows"]
    return publish(out, "fit", rows, _markdown(rows, cfg, hand_name))


def _markdown(rows: list[dict[str, Any]], cfg: TransferConfig, hand: str) -> list[str]:
    o = cfg.stage3
    lines = [
        header(f"Stage 3: {o.horizon}-frame prediction error of the fitted simulator against MuJoCo ({hand})"),
        f"Buffer: the kinematic retarget and {o.variants} noisy variants rolled out in MuJoCo; fit on windows "
        f"ending before the last {100 * o.held_out:.0f} % of each clip; errors after {o.horizon} frames on the "
        "held-out windows of the kinematic retarget's rollout (never seen by the fit). Zero motion: the object "
        f"stays where it was. Fit settings: {dataclasses.asdict(o)}.",
        "",
        "| clip | simulator | object pos (cm) | object rot (deg) | keypoints (mm) | zero-motion pos (cm) | zero-motion rot (deg) | held-out windows | fit s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['clip']} | {r['simulator']} | {r['obj_pos_cm']:.2f} | {r['obj_rot_deg']:.1f} | {r['keypoints_mm']:.1f} | "
            f"{r['static_pos_cm']:.2f} | {r['static_rot_deg']:.1f} | {r['n_windows'] - r['n_diverged']} | {r['fit_s']:.0f} |"
        )
    return [*lines, "", *prediction_summary(rows)]
