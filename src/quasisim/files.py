"""Atomic file output: a crash or kill never leaves a half-written file behind."""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from quasisim.errors import InputError


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it is renamed onto ``path`` atomically.

    On any exception the temporary file is removed and ``path`` is left untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + path.suffix, dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        with open(tmp_path, "rb+") as f:
            os.fsync(f.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp_path, 0o666 & ~umask)  # mkstemp creates 0600; final files get the usual permissions
        os.replace(tmp_path, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


def write_atomic(path: str | Path, writer: Callable[[Path], Any]) -> Path:
    """Call ``writer(tmp_path)`` and move the result onto ``path`` atomically."""
    with atomic_path(path) as tmp:
        writer(tmp)
    return Path(path)


def save_npz_atomic(path: str | Path, **arrays: Any) -> Path:
    """``np.savez_compressed`` to ``path`` atomically (no pickles)."""

    def _w(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)

    return write_atomic(path, _w)


def save_json_atomic(path: str | Path, obj: Any) -> Path:
    def _w(tmp: Path) -> None:
        tmp.write_text(json.dumps(obj, indent=2, sort_keys=False) + "\n")

    return write_atomic(path, _w)


def save_text_atomic(path: str | Path, text: str) -> Path:
    return write_atomic(path, lambda tmp: tmp.write_text(text))


CACHE_ENV = "QUASISIM_CACHE"


def cache_dir() -> Path:
    """``$QUASISIM_CACHE`` or ``~/.cache/quasisim`` (created on demand)."""
    d = Path(os.environ.get(CACHE_ENV) or Path.home() / ".cache" / "quasisim").expanduser()
    d.mkdir(parents=True, exist_ok=True)
    return d


def open_npz(path: Path, fmt: str, what: str) -> np.lib.npyio.NpzFile:
    """Open ``path`` as a ``.npz`` archive (no pickles); :class:`~quasisim.errors.InputError` naming the file
    when it is missing (``what``: e.g. "controls .npz file") or not an archive of format ``fmt``."""
    if not path.is_file():
        raise InputError(path, None, f"an existing {what}", "no such file")
    try:
        z = np.load(path, allow_pickle=False)
    except (ValueError, OSError, zipfile.BadZipFile, EOFError) as e:
        raise InputError(path, None, f"a numpy .npz archive in {fmt} format", f"unreadable file ({e})") from None
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise InputError(path, None, "a numpy .npz archive (several named arrays)", "a single .npy array")
    return z
