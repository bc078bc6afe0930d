"""Traced programs kept on disk (quasisim.tracecache): the same values as jax.jit, no tracing when an entry
is there, one entry per argument structure, shape and static argument, and damaged entries traced again."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from quasisim import tracecache
from quasisim.sim.types import pytree, static


@pytree
class Box:
    a: jax.Array
    b: jax.Array
    scale: float = static()


TRACES: list[int] = []


def f(box: Box, x: jax.Array, n: int) -> dict[str, jax.Array]:
    TRACES.append(1)  # runs only while tracing
    y = x
    for _ in range(n):
        y = jnp.sin(y) * box.a + box.b * box.scale
    return {"y": y, "sum": jnp.sum(y)}


@pytest.fixture
def cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("QUASISIM_CACHE", str(tmp_path))
    monkeypatch.setenv(tracecache.ENV, "1")
    TRACES.clear()
    return tmp_path / "traces"


def _args(k: int = 5, scale: float = 2.0) -> tuple[Box, np.ndarray]:
    r = np.random.default_rng(k)
    return Box(jnp.asarray(r.normal(size=k), jnp.float32), jnp.float32(0.5), scale), r.normal(size=k).astype(np.float32)


def test_a_fresh_process_reads_the_trace_and_gets_jits_values(cache: Path) -> None:
    box, x = _args()
    want = jax.jit(f, static_argnames=("n",))(box, x, n=3)
    TRACES.clear()
    got = tracecache.cached_jit(f, static_argnames=("n",))(box, x, n=3)
    assert TRACES == [1] and len(list(cache.glob("*.bin"))) == 1
    np.testing.assert_array_equal(got["y"], want["y"])  # the same program: bit for bit
    again = tracecache.cached_jit(f, static_argnames=("n",))  # a new wrapper: nothing in memory, as a new process
    np.testing.assert_array_equal(again(box, x, n=3)["sum"], want["sum"])
    assert TRACES == [1]  # read from disk, not traced


def test_one_entry_per_structure_shape_and_static_argument(cache: Path) -> None:
    g = tracecache.cached_jit(f, static_argnames=("n",))
    for box, x, n in [(*_args(5), 3), (*_args(5), 3), (*_args(6), 3), (*_args(5), 2), (*_args(5, scale=1.0), 3)]:
        want = jax.jit(f, static_argnames=("n",))(box, x, n=n)
        np.testing.assert_allclose(g(box, x, n=n)["y"], want["y"], rtol=1e-6)
    assert len(list(cache.glob("*.bin"))) == 4  # the repeated call is a hit; shape, n and the static scale are not


def test_a_damaged_entry_is_traced_again(cache: Path) -> None:
    box, x = _args()
    want = tracecache.cached_jit(f, static_argnames=("n",))(box, x, n=3)["y"]
    (entry,) = cache.glob("*.bin")
    entry.write_bytes(entry.read_bytes()[:100])  # a partial write of another tool
    TRACES.clear()
    got = tracecache.cached_jit(f, static_argnames=("n",))(box, x, n=3)["y"]
    np.testing.assert_array_equal(got, want)
    assert TRACES == [1] and entry.stat().st_size > 100  # traced and written again


def test_switched_off_writes_nothing(cache: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(tracecache.ENV, "0")
    box, x = _args()
    tracecache.cached_jit(f, static_argnames=("n",))(box, x, n=3)
    assert not cache.exists()


def test_the_key_changes_with_the_code(cache: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    box, x = _args()
    tracecache.cached_jit(f, static_argnames=("n",))(box, x, n=3)
    monkeypatch.setattr(tracecache, "code_version", lambda: "another version of the package")
    tracecache.cached_jit(f, static_argnames=("n",))(box, x, n=3)
    assert len(list(cache.glob("*.bin"))) == 2 and len(TRACES) == 2


class Shape:
    """Static data of which the traced function reads only ``n`` (``tag`` is along for the ride)."""

    def __init__(self, n: int, tag: str) -> None:
        self.n, self.tag = n, tag

    def __hash__(self) -> int:
        return hash(self.n)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Shape) and other.n == self.n


def g(x: jax.Array, shape: Shape) -> jax.Array:
    TRACES.append(1)
    return x * shape.n


def test_key_by_keys_static_data_by_the_part_the_programs_read(cache: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(tracecache, "_KEYS", {Shape: lambda s: s.n if s.tag != "whole" else None})
    x = jnp.ones(3)
    for tag in ("a", "b"):  # another tag, the same n: one entry, read from disk by a new wrapper
        assert float(tracecache.cached_jit(g, static_argnames=("shape",))(x, Shape(2, tag))[0]) == 2.0
    assert len(list(cache.glob("*.bin"))) == 1 and TRACES == [1]
    tracecache.cached_jit(g, static_argnames=("shape",))(x, Shape(2, "whole"))  # keyed whole: its own entry
    assert len(list(cache.glob("*.bin"))) == 2


def test_a_fresh_process_traces_none_of_the_per_clip_kinematics(cache: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The programs every command runs on a clip: the retarget (its solver, keypoints and the rest pose of the
    root fit), the evaluation's hand surface points and the sampling stage's pre-screen keypoints. Once
    their traces are on disk, a process with nothing in memory calls the forward kinematics neither to trace
    them again nor op by op (each eager call of the Python function costs seconds of per-op compiles)."""
    import quasisim.sim.kinematics as kin
    from helpers import scene_with
    from quasisim.assets.hand import load_hand
    from quasisim.data.demo import load_demo
    from quasisim.data.synthetic import write_example
    from quasisim.eval.evaluate import robot_surface
    from quasisim.method.retarget import RetargetOptions, retarget
    from quasisim.method.stages.sampling import kinematic_keypoints

    demo = load_demo(write_example("cube_lift", cache.parent / "demo", n_frames=12))
    hand = load_hand("shadow")
    opts = RetargetOptions(iters=3)

    def run() -> tuple[np.ndarray, ...]:
        r = retarget(hand, demo, opts)
        kp = kinematic_keypoints(scene_with(hand, base_rot=r.base_rot))(r.q)
        return r.q, robot_surface(hand, r.base_rot, r.q), kp

    first = run()
    calls: list[int] = []
    real = kin.forward_kinematics_with_joints
    monkeypatch.setattr(kin, "forward_kinematics_with_joints", lambda *a, **k: calls.append(1) or real(*a, **k))
    tracecache.clear_memory()  # as a fresh process: nothing in memory, the traces on disk
    again = run()
    assert calls == []
    for a, b in zip(first, again, strict=True):
        np.testing.assert_array_equal(a, b)
