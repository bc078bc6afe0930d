"""Does a firmer grip make a run's controls survive a nudge? Each finger joint target moved along
``J^T n`` at every hand-object contact of the nominal replay (n: the contact normal towards the object, J: the
contact point's Jacobian; each contact's direction scaled to at most 1 per joint, summed, clipped to [-1, 1],
widened to the frames before and after), times ``eps`` rad, then judged in MuJoCo: nominal metrics and robust
success with the ``--robust N`` seeds. Reads each clip's `.work/<clip>/input/<clip>.npz` and
`.work/<clip>/runs/<run>/controls.npz` (run it where the batch ran).

    python scripts/grip_squeeze.py RUN FOLDER --eps 0,0.01,0.03 [--n 8] [--workers 2]
"""

from __future__ import annotations

import argparse
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np


def squeeze_directions(tgt: Any, q: np.ndarray) -> np.ndarray:
    """(T, D) per frame: the sum over hand-object contacts of ``J^T n`` on the finger joints (base dofs 0)."""
    import mujoco

    mm = tgt.mm
    m, hand_bodies, obj = mm.model, set(mm.hand_body.tolist()), mm.obj_body
    out, jacp = np.zeros(q.shape), np.zeros((3, m.nv))
    tgt.reset(q[0], (q[1] - q[0]) * tgt.scene.fps)
    for t in range(len(q)):
        d = tgt.data
        for c in (d.contact[i] for i in range(d.ncon)):
            b1, b2 = m.geom_bodyid[c.geom1], m.geom_bodyid[c.geom2]
            if b1 == obj and b2 in hand_bodies:  # MuJoCo's normal points from geom1 to geom2
                hand_b, n = b2, -c.frame[:3]
            elif b2 == obj and b1 in hand_bodies:
                hand_b, n = b1, c.frame[:3]
            else:
                continue
            mujoco.mj_jac(m, d, jacp, None, c.pos, hand_b)
            g = jacp[:, mm.hand_dof].T @ n
            g[:6] = 0.0
            if np.abs(g).max() > 1e-9:
                out[t] += g / np.abs(g).max()
        if t < len(q) - 1:
            tgt.advance(q[t], q[t + 1])
    g = np.pad(np.clip(out, -1, 1), ((1, 1), (0, 0)))
    stack = np.stack([g[:-2], g[1:-1], g[2:]])  # frames t-1, t, t+1: the largest move of the three
    return np.take_along_axis(stack, np.abs(stack).argmax(0)[None], 0)[0]


def clip_rows(args: tuple[Path, str, tuple[float, ...], int]) -> tuple[str, dict[float, tuple[float, ...]]]:
    from quasisim.data.controls import load_controls
    from quasisim.data.demo import load_demo
    from quasisim.eval.metrics import evaluate_rollout
    from quasisim.eval.robust import RobustConfig, robust_success
    from quasisim.targets import make_target
    from quasisim.targets.build import demo_hands, scene_for
    from quasisim.targets.scene import place_hands

    clip_dir, run, eps, n = args
    demo = load_demo(clip_dir / "input" / f"{clip_dir.name}.npz")
    c = load_controls(clip_dir / "runs" / run / "controls.npz")
    scene = scene_for(demo, place_hands(demo_hands(c.hand, c.sides), c.base_rots))
    with make_target("mujoco", scene) as tgt:
        g = squeeze_directions(tgt, c.q_targets)
    rows = {}
    for e in eps:
        q = c.q_targets + e * g  # not clipped: PD targets may lie beyond the joint range
        with make_target("mujoco", scene) as tgt:
            m = evaluate_rollout(demo, tgt.rollout(q), None)[0]
        r = robust_success(demo, scene, q, "mujoco", RobustConfig(n=n))
        ok = m["success"]
        rows[e] = (m["R_err_deg"], m["T_err_cm"], ok["strict"], ok["20deg_20cm"], r["strict"], r["20deg_20cm"])
    return clip_dir.name, rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run")
    ap.add_argument("folder", type=Path)
    ap.add_argument("--eps", default="0,0.01,0.03", help="squeezes (rad), comma-separated")
    ap.add_argument("--n", type=int, default=8)
    ap.add_argument("--workers", type=int, default=2)
    a = ap.parse_args()
    eps = tuple(float(x) for x in a.eps.split(","))
    clips = sorted(p.parents[2] for p in a.folder.glob(f".work/*/runs/{a.run}/controls.npz"))
    if not clips:
        raise SystemExit(f"no clip of {a.folder} has {a.run}'s controls.npz under .work/")
    with ProcessPoolExecutor(a.workers) as ex:
        res = dict(ex.map(clip_rows, [(c, a.run, eps, a.n) for c in clips]))
    print(f"{len(res)} clips; R_err / T_err, S strict, o 20/20 only, x neither; robust strict / 20 (%), {a.n} replays")
    print("| clip | " + " | ".join(f"eps {e}" for e in eps) + " |\n" + "|---" * (len(eps) + 1) + "|")
    for clip, rows in res.items():
        cells = [f"{r[0]:.1f} / {r[1]:.2f} {'S' if r[2] else 'o' if r[3] else 'x'}, {100 * r[4]:.0f} / {100 * r[5]:.0f}"
                 for r in rows.values()]  # fmt: skip
        print(f"| {clip} | " + " | ".join(cells) + " |")
    mean = [np.mean([res[k][e] for k in res], axis=0) for e in eps]
    print("| **mean** | " + " | ".join(
        f"**{m[0]:.1f} / {m[1]:.2f}, strict {100 * m[2]:.0f}, 20/20 {100 * m[3]:.0f}; robust {100 * m[4]:.0f} / {100 * m[5]:.0f}**"
        for m in mean) + " |")  # fmt: skip


if __name__ == "__main__":
    main()
