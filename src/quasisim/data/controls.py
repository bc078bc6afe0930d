"""Control trajectories for the target simulators: PD targets per frame (``quasisim-controls-v1``).

============== ============ =====================================================================
key            shape        meaning
============== ============ =====================================================================
``format``     ()           ``"quasisim-controls-v1"``
``hand``       ()           built-in hand name or path of the hand YAML
``demo``       ()           name of the demonstration
``method``     ()           how the controls were made (``kinematic``, ``transfer``, ...)
``fps``        ()           control frame rate (Hz)
``base_rot``   (3, 3)       fixed frame of the base hinges
``q_targets``  (T, 6 + J)   PD position targets: base x y z (m), base angles (rad), joints (rad/m)
``joint_names`` (J,)        names of the joints, in column order after the 6 base columns
============== ============ =====================================================================
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from quasisim.errors import InputError
from quasisim.files import open_npz, save_npz_atomic

FORMAT = "quasisim-controls-v1"
BASE_NAMES = ("base_tx", "base_ty", "base_tz", "base_rx", "base_ry", "base_rz")


@dataclass(frozen=True, eq=False)
class Controls:
    hand: str
    demo: str
    method: str
    fps: float
    base_rot: np.ndarray
    q_targets: np.ndarray
    joint_names: tuple[str, ...]
    extras: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        return int(self.q_targets.shape[0])

    def save(self, path: str | Path) -> Path:
        extras = {f"extra_{k}": np.asarray(v) for k, v in self.extras.items()}
        return save_npz_atomic(
            path,
            format=np.array(FORMAT),
            hand=np.array(self.hand),
            demo=np.array(self.demo),
            method=np.array(self.method),
            fps=np.array(self.fps),
            base_rot=np.asarray(self.base_rot, dtype=np.float64),
            q_targets=np.asarray(self.q_targets, dtype=np.float64),
            joint_names=np.array(self.joint_names),
            column_names=np.array([*BASE_NAMES, *self.joint_names]),
            **extras,
        )


def load_controls(path: str | Path) -> Controls:
    """Read and validate a controls file; raise :class:`InputError` naming the field on problems."""
    path = Path(path)
    with open_npz(path, FORMAT, "controls .npz file") as z:
        for key in ("format", "hand", "fps", "base_rot", "q_targets", "joint_names"):
            if key not in z.files:
                raise InputError(path, key, "a key present in every controls file", "missing")
        fmt = str(z["format"])
        if fmt != FORMAT:
            raise InputError(path, "format", f"'{FORMAT}'", f"'{fmt}'")
        q = np.asarray(z["q_targets"], dtype=np.float64)
        names = tuple(str(s) for s in z["joint_names"])
        base_rot = np.asarray(z["base_rot"], dtype=np.float64)
        extras: dict[str, Any] = {k[6:]: z[k] for k in z.files if k.startswith("extra_")}
        c = Controls(
            hand=str(z["hand"]),
            demo=str(z["demo"]) if "demo" in z.files else "",
            method=str(z["method"]) if "method" in z.files else "",
            fps=float(z["fps"]),
            base_rot=base_rot,
            q_targets=q,
            joint_names=names,
            extras=extras,
        )
    if q.ndim != 2 or q.shape[1] != 6 + len(names) or q.shape[0] < 2:
        raise InputError(path, "q_targets", f"shape (T >= 2, {6 + len(names)})", str(q.shape))
    if not np.isfinite(q).all():
        raise InputError(path, "q_targets", "finite values", "NaN or inf")
    if base_rot.shape != (3, 3) or not np.allclose(base_rot @ base_rot.T, np.eye(3), atol=1e-5):
        raise InputError(path, "base_rot", "a 3x3 rotation matrix", str(base_rot.round(4).tolist()))
    if not c.fps > 0:
        raise InputError(path, "fps", "a positive frame rate", str(c.fps))
    return c
