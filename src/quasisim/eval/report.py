"""The run's report: ``report.html`` with ``video.mp4`` beside it (H.264; the page plays it with pause and
scrubbing), per-frame error plots whose cursor follows the video, the metrics with what each criterion
means, the run's settings and a frame strip. Everything but the video is inline."""

from __future__ import annotations

import base64
import html
import io
import json
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import imageio.v3 as iio
import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from quasisim.eval.metrics import MOVE_FRACTION, PAPER_KEYS, STRICT_CM, STRICT_DEG, PerFrame
from quasisim.eval.robust import CLOSED_LOOP_SUFFIX, ROBUST_SETS
from quasisim.eval.summary import lifted_text, yes_no
from quasisim.files import atomic_path, save_text_atomic

VIDEO_FILE = "video.mp4"


def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


def png_bytes(img: np.ndarray) -> bytes:
    buf = io.BytesIO()
    iio.imwrite(buf, img, extension=".png")
    return buf.getvalue()


def write_mp4(path: str | Path, frames: Sequence[np.ndarray], fps: float) -> Path:
    """H.264 MP4 (yuv420p, moov atom first: browsers play and seek it at once), one video frame per frame."""
    import imageio_ffmpeg

    h, w = (n - n % 2 for n in frames[0].shape[:2])  # yuv420p needs even sizes
    with atomic_path(path) as tmp, warnings.catch_warnings():
        # JAX warns on any fork; this one execs ffmpeg at once (no Python runs in the child)
        warnings.filterwarnings("ignore", message="os.fork", category=RuntimeWarning)
        writer = imageio_ffmpeg.write_frames(
            str(tmp), (w, h), fps=fps, codec="libx264", pix_fmt_out="yuv420p", macro_block_size=2,
            output_params=["-movflags", "+faststart", "-crf", "23"], ffmpeg_log_level="error",
        )  # fmt: skip
        writer.send(None)
        for f in frames:
            writer.send(np.ascontiguousarray(f[:h, :w]))
        writer.close()
    return Path(path)


def frame_strip(frames: Sequence[np.ndarray], n: int = 6) -> np.ndarray:
    """Stack ``n`` evenly spaced side-by-side frames vertically (reference left, result right)."""
    idx = np.linspace(0, len(frames) - 1, n).round().astype(int)
    return np.concatenate([frames[i] for i in idx], axis=0)


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
        *_robust_rows(metrics),
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


def _robust_rows(metrics: dict[str, Any]) -> list[tuple[str, str, str]]:
    """The robust-success rows of the metrics table, open and closed loop side by side, one pair of rows per
    perturbation set (none without robust replays)."""
    rows = []
    for name, what in ROBUST_SETS.items():
        opened, closed = metrics.get(name), metrics.get(name + CLOSED_LOOP_SUFFIX)
        if not opened:
            continue
        why = f"fraction of {opened['n']} replays in perturbed targets ({what}) that pass"
        if closed:
            why += (f"; open loop / closed loop (a tracker re-planning from the observed state, "
                    f"{closed['seconds_per_replay']:.1f} s and {closed['tracker']['replans']:.0f} re-plans per replay)")  # fmt: skip
        for k, label in (("strict", "strict"), ("20deg_20cm", "20 deg / 20 cm")):
            value = f"{opened[k]:.0%}" + (f" / {closed[k]:.0%}" if closed else "")
            rows.append((f"{name.replace('_', ' ')} success {k}", value, f"{why} {label}"))
    return rows


# (PerFrame field, title, unit, strict limit): the per-frame plots, in order
PANELS = (
    ("rot_deg", "object rotation error", "deg", STRICT_DEG),
    ("trans_cm", "object translation error", "cm", STRICT_CM),
    ("mpjpe_mm", "hand keypoint error (MPJPE)", "mm", None),
    ("cd_mm", "hand Chamfer distance", "mm", None),
)
SVG_W, SVG_H, PAD_L, PAD_R, PAD_T, PAD_B = 330, 170, 42, 10, 24, 26


def _frame_step(n: int) -> int:
    """The frame axis' tick step: the smallest 1-2-5 multiple of 5 that gives at most 8 steps (any length)."""
    if n <= 5:
        return 1
    step = 5
    while n / step > 8:
        step = step * 5 // 2 if str(step)[0] == "2" else step * 2  # 5, 10, 20, 50, 100, 200, 500, ...
    return step


def svg_plot(y: np.ndarray, title: str, unit: str, limit: float | None) -> str:
    """One per-frame plot (frame axis) as inline SVG with a cursor line (class ``cursor``) for the page's script;
    ``data-x0`` / ``data-x1`` are the x positions of the first and the last frame."""
    n = len(y)
    fin = y[np.isfinite(y)]
    ticks = MaxNLocator(nbins=3).tick_values(0.0, max(float(fin.max()) if fin.size else 1.0, limit or 0.0, 1e-3))
    top = float(ticks[-1])

    def x(i: float) -> float:  # frame -> SVG x
        return PAD_L + (SVG_W - PAD_L - PAD_R) * i / max(n - 1, 1)

    def yy(v: float) -> float:  # value -> SVG y
        return SVG_H - PAD_B - (SVG_H - PAD_B - PAD_T) * v / top

    out = [
        f"<svg class='plot' viewBox='0 0 {SVG_W} {SVG_H}' width='{SVG_W}' height='{SVG_H}' "
        f"data-x0='{x(0):.2f}' data-x1='{x(n - 1):.2f}'>",
        f"<text x='{PAD_L}' y='15' class='title'>{html.escape(title)} ({unit})</text>",
        f"<line class='axis' x1='{PAD_L}' y1='{yy(0):.1f}' x2='{x(n - 1):.1f}' y2='{yy(0):.1f}'/>",
        f"<line class='axis' x1='{PAD_L}' y1='{PAD_T}' x2='{PAD_L}' y2='{yy(0):.1f}'/>",
    ]
    for v in ticks:
        out.append(f"<text class='tick' x='{PAD_L - 4}' y='{yy(v) + 4:.1f}' text-anchor='end'>{v:.3g}</text>")
    for i in range(0, n, _frame_step(n)):
        out.append(f"<text class='tick' x='{x(i):.1f}' y='{SVG_H - 12}' text-anchor='middle'>{i}</text>")
    out.append(f"<text class='tick' x='{SVG_W - PAD_R}' y='{SVG_H - 1}' text-anchor='end'>frame</text>")
    if limit is not None:
        out.append(f"<line class='limit' x1='{PAD_L}' y1='{yy(limit):.1f}' x2='{x(n - 1):.1f}' y2='{yy(limit):.1f}'/>")
        out.append(
            f"<text class='tick limit-label' x='{x(n - 1):.1f}' y='{yy(limit) - 3:.1f}' text-anchor='end'>strict limit {limit:g}</text>"
        )
    pts = " ".join(f"{x(i):.1f},{yy(v):.1f}" for i, v in enumerate(y) if np.isfinite(v))
    out.append(f"<polyline class='series' points='{pts}'/>")
    out.append(f"<line class='cursor' x1='{x(0):.2f}' y1='{PAD_T}' x2='{x(0):.2f}' y2='{yy(0):.1f}'/></svg>")
    return "".join(out)


def _page_data(per_frame: PerFrame, fps: float, video: str | None) -> str:
    """The per-frame values for the page's script (JSON; NaN as null), safe inside a <script> element."""
    series = [
        {"name": title, "unit": unit, "values": [None if not np.isfinite(v) else round(float(v), 4) for v in getattr(per_frame, key)]}
        for key, title, unit, _ in PANELS
    ]  # fmt: skip
    data = {"fps": float(fps), "frames": len(per_frame.rot_deg), "video": video, "series": series}
    return json.dumps(data).replace("</", "<\\/")


STYLE = """body{font-family:sans-serif;margin:24px;max-width:1400px;color:#222}table{border-collapse:collapse}
td{border:1px solid #ccc;padding:4px 10px;vertical-align:top}img{max-width:100%}h2{margin-top:28px}
video{max-width:100%;background:#000}.controls{margin:6px 0}.controls button{margin-right:4px}
#qs-readout{font-family:monospace;margin:6px 0;min-height:1.3em}.plots{display:flex;flex-wrap:wrap;gap:8px}
svg.plot{background:#fafafa;border:1px solid #ddd;cursor:crosshair}svg .title{font-size:12px;font-weight:bold}
svg .tick{font-size:10px;fill:#555}svg .axis{stroke:#888}svg .series{fill:none;stroke:#1f77b4;stroke-width:1.8}
svg .limit{stroke:#d62728;stroke-dasharray:4 3}svg .limit-label{fill:#d62728}svg .cursor{stroke:#000;stroke-width:1.2}
#qs-errors{color:#b00}.verdict{font-size:1.1em}"""

# Keeps the plots' cursors and the readout on the video's frame; a click on a plot seeks the video there;
# report.html#frame=N opens at frame N.
# Writes the video's duration into body[data-video-duration] and any page error into #qs-errors (the
# report test reads both in headless Chromium).
SCRIPT = """(function () {
  var errs = document.getElementById('qs-errors');
  function note(msg) { var li = document.createElement('li'); li.textContent = msg; errs.appendChild(li); errs.hidden = false; }
  window.addEventListener('error', function (e) { note('script error: ' + e.message); });
  var data = JSON.parse(document.getElementById('qs-data').textContent);
  var T = data.frames, fps = data.fps, v = document.getElementById('qs-video');
  var plots = document.querySelectorAll('svg.plot'), readout = document.getElementById('qs-readout');
  function fmt(x) { return x === null ? 'n/a' : x.toFixed(x < 10 ? 2 : 1); }
  function show(f) {
    plots.forEach(function (s) {
      var x0 = +s.dataset.x0, x1 = +s.dataset.x1, x = x0 + (x1 - x0) * f / Math.max(T - 1, 1);
      var c = s.querySelector('.cursor'); c.setAttribute('x1', x); c.setAttribute('x2', x);
    });
    readout.textContent = 'frame ' + f + ' / ' + (T - 1) + ' (' + (f / fps).toFixed(2) + ' s): ' +
      data.series.map(function (s) { return s.name + ' ' + fmt(s.values[f]) + ' ' + s.unit; }).join(', ');
  }
  function frameAt(t) { return Math.max(0, Math.min(T - 1, Math.floor(t * fps + 1e-6))); }
  var current = 0;
  function seek(f) { current = Math.max(0, Math.min(T - 1, f)); if (v) { v.pause(); v.currentTime = (current + 0.5) / fps; } show(current); }
  plots.forEach(function (s) {
    s.addEventListener('click', function (e) {
      var r = s.getBoundingClientRect(), vx = (e.clientX - r.left) * s.viewBox.baseVal.width / r.width;
      var x0 = +s.dataset.x0, x1 = +s.dataset.x1;
      seek(Math.round((vx - x0) / (x1 - x0) * (T - 1)));
    });
  });
  if (v) {
    var tick = function () { current = frameAt(v.currentTime); show(current); if (!v.paused && !v.ended) requestAnimationFrame(tick); };
    ['timeupdate', 'seeked', 'play'].forEach(function (n) { v.addEventListener(n, tick); });
    var meta = function () { document.body.dataset.videoDuration = v.duration; };
    v.addEventListener('loadedmetadata', meta);
    if (v.readyState >= 1) meta();
    v.addEventListener('error', function () {
      note('the video could not be played (' + (v.error ? v.error.message || v.error.code : 'unknown error') + '); ' + data.video + ' must sit beside this page');
    });
    document.getElementById('qs-prev').addEventListener('click', function () { seek(current - 1); });
    document.getElementById('qs-next').addEventListener('click', function () { seek(current + 1); });
    document.getElementById('qs-speed').addEventListener('change', function (e) { v.playbackRate = +e.target.value; });
    document.addEventListener('keydown', function (e) {
      if (e.key === ',') seek(current - 1); else if (e.key === '.') seek(current + 1);
    });
  }
  var linked = /frame=(\\d+)/.exec(location.hash);  // report.html#frame=30 opens at frame 30
  if (linked) seek(+linked[1]); else show(0);
})();"""


def _video_block(video: str | None, fps: float, n: int) -> str:
    if video is None:
        return "<p><i>No video (rendering was disabled or unavailable, see the notes).</i></p>"
    speeds = "".join(f"<option value='{s}'{' selected' if s == 1 else ''}>{s:g}x</option>" for s in (0.25, 0.5, 1, 2))
    return (
        f"<video id='qs-video' controls preload='auto' muted playsinline src='{html.escape(video)}'></video>"
        "<div class='controls'><button id='qs-prev' title='previous frame (,)'>&#9664; frame</button>"
        "<button id='qs-next' title='next frame (.)'>frame &#9654;</button> "
        f"speed <select id='qs-speed'>{speeds}</select> <small>{n} frames at {fps:g} fps; keys , and . step "
        "one frame; click a plot to go to its frame</small></div>"
    )


def _verdict(metrics: dict[str, Any]) -> str:
    s = metrics["success"]
    paper = ", ".join(f"{k.split('deg')[0]}: {yes_no(s[k])}" for k in PAPER_KEYS)
    return (
        f"<p class='verdict'>success <b>strict: {yes_no(s['strict'])}</b>; the paper's thresholds {paper}; "
        f"object lifted: {html.escape(lifted_text(metrics['object_motion']))}</p>"
    )


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
    """Write ``path`` (HTML) and, with ``frames`` (labelled side-by-side images), ``video.mp4`` beside it."""
    path = Path(path)
    notes = list(notes)
    video = None
    if frames:
        try:
            video = write_mp4(path.parent / VIDEO_FILE, frames, fps).name
        except Exception as e:  # no ffmpeg binary on this platform: keep the report, say why
            notes.append(f"video unavailable ({type(e).__name__}: {e})")
    if video is None:
        (path.parent / VIDEO_FILE).unlink(missing_ok=True)  # an earlier run's video would not be this run's
    n = len(per_frame.rot_deg)
    plots = "".join(svg_plot(getattr(per_frame, k), t, u, lim) for k, t, u, lim in PANELS)
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'>",
        f"<title>{html.escape(title)}</title><style>{STYLE}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        _verdict(metrics),
        "<ul id='qs-errors' hidden></ul>",
        "<h2>Reference (demo) and result, frame by frame</h2>",
        "<p>Left: the demo (human keypoints, demo object). Right: the robot hand and the simulated object, with "
        "the demo's keypoints in blue.</p>",
        _video_block(video, fps, n),
        "<div id='qs-readout'></div>",
        f"<h2>Per-frame errors</h2><div class='plots'>{plots}</div>",
        "<h2>Metrics (judged in the target simulator)</h2>",
        _metrics_table(metrics),
        "<h2>Run</h2><table>",
        "".join(f"<tr><td>{html.escape(str(k))}</td><td>{html.escape(str(v))}</td></tr>" for k, v in info.items()),
        "</table>",
    ]
    if notes:
        parts.append("<h2>Notes</h2><ul>" + "".join(f"<li>{html.escape(n)}</li>" for n in notes) + "</ul>")
    if frames:
        strip = _b64(png_bytes(frame_strip(frames)))
        parts.append(
            f"<h2>Frame strip</h2><img alt='frames' style='max-width:820px' src='data:image/png;base64,{strip}'>"
        )
    for name, png in (extra_images or {}).items():
        parts.append(
            f"<h2>{html.escape(name)}</h2><img alt='{html.escape(name)}' src='data:image/png;base64,{_b64(png)}'>"
        )
    parts.append(f"<script type='application/json' id='qs-data'>{_page_data(per_frame, fps, video)}</script>")
    parts.append(f"<script>{SCRIPT}</script></body></html>")
    return save_text_atomic(path, "\n".join(parts))
