"""Seconds per physics step of a target's rollout: a box dropped between the fingers of a closing Shadow hand
(the contact scene of tests/test_targets.py), 20 frames, best of ``--repeat`` rollouts after one warm-up.

Run it with two source trees in turn to compare two versions of a target side by side, e.g.

    for src in /path/old/src /path/new/src; do PYTHONPATH=$src python scripts/target_step_cost.py pybullet; done

It also prints a checksum of the rollout (object and hand positions), so that two versions can be seen to
compute the same bits.
"""

from __future__ import annotations

import argparse
import hashlib
import time
from types import SimpleNamespace

import numpy as np
import trimesh

from quasisim.assets.hand import load_hand
from quasisim.targets import make_target
from quasisim.targets.scene import Placement, Scene, Table


def _box(extents: float = 0.05, density: float = 500.0) -> SimpleNamespace:
    """A 5 cm box of 500 kg/m^3 with the fields of an object asset that a scene reads."""
    m = trimesh.creation.box(extents=(extents,) * 3)
    m.density = density
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    return SimpleNamespace(
        name="box", vertices=v, faces=f, mass=float(m.mass), com=np.asarray(m.center_mass),
        inertia=np.asarray(m.moment_inertia), convex_parts=lambda *a, **k: [(v, f)],
    )  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("target", choices=("mujoco", "pybullet"))
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--repeat", type=int, default=4)
    args = ap.parse_args()
    hand = load_hand("shadow")
    scene = Scene(
        placements=(Placement(hand, np.eye(3)),), obj=_box(), table=Table(-0.3, 0.3, -0.3, 0.3, 0.8),
        object_pos0=np.array([0.0, 0.0, 0.86]), object_quat0=np.array([1.0, 0.0, 0.0, 0.0]), fps=20.0,
    )  # fmt: skip
    s = np.linspace(0, 1, args.frames)
    s = s * s * (3 - 2 * s)  # smoothstep: the base moves 5 cm, every joint closes towards 0.8 rad
    q = np.zeros((args.frames, 6 + hand.n_joints))
    q[:, :3] = np.array([0.0, -0.1, 0.95]) + s[:, None] * np.array([0.0, 0.05, -0.02])
    q[:, 6:] = np.clip(s[:, None] * 0.8, hand.joint_range[:, 0], hand.joint_range[:, 1])
    with make_target(args.target, scene) as tgt:
        r = tgt.rollout(q)
        best = np.inf
        for _ in range(args.repeat):
            t = time.perf_counter()
            r = tgt.rollout(q)
            best = min(best, time.perf_counter() - t)
        steps = (args.frames - 1) * tgt.substeps
    digest = hashlib.sha256(np.concatenate([r.qpos.ravel(), r.object_pos.ravel()]).tobytes()).hexdigest()[:12]
    print(
        f"{args.target}: {best / steps * 1e6:.0f} us per physics step ({steps} steps, best of {args.repeat}); "
        f"rollout checksum {digest}"
    )


if __name__ == "__main__":
    main()
