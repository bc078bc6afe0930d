"""``quasisim bench long``: time and peak memory of the commands on clips of growing length.

Each command runs as its own process (``quasisim retarget``, ``quasisim evaluate`` of the kinematic retarget,
``quasisim transfer --method sample-target``) on the bundled example made with ``--frames N``; the wall time
and the process's peak resident memory (``wait4``'s ``ru_maxrss``) are measured beside the estimate that the
clip-length warning prints for clips longer than :data:`quasisim.data.demo.LONG_CLIP` frames. Each row is
kept in ``OUT/rows/`` as it finishes, so a cut run resumes where it stopped."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from quasisim.errors import QuasisimError
from quasisim.eval.tables import header
from quasisim.files import save_json_atomic, save_text_atomic

COMMANDS = ("retarget", "evaluate", "sample-target")


def _argv(command: str, clip: Path, folder: Path, render: bool) -> list[str]:
    """The quasisim command line of ``command`` on ``clip``, writing under ``folder``."""
    r = ["--render"] if render else ["--no-render"]
    if command == "retarget":
        return ["retarget", str(clip), "--out", str(folder / "retarget"), "--overwrite"]
    if command == "evaluate":
        kin = folder / "retarget" / "kinematic.npz"
        return ["evaluate", str(clip), str(kin), "--out", str(folder / "evaluate"), "--overwrite", *r]
    if command == "sample-target":
        return ["transfer", str(clip), "--method", "sample-target", "--out", str(folder / "sample-target"),
                "--overwrite", *r]  # fmt: skip
    raise QuasisimError(f"bench long: unknown command {command!r}; expected one of {', '.join(COMMANDS)}")


def measure(argv: list[str], log: Path) -> dict[str, Any]:
    """Run ``quasisim argv`` to the end: wall seconds, peak resident memory (GB) and exit code. Its output
    goes to ``log``."""
    cmd = [sys.executable, "-m", "quasisim.cli", *argv]
    t0 = time.perf_counter()
    with open(log, "w") as f:
        p = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, env={**os.environ, "PYTHONUNBUFFERED": "1"})
        _, status, usage = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    p.returncode = rc = os.waitstatus_to_exitcode(status)  # reaped here: Popen must not wait again
    return {"wall_s": wall, "peak_gb": usage.ru_maxrss / 1024**2, "rc": rc}


def estimate(command: str, frames: int, render: bool) -> tuple[float, float]:
    """(minutes, GB) the clip-length warning estimates for ``command`` on ``frames`` frames with the default
    settings (:func:`quasisim.data.demo.warn_long_clip`'s model, with each command's own per-frame costs)."""
    from quasisim.data.demo import BASE_MB, BASE_S
    from quasisim.eval.evaluate import judging_cost
    from quasisim.eval.robust import RobustConfig
    from quasisim.method.config import TransferConfig
    from quasisim.method.retarget import RETARGET_MB_PER_FRAME, RETARGET_S_PER_FRAME
    from quasisim.method.spec import TransferSpec
    from quasisim.method.stage import declared_stages
    from quasisim.pipeline import cost_per_frame

    if command == "retarget":
        s, mb = RETARGET_S_PER_FRAME, RETARGET_MB_PER_FRAME
    elif command == "evaluate":
        s, mb = judging_cost(render, RobustConfig.from_yaml())
    else:
        spec = TransferSpec(method="sample-target", render=render).checked()
        cfg = TransferConfig.from_yaml()
        s, mb = cost_per_frame(cfg.budget("fast"), cfg.budgets.get("fast"), declared_stages(spec.stages), spec)
    return (BASE_S + frames * s) / 60, (BASE_MB + frames * mb) / 1024


def _row(n: int, command: str, out: Path, render: bool, make_clip: Callable[[int], Path]) -> dict[str, Any]:
    path = out / "rows" / f"{n}-{command}{'' if render else '-no-render'}.json"
    if path.is_file():
        return json.loads(path.read_text())
    clip, folder = make_clip(n), out / str(n)
    print(f"bench long: {command} on {n} frames ...", file=sys.stderr, flush=True)
    row = {"frames": n, "command": command, "render": render,
           **measure(_argv(command, clip, folder, render), folder / f"{command}.log")}  # fmt: skip
    if row["rc"] != 0:
        raise QuasisimError(f"bench long: {command} on {n} frames ended with exit code {row['rc']}; see "
                            f"{folder / f'{command}.log'}")  # fmt: skip
    save_json_atomic(path, row)
    return row


def _example(out: Path, name: str) -> Callable[[int], Path]:
    def make(n: int) -> Path:
        from quasisim.data.synthetic import write_example

        folder = out / str(n)
        clip = folder / f"{name}.npz"
        return clip if clip.is_file() else Path(write_example(name, folder, n_frames=n))

    return make


def _other_rows(out: Path) -> list[dict[str, Any]]:
    return [json.loads(p.read_text()) for p in sorted((out / "rows").glob("*.json"))]


def table(rows: list[dict[str, Any]]) -> str:
    """Markdown: per command and length, wall time, peak memory, both per frame, and the warning's estimate
    (:func:`estimate`; printed for clips over 1,500 frames) with the measurement's ratio to it (1.0: exact;
    the warning aims within 2x)."""
    lines = [
        "| command | video | frames | wall (s) | ms / frame | peak memory (GB) | MB / frame | estimate: min, GB | "
        "measured / estimate (time, memory) |",
        "|---|---|---:|---:|---:|---:|---:|---|---|",
    ]
    for r in sorted(rows, key=lambda r: (COMMANDS.index(r["command"]), r["render"], r["frames"])):
        minutes, gb = estimate(r["command"], r["frames"], r["render"])
        est = f"{minutes:.1f}, {gb:.1f}"
        ratio = f"{r['wall_s'] / 60 / minutes:.2f}, {r['peak_gb'] / gb:.2f}"
        lines.append(
            f"| {r['command']} | {'yes' if r['render'] else 'no'} | {r['frames']} | {r['wall_s']:.1f} | {1e3 * r['wall_s'] / r['frames']:.1f} | "
            f"{r['peak_gb']:.2f} | {1024 * r['peak_gb'] / r['frames']:.2f} | {est} | {ratio} |"
        )
    return "\n".join(lines) + "\n"


def run_long_bench(
    frames: tuple[int, ...], commands: tuple[str, ...], out: Path, render: bool, name: str = "cube_lift"
) -> str:
    """Every command on every length (shortest first), resumable per row; writes ``OUT/long.md`` and
    ``OUT/long.json`` and returns the markdown."""
    for c in commands:
        if c not in COMMANDS:
            raise QuasisimError(f"bench long --commands: unknown {c!r}; expected some of {', '.join(COMMANDS)}")
    make_clip = _example(out, name)
    rows = [_row(n, c, out, render, make_clip) for n in sorted(frames) for c in commands]
    rows += [r for r in _other_rows(out) if r not in rows]  # kept rows of other runs (e.g. with rendering)
    md = header("Commands on long clips") + (
        f"\nThe bundled example `{name}` made with N frames; each command in its own process; peak memory is the "
        "process's maximum resident set. The estimate is the clip-length warning's model, `15 s + T x (s per frame)` "
        "and `600 MB + T x (MB per frame)` with each command's figures (the warning prints it above 1,500 frames); "
        "measured / estimate should lie within 0.5-2.\n\n"
    ) + table(rows)  # fmt: skip
    save_json_atomic(out / "long.json", rows)
    save_text_atomic(out / "long.md", md)
    return md
