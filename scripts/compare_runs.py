"""Compare two transfer output folders array by array: controls, metrics and checkpoints.

Used to show that a change of the code left results untouched (bit-identical) or to say where they differ.
Run: python scripts/compare_runs.py OUT_A OUT_B   (exit code 0: identical, 1: different)
"""

from __future__ import annotations

import sys
from pathlib import Path

from quasisim.method.compare import compare_runs


def main(a: Path, b: Path) -> int:
    n, diffs = compare_runs(a, b)
    print(f"compared {n} npz files and metrics.json")
    print("\n".join(diffs) if diffs else "identical (bit for bit, wall times aside)")
    return 1 if diffs else 0


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1]), Path(sys.argv[2])))
