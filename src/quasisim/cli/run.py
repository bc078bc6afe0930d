"""The commands of one clip and of many: example, retarget, evaluate, transfer, batch."""

from __future__ import annotations

import time
from pathlib import Path

import click

from quasisim.cli._common import (
    _CLOSED_LOOP,
    _LEAD_CLIP,
    _OVERWRITE,
    _RANGES,
    _ROBUST,
    _ROBUST_SET,
    _SPEC,
    _TRACK_SET,
    _TRACKER,
    TARGET_CHOICE,
    _ablation_flags,
    _friendly,
    _interruptible,
    _outputs_free,
    _parse_sets,
    _ranges,
    _robust_over,
    _robust_sets,
    _setup_runtime,
    _stages,
    _summary,
    _track_overrides,
    main,
)
from quasisim.errors import QuasisimError
from quasisim.method.registry import METHODS as REGISTERED_METHODS
from quasisim.method.spec import DEFAULT_METHOD, FULL_STAGES, METHODS, TransferSpec, networks_from_flags


@main.command()
@click.option("--out", "out", type=click.Path(path_type=Path), required=True, help="Output folder.")
@click.option(
    "--name", "names", multiple=True, help="Example to write (repeatable): cube_lift, cylinder_lift_turn; default: all."
)
@click.option(
    "--frames", type=click.IntRange(12, 100_000), default=60, show_default=True, help="Frames per example (20 fps)."
)
@_OVERWRITE
@_friendly
def example(out: Path, names: tuple[str, ...], frames: int, overwrite: bool) -> None:
    """Write the built-in synthetic example demo(s) (demo npz v1 + meshes/) to OUT."""
    from quasisim.data.synthetic import EXAMPLES, write_example
    from quasisim.errors import choice_error

    for n in names:
        if n not in EXAMPLES:
            raise choice_error("example", n, EXAMPLES)
    _outputs_free(out, tuple(f"{n}.npz" for n in names or EXAMPLES), overwrite)

    for n in names or EXAMPLES:
        p = write_example(n, out, n_frames=frames)
        click.echo(str(p))


@main.command()
@click.argument("demo", type=click.Path(path_type=Path))
@click.option(
    "--hand",
    default="shadow",
    show_default=True,
    help="Built-in hand (shadow, shadow-left, shadow-short-thumb, allegro) or a hand YAML (docs/hands.md).",
)
@click.option("--out", "out", type=click.Path(path_type=Path), required=True, help="Output folder.")
@_OVERWRITE
@_friendly
def retarget(demo: Path, hand: str, out: Path, overwrite: bool) -> None:
    """Kinematic retargeting of DEMO to a robot hand: writes OUT/kinematic.npz (PD targets per frame)."""
    _setup_runtime()
    import numpy as np

    from quasisim.data.demo import load_demo, warn_long_clip
    from quasisim.method.retarget import RETARGET_MB_PER_FRAME, RETARGET_S_PER_FRAME, kinematic_controls
    from quasisim.targets.build import demo_hands

    d = load_demo(demo)
    hands = demo_hands(hand, d.sides)  # two-hand demos: the hand and its mirror image
    from quasisim.files import check_out_dir, run_lock

    check_out_dir(out)
    with run_lock(out, f"retarget {d.name}"):  # one run per folder
        _outputs_free(out, ("kinematic.npz",), overwrite)
        warn_long_clip(d, RETARGET_S_PER_FRAME, RETARGET_MB_PER_FRAME, "retargeting")
        t0 = time.perf_counter()
        c = kinematic_controls(hands, d, hand, progress=True)
        path = c.save(out / "kinematic.npz")
    metric = np.concatenate([h.kp_metric for h in hands])
    err = c.extras["retarget_keypoint_error"][:, metric].mean() * 1e3
    click.echo(
        f"{path}  ({d.n_frames} frames, mean metric keypoint error {err:.1f} mm, {time.perf_counter() - t0:.1f} s)"
    )


@main.command()
@click.argument("demo", type=click.Path(path_type=Path))
@click.argument("controls", type=click.Path(path_type=Path))
@click.option("--target", type=TARGET_CHOICE, default="mujoco", show_default=True)
@click.option("--out", "out", type=click.Path(path_type=Path), required=True, help="Output folder.")
@click.option("--render/--no-render", default=True, show_default=True, help="Render the video for the report.")
@click.option("--force", is_flag=True, help="Replay controls made for another demo (a different content hash).")
@_ROBUST
@_CLOSED_LOOP
@_TRACKER
@_TRACK_SET
@_RANGES
@_ROBUST_SET
@_OVERWRITE
@_friendly
def evaluate(
    demo: Path, controls: Path, target: str, out: Path, render: bool, force: bool, robust: int | None,
    closed_loop: bool, tracker: str, track_sets: tuple[str, ...], ranges: str, robust_sets: tuple[str, ...],
    overwrite: bool,
) -> None:  # fmt: skip
    """Replay CONTROLS for DEMO in a target simulator: writes metrics.json, rollout.npz, report.html."""
    _setup_runtime()
    from quasisim.data.controls import check_demo_hash, load_controls
    from quasisim.data.demo import content_hash, load_demo, warn_long_clip
    from quasisim.eval.evaluate import OUTPUTS, check_controls, evaluate_controls, hands_of, judging_cost
    from quasisim.files import MANIFEST

    d = load_demo(demo)
    c = load_controls(controls)
    check_controls(d, c, hands_of(c, controls), controls)
    note = check_demo_hash(c, content_hash(d), controls, force)
    from quasisim.files import check_out_dir, run_lock

    check_out_dir(out)
    with run_lock(out, f"evaluate {d.name}"):  # one run per folder
        _outputs_free(out, (*OUTPUTS, MANIFEST), overwrite)
        if note:
            click.echo(f"warning: {note}", err=True)
        robust_cfg = _robust_sets(robust, ranges, closed_loop, robust_sets)
        cost = judging_cost(render, robust_cfg, closed_loop)
        warn_long_clip(d, *cost, "evaluation" + (" with rendering" if render else ""))
        maker = None
        if closed_loop:
            from quasisim.method.track import TrackOptions
            from quasisim.method.track import closed_loop as make_tracker

            maker = make_tracker(TrackOptions.from_yaml(None, _track_overrides(tracker, track_sets)))
        ev = evaluate_controls(d, c, target, out, render=render, progress=True, robust=robust_cfg, closed_loop=maker)
    click.echo(f"wrote {out / 'metrics.json'}, {out / 'rollout.npz'}")
    label = c.method.split("[")[0] or "controls"  # e.g. "sample-target[default;stages sample;fast]"
    _summary(f"{d.name}: {label} in {target}", {label: ev.metrics}, out / "report.html")


@main.command()
@click.argument("demo", type=click.Path(path_type=Path))
@click.option(
    "--hand",
    default=_SPEC.hand,
    show_default=True,
    help="Built-in hand (shadow, shadow-left, shadow-short-thumb, allegro) or a hand YAML (docs/hands.md).",
)
@click.option(
    "--target", type=TARGET_CHOICE, default=_SPEC.target, show_default=True, help="Simulator that judges the result."
)
@click.option(
    "--curriculum",
    default=_SPEC.curriculum,
    show_default=True,
    help="short (4 analytical simulators), default (the paper's 8), curriculum2, none or a YAML path.",
)
@click.option(
    "--stages",
    default=None,
    help="Stages of method ours (given alone, they imply --method ours; default "
    f"{','.join(FULL_STAGES)}): quick: sampling in the target that ends the run where it passes strict success, "
    "1: point dynamics, 2: contact curriculum, mpc: closed-loop MPC in MuJoCo with the "
    "quasi-physical model, sample: sampling MPC in the target, select: keep the best trajectory seen, judged in "
    "the target.",
)
@click.option(
    "--method",
    type=click.Choice(METHODS),
    default=None,
    help=f"Default {DEFAULT_METHOD} (ours where --stages is given). "
    + "; ".join(f"{name}: {m.summary}" for name, m in REGISTERED_METHODS.items())
    + ".",
)
@click.option("--budget", default=_SPEC.budget, show_default=True, help="Step budget from the config: fast or paper.")
@click.option("--out", "out", type=click.Path(path_type=Path), required=True, help="Output folder.")
@click.option("--resume", is_flag=True, help="Continue the run in OUT from its last checkpoint.")
@click.option(
    "--overwrite", is_flag=True, help="Start afresh in OUT, replacing an earlier run's outputs and checkpoints."
)
@click.option("--config", "config_path", type=click.Path(path_type=Path), default=None, help="Transfer config YAML.")
@click.option(
    "--set", "sets", multiple=True, help="Override a config key, e.g. --set budgets.fast.sim.control_steps=20."
)
@click.option("--render/--no-render", default=_SPEC.render, show_default=True, help="Render the video for the report.")
@click.option(
    "--record-transitions", "record", type=click.Path(path_type=Path), default=None,
    help="Keep every window the sampling stage rolls out in the target, and the final run's states, in "
    "DIR/<demo>.<method>.npz (data for fitting a simulator to the target; docs/transfer.md).",
)  # fmt: skip
@_ROBUST
@_CLOSED_LOOP
@_RANGES
@_ROBUST_SET
@_ablation_flags
@_friendly
def transfer(
    demo: Path, hand: str, target: str, curriculum: str, stages: str | None, method: str | None, budget: str, out: Path,
    resume: bool, overwrite: bool, config_path: Path | None, sets: tuple[str, ...], render: bool, record: Path | None,
    robust: int | None, closed_loop: bool, ranges: str, robust_sets: tuple[str, ...], no_residual: bool,
    no_local_residual: bool, no_control_transform: bool,
) -> None:  # fmt: skip
    """Transfer DEMO to a robot hand through the physics curriculum: writes OUT/controls.npz (PD targets),
    OUT/metrics.json (judged in the target), OUT/report.html (with per-simulator loss curves), OUT/summary.json."""
    _setup_runtime()
    from quasisim.method.config import CONFIG_PATH, TransferConfig
    from quasisim.pipeline import run_transfer

    nets = networks_from_flags(no_residual, no_local_residual, no_control_transform)
    _robust_sets(robust, ranges, closed_loop, robust_sets)
    spec = TransferSpec(
        hand, target, curriculum, _stages(stages), budget, method, render, True, nets, robust,
        closed_loop=closed_loop, ranges=_ranges(ranges), robust_set=tuple(sorted(_robust_over(robust_sets).items())),
    ).checked()  # fmt: skip
    cfg = TransferConfig.from_yaml(config_path or CONFIG_PATH, _parse_sets(sets))
    cfg.budget(budget)
    if resume and overwrite:
        raise QuasisimError("options --resume (continue OUT) and --overwrite (replace it): expected one, got both")
    res = run_transfer(demo, out, spec, cfg, resume, overwrite, record_transitions=record)
    click.echo(f"wrote {out / 'controls.npz'}, {out / 'metrics.json'}, {out / 'summary.json'}")
    label = spec.method if spec.method != "ours" else f"ours (stages {','.join(spec.stages or ())})"
    runs = {label: res.metrics, "kinematic replay": res.kinematic_metrics}
    _summary(f"{demo.stem}: {label} in {target}, beside the kinematic replay", runs, out / "report.html")


@main.command()
@click.argument("data_dir", type=click.Path(path_type=Path, exists=True, file_okay=False))
@click.option(
    "--out", "out", type=click.Path(path_type=Path), required=True, help="Output folder (one folder per clip)."
)
@click.option("--method", type=click.Choice(METHODS), default=None, help=f"As in transfer (default {DEFAULT_METHOD}).")
@click.option("--stages", default=None, help="As in transfer (method ours; given alone, they imply it).")
@click.option("--curriculum", default=_SPEC.curriculum, show_default=True)
@click.option("--hand", default=_SPEC.hand, show_default=True)
@click.option("--target", type=TARGET_CHOICE, default=_SPEC.target, show_default=True)
@click.option("--budget", default=_SPEC.budget, show_default=True)
@click.option(
    "--pattern", default="*.npz", show_default=True, help="Clips of DATA_DIR (glob); *_long.npz skipped unless named."
)
@click.option(
    "--clips", "clip_names", default="", help="Comma-separated clip names (default: every clip of --pattern)."
)
@click.option(
    "--ray",
    "ray_address",
    default=None,
    help="Run on an existing Ray cluster: auto (the one `ray start` made on this machine, or $RAY_ADDRESS) or "
    "HOST:PORT (default: a Ray of the batch's own on this machine, whatever else runs here).",
)
@click.option(
    "--workers", default=0, show_default=True, type=click.IntRange(0, None), help="Clips at once (0: one per core)."
)
@click.option(
    "--threads",
    default=0,
    show_default=True,
    type=click.IntRange(0, None),
    help="Cores per worker (0: cores / workers).",
)
@click.option(
    "--retries", default=2, show_default=True, type=click.IntRange(0, 10), help="Retries of a clip whose worker died."
)
@click.option("--config", "config_path", type=click.Path(path_type=Path), default=None, help="Transfer config YAML.")
@click.option("--set", "sets", multiple=True, help="Override a config key (as in transfer).")
@click.option("--render/--no-render", default=False, show_default=True, help="Render each clip's video.")
@click.option(
    "--record-transitions", "record", is_flag=True,
    help="Each clip's folder keeps what its sampling stage rolled out in the target (transitions/; "
    "docs/transfer.md). Clips finished before are not redone: use a new OUT.",
)  # fmt: skip
@_LEAD_CLIP
@_ROBUST
@_RANGES
@_ROBUST_SET
@_ablation_flags
@_interruptible
@_friendly
def batch(
    data_dir: Path, out: Path, method: str | None, stages: str | None, curriculum: str, hand: str, target: str, budget: str,
    pattern: str, clip_names: str, ray_address: str | None, workers: int, threads: int, retries: int, config_path: Path | None,
    sets: tuple[str, ...], render: bool, record: bool, robust: int | None, ranges: str, robust_sets: tuple[str, ...],
    no_residual: bool, no_local_residual: bool, no_control_transform: bool, lead_clip: bool,
) -> None:  # fmt: skip
    """Transfer every clip of DATA_DIR on Ray (resumable: finished clips are never redone; a failed clip is
    reported and the batch goes on): writes OUT/<clip>/ (as transfer), OUT/batch.json and OUT/batch.md."""
    _outputs_free(out)  # resumable: only a folder that can be written is required
    _setup_runtime()
    from quasisim.batch import run_batch_command

    nets = networks_from_flags(no_residual, no_local_residual, no_control_transform)
    _robust_sets(robust, ranges, False, robust_sets)
    spec = TransferSpec(
        hand, target, curriculum, _stages(stages), budget, method, render, False, nets, robust,
        ranges=_ranges(ranges), robust_set=tuple(sorted(_robust_over(robust_sets).items())),
    ).checked()  # fmt: skip
    names = tuple(c.strip() for c in clip_names.split(",") if c.strip())
    run_batch_command(
        data_dir,
        names,
        pattern,
        spec,
        out,
        ray_address,
        workers,
        threads,
        config_path,
        _parse_sets(sets),
        retries,
        record,
        lead_clip,
    )
