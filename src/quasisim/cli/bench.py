"""`quasisim bench`: the benchmarks behind the tables of BENCHMARKS.md (transfer, compare, batch, policy, env,
paper, export) and the strict-failure analysis of finished runs (failures)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import click

from quasisim.cli._common import (
    _BUDGET,
    _HAND,
    _TARGET,
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
    _stages,
    main,
)
from quasisim.errors import QuasisimError
from quasisim.method.spec import METHODS, TransferSpec, parse_stages

if TYPE_CHECKING:
    from quasisim.bench.batch import Layout


@main.group()
def bench() -> None:
    """The benchmarks behind the tables of BENCHMARKS.md, and why finished runs fail strict (failures)."""


@bench.command("env")
@click.argument("clip", type=click.Path(path_type=Path, exists=True, dir_okay=False))
@click.option("--reference", type=click.Path(path_type=Path, exists=True), default=None,
              help="The result tracked (run folder or controls.npz); default: the kinematic retarget to --hand.")  # fmt: skip
@click.option("--hand", default="shadow", show_default=True, help="Robot hand without --reference.")
@click.option("--target", type=TARGET_CHOICE, default="mujoco", show_default=True)
@click.option("--residual/--no-residual", default=True, show_default=True, help="Residual actions (ours+residual).")
@click.option("--resets", type=click.IntRange(1), default=100, show_default=True, help="Resets into training worlds.")
@click.option("--steps", type=click.IntRange(1), default=1000, show_default=True, help="Env steps.")
@click.option("--noise", type=click.FloatRange(0, 1), default=0.1, show_default=True,
              help="Std of the Gaussian actions (action units), as a fresh policy explores.")  # fmt: skip
@_friendly
def bench_env(
    clip: Path, reference: Path | None, hand: str, target: str, residual: bool, resets: int, steps: int, noise: float
) -> None:  # fmt: skip
    """Speed of quasisim/Track-v0 on CLIP: resets per second (each into another training world) and env steps
    per second, with and without the resets that end episodes; a markdown table."""
    _setup_runtime()
    from quasisim.bench.env import run_env_bench

    click.echo(run_env_bench(clip, reference, hand, target, residual, resets, steps, noise))


@bench.command("transfer")
@click.argument("data_dir", type=click.Path(path_type=Path, exists=True, file_okay=False))
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
@_BUDGET
@_TARGET
@_HAND
@click.option("--out", "out", type=click.Path(path_type=Path), default=Path("bench_out/transfer"), show_default=True)
@click.option("--report-only", is_flag=True, help="Tabulate the finished runs in OUT; run nothing.")
@click.option(
    "--judge",
    type=TARGET_CHOICE,
    default=None,
    help="Judge the runs' controls (and the kinematic replay) open loop in this simulator instead of --target.",
)
@_clips_options(
    ray_help="Run on an existing Ray cluster: auto (the one `ray start` made here) or HOST:PORT (default: local Ray).",
    set_help="Override a config key (as in transfer), e.g. --set stage2.mode=none.",
)
@_judging(
    robust=click.option(
        "--robust", type=click.IntRange(0, 1000), default=None,
        help="Perturbed replays per run for robust success (default: n of configs/robust.yaml; 0: none). Clips "
        "finished before keep their judging: use a new OUT.",
    ),
    closed_loop=click.option(
        "--closed-loop", is_flag=True,
        help="After the batch, replay every finished run in the perturbed worlds of --ranges open and closed loop "
        "(--robust N replays each; cached per run, resumable) and add the closed-loop tables.",
    ),
    tracker=True,
)  # fmt: skip
@_interruptible
@_friendly
def bench_transfer(
    data_dir: Path, runs: str, stages: str, budget: str, target: str, hand: str, out: Path, report_only: bool,
    judge: str | None, clips: Clips, judging: Judging,
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
    c = clips
    TransferConfig.from_yaml(overrides=c.overrides)  # a bad key fails here, before any clip runs
    s = Settings(
        c.ray_address, c.workers, overrides=c.overrides, keep_scratch=True, record_transitions=c.record,
        lead_clip=c.lead_clip,
    )  # fmt: skip
    loop = (judging.ranges, judging.track) if judging.closed_loop else None
    run_transfer_bench(
        data_dir, c.names, c.pattern, rs, st, budget, target, hand, out, report_only, judge, s, judging.robust,
        closed_loop=loop, robust_set=dict(judging.robust_set),
    )  # fmt: skip


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
    help="Per layout, in order: WORKERSxTHREADS of a local batch (-unpinned: workers not pinned to cores of their "
    "own, 2x1-unpinned), or cluster:NODESxCPUS, a Ray cluster of that many nodes started on this machine for the "
    "layout (cluster:1x2,cluster:2x1: one node of 2 CPUs against two nodes of 1 CPU).",
)  # fmt: skip
@click.option("--set", "sets", multiple=True, help="Override a config key (as in transfer).")
@click.option("--out", "out", type=click.Path(path_type=Path), default=Path("bench_out/batch"), show_default=True)
@_interruptible
@_friendly
def bench_batch(
    data_dir: Path, clip_names: str, pattern: str, method: str, stages: str, layouts: str, sets: tuple[str, ...],
    out: Path,
) -> None:  # fmt: skip
    """Clips per hour of `quasisim batch` with 1 and 2 Ray workers, or on Ray clusters of 1 and 2 nodes, on
    the same clips (same command)."""
    _outputs_free(out)
    _setup_runtime()
    from quasisim.bench.batch import run_batch_bench

    try:
        lay = tuple(_layout(x.strip()) for x in layouts.split(",") if x.strip())
        assert lay
    except (ValueError, AssertionError):
        raise QuasisimError(
            f"--layouts expects WORKERSxTHREADS[-unpinned] or cluster:NODESxCPUS, comma-separated (e.g. "
            f"1x1,2x1,2x1-unpinned or cluster:1x2,cluster:2x1), got {layouts!r}"
        ) from None
    spec = TransferSpec(method=method, stages=_stages(stages), render=False, progress=False).checked()
    names = tuple(c.strip() for c in clip_names.split(",") if c.strip())
    run_batch_bench(data_dir, names, pattern, spec, lay, out, _parse_sets(sets))


def _layout(text: str) -> Layout:
    """``2x1`` -> 2 local workers of 1 thread, pinned; ``2x1-unpinned``: not pinned; ``cluster:2x1`` -> a
    cluster of 2 nodes of 1 CPU each (a worker of 1 thread per CPU)."""
    from quasisim.bench.batch import Layout

    kind, _, rest = text.rpartition(":")
    shape, _, flag = rest.partition("-")
    if kind not in ("", "cluster") or flag not in ("", "unpinned") or (kind and flag):
        raise ValueError(text)
    a, b = (int(x) for x in shape.split("x"))
    if min(a, b) < 1:
        raise ValueError(text)
    return Layout(a * b, 1, True, a) if kind else Layout(a, b, flag == "")


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
@click.option("--methods", default="ours+residual,dgrasp-tracking", show_default=True,
              help="Policies to train (also: dgrasp-base, dgrasp-tracking-curriculum).")  # fmt: skip
@click.option("--set", "sets", multiple=True,
              help="A setting of every policy trained: env.KEY=V (configs/track_env.yaml), ppo.KEY=V "
                   "(configs/ppo.yaml); a folder trained with other settings is refused.")  # fmt: skip
@click.option("--out", "out", type=click.Path(path_type=Path), default=Path("bench_out/policy"), show_default=True)
@click.option("--report-only", is_flag=True, help="Tabulate the policies finished and judged in OUT; train nothing.")
@_friendly
def bench_policy(
    data_dir: Path, clip_names: str, runs: Path, run: str, steps: int, robust: int, workers: int, methods: str,
    sets: tuple[str, ...], out: Path, report_only: bool,
) -> None:  # fmt: skip
    """Learned tracking policies (ours+residual, dgrasp-tracking) beside ours open and closed loop, per clip;
    resumable (finished policies are kept, unfinished ones resume from their checkpoints)."""
    from quasisim.cli.policy import _need_rl, _split_sets

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
    env_o, ppo_o = _split_sets(sets)
    run_policy_bench(data_dir, names, runs, run, steps, robust, workers, out, chosen, overrides=(env_o, ppo_o),
                     report_only=report_only)  # fmt: skip


@bench.command("paper")
@click.argument("data_dir", type=click.Path(path_type=Path, exists=True, file_okay=False))
@click.option("--tables", default="main,ablation", show_default=True,
              help="Which of the paper's tables: main (baselines), ablation.")  # fmt: skip
@click.option("--policy", "policy", type=click.Path(path_type=Path, exists=True, file_okay=False), default=None,
              help="A folder of `quasisim bench policy` on these clips: its policies fill the learned rows.")  # fmt: skip
@click.option("--robust", type=click.IntRange(0, 1000), default=None,
              help="Perturbed replays per run (default: n of configs/robust.yaml; 0: none).")  # fmt: skip
@_BUDGET
@click.option("--out", "out", type=click.Path(path_type=Path), default=Path("bench_out/paper"), show_default=True)
@click.option("--report-only", is_flag=True, help="Tabulate the finished runs in OUT; run nothing.")
@click.option("--from", "sources", multiple=True, type=click.Path(path_type=Path, exists=True, file_okay=False),
              help="Another folder of `quasisim bench transfer` on these clips (repeatable): its finished runs fill "
                   "the rows OUT lacks (read only).")  # fmt: skip
@_clips_options(
    ray_help="Run on an existing Ray cluster: auto (the one `ray start` made here) or HOST:PORT (default: local Ray).",
    set_help="Override a config key (as in transfer).",
)
@_interruptible
@_friendly
def bench_paper(
    data_dir: Path, tables: str, policy: Path | None, robust: int | None, budget: str, out: Path, report_only: bool,
    sources: tuple[Path, ...], clips: Clips,
) -> None:  # fmt: skip
    """The paper's two tables (baselines, ablations) on clips of DATA_DIR: every row quasisim has, run as one
    resumable batch in MuJoCo with the Shadow hand, beside the paper's own figures; writes OUT/paper.md."""
    _outputs_free(out)
    _setup_runtime()
    from quasisim.batch import Settings
    from quasisim.bench.paper import run_paper_bench
    from quasisim.method.config import TransferConfig

    c = clips
    TransferConfig.from_yaml(overrides=c.overrides)
    s = Settings(c.ray_address, c.workers, overrides=c.overrides, keep_scratch=True, lead_clip=c.lead_clip)
    chosen = tuple(t.strip() for t in tables.split(",") if t.strip())
    run_paper_bench(data_dir, c.names, c.pattern, chosen, out, policy, report_only, s, robust, budget, sources)


@bench.command("failures")
@click.argument("runs", type=click.Path(path_type=Path, exists=True, file_okay=False))
@click.option("--data", "data_dir", type=click.Path(path_type=Path, file_okay=False), default=None,
              help="Folder of the runs' demos (default: $QUASISIM_DATA).")  # fmt: skip
@click.option("--out", "out", type=click.Path(path_type=Path), default=None, help="Output folder (default: RUNS).")
@click.option("--replays", is_flag=True,
              help="The perturbed replays instead, open and closed loop, from the closed-loop caches of a bench "
              "transfer folder (its --closed-loop pass): per replay the first frame over a limit and why (pushed off, "
              "drop, lost contact, carried off, rotated in grasp, slip in grasp); writes replay_failures.md.")  # fmt: skip
@click.option("--ranges", default="default", show_default=True, help="With --replays: the perturbation set.")
@click.option("--tracker", default="track.yaml", show_default=True, help="With --replays: the tracker's settings file.")
@click.option(
    "--track-set", "track_sets", multiple=True, help="With --replays: a tracker setting, as with --closed-loop."
)
@_friendly
def bench_failures(
    runs: Path, data_dir: Path | None, out: Path | None, replays: bool, ranges: str, tracker: str,
    track_sets: tuple[str, ...],
) -> None:  # fmt: skip
    """Why each finished run under RUNS fails strict success: first frame over a limit, which limit, and a
    label (symmetric, drop, never grasped, lost contact, slip); writes failures.md and failures.json. With
    --replays, why its perturbed replays fail (docs/metrics.md)."""
    import os

    from quasisim.eval.failures import analyse, write

    if replays:
        click.echo(_replay_failures(runs, out or runs, ranges, tracker, track_sets))
        return
    data = data_dir or Path(os.environ.get("QUASISIM_DATA", "../shared/data"))
    click.echo(write(runs, analyse(runs, data), out or runs))


def _replay_failures(runs: Path, out: Path, ranges: str, tracker: str, track_sets: tuple[str, ...]) -> str:
    from quasisim.bench.closed_loop import _track_dict
    from quasisim.cli._common import _track_overrides
    from quasisim.eval.replay_failures import replay_failures, replay_markdown
    from quasisim.eval.tables import header
    from quasisim.files import save_text_atomic
    from quasisim.method.track import TrackOptions
    from quasisim.targets.perturb import resolve_ranges

    track = _track_dict(TrackOptions.from_yaml(None, _track_overrides(tracker, track_sets)))
    rows = replay_failures(runs, resolve_ranges(ranges), track)
    if not rows:
        raise QuasisimError(
            f"{runs}: expected closed-loop caches (robust_closed_loop-*.json) of set {ranges!r} and this tracker, got "
            "none: run `quasisim bench transfer ... --closed-loop` with the same --ranges and tracker first"
        )
    md = (
        header(f"Why the perturbed replays of the runs under {runs} fail ({ranges} worlds)")
        + "\n"
        + replay_markdown(rows)
    )
    out.mkdir(parents=True, exist_ok=True)
    save_text_atomic(out / "replay_failures.md", md)
    return md


@bench.command("grasp")
@click.argument("runs", type=click.Path(path_type=Path, exists=True, file_okay=False))
@click.option("--data", "data_dir", type=click.Path(path_type=Path, file_okay=False), default=None,
              help="Folder of the runs' demos (default: $QUASISIM_DATA).")  # fmt: skip
@click.option("--out", "out", type=click.Path(path_type=Path), default=None, help="Output folder (default: RUNS).")
@click.option("--margin", type=click.FloatRange(0.0, 1.0, max_open=True), default=0.2, show_default=True,
              help="The friction cones shrunk by this fraction.")  # fmt: skip
@click.option("--slots", type=click.IntRange(1, 64), default=8, show_default=True,
              help="Each hand's strongest contacts counted.")  # fmt: skip
@click.option("--ranges", default="default", show_default=True, help="The perturbation set of the robust column.")
@_friendly
def bench_grasp(runs: Path, data_dir: Path | None, out: Path | None, margin: float, slots: int, ranges: str) -> None:
    """The grasp margin of every finished run under RUNS (a bench transfer folder): its controls replayed in the
    nominal MuJoCo target, per frame the load the hand-object contacts carry beyond friction cones shrunk by
    --margin (object weights), beside the run's open-loop robust strict success; writes grasp_margin.md and
    grasp_margin.json."""
    import json
    import os

    from quasisim.eval.grasp_margin import grasp_markdown, grasp_rows
    from quasisim.eval.tables import header
    from quasisim.files import save_text_atomic
    from quasisim.targets.perturb import resolve_ranges

    data = data_dir or Path(os.environ.get("QUASISIM_DATA", "../shared/data"))
    set_name = resolve_ranges(ranges)
    rows = grasp_rows(runs, data, margin, slots, set_name)
    md = header(f"Grasp margin of the runs under {runs}") + "\n" + grasp_markdown(rows, margin, set_name)
    dest = out or runs
    dest.mkdir(parents=True, exist_ok=True)
    save_text_atomic(dest / "grasp_margin.json", json.dumps({"margin": margin, "slots": slots, "rows": rows}, indent=1))
    save_text_atomic(dest / "grasp_margin.md", md)
    click.echo(md)


@bench.command("export")
@click.argument("runs", type=click.Path(path_type=Path, exists=True, file_okay=False))
@click.option(
    "--data", "data_dirs", multiple=True, type=click.Path(path_type=Path, exists=True, file_okay=False),
    help="Folder of the runs' demos (repeatable; default: as quasisim export finds them).",
)  # fmt: skip
@click.option("--closed-loop", "closed_loop", type=click.IntRange(0, 1000), default=0, show_default=True,
              help="Per run, also N closed-loop episodes (as quasisim export --closed-loop).")  # fmt: skip
@click.option("--image-size", "image_size", type=(click.IntRange(16, 2048), click.IntRange(16, 2048)),
              default=(240, 320), show_default=True, help="The LeRobot camera's height and width.")  # fmt: skip
@_friendly
def bench_export(runs: Path, data_dirs: tuple[Path, ...], closed_loop: int, image_size: tuple[int, int]) -> None:
    """Time and size of `quasisim export` per finished run under RUNS, robomimic (HDF5) beside lerobot (each run
    exported alone, in both formats, into a temporary folder); a markdown table. Needs lerobot
    (.venv-lerobot/bin/quasisim: make setup-lerobot)."""
    _setup_runtime()
    from quasisim.bench.export import run_export_bench

    click.echo(run_export_bench(runs, data_dirs, closed_loop, image_size)[1])
