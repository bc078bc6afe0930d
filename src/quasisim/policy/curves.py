"""Learning curves of training folders (``logs/*/progress.csv`` of :mod:`quasisim.policy.train`) as a figure."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from quasisim.errors import QuasisimError
from quasisim.policy.train import TrainSetup

CURVES = (("rollout/tracked", "episodes tracked: strict success\n(randomised worlds)"),
          ("rollout/frames", "frames reached per episode"),
          ("rollout/ep_rew_mean", "episode return"))  # fmt: skip


def read_curves(folder: Path) -> dict[str, np.ndarray]:
    """``{"steps": (N,), key: (N,) ...}`` from every log segment of training folder ``folder`` in order
    (a key missing from a row is NaN)."""
    rows: list[dict[str, str]] = []
    for seg in sorted((folder / "logs").glob("*/progress.csv")):
        with open(seg, newline="") as f:
            rows += list(csv.DictReader(f))
    if not rows:
        raise QuasisimError(f"{folder}: no training logs (logs/*/progress.csv); train first")

    def col(k: str) -> np.ndarray:
        return np.array([float(r[k]) if r.get(k) not in (None, "") else np.nan for r in rows])

    return {"steps": col("time/total_timesteps"), **{k: col(k) for k, _ in CURVES}}


def plot_curves(folders: list[Path], out: Path) -> Path:
    """One panel per curve of :data:`CURVES`, one line per training folder (labelled clip and method)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from quasisim.files import atomic_path

    fig, axes = plt.subplots(1, len(CURVES), figsize=(5 * len(CURVES), 3.6))
    for folder in folders:
        setup, c = TrainSetup.read(folder), read_curves(folder)
        label = f"{Path(setup.clip).stem}: {setup.method}"
        for ax, (k, _) in zip(axes, CURVES, strict=True):
            ax.plot(c["steps"], c[k], label=label, lw=1.2)
    for ax, (_, title) in zip(axes, CURVES, strict=True):
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("env steps")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=6)
    fig.tight_layout()
    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=110, format=out.suffix.lstrip(".") or "png")
    plt.close(fig)
    return out
