"""Process-wide settings, applied explicitly by :func:`configure` (the CLI and the tests call it first).

Nothing here runs at import: ``import quasisim`` leaves the environment as it was.
"""

from __future__ import annotations

import gc
import os
import tempfile
from pathlib import Path

import jax

from quasisim import tracecache
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
    tracecache.clear_memory()
    gc.collect()
    return True


# XLA's CPU client sizes its thread pool by the cores the process may run on, when the backend starts (not by
# --xla_cpu_multi_thread_eigen): two unpinned batch workers on two cores run 2 x (main thread + 2 pool
# threads). A worker pinned to its own cores before JAX starts gets a pool of that size.
_CORE_LOCK: list[int] = []  # the lock file this process holds for the life of the process


def pin_to_free_cores(n: int, lock_dir: Path | None = None) -> tuple[int, ...] | None:
    """Restrict this process to ``n`` cores that no other process pinned by this function holds (a lock
    file per group of ``n`` cores under ``lock_dir``, default the temp folder, released when the process
    exits), and return them; None when none is free, when ``n`` does not divide the allowed cores, or where
    the OS has no CPU affinity. Call before JAX's CPU backend starts (its pool takes the affinity then);
    a process that already holds a group keeps it."""
    if not hasattr(os, "sched_setaffinity") or n < 1:
        return None
    import fcntl

    allowed = sorted(os.sched_getaffinity(0))
    if _CORE_LOCK:
        return tuple(allowed)
    if len(allowed) % n or len(allowed) == n:
        return None  # one group only: nothing to keep apart
    d = lock_dir or Path(tempfile.gettempdir()) / f"quasisim-cores-{os.getuid()}"
    d.mkdir(parents=True, exist_ok=True)
    for g in range(len(allowed) // n):
        cores = tuple(allowed[g * n : (g + 1) * n])
        fd = os.open(d / f"cores-{'-'.join(map(str, cores))}.lock", os.O_CREAT | os.O_RDWR, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            continue
        _CORE_LOCK.append(fd)
        for tid in _threads():  # the threads running now (Ray's among them); later ones inherit it
            try:
                os.sched_setaffinity(tid, cores)
            except ProcessLookupError:  # it ended meanwhile
                pass
        return cores
    return None


def _threads() -> list[int]:
    """This process's thread ids (Linux), else [0]: the calling thread."""
    try:
        return [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return [0]
