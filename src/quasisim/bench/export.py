"""``quasisim bench export``: the time and size of ``quasisim export`` per run, robomimic's HDF5 beside a LeRobot
dataset, each run exported alone into a temporary folder (so each figure includes what a one-run export costs:
for lerobot, creating the dataset and reading it back)."""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

HEAD = (
    "| run | frames | robomimic s | robomimic MB | lerobot s | lerobot MB | lerobot / robomimic s |\n"
    "|---|---|---|---|---|---|---|"
)


@dataclass(frozen=True)
class ExportCost:
    """One run's exports: ``frames`` frames (all its episodes), seconds and megabytes of each format."""

    run: str
    frames: int
    robomimic_s: float
    robomimic_mb: float
    lerobot_s: float
    lerobot_mb: float

    def row(self) -> str:
        return (
            f"| {self.run} | {self.frames} | {self.robomimic_s:.1f} | {self.robomimic_mb:.2f} | {self.lerobot_s:.1f} "
            f"| {self.lerobot_mb:.2f} | {self.lerobot_s / self.robomimic_s:.2f} |"
        )


def run_export_bench(
    root: Path, data_dirs: tuple[Path, ...], closed_loop: int, image_size: tuple[int, int]
) -> tuple[list[ExportCost], str]:
    """Export each finished run below ``root`` alone in both formats; the costs and a markdown table (per run,
    then the totals); :class:`~quasisim.errors.InputError` when ``root`` holds no finished run."""
    from quasisim.eval.dataset_export import export_dataset, finished_runs
    from quasisim.eval.lerobot_export import export_lerobot, require_lerobot
    from quasisim.files import size_mb

    runs = finished_runs(root)
    require_lerobot()
    rows = []
    with tempfile.TemporaryDirectory(prefix="qs-bench-export-") as tmp:
        for i, run in enumerate(runs):
            label = run.relative_to(root).as_posix() if run != root else run.name
            dirs = (*data_dirs, root)
            h5, lr = Path(tmp) / f"{i}.hdf5", Path(tmp) / f"lr{i}"
            t0 = time.perf_counter()
            res = export_dataset(run, h5, data_dirs=dirs, progress=False, closed_loop=closed_loop)
            t1 = time.perf_counter()
            export_lerobot(run, lr, data_dirs=dirs, closed_loop=closed_loop, size=image_size, progress=False)
            t2 = time.perf_counter()
            rows.append(ExportCost(label, res.total, t1 - t0, size_mb(h5), t2 - t1, size_mb(lr)))
    total = ExportCost(
        f"**all {len(rows)}**", sum(r.frames for r in rows), sum(r.robomimic_s for r in rows),
        sum(r.robomimic_mb for r in rows), sum(r.lerobot_s for r in rows), sum(r.lerobot_mb for r in rows),
    )  # fmt: skip
    return rows, "\n".join([HEAD, *(r.row() for r in [*rows, total])])
