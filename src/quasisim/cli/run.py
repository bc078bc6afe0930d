"""The commands of one clip and of many: example, retarget, evaluate, transfer, batch."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import click

from quasisim.cli._common import (
    _CONFIG,
    _HAND,
    _OVERWRITE,
    TARGET_CHOICE,
    Clips,
    Judging,
    _clips_options,
    _friendly,
    _interruptible,
    _judging,
    _outputs_free,
    _parse_sets,
    _setup_runtime,
    _spec_options,
    _summary,
    main,
)
from quasisim.errors import QuasisimError
from quasisim.method.spec import TransferSpec


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
@_HAND
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
@_judging(tracker=True)
@_OVERWRITE
@_friendly
def evaluate(
    demo: Path, controls: Path, target: str, out: Path, render: bool, force: bool, judging: Judging, overwrite: bool
) -> None:
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
        robust_cfg = judging.configs()
        cost = judging_cost(render, robust_cfg, judging.closed_loop)
        warn_long_clip(d, *cost, "evaluation" + (" with rendering" if render else ""))
        maker = None
        if judging.closed_loop:
            from quasisim.method.track import TrackOptions
            from quasisim.method.track import closed_loop as make_tracker

            maker = make_tracker(TrackOptions.from_yaml(None, judging.track))
        ev = evaluate_controls(d, c, target, out, render=render, progress=True, robust=robust_cfg, closed_loop=maker)
    click.echo(f"wrote {out / 'metrics.json'}, {out / 'rollout.npz'}")
    label = c.method.split("[")[0] or "controls"  # e.g. "sample-target[default;stages sample;fast]"
    _summary(f"{d.name}: {label} in {target}", {label: ev.metrics}, out / "report.html")


@main.command()
@click.argument("demo", type=click.Path(path_type=Path))
@_spec_options(render=True, render_help="Render the video for the report.")
@click.option("--out", "out", type=click.Path(path_type=Path), required=True, help="Output folder.")
@click.option("--resume", is_flag=True, help="Continue the run in OUT from its last checkpoint.")
@click.option(
    "--overwrite", is_flag=True, help="Start afresh in OUT, replacing an earlier run's outputs and checkpoints."
)
@_CONFIG
@click.option(
    "--set", "sets", multiple=True, help="Override a config key, e.g. --set budgets.fast.sim.control_steps=20."
)
@click.option(
    "--record-transitions", "record", type=click.Path(path_type=Path), default=None,
    help="Keep every window the sampling stage rolls out in the target, and the final run's states, in "
    "DIR/<demo>.<method>.npz (data for fitting a simulator to the target; docs/transfer.md).",
)  # fmt: skip
@_judging()
@_friendly
def transfer(
    demo: Path, spec: TransferSpec, out: Path, resume: bool, overwrite: bool, config_path: Path | None,
    sets: tuple[str, ...], record: Path | None, judging: Judging,
) -> None:  # fmt: skip
    """Transfer DEMO to a robot hand through the physics curriculum: writes OUT/controls.npz (PD targets),
    OUT/metrics.json (judged in the target), OUT/report.html (with per-simulator loss curves), OUT/summary.json."""
    _setup_runtime()
    from quasisim.method.config import CONFIG_PATH, TransferConfig
    from quasisim.pipeline import run_transfer

    spec = judging.on(spec).checked()
    cfg = TransferConfig.from_yaml(config_path or CONFIG_PATH, _parse_sets(sets))
    cfg.budget(spec.budget)
    if resume and overwrite:
        raise QuasisimError("options --resume (continue OUT) and --overwrite (replace it): expected one, got both")
    res = run_transfer(demo, out, spec, cfg, resume, overwrite, record_transitions=record)
    click.echo(f"wrote {out / 'controls.npz'}, {out / 'metrics.json'}, {out / 'summary.json'}")
    label = spec.method if spec.method != "ours" else f"ours (stages {','.join(spec.stages or ())})"
    runs = {label: res.metrics, "kinematic replay": res.kinematic_metrics}
    _summary(f"{demo.stem}: {label} in {spec.target}, beside the kinematic replay", runs, out / "report.html")


@main.command()
@click.argument("data_dir", type=click.Path(path_type=Path, exists=True, file_okay=False))
@click.option(
    "--out", "out", type=click.Path(path_type=Path), required=True, help="Output folder (one folder per clip)."
)
@_spec_options(render=False, render_help="Render each clip's video.")
@_clips_options(
    ray_help="Run on an existing Ray cluster: auto (the one `ray start` made on this machine, or $RAY_ADDRESS) or "
    "HOST:PORT (default: a Ray of the batch's own on this machine, whatever else runs here).",
    set_help="Override a config key (as in transfer).",
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
@_CONFIG
@_judging(closed_loop=None)
@_interruptible
@_friendly
def batch(
    data_dir: Path, out: Path, spec: TransferSpec, clips: Clips, threads: int, retries: int, config_path: Path | None,
    judging: Judging,
) -> None:  # fmt: skip
    """Transfer every clip of DATA_DIR on Ray (resumable: finished clips are never redone; a failed clip is
    reported and the batch goes on): writes OUT/<clip>/ (as transfer), OUT/batch.json and OUT/batch.md."""
    _outputs_free(out)  # resumable: only a folder that can be written is required
    _setup_runtime()
    from quasisim.batch import run_batch_command

    spec = judging.on(dataclasses.replace(spec, progress=False)).checked()
    c = clips
    run_batch_command(
        data_dir, c.names, c.pattern, spec, out, c.ray_address, c.workers, threads, config_path, c.overrides, retries,
        c.record, c.lead_clip,
    )  # fmt: skip
