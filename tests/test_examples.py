"""The example scripts run."""

from __future__ import annotations

import runpy
import sys
from pathlib import Path

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def test_quickstart(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(sys, "argv", ["quickstart.py", str(tmp_path)])
    ns = runpy.run_path(str(EXAMPLES / "quickstart.py"))
    metrics = ns["main"](tmp_path)
    assert set(metrics) == {"R_err_deg", "T_err_cm", "MPJPE_mm", "CD_mm", "object_motion", "success", "unstable"}
    assert (tmp_path / "mujoco" / "report.html").is_file()
