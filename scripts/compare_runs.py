"""Compare two transfer output folders array by array: controls, metrics and checkpoints.

Used to show that a change of the code left results untouched (bit-identical) or to say where they differ.
Run: python scripts/compare_runs.py OUT_A OUT_B   (exit code 0: identical, 1: different)
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

SKIP = {"wall_s"}  # wall-clock times differ between runs by nature


def compare_npz(a: Path, b: Path) -> list[str]:
    """The keys of two ``.npz`` files whose arrays differ (or exist in one only), with the largest difference."""
    out = []
    with np.load(a, allow_pickle=False) as za, np.load(b, allow_pickle=False) as zb:
        for k in sorted(set(za.files) | set(zb.files)):
            if k in SKIP:
                continue
            if k not in za.files or k not in zb.files:
                out.append(f"{a.name}:{k} only in {'B' if k not in za.files else 'A'}")
            elif not np.array_equal(za[k], zb[k]):
                x, y = za[k], zb[k]
                d = (
                    np.abs(x.astype(float) - y.astype(float)).max()
                    if x.dtype.kind in "fi" and x.shape == y.shape
                    else "?"
                )
                out.append(f"{a.name}:{k} differs (max |diff| {d})")
    return out


def main(a: Path, b: Path) -> int:
    diffs: list[str] = []
    files = sorted(p.relative_to(a) for p in a.rglob("*.npz"))
    for rel in files:
        if not (b / rel).is_file():
            diffs.append(f"{rel} only in A")
        else:
            diffs += compare_npz(a / rel, b / rel)
    if json.loads((a / "metrics.json").read_text()) != json.loads((b / "metrics.json").read_text()):
        diffs.append("metrics.json differs")
    print(f"compared {len(files)} npz files and metrics.json")
    print("\n".join(diffs) if diffs else "identical (bit for bit, wall times aside)")
    return 1 if diffs else 0


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1]), Path(sys.argv[2])))
