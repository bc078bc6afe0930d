"""``quasisim bench compare``: finished benchmark folders side by side (read back, nothing run)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner


def _metrics(r: float, t: float, strict: bool) -> dict:
    success = {"10deg_10cm": True, "15deg_15cm": True, "20deg_20cm": True, "strict": strict}
    return {"R_err_deg": r, "T_err_cm": t, "MPJPE_mm": 2 * r, "success": success, "object_motion": {"lift_ok": strict}}


def _folder(root: Path, results: dict[str, tuple[float, float, bool, float]], with_kinematic: bool = True) -> Path:
    """A `bench transfer` folder holding run short+sample+select: {clip: (R_err, T_err, strict, stiffest loss)},
    each with a kinematic replay twice as far off and never strict."""
    for clip, (r, t, strict, loss) in results.items():
        d = root / clip
        (d / "short+sample+select").mkdir(parents=True)
        row = {"metrics": _metrics(r, t, strict), "seconds": {"retarget": 1.0, "stage2": 10.0 * r, "sample": 5.0}}
        if with_kinematic:
            row["kinematic_metrics"] = _metrics(2 * r, 2 * t, False)
        (d / "clip.json").write_text(
            json.dumps({"clip": clip, "runs": {"short+sample+select": {"identity": {}, "row": row}}})
        )
        sims = [
            {"sim": 8, "loss_best": 1.0},
            {"sim": 9, "loss_best": loss, "start_losses": {"previous": 2.0, "touching": loss}},
        ]
        (d / "short+sample+select" / "summary.json").write_text(json.dumps({"simulators": sims}))
    return root


def test_bench_compare_tabulates_the_clips_every_folder_holds(tmp_path: Path) -> None:
    from quasisim.cli import main

    a = _folder(
        tmp_path / "a", {"c1": (10.0, 2.0, False, 0.5), "c2": (4.0, 1.0, True, 0.1), "c3": (9.0, 9.0, False, 0.9)}
    )
    b = _folder(tmp_path / "b", {"c1": (5.0, 1.0, True, 0.2), "c2": (6.0, 0.5, True, 0.3)})
    for f, (strict, at20) in zip(sorted(b.glob("*/clip.json")), [(0.25, 0.5), (0.75, 1.0)], strict=True):
        d = json.loads(f.read_text())  # robust success in folder b (fractions of perturbed replays)
        d["runs"]["short+sample+select"]["row"]["metrics"]["robust"] = {"n": 4, "strict": strict, "20deg_20cm": at20}
        f.write_text(json.dumps(d))
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["bench", "compare", f"old={a}", f"new={b}", "--out", str(out)])
    assert r.exit_code == 0, r.output
    md = (out / "compare.md").read_text()
    assert "2 clips held by every folder" in md and "| c3 |" not in md  # c3 is in one folder only
    assert "| old | 7.0 | 1.50 | 14.0 | 100 / 100 / 100 / 50 | - / - | 1 of 2 | 0.3000 / 0.3000 | - | 76 |" in md
    assert (
        "| new | 5.5 | 0.75 | 11.0 | 100 / 100 / 100 / 100 | 50 / 75 | 2 of 2 | 0.2500 / 0.2500 | 1 of 2 | 61 |" in md
    )
    assert "| c1 | 10.0 / 2.00 | 5.0 / 1.00 S | 0.5000 | 0.2000 |" in md
    # where the time went: the stages the folders' clip.json time (mean / median per clip), and their sum
    assert "| folder | retarget | stage2 | sample | total |" in md
    assert "| old | 1 / 1 | 70 / 70 | 5 / 5 | 76 / 76 |" in md and "| new | 1 / 1 | 55 / 55 | 5 / 5 | 61 / 61 |" in md
    assert len(json.loads((out / "compare.json").read_text())) == 4

    r = CliRunner().invoke(main, ["bench", "compare", f"old={a}", f"x={tmp_path / 'nope'}", "--out", str(out)])
    assert r.exit_code != 0 and "nope" in r.output and "not a folder" in r.output
    r = CliRunner().invoke(main, ["bench", "compare", str(a), "--run", "sample-target", "--out", str(out)])
    assert r.exit_code != 0 and "no finished run" in r.output and "run 'sample-target'" in r.output
    # one run name per folder: the same folder's run beside another's
    renamed = tmp_path / "renamed"
    for f in a.glob("*/clip.json"):
        d = json.loads(f.read_text())
        d["runs"] = {"none+sample+select": d["runs"]["short+sample+select"]}
        (renamed / f.parent.name).mkdir(parents=True)
        (renamed / f.parent.name / "clip.json").write_text(json.dumps(d))
    args = ["bench", "compare", f"old={a}", f"none={renamed}", "--out", str(tmp_path / "o3")]
    r = CliRunner().invoke(main, [*args, "--run", "short+sample+select,none+sample+select"])
    assert r.exit_code == 0, r.output
    md = (tmp_path / "o3" / "compare.md").read_text()
    assert "short+sample+select / none+sample+select: old vs none, 3 clips" in md
    assert "| none | 7.7 | 4.00 | 15.3 | 100 / 100 / 100 / 33 | - / - | 1 of 3 | - | 0 of 3 | 83 |" in md
    r = CliRunner().invoke(main, [*args, "--run", "a,b,c"])
    assert r.exit_code != 0 and "names 3 runs for 2 folders" in r.output


def test_bench_compare_puts_each_folders_kinematic_replay_beside_it(tmp_path: Path) -> None:
    from quasisim.cli import main

    a = _folder(tmp_path / "shadow", {"c1": (10.0, 2.0, False, 0.5), "c2": (4.0, 1.0, True, 0.1)})
    b = _folder(tmp_path / "allegro", {"c1": (5.0, 1.0, True, 0.2), "c2": (6.0, 0.5, True, 0.3)})
    for d in (a, b):  # a folder kept in git: clip.json only, so no stage 2 losses
        for s in d.glob("*/short+sample+select/summary.json"):
            s.unlink()
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["bench", "compare", str(a), str(b), "--kinematic", "--out", str(out)])
    assert r.exit_code == 0, r.output
    md = (out / "compare.md").read_text()
    assert "shadow vs allegro, 2 clips" in md and "stiffest loss" not in md
    assert "| shadow kinematic | 14.0 | 3.00 | 28.0 | 100 / 100 / 100 / 0 | - / - | 0 of 2 | 0 of 2 | - |" in md
    assert "| allegro | 5.5 | 0.75 | 11.0 | 100 / 100 / 100 / 100 | - / - | 2 of 2 | 1 of 2 | 61 |" in md
    assert "| clip | shadow | shadow kinematic | allegro | allegro kinematic |" in md
    assert "| c1 | 10.0 / 2.00 | 20.0 / 4.00 | 5.0 / 1.00 S | 10.0 / 2.00 |" in md

    c = _folder(tmp_path / "old", {"c1": (1.0, 1.0, True, 0.1)}, with_kinematic=False)
    r = CliRunner().invoke(main, ["bench", "compare", str(a), str(c), "--kinematic", "--out", str(tmp_path / "o2")])
    assert r.exit_code != 0 and "old kinematic" in r.output


def test_table_header_quotes_the_command_as_a_shell_needs_it(monkeypatch: pytest.MonkeyPatch) -> None:
    """A benchmark table's command line can be pasted back: arguments with spaces keep their quotes."""
    from quasisim.eval.tables import header

    monkeypatch.setattr("sys.argv", ["/x/.venv/bin/quasisim", "bench", "world", "--variant", "table on mesh samples"])
    assert "- command: `quasisim bench world --variant 'table on mesh samples'`" in header("t")
