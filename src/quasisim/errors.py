"""Errors with messages a user can act on: which file, which field, what was expected."""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np


class QuasisimError(Exception):
    """Base class of every error quasisim raises on purpose."""


class InputError(QuasisimError, ValueError):
    """Bad user input: names the file, the field and what was expected.

    The message is one line, e.g.
    ``demo.npz: field 'object_quat': expected unit quaternions (|q| = 1 +- 1e-3), got |q| = 0.5 at frame 3``.
    """

    def __init__(self, path: str | Path | None, field: str | None, expected: str, got: str | None = None) -> None:
        self.path = None if path is None else str(path)
        self.field = field
        self.expected = expected
        self.got = got
        where = self.path or "<input>"
        msg = f"{where}: "
        if field:
            msg += f"{'option' if field.startswith('--') else 'field'} '{field}': "
        msg += f"expected {expected}"
        if got is not None:
            msg += f", got {got}"
        super().__init__(msg)

    def __reduce__(self) -> tuple[Any, ...]:
        """Pickled with its own arguments, so it crosses process boundaries (a pool's worker to the driver)."""
        return type(self), (self.path, self.field, self.expected, self.got)


def choice_error(kind: str, value: object, options: list[str] | tuple[str, ...]) -> QuasisimError:
    """An error for an unknown option that lists the valid ones."""
    return QuasisimError(f"unknown {kind} {value!r}; valid options: {', '.join(sorted(options))}")


def shaped_array(
    value: Any, path: str | Path | None, field: str, shape: tuple[int | None, ...], axis: str = "T"
) -> np.ndarray:
    """``value`` as a float64 array of ``shape`` (None: any length, called ``axis`` in the message), else an
    :class:`InputError` naming ``path`` and ``field``."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(path, field, "numbers", type(value).__name__) from None
    if a.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, a.shape, strict=True)):
        want = "(" + ", ".join(axis if s is None else str(s) for s in shape) + ")"
        raise InputError(path, field, f"an array of shape {want}", str(a.shape))
    return a


class CapturedStderr:
    """What C libraries (MuJoCo, PyBullet) wrote to file descriptor 2 inside :func:`captured_stderr`:
    ``text`` once the block has ended."""

    text: str = ""

    def said(self) -> str:
        """The captured lines as one line ("" when nothing was written)."""
        return " ".join(self.text.split())


@contextlib.contextmanager
def captured_stderr() -> Iterator[CapturedStderr]:
    """Capture file descriptor 2 (where C libraries print their warnings) for the block, so that a warning that
    comes with an error can be folded into our one-line message; the caller re-emits it when there is no
    error (:func:`emit`)."""
    out = CapturedStderr()
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with tempfile.TemporaryFile() as tmp:
            os.dup2(tmp.fileno(), 2)
            try:
                yield out
            finally:
                sys.stderr.flush()
                os.dup2(saved, 2)
                tmp.seek(0)
                out.text = tmp.read().decode("utf-8", errors="replace")
    finally:
        os.close(saved)


def emit(captured: CapturedStderr) -> None:
    """Write what was captured to stderr as it came (a block that succeeded keeps its library's warnings)."""
    if captured.text:
        sys.stderr.write(captured.text)
        sys.stderr.flush()
