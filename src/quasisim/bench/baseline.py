"""``quasisim bench baseline``: the kinematic retarget replayed with PD control in each target, every clip."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from tqdm import tqdm

from quasisim.data.demo import load_demo
from quasisim.eval.evaluate import evaluate_controls
from quasisim.eval.robust import RobustConfig
from quasisim.eval.tables import CLIP_HEAD, SUMMARY_HEAD, clip_row, clips, header, lifted, publish, summary_rows
from quasisim.method.retarget import kinematic_controls
from quasisim.targets.build import demo_hands, scene_for
from quasisim.targets.scene import place_hands


def run_baseline(
    data_dir: Path, hand_name: str, targets: tuple[str, ...], out: Path, pattern: str, render: bool,
    robust: RobustConfig | None = None,
) -> str:  # fmt: skip
    """Kinematic retargeting replayed with PD control in each target, on every clip (two-hand clips: both
    hands)."""
    rows: list[dict[str, Any]] = []
    paths, robust = clips(data_dir, pattern), robust or RobustConfig.from_yaml()
    for p in tqdm(paths, desc="clips", unit="clip"):
        demo = load_demo(p)
        t0 = time.perf_counter()
        hands = demo_hands(hand_name, demo.sides)
        controls = kinematic_controls(hands, demo, hand_name)
        t_ret = time.perf_counter() - t0
        scene = scene_for(demo, place_hands(hands, controls.base_rots))
        for tgt in targets:
            t1 = time.perf_counter()
            ev = evaluate_controls(
                demo, controls, tgt, out / demo.name / tgt if render else None, render, scene=scene, robust=robust
            )
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
    return publish(out, "baseline", rows, lines)
