"""Shared pieces of the benchmarks: the header (date, machine, command), clip lists, markdown tables, output."""

from __future__ import annotations

import datetime as _dt
import os
import platform
import shlex
import sys
from pathlib import Path
from typing import Any

import numpy as np

from quasisim.errors import QuasisimError
from quasisim.eval.metrics import SUCCESS_KEYS
from quasisim.eval.robust import CLOSED_LOOP_SUFFIX
from quasisim.files import save_json_atomic, save_text_atomic


def machine_line() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{platform.system()} {platform.machine()}, {cpu}, {os.cpu_count()} logical CPUs, Python {platform.python_version()}"


def header(title: str) -> str:
    now = _dt.datetime.now().strftime("%Y-%m-%d %H:%M")
    cmd = (  # quoted as a shell would need it, so that the line can be pasted back
        "quasisim " + shlex.join(sys.argv[1:])
        if sys.argv and "quasisim" in Path(sys.argv[0]).name
        else shlex.join(sys.argv)
    )
    return f"### {title}\n\n- date: {now}\n- machine: {machine_line()}\n- command: `{cmd}`\n"


def clips(data_dir: Path, pattern: str, names: tuple[str, ...] = ()) -> list[Path]:
    """The clips ``names`` of ``data_dir`` or, without names, every clip matching ``pattern`` (``*_long``
    clips only when the pattern asks for them); an error names clips that are missing."""
    if names:
        paths = [data_dir / f"{c}.npz" for c in names]
        missing = [str(p) for p in paths if not p.is_file()]
        if missing:
            raise QuasisimError(f"clips not found: {', '.join(missing)}")
        return paths
    if not pattern.strip() or Path(pattern).is_absolute():
        raise QuasisimError(f"--pattern expects a file pattern inside the data folder (e.g. *.npz), got {pattern!r}")
    paths = sorted(data_dir.glob(pattern))
    if "_long" not in pattern:
        paths = [p for p in paths if not p.stem.endswith("_long")]
    return paths


ROBUST_KEYS = ("strict", "20deg_20cm")  # the robust-success columns (fractions of perturbed replays)


def robust_cells(rs: list[dict[str, Any]], key: str = "robust") -> str:
    """``robust strict | robust 20`` (%): the mean over ``rs`` of the fraction of perturbed replays that pass
    (metrics ``key``, :mod:`quasisim.eval.robust`), as ``open / closed`` where every row also has the closed-loop
    replays (``key + "_closed_loop"``); ``-`` where a row has none (runs made before it)."""
    if not rs or any(not r.get(key) for r in rs):
        return " | ".join("-" for _ in ROBUST_KEYS)
    closed = key + CLOSED_LOOP_SUFFIX
    has_closed = all(r.get(closed) for r in rs)

    def cell(k: str) -> str:
        text = f"{100.0 * np.mean([r[key][k] for r in rs]):.0f}"
        return text + (f" / {100.0 * np.mean([r[closed][k] for r in rs]):.0f}" if has_closed else "")

    return " | ".join(cell(k) for k in ROBUST_KEYS)


def summary_rows(rows: list[dict[str, Any]], group: str) -> list[str]:
    out = []
    for g in sorted({r[group] for r in rows}):
        rs = [r for r in rows if r[group] == g]
        m = {k: np.mean([r[k] for r in rs]) for k in ("R_err_deg", "T_err_cm", "MPJPE_mm", "CD_mm")}
        s = {k: 100.0 * np.mean([r["success"][k] for r in rs]) for k in SUCCESS_KEYS}
        out.append(
            f"| {g} | {len(rs)} | {m['R_err_deg']:.1f} | {m['T_err_cm']:.2f} | {m['MPJPE_mm']:.1f} | {m['CD_mm']:.1f} | "
            + " | ".join(f"{s[k]:.0f}" for k in SUCCESS_KEYS)
            + f" | {robust_cells(rs)} | {np.mean([r['wall_s'] for r in rs]):.2f} |"
        )
    return out


SUMMARY_HEAD = (
    "| {g} | clips | R_err (deg) | T_err (cm) | MPJPE (mm) | CD (mm) | succ 10 (%) | succ 15 (%) | succ 20 (%) | strict (%) "
    "| robust strict (%) | robust 20 (%) | wall s/clip |\n"
    "|---|---|---|---|---|---|---|---|---|---|---|---|---|"
)
CLIP_HEAD = (
    "| clip | {g} | R_err | T_err | MPJPE | CD | 10 | 15 | 20 | strict | robust strict | robust 20 | lifted | wall s |\n"
    "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
)


def clip_row(r: dict[str, Any], group: str) -> str:
    s = r["success"]
    yn = lambda b: "y" if b else "-"  # noqa: E731
    return (
        f"| {r['clip']} | {r[group]} | {r['R_err_deg']:.1f} | {r['T_err_cm']:.2f} | {r['MPJPE_mm']:.1f} | {r['CD_mm']:.1f} | "
        + " | ".join(yn(s[k]) for k in SUCCESS_KEYS)
        + f" | {robust_cells([r])} | {yn(r['lifted'])} | {r['wall_s']:.2f} |"
    )


def publish(out: Path, name: str, rows: list[dict[str, Any]], lines: list[str]) -> str:
    """Write ``out/name.json`` (rows) and ``out/name.md`` (the markdown), print the markdown."""
    text = "\n".join(lines) + "\n"
    out.mkdir(parents=True, exist_ok=True)
    save_json_atomic(out / f"{name}.json", rows)
    save_text_atomic(out / f"{name}.md", text)
    print(text)
    return text
