"""How far from the planned world a run's controls still work: robust success at fractions of the perturbation
ranges (``quasisim bench sensitivity``).

Robust success (:mod:`quasisim.eval.robust`) replays a run's PD targets open loop in ``n`` perturbed copies of
its target with the ranges of ``configs/robust.yaml``. Here the same replays are made with every range times
each of ``scales`` (0: the unperturbed target, every replay the run itself; 1: the judged ranges), so a table
shows whether a run fails under a perturbation of a physical size (a heavier object slipping out of a weak
grasp) or under any perturbation at all (a trajectory whose outcome the smallest change decides).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np

from quasisim.eval.robust import RobustConfig

RANGES = ("mass", "friction", "pd_gains", "object_pos")


def scaled(cfg: RobustConfig, scale: float) -> RobustConfig:
    """``cfg`` with every perturbation range times ``scale`` (>= 0; the relative ranges must stay below 1)."""
    return dataclasses.replace(cfg, **{k: getattr(cfg, k) * scale for k in RANGES})


def run_rows(run_dir: Path, demo: Any, cfg: RobustConfig, scales: tuple[float, ...]) -> dict[str, Any]:
    """One finished run (MuJoCo): its strict and 20 / 20 success fractions over ``cfg.n`` perturbed replays at
    each scale of the ranges."""
    from quasisim.data.controls import load_controls
    from quasisim.eval.evaluate import hands_of
    from quasisim.eval.failures import run_method
    from quasisim.eval.robust import robust_success
    from quasisim.targets.build import scene_for
    from quasisim.targets.scene import place_hands

    controls = load_controls(run_dir / "controls.npz")
    scene = scene_for(demo, place_hands(hands_of(controls, run_dir), controls.base_rots))  # as evaluate_controls
    row: dict[str, Any] = {"clip": demo.name, "method": run_method(run_dir), "run": str(run_dir), "n": cfg.n}
    for s in scales:
        r = robust_success(demo, scene, controls.q_targets, "mujoco", scaled(cfg, s))
        row[f"{s:g}"] = {"strict": r["strict"], "20deg_20cm": r["20deg_20cm"], "unstable": r["unstable"]}
    return row


def markdown(rows: list[dict[str, Any]], scales: tuple[float, ...]) -> str:
    """Per run, then the mean per method: strict % / 20-20 % of the replays at each scale."""
    keys = [f"{s:g}" for s in scales]

    def cell(fr: list[dict[str, float]]) -> str:
        return f"{100 * np.mean([f['strict'] for f in fr]):.0f} / {100 * np.mean([f['20deg_20cm'] for f in fr]):.0f}"

    head = "| clip | method | " + " | ".join(f"x{k}" for k in keys) + " |"
    lines = [head, "|---" * (2 + len(keys)) + "|"]
    lines += [f"| {r['clip']} | {r['method']} | " + " | ".join(cell([r[k]]) for k in keys) + " |" for r in rows]
    lines += ["", "| method | runs | " + " | ".join(f"x{k}" for k in keys) + " |", "|---" * (2 + len(keys)) + "|"]
    for m in sorted({r["method"] for r in rows}):
        rs = [r for r in rows if r["method"] == m]
        lines.append(f"| {m} | {len(rs)} | " + " | ".join(cell([r[k] for r in rs]) for k in keys) + " |")
    return "\n".join(lines) + "\n"


def run_sensitivity(root: Path, data_dir: Path, scales: tuple[float, ...], n: int, out: Path) -> str:
    """Every finished run under ``root`` (:func:`quasisim.eval.failures.finished_runs`, demos found in
    ``data_dir``) replayed at each scale; writes ``sensitivity.md`` and ``sensitivity.json`` to ``out``."""
    from tqdm import tqdm

    from quasisim.data.run_demo import RunDemos
    from quasisim.errors import QuasisimError
    from quasisim.eval.failures import finished_runs
    from quasisim.eval.tables import header
    from quasisim.files import save_text_atomic

    runs = finished_runs(root)
    if not runs:
        raise QuasisimError(f"{root}: no finished runs (folders with manifest.json, rollout.npz, scene.xml, "
                            "trajectory.npz, controls.npz)")  # fmt: skip
    cfg, demos = RobustConfig.from_yaml(None, {"n": n}), RunDemos((data_dir,), root)
    rows = [run_rows(d, demos.find(d), cfg, scales) for d in tqdm(runs, desc="sensitivity", unit="run")]
    text = (
        header(f"Robust success at fractions of the perturbation ranges, runs under {root}")
        + f"\n{n} replays per run and scale (configs/robust.yaml ranges x scale); cells: strict % / 20 deg 20 cm %.\n\n"
        + markdown(rows, scales)
    )
    out.mkdir(parents=True, exist_ok=True)
    save_text_atomic(out / "sensitivity.json", json.dumps(rows, indent=1))
    save_text_atomic(out / "sensitivity.md", text)
    return text
