"""Machine-independent cost of the sampling stage in finished `bench transfer` folders: physics steps
simulated (candidates, perturbed copies and applied frames) and back-ups per clip, read from each clip's
`.work/<clip>/runs/<run>/checkpoints/sample.npz` (the `.work` folders are not committed: run it where the
batch ran).

    python scripts/sampling_cost.py RUN_NAME NAME=FOLDER [NAME=FOLDER ...]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np


def costs(folder: Path, run: str) -> dict[str, tuple[int, int]]:
    """clip -> (physics steps, back-ups) of ``run`` in ``folder``."""
    out = {}
    for f in sorted(folder.glob(f".work/*/runs/{run}/checkpoints/sample.npz")):
        with np.load(f) as d:
            out[f.parents[3].name] = (int(d["n_physics_steps"]), int(d["backups"]))
    return out


def main(argv: list[str]) -> None:
    if len(argv) < 2 or any("=" not in a for a in argv[1:]):
        raise SystemExit(__doc__)
    run, folders = argv[0], dict(a.split("=", 1) for a in argv[1:])
    found = {name: costs(Path(p), run) for name, p in folders.items()}
    clips = sorted(set.intersection(*(set(c) for c in found.values())))
    if not clips:
        raise SystemExit(f"no clip has {run}'s sample.npz in every folder: {folders}")
    first = next(iter(found))
    print(f"{len(clips)} clips held by every folder; physics steps in millions per clip (mean), back-ups per clip")
    print("| folder | physics steps (M) | x " + first + " | back-ups |\n|---|---|---|---|")
    base = np.mean([found[first][c][0] for c in clips])
    for name, c in found.items():
        steps = np.mean([c[k][0] for k in clips])
        print(f"| {name} | {steps / 1e6:.2f} | {steps / base:.2f} | {np.mean([c[k][1] for k in clips]):.1f} |")


if __name__ == "__main__":
    main(sys.argv[1:])
