"""``quasisim bench transfer``: transfer runs (curricula, ``+mpc``, MPC baselines) on clips beside the
kinematic replay, as one batch (:mod:`quasisim.batch`: Ray workers, resumable); optionally judged open loop
in the other target."""

from __future__ import annotations

import dataclasses
import json
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from quasisim.batch import Job, Run, Settings, finished_runs, lifted_as_demo, method_seconds, run_batch
from quasisim.data.controls import load_controls
from quasisim.data.demo import load_demo
from quasisim.errors import QuasisimError
from quasisim.eval.evaluate import evaluate_controls
from quasisim.eval.metrics import SUCCESS_KEYS
from quasisim.eval.tables import SUMMARY_HEAD, clips, header, publish, robust_cells, summary_rows
from quasisim.files import save_json_atomic
from quasisim.method import registry
from quasisim.method.curriculum import load_curriculum
from quasisim.method.spec import TransferSpec, networks_from_flags

RUN_KINDS = (
    "CURRICULUM (stages 1,2), CURRICULUM+3, CURRICULUM+mpc, CURRICULUM+sample, CURRICULUM+3+sample+select, ... "
    "(those stages after 1,2), each optionally with ablations of stage 3 (':no-residual', ':no-local-residual', "
    "':no-control-transform', e.g. default+3+mpc:no-residual), mpc-base, mpc-soften, sample-target"
)


def run_spec(run: str, stages: tuple[str, ...], base: TransferSpec) -> TransferSpec:
    """A benchmark run name (``default``, ``none+mpc``, ``mpc-base`` ...) as the transfer it stands for: a
    method with stages of its own (:data:`quasisim.method.registry.METHODS`), or a curriculum with ``stages``
    and the stages after stage 2 named after it."""
    preset = registry.METHODS[run].stages if run in registry.METHODS else None
    if preset:  # a method with stages of its own; the curriculum matters only to stages 1 and 2
        cur = base.curriculum if {"1", "2"} & set(preset) else "none"
        return dataclasses.replace(base, method=run, curriculum=cur).checked()
    name, *ablations = run.split(":")
    cur, *extra = name.split("+")
    flags = {"no-residual", "no-local-residual", "no-control-transform"}
    after = set(list(registry.STAGES)[list(registry.STAGES).index("2") + 1 :])
    bad_extra = not set(extra) <= after or len(set(extra)) < len(extra)
    if bad_extra or not set(ablations) <= flags or (ablations and "3" not in extra):
        raise QuasisimError(f"unknown benchmark run {run!r}; valid forms: {RUN_KINDS}")
    load_curriculum(cur)
    nets = networks_from_flags(*(f in ablations for f in ("no-residual", "no-local-residual", "no-control-transform")))
    return dataclasses.replace(base, method="ours", curriculum=cur, stages=(*stages, *extra), networks=nets).checked()


def jobs(paths: list[Path], specs: dict[str, TransferSpec]) -> list[Job]:
    """One batch job per clip: its runs, each ``CURRICULUM+A+B`` run after (and seeded by the checkpoints of)
    the longest of ``CURRICULUM+A``, ``CURRICULUM`` asked for too, and each of the paper's ablations
    (``paper-no-residual`` ...) after the first run asked for with its curriculum (checkpoints are reused
    only where they match, piece by piece: stage 3 with other networks is computed again)."""
    order = sorted(specs, key=lambda r: r.count("+"))
    seeds = {r: _seed(r, specs) or _preset_seed(r, order, specs) for r in order}
    return [Job(p, tuple(Run(r, specs[r], seeds[r]) for r in order)) for p in paths]


def _seed(run: str, specs: dict[str, TransferSpec]) -> str | None:
    parts = run.split("+")
    return next((p for p in ("+".join(parts[:n]) for n in range(len(parts) - 1, 0, -1)) if p in specs), None)


def _preset_seed(run: str, order: list[str], specs: dict[str, TransferSpec]) -> str | None:
    """For a method with a curriculum of its own (:data:`quasisim.method.registry.METHODS`), the first run
    before it in ``order`` with the same curriculum and stage 1 (None for every other run: the seeds of
    folders made before these methods stay as they were)."""
    m = registry.METHODS.get(run)
    if m is None or m.curriculum is None:
        return None
    earlier = order[: order.index(run)]
    same = (r for r in earlier if specs[r].curriculum == specs[run].curriculum and "1" in specs[r].stages)
    return next(same, None)


def _rows(r: dict[str, Any], run_dir: Path, demo_path: Path, judge: str | None, target: str) -> list[dict[str, Any]]:
    """A batch result row as the kinematic replay's row and the run's (judged in ``judge`` when given)."""
    m, k = r["metrics"], r["kinematic_metrics"]
    if judge and judge != target:
        m, k = _judged(demo_path, run_dir, judge)
    better = bool(m["T_err_cm"] < k["T_err_cm"] and m["R_err_deg"] < k["R_err_deg"])
    return [
        {"clip": r["clip"], "method": "kinematic", **k, "wall_s": float(r["seconds"].get("retarget", 0.0)), "seconds": {}},
        {"clip": r["clip"], "method": r["run"], **m, "seconds": r["seconds"], "wall_s": method_seconds(r["seconds"]),
         "better": better, **stiffest_simulator(run_dir / "summary.json")},
    ]  # fmt: skip


def stiffest_simulator(summary: Path) -> dict[str, Any]:
    """Stage 2's last (stiffest) simulator of a run: its best loss and the start the restart guard chose
    there (``{}`` for a run without stage 2)."""
    sims = json.loads(summary.read_text()).get("simulators") if summary.is_file() else None
    if not sims:
        return {}
    starts = sims[-1].get("start_losses") or {}
    return {"stiffest_loss": sims[-1]["loss_best"], "stiffest_start": min(starts, key=starts.get) if starts else "-"}


def run_transfer_bench(
    data_dir: Path, clip_names: tuple[str, ...], pattern: str, runs: tuple[str, ...], stages: tuple[str, ...],
    budget: str, target: str, hand_name: str, out: Path, report_only: bool = False, judge: str | None = None,
    settings: Settings | None = None, robust: int | None = None,
    closed_loop: tuple[tuple[str, ...], dict[str, Any]] | None = None, robust_set: dict[str, Any] | None = None,
) -> str:  # fmt: skip
    """Each run of ``runs`` on each clip into ``out/<clip>/<run>`` with :func:`quasisim.batch.run_batch`
    (resumable; ``report_only``: nothing is run, the finished runs are tabulated), beside the kinematic
    replay in the same target; with ``judge`` (another simulator) every run's controls and the kinematic
    retarget are judged open loop there instead (cached as ``metrics_<judge>.json`` beside each run).
    ``robust``: perturbed replays per run for robust success (None: ``configs/robust.yaml``'s ``n``).
    ``closed_loop``: perturbation sets (:data:`quasisim.eval.robust.RANGES`) whose ``robust`` worlds every
    finished run is then replayed in, open and closed loop (:mod:`quasisim.bench.closed_loop`), and overrides
    of the tracker's settings (``configs/track.yaml``). ``robust_set``: overrides of every perturbation set
    (``--robust-set seed=7``), open and closed loop. An OUT whose runs were judged with another ``robust`` or
    ``robust_set`` is refused, report-only too (:func:`quasisim.batch.finished_runs`).
    Prints and writes the markdown tables."""
    s = (settings or Settings(keep_scratch=True)).resolved()
    rows = transfer_rows(data_dir, clip_names, pattern, runs, stages, budget, target, hand_name, out, report_only, judge,
                         s, robust, robust_set)  # fmt: skip
    lines = []
    if closed_loop:
        from quasisim.bench import closed_loop as cl

        by_clip = {p.stem: p for p in clips(data_dir, pattern, clip_names)}
        sets, track = closed_loop
        rows = cl.add_closed_loop(
            rows, out, by_clip, robust or 0, sets, judge or target, s.workers or 2, track, robust_set
        )
        lines = ["", *cl.markdown(rows, runs, sets, track)]
    return publish(
        out,
        "transfer" if (judge or target) == target else f"transfer_{judge}",
        rows,
        _markdown(rows, runs, hand_name, target, judge or target, budget) + lines,
    )


def transfer_rows(
    data_dir: Path, clip_names: tuple[str, ...], pattern: str, runs: tuple[str, ...], stages: tuple[str, ...],
    budget: str, target: str, hand_name: str, out: Path, report_only: bool = False, judge: str | None = None,
    settings: Settings | None = None, robust: int | None = None, robust_set: dict[str, Any] | None = None,
) -> list[dict[str, Any]]:  # fmt: skip
    """The rows of :func:`run_transfer_bench` (its arguments), without the closed-loop pass and without writing
    the tables: each finished run's, after running the rest unless ``report_only``, and the kinematic replay's."""
    over = tuple(sorted((robust_set or {}).items()))
    base = TransferSpec(
        hand=hand_name, target=target, budget=budget, render=False, progress=False, robust=robust, robust_set=over
    )
    paths = clips(data_dir, pattern, clip_names)
    js = jobs(paths, {r: run_spec(r, stages, base) for r in runs})
    s = (settings or Settings(keep_scratch=True)).resolved()
    if report_only:
        results = [row for j in js for row in finished_runs(out, j, s, any_revision=True).values()]
    else:
        res = run_batch(js, out, s)
        results = res.rows
        for clip, err in sorted(res.failures.items()):
            print(f"failed: {clip}: {err}")
    by_clip = {p.stem: p for p in paths}
    rows: list[dict[str, Any]] = []
    for r in sorted(results, key=lambda r: (r["clip"], runs.index(r["run"]))):
        kin, row = _rows(r, out / r["clip"] / r["run"], by_clip[r["clip"]], judge, target)
        if not any(x["clip"] == r["clip"] and x["method"] == "kinematic" for x in rows):
            rows.append(kin)
        rows.append(row)
    for r in rows:
        r["lifted"] = lifted_as_demo(r)
    return rows


def _markdown(
    rows: list[dict[str, Any]], runs: tuple[str, ...], hand: str, target: str, judged_in: str, budget: str
) -> list[str]:
    lines = [
        header(f"Transfer ({hand}, optimised for {target}, judged in {judged_in}, budget {budget})"),
        SUMMARY_HEAD.format(g="method"),
        *summary_rows(rows, "method"),
        "",
    ]
    for run in runs:
        rs = [r for r in rows if r["method"] == run]
        st = [r["seconds"] for r in rs]
        per_stage = {k: np.mean([s.get(k, 0.0) for s in st]) for k in sorted({k for s in st for k in s})}
        lines.append(
            f"- {run}: lower T_err and lower R_err than the kinematic replay on {sum(r['better'] for r in rs)} of "
            f"{len(rs)} clips{_versus(rows, rs, 'sample-target')}; mean seconds per stage: "
            + ", ".join(f"{k} {v:.0f}" for k, v in per_stage.items())
            + _stiffest_line(rs)
        )
    lines += [
        "",
        "Seconds per clip are the sum of the stages' own timings (a stage read back from a checkpoint, e.g. the "
        "curriculum shared by `default` and `default+...`, counts the time it took), judging aside.",
        "",
        "`stiffest`: stage 2's best loss in its stiffest simulator and the start the restart guard chose there.",
        "",
        "| clip | method | R_err | T_err | MPJPE | CD | 10 | 15 | 20 | strict | robust strict | robust 20 | s (stages) "
        "| stiffest |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    yn = lambda b: "y" if b else "-"  # noqa: E731
    for r in rows:
        s = r["success"]
        st = f"{loss_cell(r['stiffest_loss'])} ({r['stiffest_start']})" if "stiffest_loss" in r else "-"
        lines.append(
            f"| {r['clip']} | {r['method']} | {r['R_err_deg']:.1f} | {r['T_err_cm']:.2f} | {r['MPJPE_mm']:.1f} | "
            f"{r['CD_mm']:.1f} | "
            + " | ".join(yn(s[k]) for k in SUCCESS_KEYS)
            + f" | {robust_cells([r])} | {r['wall_s']:.0f} | {st} |"
        )
    return lines


def loss_cell(x: float | None) -> str:
    """A stage-2 loss as a table cell ("-": none finite)."""
    return "-" if x is None else f"{x:.4f}"


def _stiffest_line(rs: list[dict[str, Any]]) -> str:
    """ "; stage 2 in its stiffest simulator: mean loss x (median y), started from: ..." for runs with stage 2."""
    with_2 = [r for r in rs if "stiffest_loss" in r]
    if not with_2:
        return ""
    loss = [r["stiffest_loss"] for r in with_2 if r["stiffest_loss"] is not None]  # None: no finite loss
    starts = Counter(r["stiffest_start"] for r in with_2)
    mean = f"mean loss {np.mean(loss):.4f} (median {np.median(loss):.4f}), " if loss else ""
    return (
        "; stage 2 in its stiffest simulator: "
        + mean
        + "started from "
        + ", ".join(f"{k} {n}" for k, n in starts.most_common())
    )


def _judged(demo_path: Path, run_dir: Path, judge: str) -> tuple[dict[str, Any], dict[str, Any]]:
    """Metrics of a finished run's controls and of its kinematic retarget, replayed open loop in ``judge``."""
    cache = run_dir / f"metrics_{judge}.json"
    if cache.is_file():
        d = json.loads(cache.read_text())
        return d["metrics"], d["kinematic_metrics"]
    demo = load_demo(demo_path)
    c = load_controls(run_dir / "controls.npz")
    kin = dataclasses.replace(c, q_targets=np.asarray(c.extras["kinematic_q"]), method="kinematic")
    d = {
        "metrics": evaluate_controls(demo, c, judge, None, render=False).metrics,
        "kinematic_metrics": evaluate_controls(demo, kin, judge, None, render=False).metrics,
    }
    save_json_atomic(cache, d)
    return d["metrics"], d["kinematic_metrics"]


def _versus(rows: list[dict[str, Any]], rs: list[dict[str, Any]], other: str) -> str:
    """ ", lower T_err and lower R_err than OTHER on n of m clips" (nothing when OTHER is not among the runs)."""
    ref = {r["clip"]: r for r in rows if r["method"] == other}
    pairs = [(r, ref[r["clip"]]) for r in rs if r["clip"] in ref and r["method"] != other]
    if not pairs:
        return ""
    n = sum(a["T_err_cm"] < b["T_err_cm"] and a["R_err_deg"] < b["R_err_deg"] for a, b in pairs)
    return f", than {other} on {n} of {len(pairs)}"
