"""Does a firmer grasp make a run's controls survive perturbed targets? (issue "strict and robust", point 4)

For every finished run under ROOT (folders with controls.npz, as `quasisim bench failures` finds them), the
controls are replayed once in MuJoCo; then each finger joint that the replay holds away from its PD target by
more than EPS rad (a finger the object blocks) gets its target moved further in the same direction:

    q'_tj = q_tj + alpha (q_tj - qpos_tj)        ("x<alpha>": alpha times more pressing force)
    q'_tj = q_tj + delta sign(q_tj - qpos_tj)    ("+<delta>": a fixed extra closure)

and every variant is judged as the run was: nominal strict / errors and robust success over N perturbed
replays (configs/robust.yaml, seed 0: the judge's own copies; --seed 1 for other copies).

    python scripts/grip_study.py ROOT --data ../shared/data [--n 8] [--seed 0] [--out study.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def variants(q: np.ndarray, qpos: np.ndarray, finger: np.ndarray, eps: float) -> dict[str, np.ndarray]:
    gap = np.where(finger[None, :], q - qpos, 0.0)
    blocked = np.abs(gap) > eps
    out = {"x0": q}
    for a in (0.5, 1.0, 2.0):
        out[f"x{a:g}"] = q + np.where(blocked, a * gap, 0.0)
    for d in (0.05, 0.1, 0.2):
        out[f"+{d:g}"] = q + np.where(blocked, d * np.sign(gap), 0.0)
    return out


def main() -> None:
    from quasisim.data.controls import load_controls
    from quasisim.data.demo import load_demo
    from quasisim.eval.evaluate import hands_of
    from quasisim.eval.failures import finished_runs, run_method
    from quasisim.eval.metrics import evaluate_rollout
    from quasisim.eval.robust import RobustConfig, robust_success
    from quasisim.targets import make_target
    from quasisim.targets.build import scene_for
    from quasisim.targets.scene import place_hands

    ap = argparse.ArgumentParser()
    ap.add_argument("root", type=Path)
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--n", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--eps", type=float, default=0.02)
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()
    cfg = RobustConfig.from_yaml(None, {"n": a.n, "seed": a.seed})
    rows = []
    for run in finished_runs(a.root):
        controls = load_controls(run / "controls.npz")
        demo = load_demo(a.data / f"{controls.demo}.npz")
        scene = scene_for(demo, place_hands(hands_of(controls, run), controls.base_rots))
        finger = np.zeros(controls.q_targets.shape[1], bool)
        for sl in scene.dof_slices:
            finger[sl.start + 6 : sl.stop] = True
        with make_target("mujoco", scene) as tgt:
            base = tgt.rollout(controls.q_targets)
        row = {"clip": demo.name, "method": run_method(run)}
        for name, q in variants(controls.q_targets, base.qpos, finger, a.eps).items():
            with make_target("mujoco", scene) as tgt:
                ro = tgt.rollout(q)
            m = evaluate_rollout(demo, ro, None)[0]
            r = robust_success(demo, scene, q, "mujoco", cfg)
            row[name] = {"R": m["R_err_deg"], "T": m["T_err_cm"], "strict": bool(m["success"]["strict"]),
                         "s20": bool(m["success"]["20deg_20cm"]), "rob_strict": r["strict"], "rob_20": r["20deg_20cm"]}
        rows.append(row)
        print(demo.name, row["method"], " ".join(
            f"{k}:{'S' if v['strict'] else '-'}{v['rob_strict']:.2f}/{v['rob_20']:.2f}" for k, v in row.items()
            if isinstance(v, dict)), flush=True)  # fmt: skip
    names = [k for k in rows[0] if isinstance(rows[0][k], dict)] if rows else []
    for m in sorted({r["method"] for r in rows}):
        rs = [r for r in rows if r["method"] == m]
        print(f"\n{m}, {len(rs)} runs: variant  R  T  strict%  20%  robust strict%  robust 20%")
        for k in names:
            v = [r[k] for r in rs]
            print(f"  {k:6s} {np.mean([x['R'] for x in v]):5.1f} {np.mean([x['T'] for x in v]):5.2f} "
                  f"{100 * np.mean([x['strict'] for x in v]):4.0f} {100 * np.mean([x['s20'] for x in v]):4.0f} "
                  f"{100 * np.mean([x['rob_strict'] for x in v]):4.0f} {100 * np.mean([x['rob_20'] for x in v]):4.0f}")
    if a.out:
        a.out.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
