"""Process-wide settings: the compiled-program release that keeps long runs below the mapping limit."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from quasisim import runtime


def test_free_compiled_programs_drops_jax_programs_only_when_asked_or_needed(monkeypatch) -> None:
    f = jax.jit(lambda x: jnp.sin(x) * 2.0)
    f(jnp.ones(3))
    assert f._cache_size() == 1
    monkeypatch.setattr(runtime, "_map_counts", lambda: (100, 65530))  # far below the limit: kept
    assert not runtime.free_compiled_programs() and f._cache_size() == 1
    monkeypatch.setattr(runtime, "_map_counts", lambda: (40000, 65530))  # over half of it: dropped
    assert runtime.free_compiled_programs() and f._cache_size() == 0
    f(jnp.ones(3))
    monkeypatch.setattr(runtime, "_map_counts", lambda: None)  # no /proc: only when forced
    assert not runtime.free_compiled_programs() and f._cache_size() == 1
    assert runtime.free_compiled_programs(force=True) and f._cache_size() == 0


def test_map_counts_reads_this_process() -> None:
    counts = runtime._map_counts()
    if counts is not None:  # Linux
        n, limit = counts
        assert 0 < n < limit
