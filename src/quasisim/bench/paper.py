"""``quasisim bench paper``: the paper's two tables (its comparison with baselines and its ablations), every
row measured on our clips where quasisim has it, beside the paper's own figures.

Each row of the paper (:data:`ROWS`) is one of:

* a transfer run (``run``): a named method of :data:`quasisim.method.registry.METHODS` (``mpc-base``,
  ``paper``, ``paper-no-residual`` ...), run on every clip by :func:`quasisim.bench.transfer.run_transfer_bench`
  into ``OUT`` (one Ray batch, resumable; the ablations reuse the stage 1/2 checkpoints of ``paper``);
* a learned policy (``policy``): read from a folder of ``quasisim bench policy`` (``--policy``:
  ``POLICY/<clip>/<method>/eval/metrics.json``, the best validated model), trained there;

The paper's figures were measured in Bullet and Isaac Gym on its own clips (GRAB, TACO, ARCTIC sequences with
the Shadow hand); ours in MuJoCo on the clips given. They orient, they do not compare: the table says so.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from quasisim.errors import QuasisimError
from quasisim.eval.metrics import PAPER_KEYS, SUCCESS_KEYS
from quasisim.eval.robust import CLOSED_LOOP_SUFFIX, ROBUST_KEY
from quasisim.eval.tables import header, publish

# R_err (deg), T_err (cm), MPJPE (mm), CD (mm), success 10 / 15 / 20 (%): the paper's tables, as printed
Figures = tuple[float, float, float, float, float, float, float]


@dataclass(frozen=True)
class PaperRow:
    """One row of the paper's tables.

    Attributes:
        table: ``main`` (the comparison with baselines) or ``ablation``.
        label: the paper's name of the row.
        run: our transfer run that stands for it (a named method), or None.
        policy: our policy method that stands for it (``quasisim bench policy``), or None.
        bullet: the paper's figures in Bullet.  isaac: in Isaac Gym (the main table only).
    """

    table: str
    label: str
    run: str | None
    policy: str | None
    bullet: Figures
    isaac: Figures | None = None


OURS_BULLET: Figures = (24.21, 1.97, 24.40, 9.85, 27.45, 37.25, 58.82)  # the paper's method, in both tables

ROWS: tuple[PaperRow, ...] = (
    PaperRow("main", "DGrasp-Base", None, "dgrasp-base", (44.24, 5.82, 40.55, 16.37, 0, 13.73, 15.69),
             (36.41, 4.56, 50.97, 18.78, 0, 7.84, 7.84)),
    PaperRow("main", "DGrasp-Tracking", None, "dgrasp-tracking", (44.45, 5.04, 37.56, 14.72, 0, 15.69, 15.69),
             (44.71, 5.57, 41.53, 16.72, 0, 0, 7.84)),
    PaperRow("main", "DGrasp-Tracking (w/ curric.)", None, "dgrasp-tracking-curriculum", (33.86, 4.60, 30.47, 13.53, 7.84, 23.53, 37.25),
             (38.75, 5.13, 40.09, 16.26, 0, 23.53, 31.37)),
    PaperRow("main", "Control-VAE", "control-vae", None, (42.45, 2.73, 25.21, 10.94, 0, 15.68, 23.53),
             (35.40, 4.61, 27.63, 13.17, 0, 13.73, 29.41)),
    PaperRow("main", "MPC (w/ base sim.)", "mpc-base", None, (32.56, 3.67, 24.62, 10.80, 0, 15.68, 31.37),
             (37.23, 4.73, 23.19, 9.75, 0, 15.69, 31.37)),
    PaperRow("main", "MPC (w/ base sim. w/ soften)", "mpc-soften", None, (31.89, 3.63, 28.26, 11.31, 0, 21.57, 37.25),
             (36.40, 4.46, 23.27, 10.34, 0, 9.80, 23.53)),
    PaperRow("main", "Ours", "paper", None, OURS_BULLET, (25.97, 2.08, 25.33, 10.31, 21.57, 43.14, 56.86)),
    PaperRow("ablation", "Ours w/o Analytical Sim.", "paper-no-analytical", None, (44.27, 4.39, 29.84, 12.91, 0, 13.73, 25.49)),
    PaperRow("ablation", "Ours w/o Residual Physics", "paper-no-residual", None,
             (33.69, 3.81, 26.57, 10.34, 5.88, 23.53, 41.18)),
    PaperRow("ablation", "Ours w/o Local Force NN", "paper-no-local-force", None,
             (35.98, 2.90, 32.87, 12.44, 0, 19.61, 35.29)),
    PaperRow("ablation", "Ours w/o Curriculum", "paper-no-curriculum", None, (42.40, 4.87, 32.61, 13.37, 0, 17.64, 29.41)),
    PaperRow("ablation", "Ours w/ Curriculum II", "paper-curriculum2", None,
             (29.58, 2.33, 31.61, 10.29, 11.76, 27.45, 50.98)),
    PaperRow("ablation", "Ours", "paper", None, OURS_BULLET),
)  # fmt: skip

DEFAULT_RUN = "cascade"  # quasisim's default method: a row of ours beside the paper's in the main table
TABLES = ("main", "ablation")


def runs_of(tables: tuple[str, ...]) -> tuple[str, ...]:
    """The transfer runs the tables need, in the order they run (``paper`` first: the ablations start from its
    stage 1/2 checkpoints where the curriculum is the same), with quasisim's default in the main table."""
    runs = [r.run for r in ROWS if r.table in tables and r.run]
    runs += [DEFAULT_RUN] if "main" in tables else []
    return tuple(dict.fromkeys(sorted(runs, key=lambda r: r != "paper")))


def policy_metrics(folder: Path, method: str, clips: list[str]) -> dict[str, dict[str, Any]]:
    """{clip: metrics} of ``method``'s best validated policy in a ``quasisim bench policy`` folder, for the
    clips it has."""
    out = {}
    for c in clips:
        p = folder / c / method / "eval" / "metrics.json"
        if p.is_file():
            out[c] = json.loads(p.read_text())
    return out


def measured(rows: dict[str, dict[str, Any]], clips: list[str]) -> dict[str, Any] | None:
    """The paper's columns (means over the clips; success in %) and ours (strict %, robust strict % open /
    closed loop) of one row's per-clip metrics ``rows``; None where it has no clip."""
    ms = [rows[c] for c in clips if c in rows]
    if not ms:
        return None
    mean = lambda k: float(np.mean([m[k] for m in ms]))  # noqa: E731
    pct = lambda f: 100.0 * float(np.mean([f(m) for m in ms]))  # noqa: E731

    def robust(key: str) -> float | None:
        return pct(lambda m: m[key]["strict"]) if all(m.get(key) for m in ms) else None

    return {
        "clips": len(ms), "R_err_deg": mean("R_err_deg"), "T_err_cm": mean("T_err_cm"), "MPJPE_mm": mean("MPJPE_mm"),
        "CD_mm": mean("CD_mm"), **{k: pct(lambda m, k=k: m["success"][k]) for k in SUCCESS_KEYS},
        "robust_open": robust(ROBUST_KEY), "robust_closed": robust(ROBUST_KEY + CLOSED_LOOP_SUFFIX),
    }  # fmt: skip


def _cells(m: dict[str, Any] | None, n: int) -> str:
    if m is None:
        return " | ".join(["-"] * 9)  # clips, 4 errors, success, strict, robust open / closed
    f = lambda v: "-" if v is None else f"{v:.0f}"  # noqa: E731
    clips = f"{m['clips']}" if m["clips"] == n else f"{m['clips']} of {n}"
    return (
        f"{clips} | {m['R_err_deg']:.1f} | {m['T_err_cm']:.2f} | {m['MPJPE_mm']:.1f} | {m['CD_mm']:.1f} | "
        + "/".join(f"{m[k]:.0f}" for k in PAPER_KEYS)
        + f" | {m['strict']:.0f} | {f(m['robust_open'])} | {f(m['robust_closed'])}"
    )


def _paper(f: Figures | None) -> str:
    if f is None:
        return "-"
    return f"{f[0]:.1f} / {f[1]:.2f} / {f[2]:.1f} / {f[3]:.1f} / " + "/".join(f"{v:.0f}" for v in f[4:])


def _source(row: PaperRow) -> str:
    return f"`{row.run}`" if row.run else f"policy `{row.policy}`"


def markdown(results: dict[str, dict[str, Any] | None], tables: tuple[str, ...], n: int) -> list[str]:
    """The two tables: per row ours (the mean over the clips) and the paper's figures; ``results`` maps a row's
    run or policy name (and :data:`DEFAULT_RUN`) to :func:`measured`'s summary."""
    head = (
        "| row (paper) | ours | clips | R_err (deg) | T_err (cm) | MPJPE (mm) | CD (mm) | succ 10/15/20 (%) "
        "| strict (%) | robust strict open (%) | robust strict closed (%) | paper, Bullet: R / T / MPJPE / CD / "
        "succ 10/15/20 |"
    )
    lines = [header("The paper's tables on our clips (MuJoCo, Shadow hand)"),
             f"Ours: means over {n} clips judged in MuJoCo. The paper's figures (its Bullet column; the main table's "
             "Isaac Gym column in the last cell) were measured on its own clips and simulators: they orient, they do "
             "not compare. Robust: the fraction of perturbed replays within the strict limits (configs/robust.yaml), "
             "open loop and, where measured, closed loop. A policy is closed loop by nature: its robust figure is "
             "in the closed column.", ""]  # fmt: skip
    for t in tables:
        title = "Comparison with baselines" if t == "main" else "Ablations (the paper's: Bullet)"
        cols = head + (" paper, Isaac Gym |" if t == "main" else "")
        lines += [f"#### {title}", "", cols, "|" + "---|" * (cols.count("|") - 1)]
        rows = [r for r in ROWS if r.table == t]
        for r in rows:
            key = r.run or r.policy
            cells = _cells(results.get(key) if key else None, n)
            isaac = f" {_paper(r.isaac)} |" if t == "main" else ""
            lines.append(f"| {r.label} | {_source(r)} | {cells} | {_paper(r.bullet)} |{isaac}")
        if t == "main":
            lines.append(f"| (quasisim's default) | `{DEFAULT_RUN}` | {_cells(results.get(DEFAULT_RUN), n)} | - | - |")
        lines.append("")
    return lines


def run_paper_bench(
    data_dir: Path, clip_names: tuple[str, ...], pattern: str, tables: tuple[str, ...], out: Path,
    policy: Path | None, report_only: bool, settings: Any, robust: int | None, budget: str = "fast",
    sources: tuple[Path, ...] = (),
) -> str:  # fmt: skip
    """Run the tables' transfer runs on the clips (resumable, :func:`run_transfer_bench`, whose per-clip
    tables land in ``out/transfer.md``), read the policy rows from ``policy``, and write ``out/paper.md``
    (and ``paper.json``: each row's summary); returns the markdown. ``sources``: other folders of ``quasisim
    bench transfer`` on these clips (with the same settings) whose finished runs stand where ``out`` has none of a
    clip's run (read only, nothing run or written there; the first folder that has it)."""
    from quasisim.bench.transfer import run_transfer_bench, transfer_rows
    from quasisim.eval.tables import clips as clip_paths

    bad = [t for t in tables if t not in TABLES]
    if bad or not tables:
        raise QuasisimError(f"unknown table {bad[0] if bad else '(none given)'!r}; valid tables: {', '.join(TABLES)}")
    names = [p.stem for p in clip_paths(data_dir, pattern, clip_names)]
    runs = runs_of(tables)
    run_transfer_bench(data_dir, clip_names, pattern, runs, ("1", "2"), budget, "mujoco", "shadow", out, report_only,
                       None, settings, robust)  # fmt: skip
    rows = json.loads((out / "transfer.json").read_text())
    for folder in sources:
        have = {(x["clip"], x["method"]) for x in rows}
        more = transfer_rows(data_dir, clip_names, pattern, runs, ("1", "2"), budget, "mujoco", "shadow", folder, True,
                             None, settings, robust)  # fmt: skip
        rows += [x for x in more if (x["clip"], x["method"]) not in have]
    results: dict[str, dict[str, Any] | None] = {
        r: measured({x["clip"]: x for x in rows if x["method"] == r}, names) for r in runs
    }
    for row in ROWS:
        if row.policy and row.table in tables:
            results[row.policy] = measured(policy_metrics(policy, row.policy, names), names) if policy else None
    text = "\n".join(markdown(results, tables, len(names)))
    publish(out, "paper", [{"row": k, **(v or {})} for k, v in results.items()], text.splitlines())
    return text
