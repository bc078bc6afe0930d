"""``quasisim bench batch``: clips per hour of :mod:`quasisim.batch` with 1 and 2 (or more) Ray workers on
the same clips, one after the other in the same command, and whether they give the same controls."""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from quasisim.batch import Job, Run, Settings, run_batch, throughput
from quasisim.eval.tables import clips, header, publish
from quasisim.files import CACHE_ENV
from quasisim.method.spec import TransferSpec


def run_batch_bench(
    data_dir: Path, names: tuple[str, ...], pattern: str, spec: TransferSpec,
    layouts: tuple[tuple[int, int, bool], ...], out: Path, overrides: dict[str, Any],
) -> str:  # fmt: skip
    """Each (workers, threads per worker, workers pinned to cores) of ``layouts`` runs every clip from scratch
    into ``out/w<W>t<T>`` (``...u`` unpinned), with caches of its own (SDF grids, convex decompositions,
    compiled programs) that start empty: a layout run after another would otherwise find the first one's
    caches full and look faster."""
    paths = clips(data_dir, pattern, names)
    jobs = [Job(p, (Run("", spec),)) for p in paths]
    rows: list[dict[str, Any]] = []
    first = out / layout_folder(*layouts[0])
    for w, t, pin in layouts:
        d = out / layout_folder(w, t, pin)
        shutil.rmtree(d, ignore_errors=True)
        with _cache_at(d / ".cache"):
            res = run_batch(jobs, d, Settings(workers=w, threads=t, overrides=overrides, pin_cores=pin))
        tp = throughput(res)
        rows.append({"workers": w, "threads": t, "pinned": pin, "failures": res.failures, **tp,
                     "same_controls": _same_controls(first, d, paths)})  # fmt: skip
    return publish(out, "batch", rows, _markdown(rows, spec, len(paths)))


def layout_folder(workers: int, threads: int, pinned: bool) -> str:
    """The subfolder of a layout's batch: ``w2t1`` (pinned) or ``w2t1u``."""
    return f"w{workers}t{threads}{'' if pinned else 'u'}"


@contextmanager
def _cache_at(path: Path) -> Iterator[None]:
    """Local Ray workers started inside use the cache folder ``path`` (they inherit the driver's environment)."""
    before = os.environ.get(CACHE_ENV)
    os.environ[CACHE_ENV] = str(path)
    try:
        yield
    finally:
        if before is None:
            os.environ.pop(CACHE_ENV)
        else:
            os.environ[CACHE_ENV] = before


def _same_controls(a: Path, b: Path, paths: list[Path]) -> bool:
    """Are the PD targets of every clip bit-identical in the two batches?"""
    for p in paths:
        fa, fb = a / p.stem / "controls.npz", b / p.stem / "controls.npz"
        if not (fa.is_file() and fb.is_file()):
            return False
        with np.load(fa) as za, np.load(fb) as zb:
            if not np.array_equal(za["q_targets"], zb["q_targets"]):
                return False
    return True


def _markdown(rows: list[dict[str, Any]], spec: TransferSpec, n: int) -> list[str]:
    base = rows[0]["clips_per_hour"]
    lines = [
        header(
            f"Batch throughput ({spec.method}, {spec.hand}, {spec.target}, {n} clips, each layout from scratch, its caches empty)"
        ),
        "| workers | threads per worker | pinned | clips | failed | wall s | clips/hour | speed-up vs first row | peak RSS per worker (MB) | same controls as first row |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        mem = ", ".join(f"{v:.0f}" for v in r["peak_rss_mb_per_worker"].values())
        lines.append(
            f"| {r['workers']} | {r['threads']} | {'yes' if r['pinned'] else 'no'} | {r['clips_run']} | {len(r['failures'])} | {r['wall_s']:.0f} | "
            f"{r['clips_per_hour']:.1f} | {r['clips_per_hour'] / base:.2f}x | {mem} | {'yes' if r['same_controls'] else 'NO'} |"
        )
    return lines
