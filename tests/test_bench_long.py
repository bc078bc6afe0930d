"""``quasisim bench long``: each command measured in its own process, rows kept and reused, the clip-length
warning's estimate read back as the user sees it."""

from __future__ import annotations

import json
from types import SimpleNamespace

from click.testing import CliRunner

from quasisim.bench.long import _ESTIMATE, table
from quasisim.cli import main


def test_the_warnings_estimate_is_read_back(capsys) -> None:
    from quasisim.data.demo import warn_long_clip

    warn_long_clip(SimpleNamespace(name="c", n_frames=3000), 0.02, 0.15, "evaluation")
    m = _ESTIMATE.search(capsys.readouterr().err)
    assert m is not None and (float(m.group(1)), float(m.group(2))) == (
        1.2,
        1.0,
    )  # (15 + 60) s = 1.25 min, (600 + 450) MB
    row = {"command": "evaluate", "render": False, "frames": 3000, "wall_s": 39.0, "peak_gb": 2.0,
           "estimate_min": 1.3, "estimate_gb": 1.0}  # fmt: skip
    assert "| 0.50, 2.00 |" in table([row])  # measured / estimate: time, memory


def test_commands_are_measured_once_and_tabulated(tmp_path) -> None:
    out = tmp_path / "long"
    args = ["bench", "long", "--frames", "20", "--commands", "retarget,evaluate", "--no-render", "--out", str(out)]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0, r.output
    rows = json.loads((out / "long.json").read_text())
    assert [(x["command"], x["frames"], x["rc"]) for x in rows] == [("retarget", 20, 0), ("evaluate", 20, 0)]
    assert all(x["wall_s"] > 0 and 0.1 < x["peak_gb"] < 20 and x["estimate_min"] is None for x in rows)
    assert (out / "20" / "evaluate" / "metrics.json").is_file()  # the command ran for real
    kept = (out / "rows" / "20-retarget-no-render.json").stat().st_mtime_ns
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0 and (out / "rows" / "20-retarget-no-render.json").stat().st_mtime_ns == kept
    assert "| retarget | no | 20 |" in (out / "long.md").read_text()
    bad = CliRunner().invoke(main, ["bench", "long", "--commands", "mpc", "--out", str(out)])
    assert bad.exit_code != 0 and "expected some of retarget, evaluate, sample-target" in bad.output
