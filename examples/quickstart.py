"""Quickstart: retarget the bundled example demo to the Shadow hand and judge it in MuJoCo.

Run: python examples/quickstart.py [OUT_DIR]
"""

from __future__ import annotations

import sys
from pathlib import Path

from quasisim.assets.hand import load_hand
from quasisim.demo import load_demo
from quasisim.evaluate import evaluate_controls
from quasisim.retarget import kinematic_controls
from quasisim.synthetic import write_example


def main(out: Path) -> dict:
    demo = load_demo(write_example("cube_lift", out / "demo"))
    controls = kinematic_controls(load_hand("shadow"), demo, "shadow")
    controls.save(out / "kinematic.npz")
    ev = evaluate_controls(demo, controls, "mujoco", out_dir=out / "mujoco", render=False)
    print(ev.metrics)
    return ev.metrics


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "out/quickstart"))
