"""Control trajectories for the target simulators: PD targets per frame (``quasisim-controls-v1``).

============== ============ =====================================================================
key            shape        meaning
============== ============ =====================================================================
``format``     ()           ``"quasisim-controls-v1"``
``hand``       ()           built-in hand name or path of the hand YAML
``demo``       ()           name of the demonstration
``demo_hash``  ()           content hash of the demonstration (:func:`quasisim.data.demo.content_hash`)
``method``     ()           how the controls were made (``kinematic``, ``transfer``, ...)
``fps``        ()           control frame rate (Hz)
``base_rot``   (3, 3)       fixed frame of the base hinges
``q_targets``  (T, 6 + J)   PD position targets: base x y z (m), base angles (rad), joints (rad/m)
``joint_names`` (J,)        names of the joints, in column order after the 6 base columns
``left_base_rot`` (3, 3)    optional: two hands (a demo with ``left_joints``): the base frame of the left
                            hand (``hand``'s mirror image); ``q_targets`` is then (T, 2 (6 + J)),
                            the right hand's columns, then the left hand's
============== ============ =====================================================================

In memory the base frames are :attr:`Controls.base_rots`, one per hand (right, then left); the file keeps
them under :data:`BASE_ROT_KEYS` (``base_rot``, ``left_base_rot``), and files of one hand have no
``left_base_rot``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from quasisim.data.demo import FPS_RANGE, SIDES
from quasisim.errors import InputError
from quasisim.files import npz_array, npz_member, npz_number, npz_str, open_npz, save_npz_atomic

FORMAT = "quasisim-controls-v1"
BASE_NAMES = ("base_tx", "base_ty", "base_tz", "base_rx", "base_ry", "base_rz")
BASE_ROT_KEYS = ("base_rot", "left_base_rot")  # the file key of each hand's base frame (right, left)


@dataclass(frozen=True, eq=False)
class Controls:
    """PD targets for the hand(s) of one demo (see the module docstring for the file).

    Attributes:
        hand: built-in hand name or path of the hand YAML (the right hand; two hands add its mirror image).
        demo, demo_hash: name and content hash of the demonstration.
        method: how the controls were made.
        fps: control frame rate (Hz).
        base_rots: (3, 3) fixed frame of the base hinges of each hand, right then left (one or two).
        q_targets: (T, H (6 + J)) PD position targets, each hand's columns in the order of ``base_rots``.
        joint_names: (J,) the joints of one hand, in column order after its 6 base columns.
        extras: further arrays saved as ``extra_<key>``.
    """

    hand: str
    demo: str
    method: str
    fps: float
    base_rots: tuple[np.ndarray, ...]
    q_targets: np.ndarray
    joint_names: tuple[str, ...]
    extras: dict[str, np.ndarray] = field(default_factory=dict)
    demo_hash: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "base_rots", tuple(self.base_rots))
        if not 1 <= len(self.base_rots) <= len(SIDES):
            raise ValueError(f"Controls: {len(self.base_rots)} base frames, expected one per hand (1 or 2)")

    @property
    def sides(self) -> tuple[str, ...]:
        """The hands these controls drive: ``("right",)`` or ``("right", "left")``."""
        return SIDES[: len(self.base_rots)]

    @property
    def n_frames(self) -> int:
        return int(self.q_targets.shape[0])

    def save(self, path: str | Path) -> Path:
        extras = {f"extra_{k}": np.asarray(v) for k, v in self.extras.items()}
        columns = [*BASE_NAMES, *self.joint_names]
        if len(self.base_rots) > 1:
            columns = [f"{side}/{c}" for side in self.sides for c in columns]
            extras[BASE_ROT_KEYS[1]] = np.asarray(self.base_rots[1], dtype=np.float64)
        return save_npz_atomic(
            path,
            format=np.array(FORMAT),
            hand=np.array(self.hand),
            demo=np.array(self.demo),
            demo_hash=np.array(self.demo_hash),
            method=np.array(self.method),
            fps=np.array(self.fps),
            base_rot=np.asarray(self.base_rots[0], dtype=np.float64),
            q_targets=np.asarray(self.q_targets, dtype=np.float64),
            joint_names=np.array(self.joint_names),
            column_names=np.array(columns),
            **extras,
        )


def load_controls(path: str | Path) -> Controls:
    """Read and validate a controls file; raise :class:`InputError` naming the field on problems."""
    path = Path(path)
    with open_npz(path, FORMAT, "controls .npz file") as z:
        for key in ("format", "hand", "fps", "base_rot", "q_targets", "joint_names"):
            if key not in z.files:
                raise InputError(path, key, "a key present in every controls file", "missing")
        fmt = npz_str(z, "format", path)
        if fmt != FORMAT:
            raise InputError(path, "format", f"'{FORMAT}'", f"'{fmt}'")
        names = _joint_names(npz_member(z, "joint_names", path), path)
        rots = tuple(npz_array(z, k, path, (3, 3)) for k in BASE_ROT_KEYS if k in z.files)  # base_rot is present
        c = Controls(
            hand=npz_str(z, "hand", path),
            demo=npz_str(z, "demo", path) if "demo" in z.files else "",
            method=npz_str(z, "method", path) if "method" in z.files else "",
            fps=npz_number(z, "fps", path, *FPS_RANGE),
            base_rots=rots,
            q_targets=npz_array(z, "q_targets", path, ("T", len(rots) * (6 + len(names)))),
            joint_names=names,
            extras={k[6:]: npz_member(z, k, path) for k in z.files if k.startswith("extra_")},
            demo_hash=npz_str(z, "demo_hash", path) if "demo_hash" in z.files else "",
        )
        for k in z.files:  # every member must be readable
            npz_member(z, k, path)
    if c.q_targets.shape[0] < 2:
        raise InputError(path, "q_targets", f"shape (T >= 2, {c.q_targets.shape[1]})", str(c.q_targets.shape))
    for key, R in zip(BASE_ROT_KEYS, c.base_rots, strict=False):
        if not (np.allclose(R @ R.T, np.eye(3), atol=1e-5) and np.linalg.det(R) > 0):
            raise InputError(path, key, "a 3x3 rotation matrix", str(R.round(4).tolist()))
    return c


def _joint_names(a: np.ndarray, path: Path) -> tuple[str, ...]:
    if a.ndim != 1 or a.dtype.kind not in "US":
        raise InputError(path, "joint_names", "a 1-d array of joint names", f"dtype {a.dtype} shape {a.shape}")
    names = tuple(str(s) for s in a)
    if len(set(names)) != len(names) or not all(names):
        raise InputError(path, "joint_names", "distinct, non-empty joint names", ", ".join(names)[:120])
    return names


def check_demo_hash(controls: Controls, demo_hash: str, path: str | Path | None, force: bool) -> str | None:
    """Refuse controls made for another demo (a different content hash) unless ``force``; returns a warning
    when the controls carry no hash (written before hashes were recorded) or when forced past a mismatch."""
    if not controls.demo_hash:
        return f"{path}: field 'demo_hash' missing (controls written by an older version); the demo is not checked"
    if controls.demo_hash == demo_hash:
        return None
    if not force:
        raise InputError(
            path, "demo_hash", f"{demo_hash} (the content hash of this demo; --force replays them anyway)",
            f"{controls.demo_hash} (controls made for demo {controls.demo!r})",
        )  # fmt: skip
    return f"{path}: made for another demo ({controls.demo!r}, hash {controls.demo_hash}); replayed anyway (--force)"
