"""A self-contained HTML report: metrics, reference-vs-result video and frame strip, per-frame error plots."""

from __future__ import annotations

import base64
import html
import io
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import imageio.v3 as iio
import numpy as np
from matplotlib.figure import Figure

from quasisim.eval.metrics import MOVE_FRACTION, PAPER_KEYS, STRICT_CM, STRICT_DEG, PerFrame
from quasisim.eval.summary import lifted_text, yes_no
from quasisim.files import save_text_atomic


def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


def gif_bytes(frames: Sequence[np.ndarray], fps: float) -> bytes:
    buf = io.BytesIO()
    iio.imwrite(buf, np.stack(frames), extension=".gif", duration=1000.0 / fps, loop=0)
    return buf.getvalue()


def png_bytes(img: np.ndarray) -> bytes:
    buf = io.BytesIO()
    iio.imwrite(buf, img, extension=".png")
    return buf.getvalue()


def frame_strip(frames: Sequence[np.ndarray], n: int = 6) -> np.ndarray:
    """Stack ``n`` evenly spaced side-by-side frames vertically (reference left, result right)."""
    idx = np.linspace(0, len(frames) - 1, n).round().astype(int)
    return np.concatenate([frames[i] for i in idx], axis=0)


def error_plots(pf: PerFrame, fps: float, title: str = "") -> bytes:
    """PNG with per-frame object rotation/translation error, MPJPE and Chamfer distance."""
    t = np.arange(len(pf.rot_deg)) / fps
    fig = Figure(figsize=(16, 3.2), layout="constrained")
    axes = fig.subplots(1, 4)
    specs = [
        (pf.rot_deg, "object rotation error (deg)", STRICT_DEG),
        (pf.trans_cm, "object translation error (cm)", STRICT_CM),
        (pf.mpjpe_mm, "MPJPE (mm)", None),
        (pf.cd_mm, "hand Chamfer distance (mm)", None),
    ]
    for ax, (y, label, thr) in zip(axes, specs, strict=True):
        ax.plot(t, y, lw=1.8)
        if thr is not None:
            ax.axhline(thr, color="tab:red", ls="--", lw=1, label=f"strict limit {thr:g}")
            ax.legend(loc="upper left", fontsize=8)
        ax.set_xlabel("time (s)")
        ax.set_title(label, fontsize=10)
        ax.grid(alpha=0.3)
    if title:
        fig.suptitle(title, fontsize=11)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    return buf.getvalue()


def loss_plot(curves: dict[str, Sequence[float]], title: str = "optimisation loss") -> bytes:
    """PNG of named loss curves (one line per stage/simulator), log-scaled."""
    fig = Figure(figsize=(9, 3.5), layout="constrained")
    ax = fig.subplots()
    offset = 0
    for name, ys in curves.items():
        ys = np.asarray(ys, dtype=float)
        if ys.size == 0:
            continue
        ax.plot(np.arange(offset, offset + len(ys)), ys, lw=1.5, label=name)
        offset += len(ys)
    ax.set_yscale("log")
    ax.set_xlabel("optimisation step (cumulative)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    if curves:
        ax.legend(fontsize=7, ncol=4)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    return buf.getvalue()


def _metrics_table(metrics: dict[str, Any]) -> str:
    s, mo = metrics["success"], metrics["object_motion"]
    rows = [
        ("success strict", yes_no(s["strict"]), f"the object within {STRICT_CM:g} cm and {STRICT_DEG:g} deg of the demo at every frame"),
        *[(f"success {k} (paper's threshold)", yes_no(s[k]), "mean R_err <= {0} deg, T_err <= {0} cm, MPJPE <= {0} cm".format(k.split("deg")[0])) for k in PAPER_KEYS],
        ("object lifted as in the demo", lifted_text(mo), f"the rollout's object rose at least {MOVE_FRACTION:.0%} as high as the demo's"),
        ("object moved as in the demo", yes_no(mo["as_demo"]), f"lifted, and at the demo's farthest frame displaced like it (off by {mo['displacement_error_cm']:.1f} of {mo['demo_displacement_cm']:.1f} cm); every success above requires it"),
        ("object rotation error R_err", f"{metrics['R_err_deg']:.2f} deg", "mean over frames"),
        ("object translation error T_err", f"{metrics['T_err_cm']:.2f} cm", "mean over frames"),
        ("hand keypoint error MPJPE", f"{metrics['MPJPE_mm']:.1f} mm", "mean over frames and metric keypoints"),
        ("hand Chamfer distance CD", f"{metrics['CD_mm']:.1f} mm", "mean over frames, hand surfaces"),
    ]  # fmt: skip
    body = "".join(
        f"<tr><td>{html.escape(a)}</td><td><b>{html.escape(b)}</b></td><td>{html.escape(c)}</td></tr>"
        for a, b, c in rows
    )
    return f"<table>{body}</table>"


def write_report(
    path: str | Path,
    title: str,
    metrics: dict[str, Any],
    per_frame: PerFrame,
    fps: float,
    frames: Sequence[np.ndarray] | None,
    info: dict[str, Any],
    notes: Sequence[str] = (),
    extra_images: dict[str, bytes] | None = None,
) -> Path:
    """Write a single-file HTML report (images embedded) atomically."""
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'>",
        f"<title>{html.escape(title)}</title>",
        "<style>body{font-family:sans-serif;margin:24px;max-width:1400px}table{border-collapse:collapse}"
        "td{border:1px solid #ccc;padding:4px 10px}img{max-width:100%}h2{margin-top:28px}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        "<h2>Metrics (judged in the target simulator)</h2>",
        _metrics_table(metrics),
        "<h2>Run</h2><table>",
        "".join(f"<tr><td>{html.escape(str(k))}</td><td>{html.escape(str(v))}</td></tr>" for k, v in info.items()),
        "</table>",
    ]
    if notes:
        parts.append("<h2>Notes</h2><ul>" + "".join(f"<li>{html.escape(n)}</li>" for n in notes) + "</ul>")
    parts.append(
        "<h2>Reference (left: human keypoints, demo object) and result (right: robot, simulated object; "
        "blue: human keypoints)</h2>"
    )
    if frames:
        parts.append(f"<img alt='video' src='data:image/gif;base64,{_b64(gif_bytes(frames, fps))}'>")
        parts.append("<h3>Frame strip</h3>")
        parts.append(
            f"<img alt='frames' style='max-width:820px' src='data:image/png;base64,{_b64(png_bytes(frame_strip(frames)))}'>"
        )
    else:
        parts.append("<p><i>No rendering (rendering was disabled or unavailable).</i></p>")
    parts.append("<h2>Per-frame errors</h2>")
    parts.append(f"<img alt='errors' src='data:image/png;base64,{_b64(error_plots(per_frame, fps))}'>")
    for name, png in (extra_images or {}).items():
        parts.append(
            f"<h2>{html.escape(name)}</h2><img alt='{html.escape(name)}' src='data:image/png;base64,{_b64(png)}'>"
        )
    parts.append("</body></html>")
    return save_text_atomic(path, "\n".join(parts))
