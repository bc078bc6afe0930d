"""The demo a finished run folder was made from, found by what the folder records (:func:`recorded`) in the
places :class:`RunDemos` searches. Used by ``export``, ``bench failures`` and ``view --web``; imports no
MuJoCo, JAX or h5py.
"""

from __future__ import annotations

import contextlib
import glob
import hashlib
import json
import os
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from quasisim.data.demo import Demo, content_hash, load_demo
from quasisim.errors import InputError

CONTROLS_FILE, RUN_INFO = "controls.npz", Path("checkpoints") / "run.json"
CLIP_FILE = "clip.json"  # a batch's record of a clip (quasisim.batch.CLIP_FILE), in the clip's folder


@dataclass(frozen=True)
class Recorded:
    """The demo a run folder records: its ``name`` and content hash ``content`` (``controls.npz`` ``demo``,
    ``demo_hash``) and file hash ``sha`` (sha256, 16 hex digits; ``checkpoints/run.json`` ``demo_sha256``,
    written by ``transfer``). ``""`` for what is not recorded (``evaluate``'s folders: nothing)."""

    name: str = ""
    content: str = ""
    sha: str = ""


def recorded(run_dir: Path) -> Recorded:
    """What ``run_dir`` records of its demo (:class:`Recorded`); the name from ``controls.npz``, else from
    ``checkpoints/run.json``. Unreadable files count as not recording anything."""
    name = content = sha = ""
    with contextlib.suppress(OSError, ValueError, KeyError, zipfile.BadZipFile):
        with np.load(run_dir / CONTROLS_FILE, allow_pickle=False) as z:
            name, content = str(z["demo"]), str(z["demo_hash"]) if "demo_hash" in z.files else ""
    with contextlib.suppress(OSError, ValueError, AttributeError):
        info = json.loads((run_dir / RUN_INFO).read_text())
        name, sha = name or str(info.get("demo", "")), str(info.get("demo_sha256", ""))
    return Recorded(name, content, sha)


def batch_demo_file(run_dir: Path) -> str:
    """The demo file a batch ran for ``run_dir``, relative to the batch's data folder: ``clip.json``'s
    ``demo_file`` in the run's folder or the one above it (a clip's named runs); "" where none is recorded (a
    batch's older runs, ``transfer``'s)."""
    for d in (run_dir, run_dir.parent):
        with contextlib.suppress(OSError, ValueError, AttributeError):
            rel = json.loads((d / CLIP_FILE).read_text()).get("demo_file")
            if isinstance(rel, str) and rel and not Path(rel).is_absolute():
                return rel
    return ""


def file_hash(path: Path) -> str:
    """16 hex digits of the sha256 of the file's bytes (``checkpoints/run.json`` ``demo_sha256``)."""
    return hashlib.sha256(path.read_bytes()).hexdigest()[:16]


class RunDemos:
    """Finds a run's demo as the file its batch ran (:func:`batch_demo_file`, in each of the folders below),
    then as ``NAME.npz`` (and ``*/NAME.npz`` in the folders marked so below, e.g. ``arctic/``) in, first found
    wins: the ``data_dirs`` (deep), the ``data_dir`` of a ``batch.json`` in the run's folder or
    above it (deep), the run's folder and those above it (deep as far up as ``root``, by themselves above it),
    ``$QUASISIM_DATA`` (deep). A file is the run's demo when its content hash is the recorded one, else (no
    content hash recorded) its file hash, else (no hash) by name alone. Loaded demos are kept."""

    def __init__(self, data_dirs: tuple[Path, ...] = (), root: Path | None = None, check_mesh: bool = True) -> None:
        self.data_dirs = tuple(Path(d) for d in data_dirs)
        self.root = None if root is None else Path(root).resolve()
        self.check_mesh = check_mesh
        self._loaded: dict[Path, Demo] = {}
        self._hashes: dict[Path, str] = {}

    def places(self, run_dir: Path) -> list[tuple[Path, bool]]:
        """(folder, also search its subfolders) in search order."""
        out = [(d, True) for d in self.data_dirs]
        for p in [run_dir.resolve(), *run_dir.resolve().parents]:
            with contextlib.suppress(OSError, ValueError, AttributeError):
                data_dir = json.loads((p / "batch.json").read_text()).get("data_dir")
                if isinstance(data_dir, str):
                    out.append((Path(data_dir), True))
            out.append((p, self.root is not None and (p == self.root or self.root in p.parents)))
        if os.environ.get("QUASISIM_DATA"):
            out.append((Path(os.environ["QUASISIM_DATA"]), True))
        return out

    def load(self, path: Path) -> Demo:
        """The demo in ``path``, read once (:func:`~quasisim.data.demo.load_demo`; an :class:`InputError` when
        it is not a valid demo)."""
        key = path.resolve()
        if key not in self._loaded:
            self._loaded[key] = load_demo(path, check_mesh=self.check_mesh)
        return self._loaded[key]

    def is_recorded(self, path: Path, rec: Recorded) -> bool:
        """Whether the demo file ``path`` is the one ``rec`` names (by content hash, else file hash)."""
        key = path.resolve()
        if rec.content:
            if key not in self._hashes:
                self._hashes[key] = content_hash(self.load(path))
            return self._hashes[key] == rec.content
        return not rec.sha or file_hash(path) == rec.sha

    def candidates(self, run_dir: Path, name: str) -> Iterator[Path]:
        """The file its batch ran, then the files named like the demo ``name``, in search order (each once)."""
        seen: set[Path] = set()
        places, rel = self.places(run_dir), batch_demo_file(run_dir)
        for folder, _ in places if rel else ():
            if (folder / rel).is_file() and (folder / rel).resolve() not in seen:
                seen.add((folder / rel).resolve())
                yield folder / rel
        for folder, deep in places:
            below = sorted(folder.glob(f"*/{glob.escape(name)}.npz")) if deep and folder.is_dir() else []
            for p in [folder / f"{name}.npz", *below]:
                if p.is_file() and p.resolve() not in seen:
                    seen.add(p.resolve())
                    yield p

    def matches(self, run_dir: Path, rec: Recorded) -> Iterator[tuple[Path, Demo]]:
        """The files (path, demo) in search order that are the demo ``rec`` of ``run_dir``; a same-named file
        that is not a valid demo raises :class:`InputError`."""
        return ((p, self.load(p)) for p in self.candidates(run_dir, rec.name) if self.is_recorded(p, rec))

    def find(self, run_dir: Path) -> Demo:
        """The demo of ``run_dir``, else an :class:`InputError` naming its ``controls.npz``, the field ``demo``
        and where it searched."""
        rec, others = recorded(run_dir), []
        for p in self.candidates(run_dir, rec.name) if rec.name else ():
            if self.is_recorded(p, rec):
                return self.load(p)
            others.append(str(p))
        searched = ", ".join(dict.fromkeys(str(d) for d, _ in self.places(run_dir)))
        hashes = f"content hash {rec.content or 'not recorded'}" + (f", file hash {rec.sha}" if rec.sha else "")
        ran = batch_demo_file(run_dir)
        raise InputError(
            run_dir / CONTROLS_FILE, "demo",
            f"the demo {rec.name!r} ({hashes}) as {f'{ran} (the file its batch ran) or ' if ran else ''}NAME.npz "
            "or */NAME.npz under --data DIR, the batch's data_dir, the run's folder or those above it, or $QUASISIM_DATA",
            f"other content in {', '.join(others)}" if others else f"not found (searched {searched})",
        )  # fmt: skip
