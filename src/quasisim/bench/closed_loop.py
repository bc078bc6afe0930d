"""Closed-loop robust success for the finished runs of a batch (``quasisim bench transfer --closed-loop``).

Every finished run's controls (``OUT/<clip>/<run>/controls.npz``) are replayed in the seeded perturbed worlds of
each perturbation set, open loop and closed loop (:mod:`quasisim.method.track`), in ``workers`` processes, one
(run, set) per task. Each is cached in ``OUT/<clip>/<run>/robust_closed_loop-<hash of the settings>.json`` with the
settings that made it (the set, the tracker, the target) and the SHA-256 of the controls it replayed, so the pass
resumes where it stopped, a set added later reuses the others, variants of the tracker (``--track-set``) sit side
by side, and a run planned again (other controls) is judged again. A cache from before the hash was kept is used
only where the run's controls are gone (a table read back from tracked caches).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import multiprocessing
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from quasisim.eval.robust import CLOSED_LOOP_SUFFIX
from quasisim.eval.tables import ROBUST_KEYS
from quasisim.files import save_json_atomic

CACHE = "robust_closed_loop-{}.json"


def settings(
    n: int, ranges: str, track: dict[str, Any], target: str, robust_set: dict[str, Any] | None = None
) -> dict[str, Any]:
    """What a cached result of the set ``ranges`` must match: its replays (the set's file contents with the
    ``--robust-set`` overrides), the tracker, the target."""
    from quasisim.eval.robust import replays

    cfg = {k: v for k, v in dataclasses.asdict(replays(n, ranges, robust_set)).items() if k != "path"}
    return json.loads(json.dumps({"sets": {ranges: cfg}, "track": track, "target": target}))


def cache_name(want: dict[str, Any]) -> str:
    """The cache file of a run judged with settings ``want`` (:func:`settings`)."""
    return CACHE.format(hashlib.sha256(json.dumps(want, sort_keys=True).encode()).hexdigest()[:12])


def controls_sha(run_dir: str | Path) -> str | None:
    """The SHA-256 of the run's ``controls.npz`` (None where it is gone)."""
    path = Path(run_dir) / "controls.npz"
    return hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else None


def cached(run_dir: Path, name: str, sha: str | None) -> dict[str, Any] | None:
    """The metrics of the cache ``name`` in ``run_dir``, None where there is none or it judged other controls
    than the run's own, whose hash is ``sha`` (:func:`controls_sha`; a run planned again)."""
    path = run_dir / name
    if not path.is_file():
        return None
    data = json.loads(path.read_text())
    if sha is not None and data.get("controls_sha256") != sha:
        return None
    return data["metrics"]


def judge_run(
    demo_path: str, run_dir: str, n: int, ranges: str, target: str, track: dict[str, Any],
    robust_set: dict[str, Any] | None = None,
) -> dict[str, Any]:  # fmt: skip
    """One run's robust success in the set ``ranges``, open and closed loop (written to its cache); in a
    worker."""
    from quasisim.data.controls import load_controls
    from quasisim.data.demo import load_demo
    from quasisim.eval.evaluate import hands_of, robust_metrics
    from quasisim.eval.robust import replays
    from quasisim.method.track import TrackOptions, closed_loop
    from quasisim.targets.build import scene_for
    from quasisim.targets.scene import place_hands

    demo, c = load_demo(demo_path), load_controls(Path(run_dir) / "controls.npz")
    scene = scene_for(demo, place_hands(hands_of(c, run_dir), c.base_rots))
    opts = TrackOptions.from_yaml(None, track)
    metrics = robust_metrics(demo, scene, c.q_targets, target, [replays(n, ranges, robust_set)], closed_loop(opts))
    want = settings(n, ranges, _track_dict(opts), target, robust_set)
    out = {"settings": want, "controls_sha256": controls_sha(run_dir), "metrics": metrics}
    save_json_atomic(Path(run_dir) / cache_name(want), out)
    return out


# tracker settings added after caches were written: left out of the settings at their default, so that the
# older caches (made when the setting did not exist, i.e. at that default) still match
ADDED_LATER = {
    "lead": 0, "keep": 0.0, "shift_fade": 0.0, "obs_adapt": False, "obs_adapt_decay": 0.9, "grip": (), "grip_gap": 0.02,
    "object_weight": 1.0, "worlds": (), "world_thin": 0.001, "world_risk": "worst", "world_cvar": 0.5,
    "grasp_weight": 0.0, "grasp_margin": 0.2, "grasp_slots": 8,
}  # fmt: skip


def _track_dict(track: Any) -> dict[str, Any]:
    d = dataclasses.asdict(track)
    return {k: v for k, v in d.items() if k != "path" and not (k in ADDED_LATER and v == ADDED_LATER[k])}


def add_closed_loop(
    rows: list[dict[str, Any]], out: Path, demo_paths: dict[str, Path], n: int, ranges: tuple[str, ...],
    target: str, workers: int, track: dict[str, Any] | None = None, robust_set: dict[str, Any] | None = None,
) -> list[dict[str, Any]]:  # fmt: skip
    """``rows`` (a batch's run rows, ``method`` = run name; the kinematic rows pass through) with every
    perturbation set's open- and closed-loop robust success merged in, computed where no cache matches;
    ``track``: overrides of ``configs/track.yaml``; ``robust_set``: of every perturbation set."""
    from quasisim.method.track import TrackOptions

    track = track or {}
    opts = _track_dict(TrackOptions.from_yaml(None, track))
    todo, done = [], {(r["clip"], r["method"]): {} for r in rows}
    for r in rows:
        run_dir = out / r["clip"] / r["method"]
        if r["method"] == "kinematic":
            continue
        missing, sha = [], controls_sha(run_dir)
        for s in ranges:
            metrics = cached(run_dir, cache_name(settings(n, s, opts, target, robust_set)), sha)
            if metrics is not None:
                done[(r["clip"], r["method"])].update(metrics)
            else:
                missing.append(s)
        if missing and sha is None:
            print(f"closed loop: {r['clip']} {r['method']}: no controls.npz in {run_dir}; skipped")
        elif missing:
            todo += [(r["clip"], r["method"], s, str(demo_paths[r["clip"]]), str(run_dir)) for s in missing]
    if todo:
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max(1, workers), mp_context=ctx) as pool:
            futs = {pool.submit(judge_run, d, rd, n, s, target, track, robust_set): (c, m) for c, m, s, d, rd in todo}
            for f in tqdm(as_completed(futs), total=len(futs), desc="closed loop", unit="run x set"):
                done[futs[f]].update(f.result()["metrics"])
    return [r | done.get((r["clip"], r["method"]), {}) for r in rows]


def markdown(
    rows: list[dict[str, Any]], runs: tuple[str, ...], ranges: tuple[str, ...], track: dict[str, Any] | None = None
) -> list[str]:
    """The closed-loop tables: per set and run, open vs closed loop robust success and the tracker's cost
    (summary), then per clip."""
    from quasisim.eval.robust import replays

    keys = [replays(None, r).name for r in ranges]
    lines = [
        "### Robust success open vs closed loop",
        "",
        "Fractions of the perturbed replays that pass (%), open loop / closed loop; the tracker's cost per replay and "
        "its time per control step and per re-plan (median / 95th percentile, ms, the mean over replays; a re-plan "
        "beside the controller, `lead` > 0, must take at most `every` frame periods); `replays / plan`: the "
        "closed-loop replays' seconds over the run's own (its stages'). Tracker: "
        "configs/track.yaml" + (" with " + ", ".join(f"{k}={v}" for k, v in track.items()) if track else "") + ".",
        "",
        "| set | method | clips | strict open | strict closed | 20/20 open | 20/20 closed | s per replay | ms per "
        "step p50 / p95 | ms per re-plan p50 / p95 | re-plans per replay | replays / plan |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for key in keys:
        for run in runs:
            rs = [r for r in rows if r["method"] == run and r.get(key) and r.get(key + CLOSED_LOOP_SUFFIX)]
            if rs:
                lines.append(_summary_row(key, run, rs))
    lines += ["", "| clip | method | set | strict open / closed | 20/20 open / closed | s per replay | ms per step "
              "p50 / p95 |", "|---|---|---|---|---|---|---|"]  # fmt: skip
    for r in rows:
        for key in keys:
            o, c = r.get(key), r.get(key + CLOSED_LOOP_SUFFIX)
            if r["method"] == "kinematic" or not (o and c):
                continue
            cells = " | ".join(f"{100 * o[k]:.0f} / {100 * c[k]:.0f}" for k in ROBUST_KEYS)
            lines.append(f"| {r['clip']} | {r['method']} | {key} | {cells} | {c['seconds_per_replay']:.1f} | "
                         f"{step_ms([c])} |")  # fmt: skip
    return lines


def _summary_row(key: str, run: str, rs: list[dict[str, Any]]) -> str:
    c = [r[key + CLOSED_LOOP_SUFFIX] for r in rs]
    pct = lambda xs: f"{100.0 * np.mean(xs):.0f}"  # noqa: E731
    cols = [pct([r[key][k] for r in rs]) + " | " + pct([x[k] for x in c]) for k in ROBUST_KEYS]
    ratio = [x["seconds_per_replay"] * x["n"] / r["wall_s"] for x, r in zip(c, rs, strict=True) if r.get("wall_s")]
    return (
        f"| {key} | {run} | {len(rs)} | {' | '.join(cols)} | {np.mean([x['seconds_per_replay'] for x in c]):.1f} | "
        f"{step_ms(c)} | {step_ms(c, 'replan')} | {np.mean([x['tracker']['replans'] for x in c]):.0f} | "
        + (f"{np.mean(ratio):.2f} (max {np.max(ratio):.2f})" if ratio else "-")
        + " |"
    )


def step_ms(results: list[dict[str, Any]], what: str = "step") -> str:
    """The tracker's time per control step (``what`` "step") or per re-plan ("replan") over closed-loop results,
    "p50 / p95" ms (means over runs; "-" for results cached before the tracker timed them)."""
    t = [r["tracker"] for r in results if f"{what}_ms_p50" in r["tracker"]]
    if not t:
        return "-"
    return f"{np.mean([x[f'{what}_ms_p50'] for x in t]):.0f} / {np.mean([x[f'{what}_ms_p95'] for x in t]):.0f}"
