"""How much grasp margin a finished run's plan holds, and whether that tells which plans survive perturbed
worlds (``quasisim bench grasp RUNS``): each run's controls replayed once in its nominal MuJoCo target, per
frame the load its hand-object contacts carry beyond friction cones shrunk by ``margin``
(:func:`quasisim.targets.grasp.slack_excess`, in object weights), beside the run's open-loop robust strict
success from its closed-loop caches (``bench transfer --closed-loop``); over the clips, Spearman's rank
correlation of the two.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

CONTROLS = "controls.npz"


def replay_excess(demo: Any, controls: Any, run_dir: Path, margin: float, slots: int) -> np.ndarray:
    """(T - 1,) per frame the excess load (object weights) of the run's controls replayed in its nominal MuJoCo
    target, each hand's ``slots`` strongest contacts."""
    from quasisim.eval.evaluate import hands_of
    from quasisim.targets import make_target
    from quasisim.targets.build import scene_for
    from quasisim.targets.grasp import slack_excess
    from quasisim.targets.scene import place_hands

    scene = scene_for(demo, place_hands(hands_of(controls, run_dir), controls.base_rots))
    q = controls.q_targets
    out = np.zeros(len(q) - 1)
    with make_target("mujoco", scene) as tgt:
        tgt.reset(q[0], (q[1] - q[0]) * scene.fps)
        for t in range(len(q) - 1):
            tgt.advance(q[t], q[t + 1])
            out[t] = slack_excess(tgt.contact_cones(slots), margin)
    return out


def open_loop_robust(run_dir: Path, set_name: str) -> float | None:
    """The run's open-loop robust strict success in the perturbation set ``set_name`` from any of its
    closed-loop caches of that set (open loop does not depend on the tracker); None without one."""
    for cache in sorted(run_dir.glob("robust_closed_loop-*.json")):
        data = json.loads(cache.read_text())
        sets = data.get("settings", {}).get("sets", {})
        if set_name in sets:
            return float(data["metrics"][sets[set_name]["name"]]["strict"])
    return None


def grasp_rows(
    root: Path, data_dir: Path, margin: float, slots: int, set_name: str = "default"
) -> list[dict[str, Any]]:
    """Per finished run under ``root`` (``<clip>/<run>/controls.npz``): clip, run, the mean, 90th percentile
    and largest excess per frame, the share of frames with any, and the open-loop robust strict success."""
    from quasisim.data.controls import load_controls
    from quasisim.data.run_demo import RunDemos
    from quasisim.errors import QuasisimError

    runs = sorted(p.parent for p in root.glob(f"*/*/{CONTROLS}"))
    if not runs:
        raise QuasisimError(f"{root}: no finished runs (<clip>/<run>/{CONTROLS}); expected a bench transfer folder")
    demos, rows = RunDemos((data_dir,), root), []
    for run_dir in runs:
        ex = replay_excess(demos.find(run_dir), load_controls(run_dir / CONTROLS), run_dir, margin, slots)
        rows.append({
            "clip": run_dir.parent.name, "run": run_dir.name, "mean": float(ex.mean()),
            "p90": float(np.percentile(ex, 90)), "max": float(ex.max()), "frames": float(np.mean(ex > 0)),
            "robust_strict_open": open_loop_robust(run_dir, set_name),
        })  # fmt: skip
    return rows


def rank_correlation(rows: list[dict[str, Any]]) -> tuple[float, int]:
    """Spearman's rho of the mean excess and the open-loop robust strict success over the rows that have both,
    and how many (nan below 3)."""
    from scipy.stats import spearmanr

    pairs = [(r["mean"], r["robust_strict_open"]) for r in rows if r["robust_strict_open"] is not None]
    if len(pairs) < 3:
        return float("nan"), len(pairs)
    rho = spearmanr(*zip(*pairs, strict=True)).statistic
    return float(rho), len(pairs)


def grasp_markdown(rows: list[dict[str, Any]], margin: float, set_name: str) -> str:
    """Per run its excess (object weights) and open-loop robust strict, then the summary."""
    pct = lambda v: "-" if v is None else f"{100 * v:.0f}"  # noqa: E731
    lines = [
        f"Excess load per frame (object weights) beyond friction cones shrunk by {margin:g}, nominal MuJoCo replay; "
        f"open-loop robust strict (%) in the {set_name} worlds.",
        "",
        "| clip | run | mean | p90 | max | frames with excess (%) | robust strict open (%) |",
        "|---|---|---|---|---|---|---|",
    ]
    lines += [
        f"| {r['clip']} | {r['run']} | {r['mean']:.2f} | {r['p90']:.2f} | {r['max']:.2f} | {100 * r['frames']:.0f} | "
        f"{pct(r['robust_strict_open'])} |"
        for r in rows
    ]
    rho, n = rank_correlation(rows)
    lines += ["", f"Runs: {len(rows)}; mean excess over them {np.mean([r['mean'] for r in rows]):.2f}; Spearman rho "
              f"of mean excess and open-loop robust strict: {rho:.2f} over {n} runs."]  # fmt: skip
    return "\n".join(lines) + "\n"
