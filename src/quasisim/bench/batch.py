"""``quasisim bench batch``: clips per hour of :mod:`quasisim.batch` with 1 and 2 (or more) Ray workers on
the same clips, one after the other in the same command, and whether they give the same controls. A layout
is a local batch (its own Ray, workers x threads) or a Ray cluster started on this machine for it
(``cluster:NODESxCPUS``: that many ``ray start`` nodes, a worker of one thread per CPU; the batch runs on it
as on any cluster, ``--ray``), so one node of 2 CPUs and two nodes of 1 CPU compare on the same clips."""

from __future__ import annotations

import dataclasses
import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from quasisim.batch import CLIP_FILE, BatchResult, Job, Run, Settings, run_batch, throughput
from quasisim.errors import InputError
from quasisim.eval.tables import clips, header, publish
from quasisim.files import CACHE_ENV
from quasisim.method.spec import TransferSpec
from quasisim.raycluster import LocalCluster


@dataclass(frozen=True)
class Layout:
    """How a batch of the benchmark runs: ``workers`` of ``threads`` each, pinned to cores of their own or
    not; ``nodes`` > 0: on a Ray cluster of that many nodes started on this machine, ``workers / nodes``
    CPUs each (0: a local batch)."""

    workers: int
    threads: int
    pinned: bool = True
    nodes: int = 0

    @property
    def folder(self) -> str:
        """The subfolder of its batch: ``w2t1`` (pinned), ``w2t1u`` (unpinned), ``n2c1`` (2 nodes of 1 CPU)."""
        if self.nodes:
            return f"n{self.nodes}c{self.workers // self.nodes}"
        return f"w{self.workers}t{self.threads}{'' if self.pinned else 'u'}"

    @property
    def label(self) -> str:
        if self.nodes:
            return f"cluster: {self.nodes} node(s) x {self.workers // self.nodes} CPU"
        return f"local: {self.workers} x {self.threads}{'' if self.pinned else ', unpinned'}"


def run_batch_bench(
    data_dir: Path, names: tuple[str, ...], pattern: str, spec: TransferSpec, layouts: tuple[Layout, ...], out: Path,
    overrides: dict[str, Any],
) -> str:  # fmt: skip
    """Each layout runs every clip from scratch into ``out/<layout folder>``, with caches of its own (SDF
    grids, convex decompositions, compiled programs) that start empty: a layout run after another would
    otherwise find the first one's caches full and look faster."""
    paths = clips(data_dir, pattern, names)
    jobs = [Job(p, (Run("", spec),)) for p in paths]
    rows: list[dict[str, Any]] = []
    first = out / layouts[0].folder
    for lay in layouts:
        _check_layout_folder(out / lay.folder)
    for lay in layouts:
        d = out / lay.folder
        shutil.rmtree(d, ignore_errors=True)
        with _cache_at(d / ".cache"):
            res = _run_layout(jobs, d, lay, overrides)
        tp = throughput(res)
        rows.append({"layout": lay.label, "nodes": lay.nodes, "workers": lay.workers, "threads": lay.threads,
                     "pinned": lay.pinned, "failures": res.failures, **tp,
                     "same_controls": _same_controls(first, d, paths)})  # fmt: skip
    return publish(out, "batch", rows, _markdown(rows, spec, len(paths)))


def _check_layout_folder(d: Path) -> None:
    """:class:`InputError` unless ``d`` is missing or a layout folder of an earlier bench batch (what
    :func:`run_batch` writes: ``.work/``, ``.cache/``, clip folders with ``clip.json``, a clip's folder written
    aside), which the layout removes to start from scratch: nothing else there is removed."""
    if not (d.exists() or d.is_symlink()):
        return
    if d.is_symlink() or not d.is_dir():
        got = "a symbolic link" if d.is_symlink() else "a file"
    else:
        got = next((f"a folder holding {p.name}" for p in sorted(d.iterdir()) if not _batch_entry(p)), "")
    if got:
        raise InputError(
            d, "--out", "no file or folder of that name, or a layout folder of an earlier bench batch (.work/, .cache/, "
            f"clip folders with {CLIP_FILE}); move it away or choose another --out", got,
        )  # fmt: skip


def _batch_entry(p: Path) -> bool:
    """Is ``p`` (in a layout folder) something :func:`run_batch` writes?"""
    if p.is_symlink():
        return False
    if p.name in (".work", ".cache"):
        return p.is_dir()
    if p.name.startswith(".") and p.name.endswith((".incoming", ".old")):  # a clip's folder, aside (_persist)
        return p.is_dir()
    return p.is_dir() and (p / CLIP_FILE).is_file()


def _run_layout(jobs: list[Job], d: Path, lay: Layout, overrides: dict[str, Any]) -> BatchResult:
    """The batch of one layout (on a cluster of its own, started and stopped around it, where it has nodes)."""
    s = Settings(workers=lay.workers, threads=lay.threads, overrides=overrides, pin_cores=lay.pinned)
    if not lay.nodes:
        return run_batch(jobs, d, s)
    cluster = LocalCluster.start((lay.workers // lay.nodes,) * lay.nodes)
    try:
        return run_batch(jobs, d, dataclasses.replace(s, ray_address=cluster.address))
    finally:
        cluster.stop()
        cluster.remove()


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
        "| layout | workers | threads per worker | pinned | nodes used | clips | failed | wall s | clips/hour | speed-up vs first row | peak RSS per worker (MB) | same controls as first row |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        mem = ", ".join(f"{v:.0f}" for v in r["peak_rss_mb_per_worker"].values())
        cph = r["clips_per_hour"]
        speed = f"{cph / base:.2f}x" if cph and base else "-"
        lines.append(
            f"| {r['layout']} | {r['workers']} | {r['threads']} | {'yes' if r['pinned'] else 'no'} | {r['nodes_used']} | "
            f"{r['clips_run']} | {len(r['failures'])} | {r['wall_s']:.0f} | {_num(cph)} | {speed} | {mem} | "
            f"{'yes' if r['same_controls'] else 'NO'} |"
        )
    return lines


def _num(x: float | None) -> str:
    return "-" if x is None else f"{x:.1f}"
