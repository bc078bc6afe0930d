"""Process-wide settings: cache folder and JAX configuration."""

from __future__ import annotations

import os
from pathlib import Path

CACHE_ENV = "QUASISIM_CACHE"


def cache_dir() -> Path:
    """``$QUASISIM_CACHE`` or ``~/.cache/quasisim`` (created on demand)."""
    d = Path(os.environ.get(CACHE_ENV) or Path.home() / ".cache" / "quasisim").expanduser()
    d.mkdir(parents=True, exist_ok=True)
    return d


_configured = False


def configure_jax() -> None:
    """Persistent XLA compilation cache under :func:`cache_dir` (compiles are slow on small CPUs)."""
    global _configured
    if _configured:
        return
    import jax

    jax.config.update("jax_compilation_cache_dir", str(cache_dir() / "jax"))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    _configured = True
