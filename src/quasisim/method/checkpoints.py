"""Checkpoints of a transfer run: one ``.npz`` per finished piece of work, written atomically.

``OUT/checkpoints/run.json`` names the settings that made the run; ``--resume`` continues only a run with
the same settings and reuses every finished piece.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from quasisim.errors import InputError, QuasisimError
from quasisim.files import save_json_atomic, save_npz_atomic
from quasisim.optim.adam import StepLog
from quasisim.optim.sysid import SysID
from quasisim.optim.trajectory import Trajectory


class Checkpoints:
    """One ``.npz`` per finished piece of work in ``folder``, plus ``run.json`` naming the run's settings."""

    def __init__(self, folder: Path, run_info: dict[str, Any], resume: bool) -> None:
        self.folder = folder
        info_path = folder / "run.json"
        existing = sorted(folder.glob("*.npz")) if folder.is_dir() else []
        if existing and not resume:
            raise QuasisimError(
                f"{folder} holds checkpoints of an earlier run ({len(existing)} files); pass --resume to continue "
                "it or choose another --out"
            )
        if resume and info_path.is_file():
            old = json.loads(info_path.read_text())
            for k, v in run_info.items():
                if k in old and old[k] != v:  # keys an older version did not write are not compared
                    raise InputError(info_path, k, f"{old.get(k)!r} to resume this run (or a new --out)", repr(v))
        save_json_atomic(info_path, run_info)

    def load(self, name: str) -> dict[str, np.ndarray] | None:
        """The arrays of checkpoint ``name``, or None when it was not written."""
        p = self.folder / f"{name}.npz"
        if not p.is_file():
            return None
        with np.load(p, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}

    def save(self, name: str, **arrays: Any) -> None:
        save_npz_atomic(self.folder / f"{name}.npz", **arrays)

    def get(self, name: str, compute: Callable[[], dict[str, Any]]) -> dict[str, Any]:
        """Checkpoint ``name``: loaded when it was written, else computed by ``compute`` and saved."""
        d = self.load(name)
        if d is None:
            d = compute()
            self.save(name, **d)
        return d


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


def trajectory_from(d: dict[str, np.ndarray]) -> tuple[Trajectory, SysID]:
    """Inverse of :func:`trajectory_arrays` (trajectory and S)."""
    t = Trajectory(jnp.asarray(d["base"]), jnp.asarray(d["joints"]), jnp.asarray(d["point_force"]))
    return t, SysID.from_array(d["sysid"])
