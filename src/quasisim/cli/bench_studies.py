"""`quasisim bench`: the studies (predict, sensitivity, fit)."""

from __future__ import annotations

import math
from pathlib import Path

import click

from quasisim.cli._common import (
    _friendly,
    _outputs_free,
    _parse_sets,
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


@bench.command("policy")
@click.argument("data_dir", type=click.Path(path_type=Path, exists=True, file_okay=False))
@click.option("--clips", "clip_names", required=True, help="Comma-separated clip names.")
@click.option("--runs", "runs", type=click.Path(path_type=Path, exists=True, file_okay=False), required=True,
              help="Folder of our results (RUNS/<clip>/<run>/controls.npz and metrics.json with --robust N).")  # fmt: skip
@click.option("--run", "run", default="cascade", show_default=True, help="Which run of each clip is ours.")
@click.option("--steps", type=click.IntRange(1), default=81920, show_default=True, help="Env steps per policy.")
@click.option("--robust", type=click.IntRange(1, 1000), default=8, show_default=True, help="Perturbed worlds.")
@click.option("--workers", type=click.IntRange(1), default=2, show_default=True,
              help="Processes for the closed-loop replays of ours.")  # fmt: skip
@click.option("--methods", default="ours+residual,dgrasp-tracking", show_default=True, help="Policies to train.")
@click.option("--out", "out", type=click.Path(path_type=Path), default=Path("bench_out/policy"), show_default=True)
@_friendly
def bench_policy(
    data_dir: Path, clip_names: str, runs: Path, run: str, steps: int, robust: int, workers: int, methods: str,
    out: Path,
) -> None:  # fmt: skip
    """Learned tracking policies (ours+residual, dgrasp-tracking) beside ours open and closed loop, per clip;
    resumable (finished policies are kept, unfinished ones resume from their checkpoints)."""
    from quasisim.cli.policy import _need_rl

    _need_rl()
    _outputs_free(out)
    _setup_runtime()
    from quasisim.bench.policy import POLICY_METHODS, run_policy_bench
    from quasisim.errors import choice_error

    chosen = tuple(m.strip() for m in methods.split(",") if m.strip())
    for m in chosen:
        if m not in POLICY_METHODS:
            raise choice_error("--methods entry", m, POLICY_METHODS)
    names = [c.strip() for c in clip_names.split(",") if c.strip()]
    run_policy_bench(data_dir, names, runs, run, steps, robust, workers, out, chosen)
