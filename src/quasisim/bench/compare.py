"""``quasisim bench compare``: one run of several finished ``bench transfer`` folders side by side.

A change of settings (e.g. ``--set stage2.mode=...``) goes to its own folder (a folder holds one set of
settings); this command reads the folders' results back (each clip's ``clip.json`` and the run's
``summary.json``; nothing is run or checked against the current settings) and tabulates the clips they
share: per clip R_err / T_err / strict success and stage 2's loss in its stiffest simulator (where the run's
``summary.json`` is there: a folder kept in git holds only ``clip.json``), then a summary with each folder
against the first.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from quasisim.batch import CLIP_FILE
from quasisim.bench.tables import header, publish
from quasisim.bench.transfer import stiffest_simulator
from quasisim.errors import QuasisimError
from quasisim.eval.metrics import SUCCESS_KEYS


def folder_rows(folder: Path, run: str) -> dict[str, dict[str, Any]]:
    """{clip: metrics of ``run`` (+ stage 2's stiffest loss where the run has stage 2)} of a folder."""
    rows = {}
    for p in sorted(folder.glob(f"*/{CLIP_FILE}")):
        runs = json.loads(p.read_text())["runs"]
        if run in runs:
            rows[p.parent.name] = {**runs[run]["row"]["metrics"], **stiffest_simulator(p.parent / run / "summary.json")}
    return rows


def compare_folders(folders: list[tuple[str, Path]], run: str, out: Path) -> str:
    """Markdown of ``run`` in each ``(label, folder)`` on the clips every folder holds (written to ``out``)."""
    per = {label: folder_rows(f, run) for label, f in folders}
    empty = [f"{label} ({f})" for label, f in folders if not per[label]]
    if empty:
        raise QuasisimError(f"no finished run {run!r} in: {', '.join(empty)} (folders of `quasisim bench transfer`)")
    shared = sorted(set.intersection(*(set(r) for r in per.values())))
    labels = [label for label, _ in folders]
    lines = [
        header(f"{run}: {' vs '.join(labels)}, {len(shared)} clips held by every folder"),
        *_summary(per, labels, shared),
    ]
    lines += [
        "",
        "Per clip: R_err (deg) / T_err (cm), `S` strict success; stage 2's best loss in its stiffest simulator.",
        "",
    ]
    lines += ["| clip | " + " | ".join(labels) + " | " + " | ".join(f"stiffest loss {x}" for x in labels) + " |"]
    lines += ["|---" * (1 + 2 * len(labels)) + "|"]
    for c in shared:
        cells = [_cell(per[x][c]) for x in labels]
        losses = [f"{per[x][c]['stiffest_loss']:.4f}" if "stiffest_loss" in per[x][c] else "-" for x in labels]
        lines.append(f"| {c} | " + " | ".join(cells + losses) + " |")
    rows = [{"clip": c, "folder": x, **per[x][c]} for c in shared for x in labels]
    return publish(out, "compare", rows, lines)


def _cell(m: dict[str, Any]) -> str:
    return f"{m['R_err_deg']:.1f} / {m['T_err_cm']:.2f}" + (" S" if m["success"]["strict"] else "")


def _summary(per: dict[str, dict[str, dict[str, Any]]], labels: list[str], clips: list[str]) -> list[str]:
    out = [
        "| folder | R_err (deg) | T_err (cm) | succ 10 / 15 / 20 / strict (%) | stiffest loss (mean / median) | "
        f"lower R_err and T_err than {labels[0]} |",
        "|---|---|---|---|---|---|",
    ]
    base = per[labels[0]]
    for x in labels:
        rs = [per[x][c] for c in clips]
        succ = " / ".join(f"{100.0 * np.mean([r['success'][k] for r in rs]):.0f}" for k in SUCCESS_KEYS)
        losses = [r["stiffest_loss"] for r in rs if "stiffest_loss" in r]
        loss = f"{np.mean(losses):.4f} / {np.median(losses):.4f}" if len(losses) == len(rs) else "-"  # all or none
        better = sum(
            per[x][c]["R_err_deg"] < base[c]["R_err_deg"] and per[x][c]["T_err_cm"] < base[c]["T_err_cm"] for c in clips
        )
        vs = "-" if x == labels[0] else f"{better} of {len(clips)}"
        out.append(
            f"| {x} | {np.mean([r['R_err_deg'] for r in rs]):.1f} | {np.mean([r['T_err_cm'] for r in rs]):.2f} | "
            f"{succ} | {loss} | {vs} |"
        )
    return out
