"""Command line interface: ``quasisim --help``."""

from __future__ import annotations

import functools
import math
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click
from click.core import ParameterSource

from quasisim.errors import QuasisimError
from quasisim.method.registry import METHODS as REGISTERED_METHODS
from quasisim.method.spec import (
    DEFAULT_METHOD,
    FULL_STAGES,
    METHODS,
    TransferSpec,
    networks_from_flags,
    parse_stages,
)
from quasisim.targets import TARGETS

# The commands import their modules when they run (JAX, MuJoCo and PyBullet take seconds to load; `--help`
# and bad-option errors should not wait for them).

TARGET_CHOICE = click.Choice(list(TARGETS))


def _friendly(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Turn quasisim's own errors into a one-line message and exit code 2 (no traceback)."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except (QuasisimError, OSError) as e:  # OSError: a path the system refuses (too long, a loop, no space)
            msg = f"{e.filename}: {e.strerror}" if isinstance(e, OSError) and e.filename and e.strerror else e
            click.echo(f"error: {' '.join(str(msg).split())}", err=True)  # one line, whatever the names hold
            sys.exit(2)

    return wrapper


class _OneLineErrors(click.Group):
    """The top-level group: click's usage errors (bad or missing options) as one line on stderr, exit code 2."""

    def main(self, *args: Any, standalone_mode: bool = True, **kwargs: Any) -> Any:
        if not standalone_mode:
            return super().main(*args, standalone_mode=False, **kwargs)
        try:
            rv = super().main(*args, standalone_mode=False, **kwargs)
        except click.exceptions.NoArgsIsHelpError as e:
            click.echo(e.ctx.get_help() if e.ctx else str(e), err=True)
            sys.exit(2)
        except click.ClickException as e:
            where = f"{e.ctx.command_path}: " if getattr(e, "ctx", None) else ""
            click.echo(f"error: {where}{' '.join(e.format_message().split())} (see --help)", err=True)
            sys.exit(e.exit_code)
        except click.Abort:
            click.echo("Aborted!", err=True)
            sys.exit(1)
        sys.exit(rv if isinstance(rv, int) else 0)


def _outputs_free(out: Path, names: tuple[str, ...] = (), overwrite: bool = True) -> None:
    """Before any work: ``out`` can be written and holds none of ``names`` (unless ``overwrite``)."""
    from quasisim.files import check_out_dir, refuse_overwrite, remove_orphans

    check_out_dir(out)
    refuse_overwrite(out, names, overwrite)
    remove_orphans(out)  # what a killed atomic write left there


_OVERWRITE = click.option("--overwrite", is_flag=True, help="Replace the outputs of an earlier run in OUT.")
_TRANSITIONS_DATA = click.option(
    "--data", "data_dir", type=click.Path(path_type=Path, exists=True, file_okay=False), required=True,
    help="Folder of the demos the transitions were recorded on (their meshes beside them).",
)  # fmt: skip


def _positive_ints(text: str, option: str, example: str) -> tuple[int, ...]:
    """``text`` as comma-separated positive integers; a one-line error naming ``option`` otherwise."""
    try:
        values = tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        values = ()
    if not values or min(values) < 1:
        raise QuasisimError(f"{option}: expected comma-separated positive integers (e.g. {example}), got {text!r}")
    return values


_ROBUST = click.option(
    "--robust", type=click.IntRange(0, 1000), default=None,
    help="Perturbed replays for robust success (default: n of configs/robust.yaml; 0: none).",
)  # fmt: skip
_CLOSED_LOOP = click.option(
    "--closed-loop", is_flag=True,
    help="Also replay the perturbed worlds of robust success closed loop: a tracker observes each world's state "
    "and re-plans around the result in the nominal target (configs/track.yaml; docs/transfer.md).",
)  # fmt: skip
_TRACK_SET = click.option(
    "--track-set", "track_sets", multiple=True,
    help="With --closed-loop: override a tracker setting of configs/track.yaml, e.g. --track-set every=1.",
)  # fmt: skip
_RANGES = click.option(
    "--ranges", default="default", show_default=True,
    help="Perturbation sets of robust success, comma-separated: default (configs/robust.yaml), wide "
    "(configs/robust_wide.yaml: about 2x the ranges and a push on the object mid-clip).",
)  # fmt: skip


def _ranges(text: str) -> tuple[str, ...]:
    """``--ranges`` as a tuple of set names, each one of :data:`quasisim.eval.robust.RANGES`."""
    from quasisim.errors import choice_error
    from quasisim.eval.robust import RANGES

    names = tuple(dict.fromkeys(x.strip() for x in text.split(",") if x.strip()))
    for n in names or ("",):
        if n not in RANGES:
            raise choice_error("--ranges", n, tuple(RANGES))
    return names


def _robust_sets(robust: int | None, ranges: str, closed_loop: bool) -> list[Any]:
    """The perturbation sets of ``--ranges`` with ``--robust`` replays each; ``--closed-loop`` needs replays."""
    from quasisim.eval.robust import replays

    sets = [replays(robust, r) for r in _ranges(ranges)]
    if closed_loop and not any(c.n for c in sets):
        raise QuasisimError("--closed-loop replays the perturbed worlds of robust success: add --robust N (N > 0)")
    return sets


_LEAD_CLIP = click.option(
    "--lead-clip/--no-lead-clip", default=True, show_default=True,
    help="A local batch of several workers runs its first clip alone on every core first, so that its programs "
    "compile once on all cores (docs/batch.md).",
)  # fmt: skip


def _summary(title: str, runs: dict[str, dict[str, Any]], report: Path) -> None:
    """The human summary that ends ``evaluate`` and ``transfer`` (strict first; metrics.json has the numbers)."""
    from quasisim.eval.summary import summary_lines

    click.echo("\n" + "\n".join(summary_lines(title, runs, report if report.is_file() else None)))


def _setup_runtime() -> None:
    """Environment and JAX settings of every command (before MuJoCo or JAX load); SIGTERM ends the command
    like Ctrl-C, so atomic writes remove their temporary files."""
    import signal

    from quasisim.runtime import configure

    configure()
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))


@click.group(cls=_OneLineErrors, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="quasisim")
def main() -> None:
    """quasisim: turn human hand-object demonstrations into robot-hand controls that work in MuJoCo/PyBullet."""


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
@_TRACK_SET
@_RANGES
@_OVERWRITE
@_friendly
def evaluate(
    demo: Path, controls: Path, target: str, out: Path, render: bool, force: bool, robust: int | None,
    closed_loop: bool, track_sets: tuple[str, ...], ranges: str, overwrite: bool,
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
        robust_cfg = _robust_sets(robust, ranges, closed_loop)
        cost = judging_cost(render, robust_cfg, closed_loop)
        warn_long_clip(d, *cost, "evaluation" + (" with rendering" if render else ""))
        tracker = None
        if closed_loop:
            from quasisim.method.track import TrackOptions
            from quasisim.method.track import closed_loop as make_tracker

            tracker = make_tracker(TrackOptions.from_yaml(None, _parse_sets(track_sets)))
        ev = evaluate_controls(d, c, target, out, render=render, progress=True, robust=robust_cfg, closed_loop=tracker)
    click.echo(f"wrote {out / 'metrics.json'}, {out / 'rollout.npz'}")
    label = c.method.split("[")[0] or "controls"  # e.g. "sample-target[default;stages sample;fast]"
    _summary(f"{d.name}: {label} in {target}", {label: ev.metrics}, out / "report.html")


@main.command()
@click.argument("run_dir", type=click.Path(path_type=Path))
@click.option("--web", is_flag=True, help="Serve a 3D viewer to a browser instead (headless servers; docs/viewer.md).")
@click.option("--port", type=click.IntRange(0, 65535), default=8080, show_default=True, help="--web: port to serve on.")
@click.option("--host", default="127.0.0.1", show_default=True, help="--web: address to listen on (0.0.0.0: all).")
@click.option("--demo", type=click.Path(path_type=Path), help="--web: the run's demo .npz (default: found by name).")
@_friendly
def view(run_dir: Path, web: bool, port: int, host: str, demo: Path | None) -> None:
    """Play RUN_DIR's result (scene.xml + trajectory.npz, written by evaluate and transfer) in MuJoCo's viewer,
    or with --web in a browser: prints the URL and serves until Ctrl-C."""
    if not web:
        ctx = click.get_current_context()
        given = [
            f"--{n}" for n in ("port", "host", "demo") if ctx.get_parameter_source(n) is ParameterSource.COMMANDLINE
        ]
        if given:
            raise click.UsageError(f"{', '.join(given)} only with --web")
        from quasisim.eval.export import view as play

        play(run_dir)
        return
    from quasisim.eval.web_view import serve

    serve(run_dir, host, port, demo)


@main.group()
def convert() -> None:
    """Bring your own data in: write a quasisim-demo-v1 clip (docs/demo_format.md)."""


@convert.command("landmarks")
@click.argument("landmarks", type=click.Path(path_type=Path))
@click.argument("poses", type=click.Path(path_type=Path))
@click.argument("mesh", type=click.Path(path_type=Path))
@click.option("--out", "out", type=click.Path(path_type=Path), required=True, help="Demo .npz to write.")
@click.option("--units", default="m", show_default=True, help="Length unit of all three inputs: m, cm or mm.")
@click.option("--up", default="z", show_default=True, help="The inputs' up axis: z, y, -y, x, -x or -z.")
@click.option("--quat-order", default="wxyz", show_default=True, help="Quaternion order in POSES: wxyz or xyzw.")
@click.option("--fps", type=float, default=None, help="Frame rate (default: the landmark file's 'fps').")
@click.option(
    "--support-height", type=float, help="Table top z (m, z up; default: the object's lowest point at frame 0)."
)
@click.option("--key", default=None, help="Landmark array in an .npz (default: the only (T, 21, 3) or (T, 63) one).")
@click.option("--name", default=None, help="Clip name (default: OUT's file name).")
@click.option("--overwrite", is_flag=True, help="Replace OUT and its mesh in meshes/ when they exist.")
@_friendly
def convert_landmarks(
    landmarks: Path, poses: Path, mesh: Path, out: Path, units: str, up: str, quat_order: str, fps: float | None,
    support_height: float | None, key: str | None, name: str | None, overwrite: bool,
) -> None:  # fmt: skip
    """21 hand LANDMARKS per frame (MediaPipe order; .npz, .csv or .json), the object's POSES per frame
    (position + quaternion, or 4x4) and its MESH (object frame) -> OUT (demo npz) and meshes/ beside it.
    File layouts: docs/demo_format.md."""
    from quasisim.data import convert as cv

    opts = cv.ConvertOptions(units, up, quat_order, fps, support_height, key, name)
    click.echo(str(cv.convert_landmarks(landmarks, poses, mesh, out, opts, overwrite)))


def _raw_options(fn: Callable[..., Any]) -> Callable[..., Any]:
    """The options `convert grab` and `convert arctic` share."""
    for opt in reversed((
        click.option("--mano-dir", type=click.Path(path_type=Path), required=True,
                     help="Folder with your MANO_RIGHT.pkl / MANO_LEFT.pkl (or its mano/ subfolder); https://mano.is.tue.mpg.de."),
        click.option("--out", "out", type=click.Path(path_type=Path), required=True, help="Demo .npz to write."),
        click.option("--fps", type=float, default=20.0, show_default=True, help="Clip frame rate (0: the source rate)."),
        click.option("--start", type=int, default=0, show_default=True, help="Source frame of clip frame 0."),
        click.option("--frames", type=int, default=None, help="Clip frames (default: to the end of the sequence)."),
        click.option("--name", default=None, help="Clip name (default: OUT's file name)."),
    )):  # fmt: skip
        fn = opt(fn)
    return fn


@convert.command("grab")
@click.argument("seq", type=click.Path(path_type=Path))
@click.option("--grab-root", type=click.Path(path_type=Path), default=None,
              help="Folder holding grab/ and tools/ (default: three levels above SEQ).")  # fmt: skip
@click.option("--left", is_flag=True, help="Also write the left hand as left_joints (needs MANO_LEFT.pkl).")
@_raw_options
@_friendly
def convert_grab(
    seq: Path, grab_root: Path | None, left: bool, mano_dir: Path, out: Path, fps: float, start: int,
    frames: int | None, name: str | None,
) -> None:  # fmt: skip
    """A GRAB sequence (grab/<subject>/<object>_<intent>.npz) -> OUT (demo npz, right hand) and meshes/ beside
    it. docs/demo_format.md, "From GRAB / ARCTIC"."""
    from quasisim.data import convert_raw as cr

    opts = cr.RawOptions(fps=fps or None, start=start, frames=frames, name=name, left=left)
    click.echo(str(cr.convert_grab(seq, mano_dir, out, grab_root, opts)))


@convert.command("arctic")
@click.argument("seq", type=click.Path(path_type=Path))
@click.option("--arctic-root", type=click.Path(path_type=Path), default=None,
              help="Folder holding raw_seqs/ and meta/ (default: three levels above SEQ).")  # fmt: skip
@click.option("--source-fps", type=float, default=30.0, show_default=True, help="ARCTIC's frame rate.")
@_raw_options
@_friendly
def convert_arctic(
    seq: Path, arctic_root: Path | None, source_fps: float, mano_dir: Path, out: Path, fps: float, start: int,
    frames: int | None, name: str | None,
) -> None:  # fmt: skip
    """An ARCTIC raw sequence (raw_seqs/<subject>/<seq>.mano.npy and .object.npy) -> OUT (demo npz, both
    hands) and a rigid mesh (hinge at the clip's median angle) in meshes/. docs/demo_format.md."""
    from quasisim.data import convert_raw as cr

    opts = cr.RawOptions(fps=fps or None, start=start, frames=frames, name=name, source_fps=source_fps)
    click.echo(str(cr.convert_arctic(seq, mano_dir, out, arctic_root, opts)))


def _parse_sets(sets: tuple[str, ...]) -> dict[str, Any]:
    """``--set a.b=1.5`` options -> {"a.b": 1.5} (values parsed as YAML scalars)."""
    import yaml

    out: dict[str, Any] = {}
    for s in sets:
        if "=" not in s:
            raise QuasisimError(f"--set expects KEY=VALUE (e.g. budgets.fast.sim.control_steps=20), got {s!r}")
        k, v = s.split("=", 1)
        if not k.strip():
            raise QuasisimError(f"--set expects KEY=VALUE with a key (e.g. weights.hand=2.0), got {s!r}")
        try:
            out[k.strip()] = yaml.safe_load(v)
        except yaml.YAMLError as e:
            problem = " ".join(str(getattr(e, "problem", "") or e).split())
            raise QuasisimError(
                f"--set {k.strip()}: expected a YAML value (e.g. 2.0, true, [1, 2]), got {v!r} ({problem})"
            ) from None
    return out


_SPEC = TransferSpec()  # the defaults of `quasisim transfer`'s options


def _ablation_flags(f: Any) -> Any:
    """Stage 3's ablation flags (each removes networks from what stage 3 trains)."""
    for name, what in (
        ("--no-control-transform", "the control transformation"),
        ("--no-local-residual", "the local residual network (the global one stays)"),
        ("--no-residual", "the residual networks (local and global)"),
    ):
        f = click.option(name, is_flag=True, help=f"Stage 3 without {what}.")(f)
    return f


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
@_ablation_flags
@_friendly
def transfer(
    demo: Path, hand: str, target: str, curriculum: str, stages: str | None, method: str | None, budget: str, out: Path,
    resume: bool, overwrite: bool, config_path: Path | None, sets: tuple[str, ...], render: bool, record: Path | None,
    robust: int | None, closed_loop: bool, ranges: str, no_residual: bool, no_local_residual: bool,
    no_control_transform: bool,
) -> None:  # fmt: skip
    """Transfer DEMO to a robot hand through the physics curriculum: writes OUT/controls.npz (PD targets),
    OUT/metrics.json (judged in the target), OUT/report.html (with per-simulator loss curves), OUT/summary.json."""
    _setup_runtime()
    from quasisim.method.config import CONFIG_PATH, TransferConfig
    from quasisim.pipeline import run_transfer

    nets = networks_from_flags(no_residual, no_local_residual, no_control_transform)
    _robust_sets(robust, ranges, closed_loop)
    spec = TransferSpec(
        hand, target, curriculum, _stages(stages), budget, method, render, True, nets, robust,
        closed_loop=closed_loop, ranges=_ranges(ranges),
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
    help="Address of an existing Ray cluster (default: local Ray on this machine).",
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
@_ablation_flags
@_friendly
def batch(
    data_dir: Path, out: Path, method: str | None, stages: str | None, curriculum: str, hand: str, target: str, budget: str,
    pattern: str, clip_names: str, ray_address: str | None, workers: int, threads: int, retries: int, config_path: Path | None,
    sets: tuple[str, ...], render: bool, record: bool, robust: int | None, no_residual: bool, no_local_residual: bool,
    no_control_transform: bool, lead_clip: bool,
) -> None:  # fmt: skip
    """Transfer every clip of DATA_DIR on Ray (resumable: finished clips are never redone; a failed clip is
    reported and the batch goes on): writes OUT/<clip>/ (as transfer), OUT/batch.json and OUT/batch.md."""
    _outputs_free(out)  # resumable: only a folder that can be written is required
    _setup_runtime()
    from quasisim.batch import run_batch_command

    nets = networks_from_flags(no_residual, no_local_residual, no_control_transform)
    spec = TransferSpec(
        hand, target, curriculum, _stages(stages), budget, method, render, False, nets, robust
    ).checked()
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


@main.command("export")
@click.argument("batch_dir", type=click.Path(path_type=Path))
@click.option("--out", "out", type=click.Path(path_type=Path), required=True, help="The dataset file (.hdf5).")
@click.option(
    "--only", type=click.Choice(["strict", "20", "any"]), default="any", show_default=True,
    help="Runs to keep: strict success, success at 20 deg / 20 cm, or any finished run (unstable ones never).",
)  # fmt: skip
@click.option(
    "--min-robust", type=click.FloatRange(0.0, 1.0), default=None,
    help="Also require this robust success (fraction of perturbed replays) for --only's criterion (20 for any).",
)  # fmt: skip
@click.option(
    "--data", "data_dirs", multiple=True, type=click.Path(path_type=Path, exists=True, file_okay=False),
    help="Folder of the runs' demos (repeatable; default: the batch's data_dir, then $QUASISIM_DATA).",
)  # fmt: skip
@click.option(
    "--closed-loop", "closed_loop", type=click.IntRange(0, 1000), default=0, show_default=True,
    help="Per run, also N closed-loop episodes: the tracker driving the perturbed worlds of robust success "
    "(configs/robust.yaml, replays 0..N-1), each marked with its world's parameters (docs/dataset.md).",
)  # fmt: skip
@click.option("--check", is_flag=True, help="Then replay every episode in MuJoCo; exit 1 if one deviates > 1e-9.")
@click.option("--overwrite", is_flag=True, help="Replace an existing --out file.")
@_friendly
def export_cmd(
    batch_dir: Path, out: Path, only: str, min_robust: float | None, data_dirs: tuple[Path, ...], closed_loop: int,
    check: bool, overwrite: bool,
) -> None:  # fmt: skip
    """Finished runs under BATCH_DIR (batch, transfer or bench transfer outputs) as one HDF5 training set in
    robomimic's layout: observations, PD-target actions, MuJoCo states, the scene (docs/dataset.md)."""
    from quasisim.errors import InputError
    from quasisim.files import check_out_dir

    if out.suffix not in (".hdf5", ".h5"):
        raise InputError(out, "--out", "a file name ending in .hdf5 or .h5", repr(out.name))
    check_out_dir(out.parent)
    if out.exists() and not overwrite:
        raise InputError(out, "--out", "a new file (pass --overwrite to replace it)", "an existing file")
    _setup_runtime()
    from quasisim.data.dataset_export import export_dataset

    res = export_dataset(batch_dir, out, only, min_robust, data_dirs, closed_loop=closed_loop)
    mb = out.stat().st_size / 1e6
    click.echo(f"wrote {out}: {len(res.episodes)} episodes, {res.total} samples, {mb:.1f} MB in {res.seconds:.1f} s")
    if res.skipped:
        click.echo(f"skipped {len(res.skipped)}: " + "; ".join(f"{r} ({why})" for r, why in res.skipped))
    if check:
        _export_check(out, {name: run for name, run, _ in res.episodes})


def _export_check(out: Path, runs: dict[str, str]) -> None:
    """``export --check``: replay each episode of ``out`` in its MJCF; exit 1 when one deviates."""
    from quasisim.data.dataset import REPLAY_TOL, load_episodes, replay_episode

    t0, worst = time.perf_counter(), {}
    for ep in load_episodes(out):
        worst[ep.name] = float(replay_episode(ep).max())
        label = runs.get(ep.name, ep.clip)
        click.echo(f"check {ep.name} {label}: {ep.num_samples} frames, max deviation {worst[ep.name]:.3g}")
    bad = [n for n, d in worst.items() if not d <= REPLAY_TOL]
    click.echo(f"check: {len(worst)} episodes replayed in {time.perf_counter() - t0:.1f} s, max deviation "
               f"{max(worst.values()):.3g} (tolerance {REPLAY_TOL:g}): " + (f"FAILED ({', '.join(bad)})" if bad else "ok"))  # fmt: skip
    if bad:
        sys.exit(1)


@main.command()
@click.argument("transitions_dir", type=click.Path(path_type=Path, exists=True, file_okay=False))
@click.option("--out", "out", type=click.Path(path_type=Path), required=True, help="The world model file (.eqx).")
@_TRANSITIONS_DATA
@click.option(
    "--held-out", "held_out", default=None,
    help="Comma-separated clips never trained on (default: the fixed split of docs/world_model.md).",
)  # fmt: skip
@click.option("--steps", default=None, type=click.IntRange(0, None), help="Adam steps (default: the config's).")
@click.option("--workers", default=2, show_default=True, type=click.IntRange(1, 64), help="Clips at once.")
@_friendly
def fit(
    transitions_dir: Path, out: Path, data_dir: Path, held_out: str | None, steps: int | None, workers: int
) -> None:
    """Train a world model (the stiffest simulator + a learned correction of the object's state per frame) on
    the transitions recorded under TRANSITIONS_DIR (transfer/batch --record-transitions); resumable."""
    from quasisim.files import check_out_dir

    check_out_dir(out.parent, "--out")
    _setup_runtime()
    import dataclasses

    from quasisim.method.transitions import HELD_OUT
    from quasisim.method.world_fit import fit_world_model
    from quasisim.method.world_model import WorldModelConfig

    cfg = WorldModelConfig() if steps is None else dataclasses.replace(WorldModelConfig(), steps=steps)
    names = HELD_OUT if held_out is None else tuple(c.strip() for c in held_out.split(",") if c.strip())
    model = fit_world_model(transitions_dir, data_dir, out, cfg, names, workers)
    info = model.info
    click.echo(
        f"{out}: trained on {len(info['trained_on'])} clips ({info['n_pairs']} frames), held out "
        f"{len(info['held_out'])}; final loss {info['losses'][-1] if info['losses'] else float('nan'):.3f}"
    )


@main.group()
def bench() -> None:
    """Benchmarks whose output goes into BENCHMARKS.md."""


@bench.command("baseline")
@click.argument("data_dir", type=click.Path(path_type=Path, exists=True, file_okay=False))
@click.option("--hand", default="shadow", show_default=True)
@click.option(
    "--target", "targets", type=TARGET_CHOICE, multiple=True, default=("mujoco", "pybullet"), show_default=True
)
@click.option("--out", "out", type=click.Path(path_type=Path), default=Path("bench_out/baseline"), show_default=True)
@click.option(
    "--pattern", default="*.npz", show_default=True, help="Clips to run (glob); *_long.npz are skipped unless named."
)
@click.option("--render/--no-render", default=False, show_default=True)
@_ROBUST
@_friendly
def bench_baseline(
    data_dir: Path, hand: str, targets: tuple[str, ...], out: Path, pattern: str, render: bool, robust: int | None
) -> None:  # fmt: skip
    """Kinematic-replay baseline on every clip of DATA_DIR: metrics table, success rates, wall time."""
    _outputs_free(out)  # resumable: only a folder that can be written is required
    _setup_runtime()
    from quasisim.bench.baseline import run_baseline
    from quasisim.eval.robust import replays

    run_baseline(data_dir, hand, targets, out, pattern, render, replays(robust))


@bench.command("sim")
@click.option(
    "--data",
    "data_dir",
    type=click.Path(path_type=Path, file_okay=False),
    default=None,
    help="Folder of clips (default: $QUASISIM_DATA).",
)
@click.option("--clip", default="grab_s1_apple_lift", show_default=True, help="Clip of the speed measurement.")
@click.option("--study-clips", default="grab_s1_apple_lift,grab_s1_cubesmall_lift,grab_s1_mug_lift", show_default=True)
@click.option("--hand", default="shadow", show_default=True)
@click.option(
    "--substeps", type=click.IntRange(1, None), default=None, help="Substeps per frame (default: the fast budget's)."
)
@click.option(
    "--dt-study",
    default="50,20,10",
    show_default=True,
    help="Substeps per frame compared with 100 (dt 0.5 ms at 20 fps).",
)
@click.option(
    "--study-sims", default="", help="Simulators of the default curriculum (1-based) of the step-size study "
    "(default: the stiffest analytical one).",
)  # fmt: skip
@click.option("--json", "as_json", is_flag=True, help="Print JSON only.")
@_friendly
def bench_sim(
    data_dir: Path | None, clip: str, study_clips: str, hand: str, substeps: int | None, dt_study: str,
    study_sims: str, as_json: bool,
) -> None:  # fmt: skip
    """Simulator speed (forward, forward+backward, memory), MuJoCo on the same scene, step-size study."""
    import os

    _setup_runtime()
    from quasisim.bench.sim import run_sim_bench
    from quasisim.method.curriculum import load_curriculum

    data = data_dir or Path(os.environ.get("QUASISIM_DATA", "../shared/data"))
    if not (data / f"{clip}.npz").is_file():
        raise QuasisimError(f"clip {clip} not found in {data} (pass --data or set QUASISIM_DATA)")
    study = _positive_ints(dt_study, "--dt-study", "50,20,10")
    sims = _positive_ints(study_sims, "--study-sims", "1,5,9") if study_sims.strip() else ()
    analytical = [i + 1 for i, st in enumerate(load_curriculum("default").stages) if not st.residual]
    if bad := sorted(set(sims) - set(analytical)):
        raise QuasisimError(
            f"--study-sims: {bad} are not analytical simulators of the default curriculum (valid: {analytical})"
        )
    clips_ = tuple(c for c in study_clips.split(",") if c.strip())
    run_sim_bench(data, clip, clips_, hand, substeps, study, as_json, sims)


@bench.command("transfer")
@click.argument("data_dir", type=click.Path(path_type=Path, exists=True, file_okay=False))
@click.option(
    "--clips", "clip_names", default="", help="Comma-separated clip names (default: every clip of --pattern)."
)
@click.option(
    "--pattern", default="*.npz", show_default=True, help="Clips to run (glob); *_long.npz skipped unless named."
)
@click.option(
    "--runs",
    "--curricula",
    "runs",
    default="default,none,curriculum2",
    show_default=True,
    help="Comma-separated runs: a curriculum (its stages, --stages), CURRICULUM+3, +mpc, +sample, +select (those "
    "stages after them, e.g. short+sample+select = method ours), cascade (transfer's default), mpc-base, mpc-soften, "
    "sample-target.",
)
@click.option("--stages", default="1,2", show_default=True)
@click.option("--budget", default="fast", show_default=True)
@click.option("--target", type=TARGET_CHOICE, default="mujoco", show_default=True)
@click.option("--hand", default="shadow", show_default=True)
@click.option("--out", "out", type=click.Path(path_type=Path), default=Path("bench_out/transfer"), show_default=True)
@click.option("--report-only", is_flag=True, help="Tabulate the finished runs in OUT; run nothing.")
@click.option(
    "--judge",
    type=TARGET_CHOICE,
    default=None,
    help="Judge the runs' controls (and the kinematic replay) open loop in this simulator instead of --target.",
)
@click.option("--ray", "ray_address", default=None, help="Address of an existing Ray cluster (default: local Ray).")
@click.option(
    "--workers", default=0, show_default=True, type=click.IntRange(0, None), help="Clips at once (0: one per core)."
)
@click.option(
    "--set", "sets", multiple=True, help="Override a config key (as in transfer), e.g. --set stage2.mode=none."
)
@click.option(
    "--record-transitions", "record", is_flag=True,
    help="Each clip's folder keeps what its sampling stage rolled out in the target (transitions/; "
    "docs/transfer.md). Clips finished before are not redone: use a new OUT.",
)  # fmt: skip
@click.option(
    "--robust", type=click.IntRange(0, 1000), default=None,
    help="Perturbed replays per run for robust success (default: n of configs/robust.yaml; 0: none). Clips "
    "finished before keep their judging: use a new OUT.",
)  # fmt: skip
@click.option(
    "--closed-loop", is_flag=True,
    help="After the batch, replay every finished run in the perturbed worlds of --ranges open and closed loop "
    "(--robust N replays each; cached per run, resumable) and add the closed-loop tables.",
)  # fmt: skip
@_TRACK_SET
@_RANGES
@_LEAD_CLIP
@_friendly
def bench_transfer(
    data_dir: Path, clip_names: str, pattern: str, runs: str, stages: str, budget: str, target: str, hand: str,
    out: Path, report_only: bool, judge: str | None, ray_address: str | None, workers: int, sets: tuple[str, ...],
    record: bool, robust: int | None, closed_loop: bool, track_sets: tuple[str, ...], ranges: str, lead_clip: bool,
) -> None:  # fmt: skip
    """Transfer runs (curricula, +mpc, MPC baselines) on clips of DATA_DIR beside the kinematic replay, as one
    Ray batch (resumable)."""
    _outputs_free(out)  # resumable: only a folder that can be written is required
    _setup_runtime()
    from quasisim.batch import Settings
    from quasisim.bench.transfer import run_spec, run_transfer_bench
    from quasisim.method.config import TransferConfig

    st = parse_stages(stages)
    rs = tuple(c.strip() for c in runs.split(",") if c.strip())
    for r in rs:
        run_spec(r, st, TransferSpec())
    names = tuple(c.strip() for c in clip_names.split(",") if c.strip())
    overrides = _parse_sets(sets)
    TransferConfig.from_yaml(overrides=overrides)  # a bad key fails here, before any clip runs
    s = Settings(
        ray_address, workers, overrides=overrides, keep_scratch=True, record_transitions=record, lead_clip=lead_clip
    )
    loop = None
    if closed_loop:
        _robust_sets(robust, ranges, closed_loop)
        from quasisim.method.track import TrackOptions

        TrackOptions.from_yaml(None, _parse_sets(track_sets))  # a bad setting fails here, before any clip runs
        loop = (_ranges(ranges), _parse_sets(track_sets))
    run_transfer_bench(
        data_dir, names, pattern, rs, st, budget, target, hand, out, report_only, judge, s, robust, closed_loop=loop
    )


@bench.command("compare")
@click.argument("folders", nargs=-1, required=True)
@click.option(
    "--run", "run", default="short+sample+select", show_default=True,
    help="The run to compare: one name for every folder, or comma-separated, one per folder.",
)  # fmt: skip
@click.option(
    "--kinematic", is_flag=True, help="Each folder's kinematic replay beside its run (e.g. one folder per hand)."
)
@click.option("--out", "out", type=click.Path(path_type=Path), default=Path("bench_out/compare"), show_default=True)
@_friendly
def bench_compare(folders: tuple[str, ...], run: str, kinematic: bool, out: Path) -> None:
    """One run of finished `bench transfer` folders side by side: FOLDERS as LABEL=PATH (or PATH, labelled
    by its name), the first is the reference. Reads results back; runs nothing."""
    from quasisim.bench.compare import compare_folders

    pairs = []
    for f in folders:
        label, _, path = f.rpartition("=")
        p = Path(path)
        if not p.is_dir():
            raise QuasisimError(f"bench compare: {p} is not a folder (expected LABEL=PATH of a `bench transfer` --out)")
        pairs.append((label or p.name, p))
    _outputs_free(out)
    compare_folders(pairs, [r.strip() for r in run.split(",")], out, kinematic)


@bench.command("batch")
@click.argument("data_dir", type=click.Path(path_type=Path, exists=True, file_okay=False))
@click.option(
    "--clips", "clip_names", default="", help="Comma-separated clip names (default: every clip of --pattern)."
)
@click.option("--pattern", default="*.npz", show_default=True, help="Clips to run (glob); *_long.npz skipped.")
@click.option("--method", type=click.Choice(METHODS), default="sample-target", show_default=True)
@click.option("--stages", default=None, help="As in transfer (method ours).")
@click.option(
    "--layouts", default="1x1,2x1,1x2", show_default=True,
    help="WORKERSxTHREADS per layout, in order; -unpinned: workers not pinned to cores of their own (2x1-unpinned).",
)  # fmt: skip
@click.option("--set", "sets", multiple=True, help="Override a config key (as in transfer).")
@click.option("--out", "out", type=click.Path(path_type=Path), default=Path("bench_out/batch"), show_default=True)
@_friendly
def bench_batch(
    data_dir: Path, clip_names: str, pattern: str, method: str, stages: str, layouts: str, sets: tuple[str, ...],
    out: Path,
) -> None:  # fmt: skip
    """Clips per hour of `quasisim batch` with 1 and 2 Ray workers on the same clips (same command)."""
    _outputs_free(out)
    _setup_runtime()
    from quasisim.bench.batch import run_batch_bench

    try:
        lay = tuple(_layout(x.strip()) for x in layouts.split(",") if x.strip())
        assert lay and all(min(x[:2]) >= 1 for x in lay)
    except (ValueError, AssertionError):
        raise QuasisimError(
            f"--layouts expects WORKERSxTHREADS[-unpinned],... (e.g. 1x1,2x1,2x1-unpinned), got {layouts!r}"
        ) from None
    spec = TransferSpec(method=method, stages=_stages(stages), render=False, progress=False).checked()
    names = tuple(c.strip() for c in clip_names.split(",") if c.strip())
    run_batch_bench(data_dir, names, pattern, spec, lay, out, _parse_sets(sets))  # type: ignore[arg-type]


def _stages(text: str | None) -> tuple[str, ...] | None:
    """``--stages``: None where not given (the method's own stages)."""
    return None if text is None else parse_stages(text)


def _layout(text: str) -> tuple[int, int, bool]:
    """``2x1`` -> (2, 1, pinned); ``2x1-unpinned`` -> (2, 1, not pinned)."""
    shape, _, flag = text.partition("-")
    if flag not in ("", "unpinned"):
        raise ValueError(text)
    w, t = (int(x) for x in shape.split("x"))
    return w, t, flag == ""


@bench.command("profile")
@click.argument("demo", type=click.Path(path_type=Path, exists=True, dir_okay=False))
@click.option("--stages", default="1,2,3,mpc", show_default=True, help="Stages of the profiled transfer.")
@click.option("--curriculum", default=_SPEC.curriculum, show_default=True)
@click.option("--budget", default=_SPEC.budget, show_default=True)
@click.option("--cold", is_flag=True, help="Start from empty XLA compilation and trace caches.")
@click.option("--cprofile", is_flag=True, help="Also measure MuJoCo's share (cProfile; slows tracing).")
@click.option("--set", "sets", multiple=True, help="Override a config key (as in transfer).")
@click.option("--out", "out", type=click.Path(path_type=Path), default=Path("bench_out/profile"), show_default=True)
@_friendly
def bench_profile(
    demo: Path, stages: str, curriculum: str, budget: str, cold: bool, cprofile: bool, sets: tuple[str, ...], out: Path
) -> None:
    """Where one transfer's time goes: per piece, XLA compilation, MuJoCo, the rest (JAX execution, Python)."""
    _outputs_free(out)
    _setup_runtime()
    import shutil

    from quasisim.bench.profile import run_profile
    from quasisim.method.config import TransferConfig

    spec = TransferSpec(curriculum=curriculum, stages=parse_stages(stages), budget=budget, render=False, progress=False)
    shutil.rmtree(out / "run", ignore_errors=True)
    run_profile(demo, spec.checked(), TransferConfig.from_yaml(overrides=_parse_sets(sets)), out, cold, cprofile)


@bench.command("predict")
@click.argument("data_dir", type=click.Path(path_type=Path, exists=True, file_okay=False))
@click.option(
    "--clips", "clip_names", default="", help="Comma-separated clip names (default: every clip of --pattern)."
)
@click.option("--pattern", default="*.npz", show_default=True, help="Clips to run (glob); *_long.npz skipped.")
@click.option("--horizon", default=10, show_default=True, type=click.IntRange(1, 50), help="Frames predicted.")
@click.option("--curriculum", default="default", show_default=True, help="Whose rigid simulators to compare.")
@click.option("--sim", "sims", multiple=True, type=int, help="Only these simulators (1-based, repeatable).")
@click.option("--mu", "mus", multiple=True, type=float, help="Friction coefficients to compare (repeatable).")
@click.option("--hand", default="shadow", show_default=True)
@click.option("--out", "out", type=click.Path(path_type=Path), default=Path("bench_out/predict"), show_default=True)
@_friendly
def bench_predict(
    data_dir: Path, clip_names: str, pattern: str, horizon: int, curriculum: str, sims: tuple[int, ...],
    mus: tuple[float, ...], hand: str, out: Path,
) -> None:  # fmt: skip
    """Open-loop prediction error of the quasi-physical simulators against MuJoCo (the fit of stage 3)."""
    _outputs_free(out)  # resumable: only a folder that can be written is required
    _setup_runtime()
    from quasisim.bench.predict import run_predict_bench

    names = tuple(c.strip() for c in clip_names.split(",") if c.strip())
    run_predict_bench(data_dir, names, pattern, horizon, curriculum, hand, out, sims, mus)


@bench.command("world")
@click.argument("transitions_dir", type=click.Path(path_type=Path, exists=True, file_okay=False))
@click.option(
    "--model", "model_path", type=click.Path(path_type=Path), default=None,
    help="quasisim fit's file (without it: the nominal simulator and zero motion on the fixed held-out clips).",
)  # fmt: skip
@_TRANSITIONS_DATA
@click.option("--clips", "clip_names", default="", help="Comma-separated clips (default: the model's held-out ones).")
@click.option(
    "--decompose", is_flag=True, help="Also the nominal simulator with one group of constants changed at a time."
)
@click.option(
    "--variant",
    "variants",
    multiple=True,
    help="One variant of --decompose (repeatable), e.g. 'table on mesh samples'.",
)
@click.option("--horizons", default="6,10", show_default=True, help="Frames of the final trajectories' windows.")
@click.option("--out", "out", type=click.Path(path_type=Path), default=Path("bench_out/world"), show_default=True)
@_friendly
def bench_world(
    transitions_dir: Path,
    model_path: Path | None,
    data_dir: Path,
    clip_names: str,
    decompose: bool,
    variants: tuple[str, ...],
    horizons: str,
    out: Path,
) -> None:
    """Open-loop prediction of a fitted world model on held-out clips (final trajectories' windows of 6 and 10
    frames, sampled candidates) beside the nominal simulator and zero motion; resumable."""
    _outputs_free(out)
    _setup_runtime()
    from quasisim.bench.world import run_world_bench

    names = tuple(c.strip() for c in clip_names.split(",") if c.strip())
    hs = tuple(sorted(set(_positive_ints(horizons, "--horizons", "6,10"))))
    from quasisim.bench.world import MODEL_VARIANTS, VARIANTS

    valid = (*VARIANTS, *MODEL_VARIANTS)
    unknown = [v for v in variants if v not in valid]
    if unknown:
        raise click.BadParameter(f"{unknown[0]!r}; valid: {', '.join(valid)}", param_hint="--variant")
    chosen = valid if decompose else tuple(variants)
    run_world_bench(transitions_dir, data_dir, model_path, out, names, chosen, hs)


@bench.command("screen")
@click.argument("transitions_dir", type=click.Path(path_type=Path, exists=True, file_okay=False))
@click.option(
    "--model", "model_path", type=click.Path(path_type=Path, exists=True, dir_okay=False), default=None,
    help="quasisim fit's file: also the world model (without it: the nominal simulator).",
)  # fmt: skip
@_TRANSITIONS_DATA
@click.option("--clips", "clip_names", default="", help="Comma-separated clips (default: the held-out ones).")
@click.option("--top", default="1,3,6,12", show_default=True, help="Comma-separated k: the predictor's k cheapest.")
@click.option("--out", "out", type=click.Path(path_type=Path), default=Path("bench_out/screen"), show_default=True)
@_friendly
def bench_screen(
    transitions_dir: Path, model_path: Path | None, data_dir: Path, clip_names: str, top: str, out: Path
) -> None:
    """Could the simulator pre-screen the sampling stage's candidates? Every recorded candidate predicted and
    scored; the target's cost of the best of the simulator's k cheapest against k drawn at random; resumable."""
    _outputs_free(out)
    _setup_runtime()
    from quasisim.bench.screen import run_screen_bench

    names = tuple(c.strip() for c in clip_names.split(",") if c.strip())
    run_screen_bench(transitions_dir, data_dir, model_path, out, names, _positive_ints(top, "--top", "1,3,6,12"))


@bench.command("windows")
@click.argument("transitions_file", type=click.Path(path_type=Path, exists=True, dir_okay=False))
@_TRANSITIONS_DATA
@click.option("--windows", "n", default=256, show_default=True, type=click.IntRange(1, None), help="Windows predicted.")
@click.option("--batch", "batches", default="16,64", show_default=True, help="Comma-separated windows per call.")
@click.option("--out", "out", type=click.Path(path_type=Path), default=Path("bench_out/windows"), show_default=True)
@_friendly
def bench_windows(transitions_file: Path, data_dir: Path, n: int, batches: str, out: Path) -> None:
    """Speed of the quasi-physical simulator predicting sampled windows in batches, on JAX's default device
    (CPU, or a GPU where JAX has one): what pre-screening candidates in the simulator would cost."""
    _outputs_free(out)
    _setup_runtime()
    from quasisim.bench.world import run_window_speed

    run_window_speed(transitions_file, data_dir, n, _positive_ints(batches, "--batch", "16,64"), out)


@bench.command("long")
@click.option("--frames", "frames_", default="60,600,3000,10000", show_default=True, help="Clip lengths.")
@click.option("--commands", default=",".join(("retarget", "evaluate", "sample-target")), show_default=True)
@click.option("--render/--no-render", default=True, show_default=True, help="evaluate and transfer render videos.")
@click.option("--out", "out", type=click.Path(path_type=Path), default=Path("bench_out/long"), show_default=True)
@_friendly
def bench_long(frames_: str, commands: str, render: bool, out: Path) -> None:
    """Wall time and peak memory of retarget, evaluate and sample-target on clips of 60 to 10,000 frames,
    beside the clip-length warning's estimate (resumable per row)."""
    _outputs_free(out)  # resumable: only a folder that can be written is required
    from quasisim.bench.long import run_long_bench

    lengths = _positive_ints(frames_, "--frames", "60,600,3000,10000")
    click.echo(run_long_bench(lengths, tuple(c.strip() for c in commands.split(",") if c.strip()), out, render))


@bench.command("failures")
@click.argument("runs", type=click.Path(path_type=Path, exists=True, file_okay=False))
@click.option("--data", "data_dir", type=click.Path(path_type=Path, file_okay=False), default=None,
              help="Folder of the runs' demos (default: $QUASISIM_DATA).")  # fmt: skip
@click.option("--out", "out", type=click.Path(path_type=Path), default=None, help="Output folder (default: RUNS).")
@_friendly
def bench_failures(runs: Path, data_dir: Path | None, out: Path | None) -> None:
    """Why each finished run under RUNS fails strict success: first frame over a limit, which limit, and a
    label (symmetric, drop, never grasped, lost contact, slip); writes failures.md and failures.json."""
    import os

    from quasisim.eval.failures import analyse, write

    data = data_dir or Path(os.environ.get("QUASISIM_DATA", "../shared/data"))
    click.echo(write(runs, analyse(runs, data), out or runs))


@bench.command("sensitivity")
@click.argument("runs", type=click.Path(path_type=Path, exists=True, file_okay=False))
@click.option("--data", "data_dir", type=click.Path(path_type=Path, file_okay=False), default=None,
              help="Folder of the runs' demos (default: $QUASISIM_DATA).")  # fmt: skip
@click.option("--scales", default="0,0.01,0.1,1", show_default=True,
              help="Fractions of the perturbation ranges of configs/robust.yaml.")  # fmt: skip
@click.option("--n", "n", type=click.IntRange(1, 1000), default=8, show_default=True, help="Replays per run and scale.")
@click.option("--out", "out", type=click.Path(path_type=Path), default=None, help="Output folder (default: RUNS).")
@_friendly
def bench_sensitivity(runs: Path, data_dir: Path | None, scales: str, n: int, out: Path | None) -> None:
    """Robust success of every finished run under RUNS (judged in MuJoCo) with the perturbation ranges
    scaled: does a run fail under a physically sized change or under any change at all? Writes
    sensitivity.md and sensitivity.json."""
    import os

    from quasisim.bench.sensitivity import run_sensitivity

    try:
        values = tuple(float(x) for x in scales.split(",") if x.strip())
    except ValueError:
        values = ()
    if not values or not all(math.isfinite(v) and v >= 0 for v in values):
        raise QuasisimError(f"--scales: expected comma-separated numbers >= 0 (e.g. 0,0.01,0.1,1), got {scales!r}")
    data = data_dir or Path(os.environ.get("QUASISIM_DATA", "../shared/data"))
    click.echo(run_sensitivity(runs, data, values, n, out or runs))


@bench.command("fit")
@click.argument("data_dir", type=click.Path(path_type=Path, exists=True, file_okay=False))
@click.option(
    "--clips", "clip_names", default="", help="Comma-separated clip names (default: every clip of --pattern)."
)
@click.option("--pattern", default="*.npz", show_default=True, help="Clips to run (glob); *_long.npz skipped.")
@click.option("--hand", default="shadow", show_default=True)
@click.option("--residual/--no-residual", default=True, show_default=True, help="Also fit the residual networks.")
@click.option("--set", "sets", multiple=True, help="Override a config key, e.g. --set stage3.steps=20.")
@click.option("--out", "out", type=click.Path(path_type=Path), default=Path("bench_out/fit"), show_default=True)
@_friendly
def bench_fit(
    data_dir: Path, clip_names: str, pattern: str, hand: str, residual: bool, sets: tuple[str, ...], out: Path
) -> None:
    """Stage 3's measure: held-out prediction error of the simulator fitted to MuJoCo (nominal, + S and
    constants, + residual networks) beside zero motion."""
    _outputs_free(out)  # resumable: only a folder that can be written is required
    _setup_runtime()
    from quasisim.bench.fit import run_fit_bench

    names = tuple(c.strip() for c in clip_names.split(",") if c.strip())
    run_fit_bench(data_dir, names, pattern, hand, out, residual, _parse_sets(sets))


if __name__ == "__main__":  # pragma: no cover
    main()
