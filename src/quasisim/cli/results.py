"""What comes after the runs: view a result, export runs as a training set."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import click
from click.core import ParameterSource

from quasisim.cli._common import _friendly, _setup_runtime, main


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


@main.command("export")
@click.argument("batch_dir", type=click.Path(path_type=Path))
@click.option(
    "--out", "out", type=click.Path(path_type=Path), required=True,
    help="The dataset: a file ending in .hdf5 (robomimic), a new folder (lerobot).",
)  # fmt: skip
@click.option(
    "--format", "fmt", type=click.Choice(["robomimic", "lerobot"]), default="robomimic", show_default=True,
    help="robomimic: one HDF5 file with MuJoCo states; lerobot: a LeRobot dataset (v3: parquet, MP4 video) "
    "written with lerobot's API (make setup-lerobot; docs/dataset.md).",
)  # fmt: skip
@click.option(
    "--image-size", "image_size", type=(click.IntRange(16, 2048), click.IntRange(16, 2048)), default=(240, 320),
    show_default=True, help="--format lerobot: the camera's height and width (pixels).",
)  # fmt: skip
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
@click.option(
    "--check", is_flag=True,
    help="robomimic: then replay every episode in MuJoCo; exit 1 if one deviates > 1e-9 (a lerobot export is "
    "always read back through LeRobotDataset and compared before it is kept).",
)  # fmt: skip
@click.option(
    "--overwrite", is_flag=True,
    help="Replace an existing --out that quasisim export wrote (never one that is or holds an input).",
)  # fmt: skip
@_friendly
def export_cmd(
    batch_dir: Path, out: Path, fmt: str, image_size: tuple[int, int], only: str, min_robust: float | None,
    data_dirs: tuple[Path, ...], closed_loop: int, check: bool, overwrite: bool,
) -> None:  # fmt: skip
    """Finished runs under BATCH_DIR (batch, transfer or bench transfer outputs, or one run) as one training
    set: robomimic's HDF5 layout (observations, PD-target actions, MuJoCo states, the scene) or a LeRobot
    dataset (state, action, camera video, task text; docs/dataset.md)."""
    from quasisim.errors import InputError
    from quasisim.files import check_out_dir

    if fmt == "lerobot":
        _export_lerobot(batch_dir, out, image_size, only, min_robust, data_dirs, closed_loop, check, overwrite)
        return
    if image_size != (240, 320):
        raise click.UsageError("--image-size only with --format lerobot")
    if out.suffix not in (".hdf5", ".h5"):
        raise InputError(out, "--out", "a file name ending in .hdf5 or .h5", repr(out.name))
    check_out_dir(out.parent)
    _setup_runtime()
    from quasisim.eval.dataset_export import check_out, export_dataset

    check_out(out, (batch_dir, *data_dirs), overwrite)
    res = export_dataset(batch_dir, out, only, min_robust, data_dirs, closed_loop=closed_loop)
    mb = out.stat().st_size / 1e6
    click.echo(f"wrote {out}: {len(res.episodes)} episodes, {res.total} samples, {mb:.1f} MB in {res.seconds:.1f} s")
    if res.skipped:
        click.echo(f"skipped {len(res.skipped)}: " + "; ".join(f"{r} ({why})" for r, why in res.skipped))
    if check:
        _export_check(out, {name: run for name, run, _ in res.episodes})


def _export_lerobot(
    batch_dir: Path, out: Path, image_size: tuple[int, int], only: str, min_robust: float | None,
    data_dirs: tuple[Path, ...], closed_loop: int, check: bool, overwrite: bool,
) -> None:  # fmt: skip
    from quasisim.errors import InputError
    from quasisim.files import check_out_dir

    if check:
        raise click.UsageError("--check is robomimic's: a lerobot export is always read back and compared")
    if out.suffix in (".hdf5", ".h5"):
        raise InputError(out, "--out", "a folder for --format lerobot (a .hdf5 file is --format robomimic's)", out.name)
    check_out_dir(out.parent)
    _setup_runtime()
    from quasisim.eval.lerobot_export import check_out, export_lerobot
    from quasisim.files import size_mb

    check_out(out, (batch_dir, *data_dirs), overwrite)
    res = export_lerobot(batch_dir, out, only, min_robust, data_dirs, closed_loop, image_size, overwrite=overwrite)
    mb = size_mb(out)
    click.echo(f"wrote {out}: {len(res.episodes)} episodes, {res.total} frames, {mb:.1f} MB in {res.seconds:.1f} s; "
               f"read back through LeRobotDataset: vectors equal, frames' PSNR >= {res.check['min_frame_psnr_db']:.1f} dB")  # fmt: skip
    if res.skipped:
        click.echo(f"skipped {len(res.skipped)}: " + "; ".join(f"{r} ({why})" for r, why in res.skipped))


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
