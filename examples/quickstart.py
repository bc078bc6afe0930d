"""Quickstart: retarget the bundled example demo to the Shadow hand and judge it in MuJoCo.

Run: python examples/quickstart.py [OUT_DIR]
"""

from __future__ import annotations

import sys
from pathlib import Path

from quasisim.assets.hand import load_hand
from quasisim.data.demo import load_demo
from quasisim.data.synthetic import write_example
from quasisim.eval.evaluate import evaluate_controls
from quasisim.method.retarget import kinematic_controls
from quasisim.runtime import configure


def main(out: Path) -> dict:
    demo = load_demo(write_example("cube_lift", out / "demo"))
    controls = kinematic_controls(load_hand("shadow"), demo, "shadow")
    controls.save(out / "kinematic.npz")
    ev = evaluate_controls(demo, controls, "mujoco", out_dir=out / "mujoco", render=False)
    print(ev.metrics)
    return ev.metrics


if __name__ == "__main__":
    configure()  # offscreen rendering, XLA settings, compilation cache (the CLI does this too)
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "out/quickstart"))
