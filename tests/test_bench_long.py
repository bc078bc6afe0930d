"""``quasisim bench long``: each command measured in its own process, rows kept and reused, the clip-length
warning's estimate read back as the user sees it."""

from __future__ import annotations

import json
from types import SimpleNamespace

from click.testing import CliRunner

from quasisim.bench.long import estimate, table
from quasisim.cli import main


def test_the_estimate_is_the_warnings(capsys) -> None:
    """The table's estimate is the number the command's warning prints, and the ratio is measured / estimate."""
    from quasisim.data.demo import warn_long_clip
    from quasisim.method.retarget import RETARGET_MB_PER_FRAME, RETARGET_S_PER_FRAME

    warn_long_clip(SimpleNamespace(name="c", n_frames=3000), RETARGET_S_PER_FRAME, RETARGET_MB_PER_FRAME, "retargeting")
    minutes, gb = estimate("retarget", 3000, False)
    assert f"about {minutes:.1f} min and {gb:.1f} GB" in capsys.readouterr().err
    row = {"command": "retarget", "render": False, "frames": 3000, "wall_s": 30 * minutes, "peak_gb": 2 * gb}
    assert "| 0.50, 2.00 |" in table([row])
    e0, e1 = estimate("sample-target", 3000, False), estimate("sample-target", 3000, True)
    assert e1[0] > e0[0] + 3000 * 0.1 / 60  # the video costs 0.2 s per frame


def test_commands_are_measured_once_and_tabulated(tmp_path) -> None:
    out = tmp_path / "long"
    args = ["bench", "long", "--frames", "20", "--commands", "retarget,evaluate", "--no-render", "--out", str(out)]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0, r.output
    rows = json.loads((out / "long.json").read_text())
    assert [(x["command"], x["frames"], x["rc"]) for x in rows] == [("retarget", 20, 0), ("evaluate", 20, 0)]
    assert all(x["wall_s"] > 0 and 0.1 < x["peak_gb"] < 20 for x in rows)
    assert (out / "20" / "evaluate" / "metrics.json").is_file()  # the command ran for real
    kept = (out / "rows" / "20-retarget-no-render.json").stat().st_mtime_ns
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0 and (out / "rows" / "20-retarget-no-render.json").stat().st_mtime_ns == kept
    assert "| retarget | no | 20 |" in (out / "long.md").read_text()
    bad = CliRunner().invoke(main, ["bench", "long", "--commands", "mpc", "--out", str(out)])
    assert bad.exit_code != 0 and "expected some of retarget, evaluate, sample-target" in bad.output
