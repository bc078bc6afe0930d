"""Atomic file output: a crash or kill never leaves a half-written file behind."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import shutil
import socket
import tempfile
import time
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from quasisim.errors import InputError, QuasisimError

TMP_MARK = ".tmp"  # every temporary file or folder of this module is named ``.NAME.<random>.tmp[.ext]``
MANIFEST = "manifest.json"  # written last into a folder of outputs: the files of the set and their sha256


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
    except BaseException as e:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        if isinstance(e, OSError) and e.filename is None and e.strerror:  # a full disk: name the file
            raise OSError(e.errno, e.strerror, str(path)) from e
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


def check_input_file(path: Path, what: str) -> None:
    """:class:`InputError` unless ``path`` is an existing regular file (``what``: e.g. "YAML file")."""
    try:
        if path.is_file():
            return
        got = "no such file" if not path.exists() else "a folder" if path.is_dir() else "not a regular file"
    except OSError as e:  # a name too long, a loop of links
        got = e.strerror or str(e)
    raise InputError(path, None, f"an existing {what}", got)


ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")  # a zip archive with members / an empty one
NPY_MAGIC = b"\x93NUMPY"


def open_npz(path: Path, fmt: str, what: str) -> np.lib.npyio.NpzFile:
    """Open ``path`` as a ``.npz`` archive (no pickles); :class:`~quasisim.errors.InputError` naming the file
    when it is missing (``what``: e.g. "controls .npz file") or not an archive of format ``fmt``."""
    check_input_file(path, what)
    try:
        with open(path, "rb") as f:
            head = f.read(6)
    except OSError as e:
        raise InputError(path, None, f"a readable {what}", e.strerror or str(e)) from None
    if head.startswith(NPY_MAGIC):
        raise InputError(path, None, "a numpy .npz archive (several named arrays)", "a single .npy array")
    if not head.startswith(ZIP_MAGIC):
        got = "an empty file" if not head else "a file that is not a zip archive"
        raise InputError(path, None, f"a numpy .npz archive in {fmt} format", got)
    try:
        return np.load(path, allow_pickle=False)
    except (ValueError, OSError, zipfile.BadZipFile, EOFError) as e:
        raise InputError(path, None, f"a numpy .npz archive in {fmt} format", f"unreadable file ({e})") from None


def npz_member(z: np.lib.npyio.NpzFile, key: str, path: Path) -> np.ndarray:
    """Array ``key`` of an open archive; :class:`InputError` naming the field when it is damaged or pickled."""
    try:
        return z[key]
    except ValueError as e:  # object arrays need pickle
        if "pickle" in str(e) or "allow_pickle" in str(e):
            raise InputError(path, key, "a plain numeric or string array", "pickled Python objects") from None
        raise InputError(path, key, "a readable array", " ".join(str(e).split())) from None
    except (OSError, EOFError, zipfile.BadZipFile, KeyError) as e:
        raise InputError(path, key, "a readable array", f"damaged data ({type(e).__name__})") from None


def npz_str(z: np.lib.npyio.NpzFile, key: str, path: Path) -> str:
    """A 0-d string field."""
    a = npz_member(z, key, path)
    if a.shape != () or a.dtype.kind not in "US":
        raise InputError(path, key, "a 0-d string array", f"dtype {a.dtype} shape {a.shape}")
    return str(a)


def npz_number(z: np.lib.npyio.NpzFile, key: str, path: Path, lo: float = -np.inf, hi: float = np.inf) -> float:
    """A finite 0-d number field in ``[lo, hi]`` (a one-element array of shape (1,) is refused too)."""
    a = npz_member(z, key, path)
    if a.shape != () or a.dtype.kind not in "fiu":
        raise InputError(path, key, "a 0-d number", f"dtype {a.dtype} shape {a.shape}")
    v = float(a)
    if not np.isfinite(v):
        raise InputError(path, key, "a finite number", str(v))
    if not lo <= v <= hi:
        raise InputError(path, key, f"a value in [{lo:g}, {hi:g}]", f"{v:g}")
    return v


def npz_array(z: np.lib.npyio.NpzFile, key: str, path: Path, shape: tuple[int | str, ...]) -> np.ndarray:
    """A finite numeric float64 array whose shape matches ``shape`` (a str entry: any length, named so)."""
    a = npz_member(z, key, path)
    want = "(" + ", ".join(str(t) for t in shape) + ")"
    if a.dtype.kind not in "fiu":
        raise InputError(path, key, f"a numeric array of shape {want}", f"dtype {a.dtype}")
    if a.ndim != len(shape) or any(isinstance(w, int) and w != n for w, n in zip(shape, a.shape, strict=True)):
        raise InputError(path, key, f"shape {want}", f"shape {tuple(a.shape)}")
    a = np.asarray(a, dtype=np.float64)
    bad = ~np.isfinite(a)
    if bad.any():
        where = f" at frame {int(np.argwhere(bad)[0][0])}" if a.ndim > 1 else ""
        raise InputError(path, key, "finite values", f"NaN or inf{where}")
    return a


# ---- folders of outputs --------------------------------------------------------------------------


def check_out_dir(out: Path, option: str = "--out") -> None:
    """Refuse an output folder that cannot be created or written (checked before any work, leaving no trace):
    a file, a folder under a file, a folder without write permission, a virtual file system such as /proc."""
    out = Path(out)
    try:
        if out.is_symlink() and not out.exists():
            raise InputError(out, option, "a folder for the outputs", "a broken symbolic link")
        if out.exists() and not out.is_dir():
            raise InputError(out, option, "a folder for the outputs", "an existing file")
        probe = out
        while not probe.exists() and probe.parent != probe:
            probe = probe.parent
        if not probe.is_dir():
            raise InputError(out, option, "a folder that can be created", f"{probe} is a file")
        fd, tmp = tempfile.mkstemp(prefix=".write-probe.", suffix=TMP_MARK, dir=probe)
        os.close(fd)
        os.unlink(tmp)
    except OSError as e:
        raise InputError(
            out, option, "a folder quasisim may write into", f"no write access ({e.strerror or e}: {e.filename or out})"
        ) from None


def existing_outputs(out: Path, names: tuple[str, ...]) -> list[str]:
    """Which of ``names`` already exist in ``out``."""
    return [n for n in names if (Path(out) / n).exists()]


def refuse_overwrite(out: Path, names: tuple[str, ...], overwrite: bool) -> None:
    """:class:`QuasisimError` when ``out`` holds outputs of an earlier run and ``overwrite`` is false."""
    found = existing_outputs(out, names)
    if found and not overwrite:
        raise InputError(
            out, "--out", "a folder without the outputs of an earlier run (pass --overwrite to replace them)",
            ", ".join(found),
        )  # fmt: skip


# tempfile's names: PREFIX + 8 characters of [a-z0-9_] + SUFFIX (atomic_path: ``.NAME.<8>.tmp<NAME's suffix>``)
_ORPHAN_FILE = re.compile(r"\.(?P<name>.+)\.[a-z0-9_]{8}\.tmp(?P<ext>\.[^.]+)?")
_ORPHAN_STAGE = re.compile(r"\.outputs\.[a-z0-9_]{8}\.tmp")  # output_set's staging folder


def is_orphan(p: Path) -> bool:
    """Is ``p`` named as what an interrupted write of quasisim leaves: a file of :func:`atomic_path` or of
    :func:`check_out_dir`'s probe, a staging folder of :func:`output_set` (never another program's ``*.tmp``)."""
    if p.is_dir() and not p.is_symlink():
        return _ORPHAN_STAGE.fullmatch(p.name) is not None
    m = _ORPHAN_FILE.fullmatch(p.name)
    return m is not None and (m["ext"] is None or m["name"].endswith(m["ext"]))


def remove_orphans(folder: Path) -> list[Path]:
    """Remove what an interrupted atomic write left in ``folder`` (:func:`is_orphan`); returns what was removed."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    gone = []
    for p in folder.iterdir():
        if is_orphan(p):
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p, ignore_errors=True)
            else:
                with contextlib.suppress(FileNotFoundError):
                    p.unlink()
            gone.append(p)
    return gone


def size_mb(path: Path) -> float:
    """The size of file ``path``, or of every file below folder ``path``, in MB (10^6 bytes)."""
    files = [path] if path.is_file() else [f for f in path.rglob("*") if f.is_file()]
    return sum(f.stat().st_size for f in files) / 1e6


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


@contextlib.contextmanager
def output_set(out: Path) -> Iterator[Path]:
    """Write a set of outputs that a reader never sees mixed with an earlier set.

    Yields a hidden staging folder inside ``out``; when the block ends without error the earlier
    ``manifest.json`` is removed, every staged file is renamed into ``out``, the earlier set's files that the
    new one lacks are removed where they still hold what that manifest recorded, and a new manifest (the files
    and their sha256) is written last. A folder whose manifest is missing or disagrees with its files holds
    an unfinished set (see :func:`read_manifest`); on an error or a kill the earlier set stays untouched.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    remove_orphans(out)
    stage = Path(tempfile.mkdtemp(prefix=".outputs.", suffix=TMP_MARK, dir=out))
    try:
        yield stage
        files = sorted(p.name for p in stage.iterdir() if p.is_file() and not p.name.startswith("."))
        digests = {n: file_sha256(stage / n) for n in files}
        earlier = _manifest_files(out)
        (out / MANIFEST).unlink(missing_ok=True)
        for n in files:
            os.replace(stage / n, out / n)
        for n, digest in earlier.items():  # files of the earlier set that the new one does not have
            if n not in digests and _holds(out / n, digest):
                (out / n).unlink()
        save_json_atomic(out / MANIFEST, {"files": digests})
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def _holds(path: Path, digest: str) -> bool:
    """Is ``path`` a plain file (not a link) whose sha256 is ``digest``: still what a manifest recorded?"""
    return path.is_file() and not path.is_symlink() and file_sha256(path) == digest


def _manifest_files(out: Path) -> dict[str, str]:
    """The plain file names an earlier manifest in ``out`` lists, with their sha256 (none when it is missing,
    damaged or not of this module: another program's ``manifest.json`` names no file to remove)."""
    try:
        files = json.loads((out / MANIFEST).read_text())["files"]
        return {n: h for n, h in files.items() if isinstance(n, str) and isinstance(h, str)
                and n == Path(n).name and n not in (".", "..", MANIFEST)}  # fmt: skip
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return {}


def read_manifest(out: Path) -> dict[str, str] | None:
    """The files of the finished output set in ``out`` (name -> sha256), or None when the set is unfinished
    (no manifest, or a file missing or changed since)."""
    try:
        files = json.loads((Path(out) / MANIFEST).read_text())["files"]
        ok = all(file_sha256(Path(out) / n) == h for n, h in files.items())
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return files if ok else None


# ---- one run per folder --------------------------------------------------------------------------

LOCK = ".quasisim.lock"  # in a run folder while a run writes it: {"pid", "host", "since", "command"}


def _holder(lock: Path) -> dict[str, Any] | None:
    """The lock's holder, or None when the lock is gone or stale (its process has ended, on this host)."""
    try:
        info = json.loads(lock.read_text())
        pid, host = int(info["pid"]), str(info["host"])
    except FileNotFoundError:
        return None
    except (OSError, ValueError, KeyError, TypeError):
        return None  # unreadable or half-written: a writer that died before finishing it
    if host == socket.gethostname():
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return None
        except PermissionError:
            pass  # alive, another user's
    return info


@contextlib.contextmanager
def run_lock(out: Path, command: str = "") -> Iterator[None]:
    """Hold ``out/.quasisim.lock`` while a run writes ``out`` (created if missing; removed again, with ``out``
    when the run left it empty). Another live process holding it: :class:`QuasisimError` naming that process;
    a stale lock (its process gone) is taken over."""
    out = Path(out)
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    lock = out / LOCK
    me = {"pid": os.getpid(), "host": socket.gethostname(), "since": time.strftime("%Y-%m-%d %H:%M:%S"),
          "command": command}  # fmt: skip
    for _ in range(3):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            holder = _holder(lock)
            if holder is not None and holder.get("pid") != os.getpid():
                what = f" ({holder['command']})" if holder.get("command") else ""
                raise QuasisimError(
                    f"{out}: another quasisim run{what} is writing this folder: process {holder['pid']} on "
                    f"{holder['host']} since {holder.get('since', '?')}; wait for it to end or choose another "
                    f"output folder (if that process is gone, remove {lock})"
                ) from None
            with contextlib.suppress(FileNotFoundError):
                lock.unlink()  # stale: its process has ended
            continue
        with os.fdopen(fd, "w") as f:
            json.dump(me, f)
        break
    else:
        raise QuasisimError(f"{out}: could not take the run lock {lock} (another run keeps taking it)")
    try:
        yield
    finally:
        with contextlib.suppress(FileNotFoundError):
            lock.unlink()
        if created:
            with contextlib.suppress(OSError):
                out.rmdir()  # only when empty
