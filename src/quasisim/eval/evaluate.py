"""Judge a control trajectory in a target simulator: scene, rollout, metrics, report."""

from __future__ import annotations

import sys
import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from quasisim.assets.hand import HandModel, builtin_hands
from quasisim.data.controls import Controls
from quasisim.data.demo import Demo
from quasisim.errors import InputError, QuasisimError
from quasisim.eval.export import export_mujoco
from quasisim.eval.metrics import PerFrame, evaluate_rollout
from quasisim.eval.render import RenderedFrames
from quasisim.eval.report import write_report
from quasisim.eval.robust import Policy, RobustConfig, robust_success
from quasisim.files import output_set, save_json_atomic
from quasisim.sim.pointset import HandPoints, sample_hand_points, surface_points_over_time
from quasisim.targets import TargetRollout, make_target
from quasisim.targets.build import demo_hands, scene_for
from quasisim.targets.scene import Scene, place_hands

CD_SPACING = 0.006  # m between robot surface samples for the Chamfer distance
# the clip-length warning's estimate of judging a clip, per frame (2-core machine, MuJoCo; docs/history "Commands on long clips"):
# the rollout, metrics and outputs; each perturbed replay of robust success; rendering the report's video
JUDGE_S_PER_FRAME, REPLAY_S_PER_FRAME, RENDER_S_PER_FRAME, JUDGE_MB_PER_FRAME = 0.004, 0.002, 0.2, 0.15


# a closed-loop replay re-plans every frame (configs/track.yaml): about this many seconds per frame
CLOSED_LOOP_S_PER_FRAME = 0.15

PolicyMaker = Callable[[Demo, Scene, np.ndarray, str], Callable[[], Policy]]
"""``maker(demo, nominal scene, PD targets (T, D), target) -> (() -> Policy)``: how closed-loop robust success
builds a fresh controller per replay (:func:`quasisim.method.track.closed_loop`)."""


def _configs(robust: RobustConfig | Sequence[RobustConfig] | None) -> tuple[RobustConfig, ...]:
    if robust is None:
        return ()
    return (robust,) if isinstance(robust, RobustConfig) else tuple(robust)


def judging_cost(
    render: bool, robust: RobustConfig | Sequence[RobustConfig] | None, closed_loop: bool = False
) -> tuple[float, float]:
    """(seconds, MB) per frame of judging a clip in MuJoCo (PyBullet's rollouts are slower)."""
    n = sum(c.n for c in _configs(robust))
    per_replay = REPLAY_S_PER_FRAME + (CLOSED_LOOP_S_PER_FRAME if closed_loop else 0.0)
    return JUDGE_S_PER_FRAME + n * per_replay + render * RENDER_S_PER_FRAME, JUDGE_MB_PER_FRAME


OUTPUTS = ("metrics.json", "rollout.npz", "report.html", "video.mp4", "scene.xml", "trajectory.npz")
STABILITY_KEY = "unstable"  # metrics.json: the metrics of eval.metrics plus this flag (see mark_stability)  # what evaluate writes (as one set, see files.output_set)


@dataclass(frozen=True, eq=False)
class Evaluation:
    metrics: dict[str, Any]
    per_frame: PerFrame
    rollout: TargetRollout
    scene: Scene


# surface samples per hand object; entries live and die with their hand
_CD_POINTS: weakref.WeakKeyDictionary[HandModel, HandPoints] = weakref.WeakKeyDictionary()


def robot_surface(hand: HandModel, base_rot: np.ndarray, qpos: np.ndarray) -> np.ndarray:
    """(T, P, 3) robot collision-surface samples per frame (for the Chamfer distance)."""
    pts = _CD_POINTS.get(hand)
    if pts is None:
        pts = _CD_POINTS[hand] = sample_hand_points(hand, CD_SPACING, 0.0, seed=1)
    return surface_points_over_time(hand, base_rot, qpos, pts)


def scene_surface(scene: Scene, qpos: np.ndarray) -> np.ndarray:
    """(T, P, 3) :func:`robot_surface` of every hand of ``scene`` from the hands' ``qpos`` (T, D), concatenated."""
    hands = zip(scene.hands, scene.base_rots, scene.dof_slices, strict=True)
    parts = [robot_surface(h, R, qpos[:, sl]) for h, R, sl in hands]
    return parts[0] if len(parts) == 1 else np.concatenate(parts, axis=1)


def hands_of(controls: Controls, path: str | Path | None) -> tuple[HandModel, ...]:
    """The hand(s) that ``controls`` (read from ``path``) were made for (:func:`demo_hands`); an unknown hand
    names the controls file."""
    if Path(controls.hand).suffix in (".yaml", ".yml") and not Path(controls.hand).is_file():
        raise InputError(
            path, "hand", f"a built-in hand ({', '.join(builtin_hands())}) or an existing hand YAML",
            f"{controls.hand!r} (no such file)",
        )  # fmt: skip
    try:
        return demo_hands(controls.hand, controls.sides)
    except QuasisimError as e:
        if isinstance(e, InputError):
            raise
        raise InputError(
            path, "hand", f"a built-in hand ({', '.join(builtin_hands())}) or a hand YAML", repr(controls.hand)
        ) from None


def check_controls(
    demo: Demo, controls: Controls, hand: HandModel | tuple[HandModel, ...], path: str | Path | None = None
) -> None:
    """Refuse controls that do not fit ``demo`` and the robot ``hand`` (one, or one per hand of the demo)."""
    hand = hand if isinstance(hand, HandModel) else hand[0]
    if controls.sides != demo.sides:
        n, m = len(demo.sides), len(controls.sides)
        raise InputError(
            path, "left_base_rot", f"controls for {n} hand(s) (demo {demo.name} has {', '.join(demo.sides)})",
            f"controls for {m} hand(s)" + (" (no left_base_rot)" if m < n else ""),
        )  # fmt: skip
    if abs(controls.fps - demo.fps) > 1e-6 * demo.fps:
        raise InputError(path, "fps", f"{demo.fps:g} (the frame rate of demo {demo.name})", f"{controls.fps:g}")
    if controls.n_frames != demo.n_frames:
        raise InputError(path, "q_targets", f"{demo.n_frames} frames (as demo {demo.name})", f"{controls.n_frames}")
    if tuple(controls.joint_names) != tuple(hand.joint_names):
        raise InputError(
            path, "joint_names", f"the joints of hand '{hand.name}'", f"{len(controls.joint_names)} other joints"
        )


def evaluate_controls(
    demo: Demo,
    controls: Controls,
    target: str,
    out_dir: str | Path | None = None,
    render: bool = True,
    scene: Scene | None = None,
    title: str | None = None,
    extra_info: dict[str, Any] | None = None,
    extra_images: dict[str, bytes] | None = None,
    progress: bool = False,
    robust: RobustConfig | Sequence[RobustConfig] | None = None,
    closed_loop: PolicyMaker | None = None,
) -> Evaluation:
    """Roll ``controls`` out in ``target`` and compute the metrics; with ``out_dir`` write
    ``metrics.json``, ``rollout.npz``, ``report.html`` (+ ``video.mp4``), ``scene.xml`` and ``trajectory.npz``
    there, as one set (with ``manifest.json``). With ``robust`` (one or more perturbation sets with ``n`` > 0),
    the metrics hold, under each set's name (``robust``, ``robust_wide``), the fraction of ``n`` perturbed
    replays that pass each success criterion (:mod:`quasisim.eval.robust`); with ``closed_loop`` also the same
    worlds replayed closed loop (``robust_closed_loop``, ...: a controller made by ``closed_loop`` from the
    nominal scene, :func:`quasisim.method.track.closed_loop`)."""
    hands = scene.hands if scene is not None else demo_hands(controls.hand, controls.sides)
    check_controls(demo, controls, hands)
    scene = scene or scene_for(demo, place_hands(hands, controls.base_rots))
    with make_target(target, scene) as tgt:
        rollout = tgt.rollout(controls.q_targets)
    surf = scene_surface(scene, rollout.qpos)
    metrics, pf = evaluate_rollout(demo, rollout, surf)
    metrics = mark_stability(metrics, rollout.instability, f"{demo.name} in {target}")
    metrics |= robust_metrics(demo, scene, controls.q_targets, target, robust, closed_loop)
    ev = Evaluation(metrics, pf, rollout, scene)
    if out_dir is not None:
        with output_set(Path(out_dir)) as stage:
            write_outputs(ev, demo, controls, target, stage, render, title, extra_info, extra_images, progress)
    return ev


def robust_metrics(
    demo: Demo, scene: Scene, q: np.ndarray, target: str, robust: RobustConfig | Sequence[RobustConfig] | None,
    closed_loop: PolicyMaker | None,
) -> dict[str, Any]:  # fmt: skip
    """``{set name: open-loop robust success, set name + "_closed_loop": closed loop}`` for every set of
    ``robust`` with replays (closed loop only with ``closed_loop``)."""
    out: dict[str, Any] = {}
    policy = None
    for cfg in _configs(robust):
        if cfg.n == 0:
            continue
        out[cfg.name] = robust_success(demo, scene, q, target, cfg)
        if closed_loop is not None:
            policy = policy or closed_loop(demo, scene, q, target)
            out[cfg.closed_loop_key] = robust_success(demo, scene, q, target, cfg, policy)
    return out


def mark_stability(metrics: dict[str, Any], instability: str, what: str) -> dict[str, Any]:
    """``metrics`` with ``unstable`` (true when the simulation blew up); an unstable rollout is a failure
    (every success flag false), said in one line on stderr."""
    if not instability:
        return {**metrics, STABILITY_KEY: False}
    print(f"warning: {what}: unstable simulation ({instability}); counted as a failure", file=sys.stderr)
    return {**metrics, "success": dict.fromkeys(metrics["success"], False), STABILITY_KEY: True}


def write_outputs(
    ev: Evaluation,
    demo: Demo,
    controls: Controls,
    target: str,
    out_dir: Path,
    render: bool,
    title: str | None,
    extra_info: dict[str, Any] | None,
    extra_images: dict[str, bytes] | None,
    progress: bool,
) -> None:
    """Write :data:`OUTPUTS` into ``out_dir`` (a staging folder of :func:`~quasisim.files.output_set`)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    save_json_atomic(out_dir / "metrics.json", ev.metrics)
    ev.rollout.save(out_dir / "rollout.npz")
    export_mujoco(ev.scene, ev.rollout, out_dir)
    frames = None
    notes = list(ev.scene.notes)
    if ev.rollout.instability:
        notes.insert(0, f"UNSTABLE simulation, counted as a failure: {ev.rollout.instability}")
    if render:
        try:  # rendered frame by frame while the video is written (memory does not grow with the clip)
            r = ev.rollout
            labels = ("reference (demo)", f"result ({target})")
            frames = RenderedFrames(ev.scene, demo, r.qpos, r.object_pos, r.object_quat, labels, progress=progress)
        except Exception as e:  # no GL context on this machine: keep the report, say why
            notes.append(f"rendering unavailable ({type(e).__name__}: {e}); set MUJOCO_GL=egl or osmesa")
    t = ev.scene.table
    info = {
        "demo": f"{demo.name} ({demo.n_frames} frames at {demo.fps:g} fps)",
        "hand": " + ".join(h.name for h in ev.scene.hands),
        "method": controls.method,
        "target": f"{target} (dt {ev.rollout.dt * 1e3:g} ms, {ev.rollout.substeps} substeps per frame)",
        "object": f"{ev.scene.obj.name}: {ev.scene.obj.mass * 1e3:.0f} g, {len(ev.scene.obj.convex_parts())} convex parts",
        "table": f"x [{t.xmin:.3f}, {t.xmax:.3f}] y [{t.ymin:.3f}, {t.ymax:.3f}] top {t.top:.3f} m",
        "rollout wall time": f"{ev.rollout.wall_s:.2f} s",
        **(extra_info or {}),
    }
    try:
        write_report(
            out_dir / "report.html",
            title or f"{demo.name}: {controls.method} in {target}",
            ev.metrics,
            ev.per_frame,
            demo.fps,
            frames,
            info,
            notes,
            extra_images,
        )
    finally:
        if frames is not None:
            frames.close()
