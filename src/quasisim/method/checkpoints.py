"""Checkpoints of a transfer run: one ``.npz`` per finished piece of work, written atomically.

``OUT/checkpoints/run.json`` names the settings that made the run; ``--resume`` continues only a run with
the same settings. Every checkpoint also carries the identity of what made it (a hash of the settings that
determine that piece: the demo's content, the hand, the settings of its stage and of the stages before it),
so a checkpoint is reused only by a run that would compute the same piece, whatever happened to ``run.json``. A checkpoint that is unreadable, made by another run, or lacks an array
or has one of the wrong shape is discarded and recomputed, said in one line on stderr.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from quasisim.errors import InputError, QuasisimError
from quasisim.files import remove_orphans, save_json_atomic, save_npz_atomic
from quasisim.optim.adam import StepLog
from quasisim.optim.sysid import SysID
from quasisim.optim.trajectory import Trajectory, hand_layout

IDENTITY_KEY = "run_identity"
# what a checkpoint must hold: array name -> shape (None: any length on that axis) or "str" (a 0-d string)
Expect = dict[str, tuple[int | None, ...] | str]


def run_identity(run_info: dict[str, Any]) -> str:
    """16 hex digits naming the settings ``run_info`` (stored in every checkpoint of the run)."""
    return hashlib.sha256(json.dumps(run_info, sort_keys=True).encode()).hexdigest()[:16]


def _say(text: str) -> None:
    print(f"warning: {text}", file=sys.stderr)


class Checkpoints:
    """One ``.npz`` per finished piece of work in ``folder``, plus ``run.json`` naming the run's settings."""

    def __init__(
        self, folder: Path, run_info: dict[str, Any], resume: bool, overwrite: bool = False,
        scope: Callable[[str], dict[str, Any]] | None = None,
        hook: Callable[[str, Callable[[], dict[str, Any]]], dict[str, Any]] | None = None,
    ) -> None:  # fmt: skip
        """``scope(name)``: the part of ``run_info`` that determines checkpoint ``name`` (default: all of it);
        ``hook(name, compute)``: called instead of ``compute()`` for a piece that is computed (profiling)."""
        self.folder = folder
        self._hook = hook
        self._scope = scope or (lambda name: run_info)
        info_path = folder / "run.json"
        remove_orphans(folder)  # what a killed atomic write left behind
        existing = sorted(folder.glob("*.npz")) if folder.is_dir() else []
        if existing and not resume:
            if not overwrite:
                raise QuasisimError(
                    f"{folder} holds checkpoints of an earlier run ({len(existing)} files); pass --resume to "
                    "continue it, --overwrite to start afresh, or choose another --out"
                )
            _check_ours(folder)
            shutil.rmtree(folder)
        old = _read_info(info_path) if resume else None
        for k, v in run_info.items():
            if old is not None and k in old and old[k] != v:  # keys an older version did not write: not compared
                raise InputError(info_path, k, f"{old.get(k)!r} to resume this run (or a new --out)", repr(v))
        # checkpoints written before identities were stored are trusted only under a matching run.json
        self.trust_unmarked = old is not None
        save_json_atomic(info_path, run_info)

    def load(self, name: str, expect: Expect) -> dict[str, np.ndarray] | None:
        """The arrays of checkpoint ``name``, or None when it was not written or was discarded (damaged, made
        by another run, or not holding ``expect``)."""
        p = self.folder / f"{name}.npz"
        if not p.exists():
            return None
        try:
            with np.load(p, allow_pickle=False) as z:
                d = {k: z[k] for k in z.files}
        except Exception as e:  # truncated, empty, not an archive, pickled: all mean "recompute"
            return self._discard(p, f"unreadable ({type(e).__name__})")
        ident = d.pop(IDENTITY_KEY, None)
        if ident is None and not self.trust_unmarked:
            return self._discard(p, "carries no run identity and run.json did not confirm it")
        if ident is not None and str(ident) != self.identity(name):
            return self._discard(p, "made by another run (other demo, hand or settings)")
        problem = mismatch(d, expect)
        return self._discard(p, problem) if problem else d

    def _discard(self, p: Path, why: str) -> None:
        _say(f"{p}: {why}; discarded, recomputing it")
        p.unlink(missing_ok=True)

    def identity(self, name: str) -> str:
        """The identity stored in checkpoint ``name`` (a hash of what determines it)."""
        return run_identity(self._scope(name))

    def save(self, name: str, /, **arrays: Any) -> None:
        save_npz_atomic(self.folder / f"{name}.npz", **{IDENTITY_KEY: np.array(self.identity(name))}, **arrays)

    def get(self, name: str, compute: Callable[[], dict[str, Any]], expect: Expect) -> dict[str, Any]:
        """Checkpoint ``name``: loaded when it was written (and holds ``expect``), else computed by ``compute``
        and saved."""
        d = self.load(name, expect)
        if d is None:
            d = compute() if self._hook is None else self._hook(name, compute)
            problem = mismatch({k: np.asarray(v) for k, v in d.items()}, expect)
            if problem:
                raise RuntimeError(f"checkpoint {name}: the computed arrays do not match their description: {problem}")
            self.save(name, **d)
        return d


def _check_ours(folder: Path) -> None:
    """:class:`InputError` naming the first entry of ``folder`` that quasisim did not write there (anything but
    ``run.json`` and ``.npz`` pieces carrying their run identity): ``--overwrite`` removes only its own folder."""
    for p in sorted(folder.iterdir()):
        plain = p.is_file() and not p.is_symlink()
        if plain and (p.name == "run.json" or (p.suffix == ".npz" and _carries_identity(p))):
            continue
        raise InputError(
            folder, "--out", "a checkpoints folder that quasisim wrote, for --overwrite to remove (run.json and "
            "pieces carrying their run identity; move the other files away or choose another --out)",
            f"{p.name} (not a checkpoint of quasisim)",
        )  # fmt: skip


def _carries_identity(p: Path) -> bool:
    try:
        with np.load(p, allow_pickle=False) as z:
            return IDENTITY_KEY in z.files
    except Exception:  # unreadable: not one we can vouch for
        return False


def _read_info(path: Path) -> dict[str, Any] | None:
    """``run.json`` as a mapping, or None (said in one line) when it is missing or damaged."""
    if not path.exists():
        return None
    try:
        info = json.loads(path.read_text())
        if isinstance(info, dict):
            return info
    except (OSError, UnicodeDecodeError, ValueError):
        pass
    _say(f"{path}: damaged (not a JSON mapping); each checkpoint is checked against its own run identity")
    return None


def mismatch(d: dict[str, np.ndarray], expect: Expect) -> str:
    """What in ``d`` contradicts ``expect`` ("" when nothing does)."""
    for k, want in expect.items():
        if k not in d:
            return f"no array '{k}'"
        a = d[k]
        if want == "str":
            if a.shape != () or a.dtype.kind not in "US":
                return f"'{k}' is not a string"
            continue
        if a.dtype.kind not in "fiub":
            return f"'{k}' is not numeric (dtype {a.dtype})"
        if a.ndim != len(want) or any(w is not None and w != n for w, n in zip(want, a.shape, strict=True)):
            return f"'{k}' has shape {a.shape}, expected {tuple('*' if w is None else w for w in want)}"
    return ""


def trajectory_expect(T: int, J: int, P: int, H: int = 1, **more: tuple[int | None, ...] | str) -> Expect:
    """What a checkpoint of :func:`trajectory_arrays` holds (T frames, J joints, P hand points, H hands)."""
    return {"base": (T, 6 * H), "joints": (T, J), "point_force": (T - 1, P, 3), "sysid": (4,), "wall_s": (), **more}


def trajectory_arrays(traj: Trajectory, sysid: SysID, log: StepLog | None, wall_s: float) -> dict[str, Any]:
    """A trajectory, S, the loss history and the wall time as checkpoint arrays."""
    out: dict[str, Any] = {
        "base": np.asarray(traj.base),
        "joints": np.asarray(traj.joints),
        "point_force": np.asarray(traj.point_force),
        "sysid": sysid.as_array(),
        "wall_s": np.array(wall_s),
    }
    if log is not None:
        out["losses"] = np.asarray(log.losses, np.float64)
    return out


def trajectory_from(d: dict[str, np.ndarray], hand_joints: tuple[int, ...] = ()) -> tuple[Trajectory, SysID]:
    """Inverse of :func:`trajectory_arrays` (trajectory and S); ``hand_joints``: the trajectory's hand layout."""
    arrays = (jnp.asarray(d[k]) for k in ("base", "joints", "point_force"))
    t = Trajectory(*arrays, hand_layout(hand_joints))
    return t, SysID.from_array(d["sysid"])
