"""Where a MuJoCo physics step of a finished run goes: the run's controls replayed in its MuJoCo target (the
scene built from the demo, as the judge builds it), MuJoCo's own timers per step (collision broad and narrow
phase, constraint building, the solver), the solver's iterations and the contacts per step.

    python scripts/mujoco_step_profile.py RUN_DIR [RUN_DIR ...]

``RUN_DIR`` is a finished run of a `bench transfer` folder's `.work` (``.work/CLIP/runs/RUN``: the demo is read
from ``.work/CLIP/input/CLIP.npz``) or any run folder with ``--demo``. The timers are those of the last of
``--repeat`` replays (each a fresh ``MjData``); microseconds per physics step.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import mujoco
import numpy as np

from quasisim.data.controls import load_controls
from quasisim.data.demo import load_demo
from quasisim.targets.base import pd_schedule
from quasisim.targets.build import demo_hands, scene_for
from quasisim.targets.mujoco_target import MujocoTarget
from quasisim.targets.scene import place_hands

TIMERS = {
    "step": "mjTIMER_STEP", "collision": "mjTIMER_POS_COLLISION", "narrow phase": "mjTIMER_COL_NARROW",
    "constraint build": "mjTIMER_POS_MAKE", "solver": "mjTIMER_CONSTRAINT",
}  # fmt: skip


def profile(run: Path, demo_path: Path, repeat: int) -> dict[str, float]:
    demo = load_demo(demo_path)
    c = load_controls(run / "controls.npz")
    scene = scene_for(demo, place_hands(demo_hands(c.hand, c.sides), c.base_rots))
    tg = MujocoTarget(scene)
    m, q = tg.mm.model, c.q_targets
    for _ in range(repeat):
        tg.reset(q[0], (q[1] - q[0]) * scene.fps)
        its, ncon, t0 = [], [], time.perf_counter()
        for t in range(len(q) - 1):  # MujocoTarget.advance, with the solver's iterations read per step
            targets, velocity = pd_schedule(q[t], q[t + 1], tg.substeps, scene.fps)
            tg.data.ctrl[tg.mm.ff_act] = velocity
            for pd in targets:
                tg.data.ctrl[tg.mm.pd_act] = pd
                mujoco.mj_step(m, tg.data)
                its.append(int(tg.data.solver_niter[0]))
                ncon.append(int(tg.data.ncon))
        wall = time.perf_counter() - t0
    n = len(its)
    out = {"wall (Python loop)": wall / n * 1e6}
    for name, key in TIMERS.items():
        tm = tg.data.timer[getattr(mujoco.mjtTimer, key)]
        out[name] = tm.duration / max(tm.number, 1) * 1e6
    nparts = sum(int(m.geom_bodyid[g] == tg.mm.obj_body) for g in range(m.ngeom))
    out |= {"solver iterations (mean)": float(np.mean(its)), "solver iterations (max)": float(np.max(its)),
            "contacts (mean)": float(np.mean(ncon)), "object collision parts": float(nparts)}  # fmt: skip
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", type=Path, nargs="+")
    ap.add_argument("--demo", type=Path, help="the demo of every run (default: the .work folder's input)")
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    rows = {}
    for run in a.runs:
        clip = run.parents[1]
        rows[f"{clip.name}/{run.name}"] = profile(run, a.demo or clip / "input" / f"{clip.name}.npz", a.repeat)
    keys = list(next(iter(rows.values())))
    print("| run | " + " | ".join(keys) + " |\n" + "|---" * (len(keys) + 1) + "|")
    for name, r in rows.items():
        print(f"| {name} | " + " | ".join(f"{r[k]:.1f}" for k in keys) + " |")


if __name__ == "__main__":
    main()
