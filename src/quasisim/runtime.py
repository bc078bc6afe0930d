"""Process-wide settings, applied explicitly by :func:`configure` (the CLI and the tests call it first).

Nothing here runs at import: ``import quasisim`` leaves the environment as it was.
"""

from __future__ import annotations

import gc
import os
from pathlib import Path

import jax

from quasisim.files import cache_dir

# XLA's CPU backend routes small dots and reductions through YNNPACK fusions, which made the simulator's
# substep ~3x slower on CPU (measured: 3.1 ms -> 1.1 ms per substep without them).
_XLA_FLAG = "--xla_cpu_experimental_ynn_fusion_type="


def configure() -> None:
    """Call once before any simulation: offscreen MuJoCo rendering (``MUJOCO_GL=egl`` unless set), XLA
    without YNNPACK fusions on CPU (unless ``XLA_FLAGS`` names the option) and the persistent XLA
    compilation cache under :func:`cache_dir`. The environment settings take effect only if MuJoCo and
    JAX's CPU backend were not used before. Idempotent."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    if "xla_cpu_experimental_ynn_fusion_type" not in os.environ.get("XLA_FLAGS", ""):
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + _XLA_FLAG).strip()
    jax.config.update("jax_compilation_cache_dir", str(cache_dir() / "jax"))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


# Every compiled XLA program keeps its own memory mappings (LLVM's JIT sections). A process that compiles
# programs for clip after clip reaches the kernel's per-process limit (vm.max_map_count, 65530 by default)
# and XLA's next compilation aborts with "LLVM compilation error: Cannot allocate memory" (measured: the
# test suite reached 61,356 mappings at 97 % and aborted there).
MAP_SHARE = 0.5


def _map_counts() -> tuple[int, int] | None:
    """(this process's memory mappings, the kernel's limit), or None where /proc does not tell (not Linux)."""
    try:
        limit = int(Path("/proc/sys/vm/max_map_count").read_text())
        with open("/proc/self/maps", "rb") as f:
            return sum(1 for _ in f), limit
    except (OSError, ValueError):
        return None


def free_compiled_programs(force: bool = False) -> bool:
    """Drop JAX's compiled programs (they are recompiled, or read from the persistent cache, when next
    needed) when this process holds more than ``MAP_SHARE`` of the kernel's memory-mapping limit, or
    always with ``force``. Call between clips in long-lived processes. Returns whether it dropped them."""
    counts = _map_counts()
    if not force and (counts is None or counts[0] < MAP_SHARE * counts[1]):
        return False
    jax.clear_caches()
    gc.collect()
    return True
