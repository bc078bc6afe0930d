"""The report: an H.264 video beside report.html, labelled frames, per-frame plots with a cursor, the page
checked in headless Chromium (skipped without /usr/bin/chromium)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from helpers import CHROMIUM, chromium_check
from quasisim.eval.metrics import ObjectMotion, PerFrame, summarize
from quasisim.eval.render import annotate
from quasisim.eval.report import VIDEO_FILE, write_report

T, FPS = 24, 20.0


def _per_frame() -> PerFrame:
    t = np.arange(T, dtype=float)
    return PerFrame(rot_deg=t, trans_cm=0.1 * t, mpjpe_mm=np.full(T, 7.0), cd_mm=np.full(T, np.nan))


def _frames() -> list[np.ndarray]:
    x = np.linspace(0, 255, 160, dtype=np.uint8)
    return [np.stack([np.tile(x, (90, 1)), np.full((90, 160), 8 * t, np.uint8), np.zeros((90, 160), np.uint8)], -1)
            for t in range(T)]  # fmt: skip


def _write(out: Path, frames: list[np.ndarray] | None) -> Path:
    pf = _per_frame()
    metrics = summarize(pf, ObjectMotion(12.0, 11.0, 12.0, 1.0))
    labelled = annotate(frames, ("reference (demo)", "result (mujoco)"), FPS) if frames else None
    return write_report(out / "report.html", "test run", metrics, pf, FPS, labelled, {"hand": "shadow"}, ["a note"])


def test_annotate_burns_labels_and_frame_numbers() -> None:
    frames = _frames()
    out = annotate(frames, ("left", "right"), FPS)
    assert len(out) == T and out[0].shape == frames[0].shape
    assert not np.array_equal(out[0][:20, :40], frames[0][:20, :40])  # the left panel's label
    assert not np.array_equal(out[0][:20, 80:120], frames[0][:20, 80:120])  # the right panel's label
    assert not np.array_equal(out[3][:20, -60:] - frames[3][:20, -60:], out[4][:20, -60:] - frames[4][:20, -60:])


def test_report_with_video_and_plots(tmp_path: Path) -> None:
    import imageio_ffmpeg

    page = _write(tmp_path, _frames())
    video = tmp_path / VIDEO_FILE
    n, secs = imageio_ffmpeg.count_frames_and_secs(str(video))
    assert n == T and secs == pytest.approx(T / FPS, abs=0.06)
    assert video.read_bytes()[4:8] == b"ftyp" and b"avc1" in video.read_bytes()[:4096]  # MP4, H.264, moov first
    html = page.read_text()
    assert f"src='{VIDEO_FILE}'" in html and "<video id='qs-video' controls" in html
    assert html.count("<svg class='plot'") == 4 and html.count("class='cursor'") == 4
    data = json.loads(re.search(r"id='qs-data'>(.*?)</script>", html, re.S)[1])
    assert data["frames"] == T and data["fps"] == FPS and data["video"] == VIDEO_FILE
    assert data["series"][3]["values"] == [None] * T  # NaN Chamfer distance -> null, not invalid JSON
    assert html.index("success strict") < html.index("success 10deg_10cm (paper")
    assert "a note" in html and "data:image/png;base64" in html  # the frame strip


def test_report_without_frames_drops_an_old_video(tmp_path: Path) -> None:
    (tmp_path / VIDEO_FILE).write_bytes(b"old")
    html = _write(tmp_path, None).read_text()
    assert not (tmp_path / VIDEO_FILE).exists() and "<video" not in html and "No video" in html


def test_report_plays_in_chromium(tmp_path: Path) -> None:
    page = _write(tmp_path, _frames())
    start = chromium_check(page)
    if start is None:
        pytest.skip(f"{CHROMIUM} not found (apt-get install chromium to check reports in a browser)")
    assert start["duration"] == pytest.approx(T / FPS, abs=0.06)
    assert start["errors"] == [] and start["console"] == []
    assert start["readout"].startswith(f"frame 0 / {T - 1}") and len(start["cursors"]) == 4
    # the page seeks the video to a frame (as a click on a plot does); the cursors and readout follow it
    later = chromium_check(page, "frame=12")
    assert later["readout"].startswith(f"frame 12 / {T - 1} (0.60 s): object rotation error 12.0 deg")
    x0, x1 = 42.0, 320.0  # the plot's first and last frame (PAD_L, SVG_W - PAD_R)
    assert later["cursors"] == pytest.approx([x0 + (x1 - x0) * 12 / (T - 1)] * 4, abs=0.01)
    assert later["errors"] == [] and later["console"] == []


@pytest.mark.parametrize("n", [2, 60, 600, 3000, 10_000, 100_000])
def test_per_frame_plots_of_any_length(n: int) -> None:
    """A clip of any length gets its plots (a 10,000-frame clip ended in a traceback here): at most 9 frame
    ticks, the last frame on the axis."""
    from quasisim.eval.report import svg_plot

    svg = svg_plot(np.linspace(0.0, 3.0, n), "object translation error", "cm", 2.0)
    ticks = [int(t) for t in re.findall(r"text-anchor='middle'>(\d+)</text>", svg)]
    assert 1 <= len(ticks) <= 9 and ticks[0] == 0 and ticks == sorted(ticks) and ticks[-1] <= n - 1
    assert svg.count("<polyline") == 1
