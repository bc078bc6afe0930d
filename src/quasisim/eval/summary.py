"""The few lines a person reads at the end of ``evaluate`` / ``transfer``: strict success first, then the
paper's thresholds, whether the object was lifted, the mean errors, and where the report is."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from quasisim.eval.metrics import MOVE_FRACTION, MOVE_MIN_CM, PAPER_KEYS, STRICT_CM, STRICT_DEG

CRITERIA = ("strict", *PAPER_KEYS)
HEADERS = ("strict", "10deg/10cm", "15deg/15cm", "20deg/20cm")


def yes_no(flag: bool) -> str:
    return "yes" if flag else "no"


def lifted_text(motion: dict[str, Any]) -> str:
    """``yes (10.4 of 12.0 cm)``, ``no (0.1 of 12.0 cm)`` or ``not required (...)`` when the demo does not lift."""
    lift, demo = motion["lift_cm"], motion["demo_lift_cm"]
    if demo < MOVE_MIN_CM:
        return f"not required (demo {demo:.1f} cm)"
    return f"{yes_no(motion['lift_ok'])} ({lift:.1f} of {demo:.1f} cm)"


def _row(name: str, m: dict[str, Any], width: int) -> str:
    flags = "".join(f"{yes_no(m['success'][k]):<12}" for k in CRITERIA)
    errs = f"{m['R_err_deg']:5.1f} deg {m['T_err_cm']:6.2f} cm {m['MPJPE_mm']:5.1f} mm"
    return f"  {name:<{width}}{flags}{lifted_text(m['object_motion']):<26}{errs}"


def legend() -> list[str]:
    return [
        f"strict: the object within {STRICT_CM:g} cm and {STRICT_DEG:g} deg of the demo at every frame; "
        "10deg/10cm ..: the paper's thresholds on mean errors (R_err <= X deg, T_err <= X cm, MPJPE <= X cm).",
        f"Every criterion also needs the object moved as in the demo (lifted at least {MOVE_FRACTION:.0%} as "
        "high, displaced like it); docs/metrics.md.",
    ]


def _motion_note(name: str, m: dict[str, Any]) -> list[str]:
    mo = m["object_motion"]
    if mo["as_demo"]:
        return []
    why = (
        f"rose {mo['lift_cm']:.1f} cm where the demo's rose {mo['demo_lift_cm']:.1f} cm"
        if not mo["lift_ok"]
        else f"was {mo['displacement_error_cm']:.1f} cm off the demo's displacement of "
        f"{mo['demo_displacement_cm']:.1f} cm"
    )
    return [f"{name}: the object {why}: not moved as in the demo, so no success at any threshold."]


def robust_lines(name: str, m: dict[str, Any]) -> list[str]:
    """One line per perturbation set of ``m`` (metrics): robust success open loop, and closed loop where run."""
    from quasisim.eval.robust import CLOSED_LOOP_SUFFIX, ROBUST_SETS

    lines = []
    for key in ROBUST_SETS:
        r, c = m.get(key), m.get(key + CLOSED_LOOP_SUFFIX)
        if not r:
            continue
        line = (f"{name}: {key.replace('_', ' ')} success ({r['n']} perturbed targets) open loop strict "
                f"{r['strict']:.0%}, 20deg/20cm {r['20deg_20cm']:.0%}")  # fmt: skip
        if c:
            line += (f"; closed loop strict {c['strict']:.0%}, 20deg/20cm {c['20deg_20cm']:.0%} "
                     f"({c['seconds_per_replay']:.1f} s per replay)")  # fmt: skip
        lines.append(line)
    return lines


def summary_lines(title: str, runs: dict[str, dict[str, Any]], report: Path | None = None) -> list[str]:
    """Lines for the terminal: one row per named run's metrics (``metrics.json`` dictionaries)."""
    width = max(len(n) for n in runs) + 2
    head = "".join(f"{h:<12}" for h in HEADERS) + f"{'lifted':<26}mean R_err, T_err, MPJPE"
    lines = [title, f"  {'':<{width}}{head}"]
    lines += [_row(n, m, width) for n, m in runs.items()]
    for n, m in runs.items():
        lines += _motion_note(n, m)
        lines += robust_lines(n, m)
    lines += legend()
    if report is not None:
        lines.append(f"report: {report} (open it in a browser; see README for a headless server)")
    return lines
