"""Process-wide settings: the compiled-program release that keeps long runs below the mapping limit, and the
pinning of batch workers to cores of their own."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import pytest

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


def test_free_compiled_programs_drops_the_trace_caches_programs_too(tmp_path, monkeypatch) -> None:
    """The programs :func:`quasisim.tracecache.cached_jit` compiled ahead of time are held by it, not by JAX:
    released with JAX's, or a long-lived process would still reach the mapping limit."""
    from quasisim import tracecache

    monkeypatch.setenv("QUASISIM_CACHE", str(tmp_path))
    g = tracecache.cached_jit(lambda x: jnp.cos(x) + 1.0)
    g(jnp.ones(3))
    assert len(g.programs) == 1
    assert runtime.free_compiled_programs(force=True) and len(g.programs) == 0
    assert float(g(jnp.zeros(3))[0]) == 2.0  # read back from the disk cache when next called


def test_map_counts_reads_this_process() -> None:
    counts = runtime._map_counts()
    if counts is not None:  # Linux
        n, limit = counts
        assert 0 < n < limit


# A child that pins itself with the lock folder argv[1], starts JAX's CPU backend, prints its pinned cores,
# its affinity and the threads of XLA's CPU pool, then holds its cores until its stdin closes.
_PIN_CHILD = """
import json, os, sys
from pathlib import Path
from quasisim.runtime import pin_to_free_cores
cores = pin_to_free_cores(1, Path(sys.argv[1]))
import jax.numpy as jnp
jnp.ones(4).sum().block_until_ready()
pool = sum(Path(f"/proc/self/task/{t}/comm").read_text().startswith("tf_XLAEigen") for t in os.listdir("/proc/self/task"))
print(json.dumps([cores, sorted(os.sched_getaffinity(0)), pool]), flush=True)
sys.stdin.read()
"""


def _pinned_child(lock_dir: Path) -> tuple[subprocess.Popen, list]:
    """A running :data:`_PIN_CHILD` and what it printed."""
    p = subprocess.Popen([sys.executable, "-c", _PIN_CHILD, str(lock_dir)], stdin=subprocess.PIPE,
                         stdout=subprocess.PIPE, text=True)  # fmt: skip
    assert p.stdout is not None
    return p, json.loads(p.stdout.readline())  # [cores or None, affinity, XLA pool threads]


@pytest.mark.skipif(
    not hasattr(os, "sched_getaffinity") or len(os.sched_getaffinity(0)) < 2 or not Path("/proc/self/task").is_dir(),
    reason="needs Linux and at least 2 allowed cores",
)
def test_pinned_workers_get_cores_of_their_own_and_an_xla_pool_of_that_size(tmp_path: Path) -> None:
    n = len(os.sched_getaffinity(0))
    children = [_pinned_child(tmp_path) for _ in range(n)]
    try:
        got = [c[1] for c in children]
        assert sorted(c[0][0] for c in got) == sorted(os.sched_getaffinity(0))  # every core once
        assert all([c[0][0]] == c[1] for c in got)  # each child runs where it says it is pinned
        assert all(c[2] <= 1 for c in got)  # XLA sized its pool by the one core (unpinned: one per core)
        extra, (cores, affinity, _) = _pinned_child(tmp_path)  # every core is held: not pinned
        assert cores is None and affinity == sorted(os.sched_getaffinity(0))
        extra.communicate("")
        first, _ = children.pop(0)
        first.communicate("")  # its lock is released when it exits
        again, (cores, affinity, _) = _pinned_child(tmp_path)
        assert cores == got[0][0] and affinity == cores
        again.communicate("")
    finally:
        for p, _ in children:
            p.communicate("")


def test_a_run_releases_its_compiled_programs_after_each_stage_with_the_same_result(
    example_dir, tmp_path, monkeypatch
) -> None:
    """The method ``paper`` compiles more programs in one run than the kernel's mapping limit allows (aborted in
    stage 3 at 65,530 mappings): the pipeline releases them after every stage where the process holds over half
    of the limit, and the run's result is the same bit for bit as a run that kept them."""
    import numpy as np

    from quasisim.data.controls import load_controls
    from quasisim.method.config import TransferConfig
    from quasisim.method.spec import TransferSpec
    from quasisim.pipeline import run_transfer

    cfg = TransferConfig.from_yaml(
        overrides={"sampling.samples": 8, "sampling.horizon": 3, "sampling.backtrack": 0, "sampling.screen": 1}
    )
    spec = TransferSpec(stages=("sample", "select"), render=False, progress=False)
    released = []
    free = runtime.free_compiled_programs
    monkeypatch.setattr(runtime, "free_compiled_programs", lambda force=False: released.append(free(force)))
    monkeypatch.setattr(runtime, "_map_counts", lambda: (100, 65530))  # far below the limit: kept
    run_transfer(example_dir / "cube_lift.npz", tmp_path / "kept", spec, cfg)
    assert released == [False, False]
    released.clear()
    monkeypatch.setattr(runtime, "_map_counts", lambda: (40000, 65530))  # over half of it: released
    run_transfer(example_dir / "cube_lift.npz", tmp_path / "released", spec, cfg)
    assert released == [True, True]  # after each of the two stages
    kept, rel = (load_controls(tmp_path / d / "controls.npz").q_targets for d in ("kept", "released"))
    np.testing.assert_array_equal(kept, rel)
