"""`quasisim bench`: the studies (predict, world, screen, windows, sensitivity, fit)."""

from __future__ import annotations

import math
from pathlib import Path

import click

from quasisim.cli._common import (
    _TRANSITIONS_DATA,
    _friendly,
    _outputs_free,
    _parse_sets,
    _positive_ints,
    _setup_runtime,
)
from quasisim.cli.bench import bench
from quasisim.errors import QuasisimError


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
