"""What "on track" means, shared by the method (sampling's back-ups, the cascade's gate, the tracker) and the
evaluation (metrics, reports): the strict limits and the object's errors and motion against the demo.

* Strict limits: at every frame the object is within ``STRICT_CM`` = 2 cm and ``STRICT_DEG`` = 30 deg of the
  demo's pose (translation of the object's origin; rotation angle of ``q_ref^-1 q``).
* Object motion: the rollout must rise at least ``MOVE_FRACTION`` (half) as high as the demo and its
  displacement at the demo's farthest frame ``t*`` must be within half the demo's displacement of the demo's;
  demo motions under ``MOVE_MIN_CM`` = 2 cm are not required (they are within the strict tolerance).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from quasisim.rotations import quat_angle_deg

STRICT_CM, STRICT_DEG = 2.0, 30.0
MOVE_MIN_CM = 2.0  # demo motions below this are within the strict tolerance and not required
MOVE_FRACTION = 0.5  # the rollout must reproduce the demo's lift and displacement to within this fraction


@dataclass(frozen=True)
class ObjectMotion:
    """How far the object moved in the demo and in the rollout (cm), each from its own first frame.

    Attributes:
        demo_lift_cm, lift_cm: height gain (highest frame above the first) of the demo's / rollout's object.
        demo_displacement_cm: the demo's largest displacement from its start (at frame ``t*``).
        displacement_error_cm: distance between the rollout's displacement at ``t*`` and the demo's.
    """

    demo_lift_cm: float
    lift_cm: float
    demo_displacement_cm: float
    displacement_error_cm: float

    @property
    def lift_ok(self) -> bool:
        return self.demo_lift_cm < MOVE_MIN_CM or self.lift_cm >= MOVE_FRACTION * self.demo_lift_cm

    @property
    def displacement_ok(self) -> bool:
        need = MOVE_FRACTION * self.demo_displacement_cm
        return self.demo_displacement_cm < MOVE_MIN_CM or self.displacement_error_cm <= need

    @property
    def as_demo(self) -> bool:
        return self.lift_ok and self.displacement_ok

    def to_json(self) -> dict[str, Any]:
        flags = {"lift_ok": self.lift_ok, "displacement_ok": self.displacement_ok, "as_demo": self.as_demo}
        return {**asdict(self), **flags}


def object_motion(ref_pos: np.ndarray, pos: np.ndarray) -> ObjectMotion:
    """:class:`ObjectMotion` of object positions ``pos`` (T, 3) against the demo's ``ref_pos`` (T, 3), in m."""
    d_ref = 100.0 * (np.asarray(ref_pos) - ref_pos[0])
    d_sim = 100.0 * (np.asarray(pos) - pos[0])
    t_star = int(np.argmax(np.linalg.norm(d_ref, axis=1)))
    return ObjectMotion(
        demo_lift_cm=float(d_ref[:, 2].max()),
        lift_cm=float(d_sim[:, 2].max()),
        demo_displacement_cm=float(np.linalg.norm(d_ref[t_star])),
        displacement_error_cm=float(np.linalg.norm(d_sim[t_star] - d_ref[t_star])),
    )


def object_errors(
    ref_pos: np.ndarray, ref_quat: np.ndarray, pos: np.ndarray, quat: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame rotation error (deg) and translation error (cm)."""
    return quat_angle_deg(ref_quat, quat), 100.0 * np.linalg.norm(np.asarray(pos) - np.asarray(ref_pos), axis=-1)


def within_strict(rot_deg: np.ndarray, trans_cm: np.ndarray) -> bool:
    """Whether every frame's errors (deg, cm) are within the strict limits."""
    return bool(np.all(trans_cm <= STRICT_CM) and np.all(rot_deg <= STRICT_DEG))


def strict_success(ref_pos: np.ndarray, ref_quat: np.ndarray, pos: np.ndarray, quat: np.ndarray) -> bool:
    """Strict success of object poses ``pos`` (T, 3) m, ``quat`` (T, 4) w x y z against the demo's: every
    frame within the strict limits and the object moved as in the demo (the metrics' ``success.strict``)."""
    rot, trans = object_errors(ref_pos, ref_quat, pos, quat)
    return object_motion(ref_pos, pos).as_demo and within_strict(rot, trans)
