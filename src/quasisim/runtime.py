"""Process-wide settings, applied explicitly by :func:`configure` (the CLI and the tests call it first).

Nothing here runs at import: ``import quasisim`` leaves the environment as it was.
"""

from __future__ import annotations

import os

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
