"""Which perturbation breaks a run's controls: robust success with one factor of `configs/robust.yaml` at a
time (the others at 0), beside all factors together, for every clip of finished `bench transfer` folders.
Reads each clip's `.work/<clip>/input/<clip>.npz` and `.work/<clip>/runs/<run>/controls.npz` (the `.work`
folders are not committed: run it where the batch ran). Replays are judged in MuJoCo, seeded as
`--robust N` seeds them, so the `all` column repeats the folder's own robust figures.

    python scripts/robust_factors.py RUN FOLDER [--n 8] [--workers 2]
"""

from __future__ import annotations

import argparse
import dataclasses
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

FACTORS = ("mass", "friction", "object_pos", "pd_gains")


def clip_factors(args: tuple[Path, str, int]) -> tuple[str, dict[str, tuple[float, float]]]:
    """clip -> {setting: (strict fraction, 20/20 fraction)} for settings ``all`` and each factor alone."""
    from quasisim.data.controls import load_controls
    from quasisim.data.demo import load_demo
    from quasisim.eval.robust import RobustConfig, robust_success
    from quasisim.targets.build import demo_hands, scene_for
    from quasisim.targets.scene import place_hands

    clip_dir, run, n = args
    demo = load_demo(clip_dir / "input" / f"{clip_dir.name}.npz")
    controls = load_controls(clip_dir / "runs" / run / "controls.npz")
    scene = scene_for(demo, place_hands(demo_hands(controls.hand, controls.sides), controls.base_rots))
    full = RobustConfig(n=n)
    out = {}
    for name in ("all", *FACTORS):
        cfg = full if name == "all" else dataclasses.replace(full, **{f: 0.0 for f in FACTORS if f != name})
        r = robust_success(demo, scene, controls.q_targets, "mujoco", cfg)
        out[name] = (r["strict"], r["20deg_20cm"])
    return clip_dir.name, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run")
    ap.add_argument("folder", type=Path)
    ap.add_argument("--n", type=int, default=8)
    ap.add_argument("--workers", type=int, default=2)
    a = ap.parse_args()
    clips = sorted(p.parents[2] for p in a.folder.glob(f".work/*/runs/{a.run}/controls.npz"))
    if not clips:
        raise SystemExit(f"no clip of {a.folder} has {a.run}'s controls.npz under .work/")
    with ProcessPoolExecutor(a.workers) as ex:
        rows = dict(ex.map(clip_factors, [(c, a.run, a.n) for c in clips]))
    names = ("all", *FACTORS)
    print(f"{len(rows)} clips, {a.n} replays each; robust strict / 20 deg 20 cm (%), one factor at a time")
    print("| clip | " + " | ".join(names) + " |\n" + "|---" * (len(names) + 1) + "|")
    for clip, r in rows.items():
        print(f"| {clip} | " + " | ".join(f"{100 * r[k][0]:.0f} / {100 * r[k][1]:.0f}" for k in names) + " |")
    mean = {k: np.mean([r[k] for r in rows.values()], axis=0) for k in names}
    print("| **mean** | " + " | ".join(f"**{100 * m[0]:.0f} / {100 * m[1]:.0f}**" for m in mean.values()) + " |")


if __name__ == "__main__":
    main()
