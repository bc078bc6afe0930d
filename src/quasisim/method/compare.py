"""Compare two run folders array by array (controls, rollout, checkpoints) and metrics.json.

Used to show that a change of the code, or a kill and ``--resume``, left results untouched (bit-identical),
or to say where they differ (``scripts/compare_runs.py`` is the command-line front end).
"""

from __future__ import annotations

import json
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


def compare_runs(a: Path, b: Path) -> tuple[int, list[str]]:
    """(number of npz files compared, differences) between run folders ``a`` and ``b``: every ``.npz`` below
    either (hidden temporary files aside) and ``metrics.json``."""
    diffs: list[str] = []
    rel_a = {p.relative_to(a) for p in a.rglob("*.npz") if not p.name.startswith(".")}
    rel_b = {p.relative_to(b) for p in b.rglob("*.npz") if not p.name.startswith(".")}
    diffs += [f"{rel} only in {'A' if rel in rel_a else 'B'}" for rel in sorted(rel_a ^ rel_b)]
    for rel in sorted(rel_a & rel_b):
        diffs += compare_npz(a / rel, b / rel)
    if json.loads((a / "metrics.json").read_text()) != json.loads((b / "metrics.json").read_text()):
        diffs.append("metrics.json differs")
    return len(rel_a), diffs
