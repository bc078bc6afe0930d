"""Traced programs kept on disk (``jax.export``), so that a fresh process skips tracing and lowering.

JAX's persistent compilation cache (:func:`quasisim.runtime.configure`) keeps compiled programs, keyed by
the lowered program, so every process still traces and lowers each program it calls before it can look
the compiled one up: ~6-8 s of Python for each of the simulator's value-and-gradient programs, ~30 s per
process for a transfer (docs/profile.md). :func:`cached_jit` is ``jax.jit`` for module-level functions
whose arguments are pytrees of arrays (static data in the pytrees' metadata): on a call with argument
structure and shapes it has not seen in this process, it reads the program traced for them from
``cache_dir()/traces`` (:func:`jax.export.deserialize`), or traces it with :func:`jax.export.export` and
writes it there, then compiles it through ``jax.jit`` (so the compiled program comes from the persistent
cache when it is there).

The key of a traced program is a SHA-256 over everything that decides what tracing produces: the
function's module and name, the source of the quasisim package (every ``.py`` and ``.yaml`` file), the JAX
version and the 64-bit switch, the arguments' tree structure with its static metadata (as pickled; for
types registered with :func:`key_by`, the part the programs read) and
every leaf's shape, dtype and weak type, and the static arguments. A change anywhere in the package makes
every key new. Environment: ``QUASISIM_TRACE_CACHE=0`` turns the disk cache off (calls trace as with
``jax.jit``); the entries are pickles and StableHLO written by this user's own processes, trusted as
Python's own bytecode caches are.
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import io
import os
import pickle
import weakref
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax

from quasisim.files import cache_dir, write_atomic

ENV = "QUASISIM_TRACE_CACHE"
FORMAT = b"quasisim-trace-v1"


def folder() -> Path:
    """Where traced programs are read and written."""
    return cache_dir() / "traces"


@functools.cache
def code_version() -> str:
    """SHA-256 of the quasisim package's ``.py`` and ``.yaml`` files (paths and contents), JAX's version and
    the 64-bit switch: a traced program is valid only for the code and settings that traced it."""
    root = Path(__file__).resolve().parent
    h = hashlib.sha256(FORMAT + jax.__version__.encode() + str(jax.config.jax_enable_x64).encode())
    for p in sorted(q for q in root.rglob("*") if q.suffix in (".py", ".yaml") and q.is_file()):
        h.update(str(p.relative_to(root)).encode() + b"\0" + p.read_bytes() + b"\0")
    return h.hexdigest()


def enabled() -> bool:
    """Whether traced programs are read from and written to disk (``QUASISIM_TRACE_CACHE`` not ``0``)."""
    return os.environ.get(ENV, "1") != "0"


def _avals(leaves: list[Any]) -> tuple[jax.ShapeDtypeStruct, ...]:
    out = []
    for x in leaves:
        a = jax.typeof(x)
        out.append(jax.ShapeDtypeStruct(a.shape, a.dtype, weak_type=a.weak_type))
    return tuple(out)


_KEYS: dict[type, Callable[[Any], Any]] = {}


def key_by(cls: type, key: Callable[[Any], Any]) -> None:
    """Key static values of type ``cls`` in traced programs' keys by ``key(value)`` (picklable; None: the whole
    value) instead of the whole value: for static data of which the programs read only a part. Example: a per-demo human hand,
    whose programs read its topology, not its geometry (:func:`quasisim.sim.build.topology`); keyed whole,
    each demo would trace its own copy of stage 1's programs."""
    _KEYS[cls] = key


def _keyed(kind: str, key: Any) -> None:
    """Stands in a key for a value :func:`key_by` keys (never called: keys are hashed, not unpickled)."""


class _KeyPickler(pickle.Pickler):
    def reducer_override(self, obj: Any) -> Any:
        key = _KEYS.get(type(obj))
        k = None if key is None else key(obj)
        if k is None:
            return NotImplemented
        return _keyed, (f"{type(obj).__module__}.{type(obj).__qualname__}", k)


def _disk_key(name: str, treedef: Any, avals: tuple[jax.ShapeDtypeStruct, ...], static: tuple[Any, ...]) -> str | None:
    """The SHA-256 key of a traced program, or None when the structure does not pickle (never cached)."""
    buf = io.BytesIO()
    try:
        _KeyPickler(buf, protocol=5).dump((treedef, static))
        tree = buf.getvalue()
    except Exception:  # an unpicklable static value: trace in memory only
        return None
    h = hashlib.sha256(code_version().encode() + name.encode() + tree)
    h.update(repr([(a.shape, str(a.dtype), a.weak_type) for a in avals]).encode())
    return h.hexdigest()


_INSTANCES: weakref.WeakSet[_Cached] = weakref.WeakSet()


def clear_memory() -> None:
    """Drop every compiled program held in memory by :func:`cached_jit` functions (they are read from the
    disk and persistent caches when next called); :func:`quasisim.runtime.free_compiled_programs` calls it."""
    for c in list(_INSTANCES):
        c.programs.clear()


class _Cached:
    """See :func:`cached_jit`."""

    def __init__(self, fn: Callable[..., Any], static_argnames: tuple[str, ...]) -> None:
        self.fn = fn
        self.static = static_argnames
        self.sig = inspect.signature(fn)
        self.name = f"{fn.__module__}.{fn.__qualname__}"
        self.programs: dict[Any, tuple[Callable[..., Any], Any]] = {}
        self.jitted = jax.jit(fn, static_argnames=static_argnames)  # where the disk cache is off
        functools.update_wrapper(self, fn)
        _INSTANCES.add(self)

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        if not enabled():
            return self.jitted(*args, **kwargs)
        bound = self.sig.bind(*args, **kwargs)
        bound.apply_defaults()
        static = tuple((k, bound.arguments[k]) for k in self.static)
        dyn = {k: v for k, v in bound.arguments.items() if k not in self.static}
        leaves, treedef = jax.tree_util.tree_flatten(dyn)
        avals = _avals(leaves)
        key = (treedef, avals, static)
        if key not in self.programs:
            self.programs[key] = self._program(treedef, avals, dict(static))
        run, out_tree = self.programs[key]
        return jax.tree_util.tree_unflatten(out_tree, run(*leaves))

    def _program(
        self, treedef: Any, avals: tuple[jax.ShapeDtypeStruct, ...], static: dict[str, Any]
    ) -> tuple[Callable[..., Any], Any]:
        """The compiled-on-first-call program of one argument structure and its output tree structure."""
        key = _disk_key(self.name, treedef, avals, tuple(static.items()))
        path = folder() / f"{key}.bin" if key else None
        if path is not None and path.is_file():
            try:
                head, out_tree, blob = pickle.loads(path.read_bytes())
                if head == FORMAT:
                    return _compiled(jax.export.deserialize(blob), avals, self.fn.__name__), out_tree
            except Exception:  # an unreadable entry (a partial write, another version): trace again
                pass
        out_box: list[Any] = []

        def flat(*xs: Any) -> list[Any]:
            out = self.fn(**jax.tree_util.tree_unflatten(treedef, list(xs)), **static)
            ys, tree = jax.tree_util.tree_flatten(out)
            out_box.append(tree)
            return ys

        exp = jax.export.export(jax.jit(flat), platforms=[jax.default_backend()])(*avals)
        if path is not None:
            entry = pickle.dumps((FORMAT, out_box[0], bytes(exp.serialize())), protocol=5)
            write_atomic(path, lambda tmp: tmp.write_bytes(entry))
        return _compiled(exp, avals, self.fn.__name__), out_box[0]


def _compiled(exp: jax.export.Exported, avals: tuple[jax.ShapeDtypeStruct, ...], name: str) -> Callable[..., Any]:
    """The exported program compiled once, ahead of time, for ``avals``, under the function's ``name`` (as
    profiles list it): a ``jax.jit`` of it would compile again when the arguments' placement changes (plain
    arrays on the first call, arrays a program returned on the next), and every compiled copy holds its own
    memory mappings (:mod:`quasisim.runtime`)."""

    def call(*xs: Any) -> Any:
        return exp.call(*xs)

    call.__name__ = call.__qualname__ = name
    return jax.jit(call).lower(*avals).compile()


def cached_jit(fn: Callable[..., Any] | None = None, *, static_argnames: tuple[str, ...] = ()) -> Any:
    """``jax.jit(fn, static_argnames=...)`` whose traced programs persist across processes (module docstring).
    ``fn`` takes pytrees of arrays (keyword or positional) and returns a pytree of arrays; static arguments
    must be hashable and picklable. Usable as ``@cached_jit`` or ``@cached_jit(static_argnames=(...))``."""
    if fn is None:
        return functools.partial(cached_jit, static_argnames=static_argnames)
    return _Cached(fn, tuple(static_argnames))
