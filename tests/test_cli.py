"""End-to-end CLI on the bundled synthetic example (no ../shared needed) and a real clip (slow)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from helpers import chromium_check
from quasisim.cli import main
from quasisim.eval.evaluate import STABILITY_KEY
from quasisim.eval.metrics import METRIC_KEYS, SUCCESS_KEYS


def _run(args: list[str]) -> str:
    r = CliRunner().invoke(main, args, catch_exceptions=False)
    assert r.exit_code == 0, r.output
    return r.output


def _check_outputs(out: Path, demo_path: Path) -> dict:
    from quasisim.data.demo import load_demo
    from quasisim.eval.metrics import evaluate_rollout

    m = json.loads((out / "metrics.json").read_text())
    assert tuple(m) == (*METRIC_KEYS, STABILITY_KEY) and tuple(m["success"]) == SUCCESS_KEYS
    assert m[STABILITY_KEY] is False
    assert all(isinstance(m[k], float) for k in METRIC_KEYS[:4])
    z = np.load(out / "rollout.npz")
    demo = load_demo(demo_path)
    T = demo.n_frames
    assert z["object_pos"].shape == (T, 3) and z["object_quat"].shape == (T, 4)
    K = z["human_keypoint_index"].shape[0]
    assert z["robot_keypoints"].shape == (T, K, 3)
    # anyone can recompute the object and keypoint metrics from rollout.npz
    from types import SimpleNamespace

    roll = SimpleNamespace(
        object_pos=z["object_pos"], object_quat=z["object_quat"], robot_keypoints=z["robot_keypoints"],
        human_keypoint_index=z["human_keypoint_index"],
    )  # fmt: skip
    again, _ = evaluate_rollout(demo, roll, None)
    for k in ("R_err_deg", "T_err_cm", "MPJPE_mm"):
        assert abs(again[k] - m[k]) < 1e-6
    html = (out / "report.html").read_text()
    assert "Per-frame errors" in html and html.count("<svg class='plot'") == 4
    assert (out / "scene.xml").is_file() and (out / "trajectory.npz").is_file()
    return m


def test_example_retarget_evaluate(tmp_path: Path) -> None:
    _run(["example", "--out", str(tmp_path), "--name", "cube_lift", "--frames", "24"])  # short: make test-fast
    demo = tmp_path / "cube_lift.npz"
    _run(["retarget", str(demo), "--hand", "shadow", "--out", str(tmp_path / "k")])
    assert (tmp_path / "k" / "kinematic.npz").is_file()
    text = _run(["evaluate", str(demo), str(tmp_path / "k" / "kinematic.npz"), "--out", str(tmp_path / "mj")])
    m = _check_outputs(tmp_path / "mj", demo)
    assert m["MPJPE_mm"] < 40.0  # the robot follows the human hand
    # the kinematic replay does not lift the cube: the summary and the metrics say so, at every threshold
    assert not m["object_motion"]["lift_ok"] and not any(m["success"].values())
    assert "kinematic" in text and "lifted" in text and f"report: {tmp_path / 'mj' / 'report.html'}" in text
    assert "{" not in text  # a human summary, not a JSON line
    assert (tmp_path / "mj" / "video.mp4").stat().st_size > 10_000  # the video rendered (EGL/OSMesa available)
    checked = chromium_check(tmp_path / "mj" / "report.html")  # None without Chromium (test_report skips)
    if checked is not None:
        assert checked["duration"] == pytest.approx(24 / 20, abs=0.06)
        assert checked["errors"] == [] and checked["console"] == []


def test_help_names_the_examples_and_commands() -> None:
    from quasisim.data.synthetic import EXAMPLES

    assert all(n in _run(["example", "--help"]) for n in EXAMPLES)
    top = _run(["--help"])
    assert all(c in top for c in ("view", "convert", "transfer", "evaluate"))
    # `bench`: the commands behind the tables of BENCHMARKS.md and of docs/studies, and the failure and grasp
    # analyses, nothing else
    assert sorted(main.commands["bench"].commands) == [
        "batch",
        "compare",
        "env",
        "export",
        "failures",
        "grasp",
        "paper",
        "policy",
        "transfer",
    ]


def test_evaluate_rejects_mismatched_controls(tmp_path: Path) -> None:
    _run(["example", "--out", str(tmp_path), "--name", "cube_lift", "--frames", "40"])
    _run(["example", "--out", str(tmp_path / "b"), "--name", "cube_lift", "--frames", "30"])
    _run(["retarget", str(tmp_path / "b" / "cube_lift.npz"), "--out", str(tmp_path / "k")])
    r = CliRunner().invoke(
        main,
        [
            "evaluate",
            str(tmp_path / "cube_lift.npz"),
            str(tmp_path / "k" / "kinematic.npz"),
            "--out",
            str(tmp_path / "o"),
        ],
    )
    assert r.exit_code == 2 and "q_targets" in r.output and "40 frames" in r.output


@pytest.mark.slow
def test_demo_method_lifts_the_cube(tmp_path: Path) -> None:
    """What `make demo` runs: the default method (the cascade) lifts and tracks the bundled cube; the kinematic
    replay does not."""
    _run(["example", "--out", str(tmp_path), "--name", "cube_lift"])
    out = tmp_path / "transfer"
    text = _run(["transfer", str(tmp_path / "cube_lift.npz"), "--out", str(out), "--no-render"])
    m = json.loads((out / "metrics.json").read_text())
    mo = m["object_motion"]
    assert mo["as_demo"] and mo["lift_cm"] > 0.8 * mo["demo_lift_cm"] and mo["displacement_error_cm"] < 3.0
    assert m["success"]["20deg_20cm"] and m["T_err_cm"] < 2.0 and m["R_err_deg"] < 10.0
    kin = json.loads((out / "summary.json").read_text())["kinematic_metrics"]
    assert not kin["object_motion"]["lift_ok"] and not any(kin["success"].values())
    rows = [line.split() for line in text.splitlines() if line.startswith("  cascade") or "  kinematic replay" in line]
    assert [r[:5] for r in rows] == [
        [
            "cascade",
            *("yes" if m["success"][k] else "no" for k in ("strict", "10deg_10cm", "15deg_15cm", "20deg_20cm")),
        ],
        ["kinematic", "replay", "no", "no", "no"],
    ]


@pytest.mark.slow
def test_real_clip_both_targets(tmp_path: Path, data_dir: Path) -> None:
    demo = data_dir / "grab_s1_cubesmall_lift.npz"
    _run(["retarget", str(demo), "--out", str(tmp_path / "k")])
    for target in ("mujoco", "pybullet"):
        out = tmp_path / target
        _run(
            [
                "evaluate",
                str(demo),
                str(tmp_path / "k" / "kinematic.npz"),
                "--target",
                target,
                "--out",
                str(out),
                "--no-render",
                "--robust",
                "0",
            ]
        )
        m = _check_outputs_no_video(out, demo)
        assert m["MPJPE_mm"] < 60.0 and m["T_err_cm"] < 50.0


def _check_outputs_no_video(out: Path, demo: Path) -> dict:
    m = json.loads((out / "metrics.json").read_text())
    assert tuple(m) == (*METRIC_KEYS, STABILITY_KEY)
    assert np.load(out / "rollout.npz")["object_pos"].shape[1] == 3
    assert "Per-frame errors" in (out / "report.html").read_text()
    return m


def test_a_libraries_warning_that_comes_with_an_error_is_folded_into_our_one_line(tmp_path: Path) -> None:
    """MuJoCo prints "WARNING: Must provide extension ..." to stderr before failing on a model file without an
    extension: the process's stderr is our one line, with MuJoCo's words in it (a real process: the warning is
    written by C code to file descriptor 2, which an in-process runner does not see)."""
    import subprocess
    import sys

    from quasisim.assets.hand import HANDS_DIR
    from quasisim.data.synthetic import write_example

    demo = write_example("cube_lift", tmp_path, n_frames=12)
    (tmp_path / "model").write_bytes(b"\x89PNG\r\n\x1a\n0000")  # no extension, not a model
    yaml = (HANDS_DIR / "shadow.yaml").read_text().splitlines()
    yaml = [f"model: {tmp_path / 'model'}" if line.startswith("model:") else line for line in yaml]
    (tmp_path / "hand.yaml").write_text("\n".join(yaml) + "\n")
    cmd = [sys.executable, "-m", "quasisim.cli", "retarget", str(demo), "--hand", str(tmp_path / "hand.yaml"),
           "--out", str(tmp_path / "o")]  # fmt: skip
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode != 0 and r.stdout == ""
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert (
        lines[0].startswith(f"error: {tmp_path / 'model'}: expected an MJCF or URDF file")
        and "(MuJoCo: WARNING" in lines[0]
    )
