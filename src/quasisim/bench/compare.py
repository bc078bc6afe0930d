"""``quasisim bench compare``: one run of several finished ``bench transfer`` folders side by side.

A change of settings (e.g. ``--set stage2.mode=...``) goes to its own folder (a folder holds one set of
settings); this command reads the folders' results back (each clip's ``clip.json`` and the run's
``summary.json``; nothing is run or checked against the current settings) and tabulates the clips they
share: per clip R_err / T_err / strict success and stage 2's loss in its stiffest simulator (where the run's
``summary.json`` is there: a folder kept in git holds only ``clip.json``), a summary with each folder
against the first, and where each folder's time went: mean / median seconds per clip of the retarget and of
each stage (``clip.json``'s ``seconds``; stages read back from checkpoints keep the time they took). With ``--kinematic`` each folder's kinematic replay (judged beside the run, in the same
target with the same hand) joins the table, e.g. one hand per folder: every hand's replay and ours.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from quasisim.batch import CLIP_FILE, method_seconds, seconds_keys
from quasisim.bench.transfer import loss_cell, stiffest_simulator
from quasisim.errors import QuasisimError
from quasisim.eval.metrics import SUCCESS_KEYS
from quasisim.eval.tables import header, publish, robust_cells


def folder_rows(folder: Path, run: str) -> tuple[dict[str, dict[str, Any]], dict[str, dict[str, Any]]]:
    """A folder's ``run``, read once: {clip: metrics (+ stage 2's stiffest loss where the run has stage 2)}
    and {clip: metrics of the kinematic replay judged beside it} (the clips that have one)."""
    rows, kin = {}, {}
    for p in sorted(folder.glob(f"*/{CLIP_FILE}")):
        runs = json.loads(p.read_text())["runs"]
        if run not in runs:
            continue
        clip, row = p.parent.name, runs[run]["row"]
        wall = {"wall_s": method_seconds(row["seconds"]), "seconds": row["seconds"]} if "seconds" in row else {}
        rows[clip] = {**row["metrics"], **wall, **stiffest_simulator(p.parent / run / "summary.json")}
        if "kinematic_metrics" in row:
            kin[clip] = row["kinematic_metrics"]
    return rows, kin


def compare_folders(folders: list[tuple[str, Path]], runs: list[str], out: Path, kinematic: bool = False) -> str:
    """Markdown of run ``runs[i]`` of each ``(label, folder)`` (one run name for all folders, or one per folder)
    on the clips every folder holds (written to ``out``); with ``kinematic``, each folder's kinematic replay
    (its hand, its target) beside it as ``LABEL kinematic``."""
    if len(runs) not in (1, len(folders)):
        raise QuasisimError(
            f"bench compare: --run names {len(runs)} runs for {len(folders)} folders (expected 1 or {len(folders)})"
        )
    runs = runs * len(folders) if len(runs) == 1 else runs
    per: dict[str, dict[str, dict[str, Any]]] = {}
    for (label, f), run in zip(folders, runs, strict=True):
        per[label], kin = folder_rows(f, run)
        if kinematic:
            per[f"{label} kinematic"] = kin
    empty = [label for label, rows in per.items() if not rows]
    if empty:
        where = ", ".join(f"{label} ({f}, run {r!r})" for (label, f), r in zip(folders, runs, strict=True))
        raise QuasisimError(
            f"no finished run (or no kinematic replay beside it) for: {', '.join(empty)}; folders: {where} "
            "(folders of `quasisim bench transfer`)"
        )
    run = " / ".join(dict.fromkeys(runs))
    shared = sorted(set.intersection(*(set(r) for r in per.values())))
    labels = list(per)
    with_loss = any("stiffest_loss" in r for rows in per.values() for r in rows.values())
    lines = [
        header(f"{run}: {' vs '.join(label for label, _ in folders)}, {len(shared)} clips held by every folder"),
        *_summary(per, labels, shared, with_loss),
        "",
        *_stage_seconds(per, labels, shared),
        "",
        "Per clip: R_err (deg) / T_err (cm), `S` strict success"
        + ("; stage 2's best loss in its stiffest simulator." if with_loss else "."),
        "",
    ]
    loss_labels = labels if with_loss else []
    lines += ["| clip | " + " | ".join(labels + [f"stiffest loss {x}" for x in loss_labels]) + " |"]
    lines += ["|---" * (1 + len(labels) + len(loss_labels)) + "|"]
    for c in shared:
        cells = [_cell(per[x][c]) for x in labels]
        losses = [loss_cell(per[x][c]["stiffest_loss"]) if "stiffest_loss" in per[x][c] else "-" for x in loss_labels]
        lines.append(f"| {c} | " + " | ".join(cells + losses) + " |")
    rows = [
        {"clip": c, "folder": x, **{k: v for k, v in per[x][c].items() if k != "seconds"}}
        for c in shared
        for x in labels
    ]
    return publish(out, "compare", rows, lines)


def _cell(m: dict[str, Any]) -> str:
    return f"{m['R_err_deg']:.1f} / {m['T_err_cm']:.2f}" + (" S" if m["success"]["strict"] else "")


def _mean(rs: list[dict[str, Any]], key: str, fmt: str) -> str:
    """Mean of ``key`` over ``rs`` formatted, or ``-`` where a row lacks it."""
    return format(float(np.mean([r[key] for r in rs])), fmt) if all(key in r for r in rs) else "-"


def _summary(
    per: dict[str, dict[str, dict[str, Any]]], labels: list[str], clips: list[str], with_loss: bool
) -> list[str]:
    loss_head = " stiffest loss (mean / median) |" if with_loss else ""
    out = [
        "| folder | R_err (deg) | T_err (cm) | MPJPE (mm) | succ 10 / 15 / 20 / strict (%) | robust strict / 20 (%) |"
        f" lifted |{loss_head} lower R_err and T_err than {labels[0]} | wall s per clip |",
        "|---" * (9 + with_loss) + "|",
    ]
    base = per[labels[0]]
    for x in labels:
        rs = [per[x][c] for c in clips]
        succ = " / ".join(f"{100.0 * np.mean([r['success'][k] for r in rs]):.0f}" for k in SUCCESS_KEYS)
        moved = [r.get("object_motion", {}).get("lift_ok") for r in rs]
        lifted = "-" if None in moved else f"{sum(moved)} of {len(rs)}"
        losses = [r["stiffest_loss"] for r in rs if r.get("stiffest_loss") is not None]
        loss = f"{np.mean(losses):.4f} / {np.median(losses):.4f}" if len(losses) == len(rs) else "-"  # all or none
        better = sum(
            per[x][c]["R_err_deg"] < base[c]["R_err_deg"] and per[x][c]["T_err_cm"] < base[c]["T_err_cm"] for c in clips
        )
        vs = "-" if x == labels[0] else f"{better} of {len(clips)}"
        out.append(
            f"| {x} | {_mean(rs, 'R_err_deg', '.1f')} | {_mean(rs, 'T_err_cm', '.2f')} | {_mean(rs, 'MPJPE_mm', '.1f')} | "
            f"{succ} | {robust_cells(rs).replace(' | ', ' / ')} | {lifted} |"
            + (f" {loss} |" if with_loss else "")
            + f" {vs} | {_mean(rs, 'wall_s', '.0f')} |"
        )
    return out


def _stage_seconds(per: dict[str, dict[str, dict[str, Any]]], labels: list[str], clips: list[str]) -> list[str]:
    """Mean / median seconds per clip of the retarget, each stage a folder's runs have, and their sum."""
    words = [w for w in seconds_keys() if any(w in per[x][c].get("seconds", {}) for x in labels for c in clips)]
    out = [
        "Seconds per clip, mean / median (`-`: a folder without the stage, or without times):",
        "",
        "| folder | " + " | ".join([*words, "total"]) + " |",
        "|---" * (2 + len(words)) + "|",
    ]
    for x in labels:
        secs = [per[x][c].get("seconds") for c in clips]
        if None in secs:
            out.append(f"| {x} | " + " | ".join(["-"] * (1 + len(words))) + " |")
            continue
        cols = [[s.get(w) for s in secs] for w in words] + [[per[x][c]["wall_s"] for c in clips]]
        cells = ["-" if None in v else f"{np.mean(v):.0f} / {np.median(v):.0f}" for v in cols]
        out.append(f"| {x} | " + " | ".join(cells) + " |")
    return out
