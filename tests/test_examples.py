"""The example scripts run."""

from __future__ import annotations

import json
import runpy
import sys
from pathlib import Path

import numpy as np

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def test_quickstart(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(sys, "argv", ["quickstart.py", str(tmp_path)])
    ns = runpy.run_path(str(EXAMPLES / "quickstart.py"))
    metrics = ns["main"](tmp_path)
    assert set(metrics) == {"R_err_deg", "T_err_cm", "MPJPE_mm", "CD_mm", "object_motion", "success", "unstable"}
    assert (tmp_path / "mujoco" / "report.html").is_file()


def test_custom_stage(tmp_path: Path) -> None:
    """A stage added at run time (examples/custom_stage.py) runs in the pipeline: its output is the result,
    checkpointed, timed, in the run's identity, and the registry is left as it was."""
    from quasisim.method import registry

    before = dict(registry.STAGES)
    ns = runpy.run_path(str(EXAMPLES / "custom_stage.py"))
    res = ns["main"](tmp_path)
    assert registry.STAGES == before
    c = res["controls"]
    cols = [slice(0, c.q_targets.shape[1])]
    expected = ns["smooth_joints"](c.extras["kinematic_q"], cols)
    assert np.abs(c.q_targets - expected).max() < 1e-5  # the smoothed retarget (float32-rounded)
    assert np.abs(c.q_targets - c.extras["kinematic_q"])[:, 6:].max() > 1e-3  # and not the retarget itself
    run_dir = tmp_path / "smooth"
    assert (run_dir / "checkpoints" / "smooth.npz").is_file()
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["stages"] == ["smooth"] and "smooth" in summary["seconds"]
    assert c.method.startswith("ours[short;stages smooth;")
    np.testing.assert_array_equal(c.extras["before_smoothing_q"], c.extras["kinematic_q"].astype(np.float32))
