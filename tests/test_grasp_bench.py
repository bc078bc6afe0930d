"""``quasisim bench grasp``: the grasp margin of finished runs replayed in MuJoCo, beside their robust success."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner


def test_bench_grasp_tabulates_each_runs_excess_beside_its_robust_success(data_dir: Path, tmp_path: Path) -> None:
    """A kinematic retarget that holds the cube with sliding contacts carries load beyond cones shrunk by half;
    the same controls 30 cm higher touch nothing (no excess); the robust column comes from the run's cache; a
    folder without runs is one line, exit 2."""
    import dataclasses

    from quasisim.assets.hand import load_hand
    from quasisim.cli import main
    from quasisim.data.demo import load_demo
    from quasisim.eval.grasp_margin import open_loop_robust, replay_excess
    from quasisim.method.retarget import kinematic_controls

    demo = load_demo(data_dir / "grab_s1_cubesmall_lift.npz")
    c = kinematic_controls(load_hand("shadow"), demo, "shadow")
    away = dataclasses.replace(c, q_targets=c.q_targets + np.r_[0.0, 0.0, 0.3, np.zeros(c.q_targets.shape[1] - 3)])
    runs = tmp_path / "runs"
    for name, ctrl in (("kinematic", c), ("away", away)):
        (runs / demo.name / name).mkdir(parents=True)
        ctrl.save(runs / demo.name / name / "controls.npz")
    cache = {"settings": {"sets": {"default": {"name": "robust"}}}, "metrics": {"robust": {"strict": 0.5}}}
    (runs / demo.name / "kinematic" / "robust_closed_loop-x.json").write_text(json.dumps(cache))

    res = CliRunner().invoke(main, ["bench", "grasp", str(runs), "--data", str(data_dir), "--margin", "0.5"])
    assert res.exit_code == 0, res.output
    rows = {r["run"]: r for r in json.loads((runs / "grasp_margin.json").read_text())["rows"]}
    assert rows["kinematic"]["mean"] > 0.05 and rows["kinematic"]["robust_strict_open"] == 0.5
    assert rows["away"]["mean"] == 0.0 and rows["away"]["robust_strict_open"] is None
    assert f"| {demo.name} | away | 0.00 | 0.00 | 0.00 | 0 | - |" in res.output
    assert (runs / "grasp_margin.md").read_text().count(f"| {demo.name} |") == 2
    # the table's numbers are the replay's: a smaller margin leaves less beyond the cones
    run = runs / demo.name / "kinematic"
    half, fifth = (replay_excess(demo, c, run, m, 8).mean() for m in (0.5, 0.2))
    assert half == pytest.approx(rows["kinematic"]["mean"]) and fifth < half
    assert open_loop_robust(runs / demo.name / "away", "default") is None

    empty = tmp_path / "empty"
    empty.mkdir()
    res = CliRunner().invoke(main, ["bench", "grasp", str(empty), "--data", str(data_dir)])
    assert res.exit_code == 2 and "no finished runs" in res.output
