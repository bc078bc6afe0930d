"""``quasisim bench profile``: where a transfer's time goes, per piece of work (retarget, stage 1, each
stage-2 simulator, stage 3, MPC, sampling, outputs): XLA compilation (JAX's own compile events), MuJoCo
(the time inside MuJoCo's C functions, from :mod:`cProfile`), and the rest (JAX execution, forward and
backward, and Python).

The pieces are the run's checkpoints: the run's piece hook (``run_transfer(..., piece_hook=...)``) records
the time window of each piece it computes; compile events and MuJoCo calls are assigned to the window they
fall in.
"""

from __future__ import annotations

import contextlib
import cProfile
import pstats
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import jax

from quasisim import pipeline, tracecache
from quasisim.eval.tables import header, publish
from quasisim.method.config import TransferConfig
from quasisim.method.spec import TransferSpec
from quasisim.runtime import free_compiled_programs

COMPILE_EVENTS = (
    "/jax/core/compile/jaxpr_trace_duration",
    "/jax/core/compile/jaxpr_to_mlir_module_duration",
    "/jax/core/compile/backend_compile_duration",
)


class _Windows:
    """Time windows of the run's pieces, the compile events and a :mod:`cProfile` profile per piece."""

    def __init__(self, cprofile: bool) -> None:
        self.cprofile = cprofile
        self.spans: list[tuple[str, float]] = []
        self.compile: dict[str, float] = defaultdict(float)
        self.by_event: dict[tuple[str, str], float] = defaultdict(float)
        self.by_fun: dict[tuple[str, str], float] = defaultdict(float)
        self.n_compiles: dict[str, int] = defaultdict(int)
        self.profiles: dict[str, cProfile.Profile] = {GLUE: cProfile.Profile(time.perf_counter)}
        self.current = GLUE

    def on_event(self, event: str, duration: float, **kw: Any) -> None:
        if event in COMPILE_EVENTS:
            self.by_fun[self.current, str(kw.get("fun_name", "?"))] += duration
            self.compile[self.current] += duration
            self.by_event[self.current, event.rsplit("/", 1)[-1].removesuffix("_duration")] += duration
            self.n_compiles[self.current] += event == COMPILE_EVENTS[-1]

    def piece(self, name: str, compute: Any) -> dict[str, Any]:
        """Run one piece with its own profile (the glue's profile resumes after it)."""
        self.current, t0 = name, time.perf_counter()
        prof = self.profiles[name] = cProfile.Profile(time.perf_counter)
        if self.cprofile:
            prof.enable()
        try:
            return compute()
        finally:
            prof.disable()
            self.spans.append((name, time.perf_counter() - t0))
            self.current = GLUE
            if self.cprofile:
                self.profiles[GLUE].enable()


GLUE = "setup, outputs, judging, glue"


def run_profile(demo: Path, spec: TransferSpec, cfg: TransferConfig, out: Path, cold: bool, cprofile: bool) -> str:
    """Profile one transfer of ``demo`` into ``out/run`` (from scratch; ``cold``: empty XLA and trace caches and
    no program in memory, as in a fresh process; ``cprofile``: also measure MuJoCo's share, under cProfile, which
    slows Python-heavy code such as tracing)."""
    w = _Windows(cprofile)
    jax.monitoring.register_event_duration_secs_listener(w.on_event)
    cache_dir, traces = jax.config.jax_compilation_cache_dir, contextlib.nullcontext()
    if cold:
        free_compiled_programs(force=True)  # what this process compiled before (jax.jit's and cached_jit's)
        cache = Path(tempfile.mkdtemp(prefix="quasisim-cold-cache-"))
        jax.config.update("jax_compilation_cache_dir", str(cache / "jax"))
        traces = tracecache.use_folder(cache / "traces")
    t0 = time.perf_counter()
    try:
        if cprofile:
            w.profiles[GLUE].enable()
        with traces:
            pipeline.run_transfer(demo, out / "run", spec, cfg, resume=False, piece_hook=w.piece)
    finally:
        w.profiles[GLUE].disable()
        jax.monitoring.unregister_event_duration_listener(w.on_event)
        jax.config.update("jax_compilation_cache_dir", cache_dir)
    total = time.perf_counter() - t0
    rows = [_row(name, wall, w) for name, wall in w.spans]
    rows.append(_row(GLUE, total - sum(wall for _, wall in w.spans), w))
    return publish(out, "profile", rows, _markdown(rows, spec, demo, cold, cprofile, total))


def _row(name: str, wall: float, w: _Windows) -> dict[str, Any]:
    """A piece's wall time, compile time and MuJoCo time (the C functions of the ``mujoco`` module)."""
    mj: dict[str, float] = defaultdict(float)
    stats = pstats.Stats(w.profiles[name]).stats.items() if w.cprofile else ()  # type: ignore[attr-defined]
    for (_file, _line, fn), (_cc, _nc, tt, _ct, _callers) in stats:
        if "mujoco" in fn:
            mj[fn.replace("<built-in method ", "").rstrip(">")] += tt
    return {
        "piece": name, "wall_s": wall, "compile_s": w.compile.get(name, 0.0), "n_compiles": w.n_compiles.get(name, 0),
        "compile_parts": {e: v for (n, e), v in w.by_event.items() if n == name},
        "compile_top": dict(sorted(((f, v) for (n, f), v in w.by_fun.items() if n == name), key=lambda kv: -kv[1])[:4]),
        "mujoco_s": sum(mj.values()), "mujoco_top": dict(sorted(mj.items(), key=lambda kv: -kv[1])[:3]),
    }  # fmt: skip


def _markdown(
    rows: list[dict[str, Any]], spec: TransferSpec, demo: Path, cold: bool, cprofile: bool, total: float
) -> list[str]:
    lines = [
        header(
            f"Profile of one transfer ({demo.stem}, stages {','.join(spec.stages)}, {spec.budget} budget, "
            f"{'empty' if cold else 'warm'} XLA and trace caches)"
        ),
        f"Total wall time {total:.0f} s"
        + (
            " (under cProfile, which slows Python-heavy code such as tracing)."
            if cprofile
            else " (MuJoCo not measured: --cprofile)."
        ),
        "",
        "| piece | wall s | XLA compile s (programs) | of which trace / lower / backend | MuJoCo C s | rest s (JAX execution, Python) | MuJoCo's largest |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        top = ", ".join(f"{k} {v:.1f}" for k, v in r["mujoco_top"].items())
        lines.append(
            f"| {r['piece']} | {r['wall_s']:.1f} | {r['compile_s']:.1f} ({r['n_compiles']}) | {_parts(r)} | {r['mujoco_s']:.1f} | "
            f"{r['wall_s'] - r['compile_s'] - r['mujoco_s']:.1f} | {top} |"
        )
    lines += [
        "",
        *[
            f"- {r['piece']}: slowest compilations (s): "
            + ", ".join(f"{k} {v:.1f}" for k, v in r["compile_top"].items())
            for r in rows
            if r["compile_top"]
        ],
        "",
    ]
    t = {k: sum(r[k] for r in rows) for k in ("wall_s", "compile_s", "mujoco_s")}
    lines.append(
        f"| **total** | {t['wall_s']:.1f} | {t['compile_s']:.1f} | | {t['mujoco_s']:.1f} | "
        f"{t['wall_s'] - t['compile_s'] - t['mujoco_s']:.1f} | |"
    )
    return lines


def _parts(r: dict[str, Any]) -> str:
    c = r["compile_parts"]
    return " / ".join(f"{c.get(k, 0.0):.1f}" for k in ("jaxpr_trace", "jaxpr_to_mlir_module", "backend_compile"))
