"""Why a perturbed replay fails strict success (robust success, open and closed loop): its first frame over a
strict limit, which limit, and a label (:data:`REPLAY_LABELS`); recorded per replay by
:func:`quasisim.eval.robust.robust_success` and tabulated by ``quasisim bench failures OUT --replays``. (Why a
finished run fails, from its own outputs: :mod:`quasisim.eval.failures`.)
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from quasisim.data.demo import Demo
from quasisim.limits import STRICT_CM, STRICT_DEG, object_errors
from quasisim.rotations import np_quat_to_mat

DROP_CM = 3.0  # the object this much below the demo's, with no hand contact: dropped
AFTER = 10  # frames after the first failing one in which a drop is looked for
REST_CM, REST_DEG = 1.0, 5.0  # the demo's object counts as still at rest within this of its first pose
HELD_CM, HELD_DEG = 1.0, 10.0  # "carried off": the object within this of its nominal pose relative to the hand
REPLAY_LABELS = ("pushed off", "drop", "lost contact", "carried off", "rotated in grasp", "slip in grasp")
"""Why a perturbed replay leaves the strict limits, the first that applies at its first failing frame ``f``:

* ``pushed off``: the demo's object has not moved yet at ``f`` (every frame up to ``f`` within :data:`REST_CM`,
  :data:`REST_DEG` of its first pose): the hand moved it before the demo does (a knock on the approach, a grasp closing off-centre);
* ``drop``: within :data:`AFTER` frames of ``f`` the hand touches the object nowhere and it ends at least
  :data:`DROP_CM` lower than the demo's;
* ``lost contact``: no hand contact at ``f``;
* ``carried off``: the object sits in the hand as in the nominal replay (its pose relative to the hand's
  keypoints within :data:`HELD_CM`, :data:`HELD_DEG` of the nominal's): the grasp held, the hand itself is off
  course (weaker gains, a start offset carried along, a tracker that moved the hand);
* ``rotated in grasp``: only the rotation limit is exceeded at ``f`` (the object turned in the hand);
* ``slip in grasp``: the translation limit is exceeded while the hand touches the object.
"""


@dataclass(frozen=True)
class ReplayFailure:
    """One perturbed replay's strict outcome: ``label`` "pass" (``frame`` -1) or one of :data:`REPLAY_LABELS`;
    ``over`` "translation", "rotation" or "both" at ``frame``."""

    replay: int
    label: str
    frame: int
    over: str


def _hand_frame(keypoints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T, 3) origin and (T, 3, 3) rotation of a frame fixed to the hand, from its keypoints (T, K, 3): the
    centroid, and the axes of the keypoints' first point towards the centroid and the first two keypoints'
    plane (K >= 3), orthonormalised."""
    c = keypoints.mean(axis=1)
    a = c - keypoints[:, 0]
    b = keypoints[:, 1] - keypoints[:, 0]
    x = a / np.maximum(np.linalg.norm(a, axis=-1, keepdims=True), 1e-9)
    z = np.cross(x, b)
    z /= np.maximum(np.linalg.norm(z, axis=-1, keepdims=True), 1e-9)
    return c, np.stack([x, np.cross(z, x), z], axis=-1)


def _in_hand(rollout: Any) -> tuple[np.ndarray, np.ndarray]:
    """The object's position (T, 3) and rotation matrices (T, 3, 3) in the hand frame of :func:`_hand_frame`."""
    c, R = _hand_frame(np.asarray(rollout.robot_keypoints))
    pos = np.einsum("tji,tj->ti", R, np.asarray(rollout.object_pos) - c)
    rot = np.einsum("tji,tjk->tik", R, np_quat_to_mat(rollout.object_quat))
    return pos, rot


def replay_failure(demo: Demo, rollout: Any, nominal: Any, contacts: np.ndarray | None, replay: int) -> ReplayFailure:
    """The :class:`ReplayFailure` of a perturbed replay ``rollout`` (a :class:`~quasisim.targets.TargetRollout`)
    against ``demo``, with the nominal replay of the same controls ``nominal`` and the replay's hand-object
    contacts per frame (T,) (None where the target cannot say: ``drop`` and ``lost contact`` are then never
    given)."""
    rot, trans = object_errors(demo.object_pos, demo.object_quat, rollout.object_pos, rollout.object_quat)
    bad = ~((rot <= STRICT_DEG) & (trans <= STRICT_CM))  # NaN (unstable) counts as over
    if not bad.any():
        return ReplayFailure(replay, "pass", -1, "")
    f = int(np.argmax(bad))
    over = "both" if rot[f] > STRICT_DEG and trans[f] > STRICT_CM else "rotation" if rot[f] > STRICT_DEG else (
        "translation")  # fmt: skip
    n = f + 1  # the demo's object up to f against its first pose
    rest_rot, rest_trans = object_errors(
        np.repeat(demo.object_pos[:1], n, 0), np.repeat(demo.object_quat[:1], n, 0), demo.object_pos[:n],
        demo.object_quat[:n],
    )  # fmt: skip
    after = slice(f, min(len(trans), f + AFTER + 1))
    below = 100.0 * (demo.object_pos[after, 2] - np.asarray(rollout.object_pos)[after, 2])
    if rest_rot.max() <= REST_DEG and rest_trans.max() <= REST_CM:
        label = "pushed off"
    elif contacts is not None and (contacts[after] == 0).any() and np.nanmax(below) >= DROP_CM:
        label = "drop"
    elif contacts is not None and contacts[f] == 0:
        label = "lost contact"
    elif _held_as_nominal(rollout, nominal, f):
        label = "carried off"
    elif over == "rotation":
        label = "rotated in grasp"
    else:
        label = "slip in grasp"
    return ReplayFailure(replay, label, f, over)


def _held_as_nominal(rollout: Any, nominal: Any, f: int) -> bool:
    """Whether at frame ``f`` the object sits in the hand as in the ``nominal`` replay (:data:`HELD_CM`,
    :data:`HELD_DEG`)."""
    p, R = _in_hand(rollout)
    p0, R0 = _in_hand(nominal)
    cos = (np.trace(R0[f].T @ R[f]) - 1.0) / 2.0
    angle = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    return bool(100.0 * np.linalg.norm(p[f] - p0[f]) <= HELD_CM and angle <= HELD_DEG)


def label_counts(failures: list[dict[str, Any]]) -> dict[str, int]:
    """``{label: count}`` over :class:`ReplayFailure` rows (as dicts), every label of :data:`REPLAY_LABELS` and
    "pass" present."""
    return {lab: sum(f["label"] == lab for f in failures) for lab in ("pass", *REPLAY_LABELS)}


def replay_failures(root: Path, set_name: str, track: dict[str, Any]) -> list[dict[str, Any]]:
    """Per run under ``root`` (a ``bench transfer`` folder, ``<clip>/<run>/``), the replays' failures of its
    closed-loop cache for the perturbation set ``set_name`` (``default``, ``wide``, ``sensing`` or a file's) and
    the tracker ``track`` (:func:`quasisim.bench.closed_loop._track_dict`'s form): ``{clip, run, open, closed}``,
    each a list of :class:`ReplayFailure` dicts or None where the cache was judged before they were recorded."""
    rows, track = [], json.loads(json.dumps(track))  # as the cache holds it (lists, not tuples)
    for cache in sorted(root.glob("*/*/robust_closed_loop-*.json")):
        data = json.loads(cache.read_text())
        st = data.get("settings", {})
        if set_name not in st.get("sets", {}) or st.get("track") != track:
            continue
        key = st["sets"][set_name]["name"]
        m = data["metrics"]
        rows.append({"clip": cache.parent.parent.name, "run": cache.parent.name,
                     "open": m.get(key, {}).get("failures"), "closed": m.get(key + "_closed_loop", {}).get("failures")})  # fmt: skip
    return rows


def replay_markdown(rows: list[dict[str, Any]]) -> str:
    """Per clip and run, the labels of the open- and closed-loop replays (count x label, the first failing frames),
    then the label counts over every replay."""
    labels = ("pass", *REPLAY_LABELS)
    cell = lambda fs: "not recorded" if fs is None else ", ".join(  # noqa: E731
        f"{n} {lab}" + ("" if lab == "pass" else f" (f {','.join(str(f['frame']) for f in fs if f['label'] == lab)})")
        for lab, n in label_counts(fs).items() if n
    )  # fmt: skip
    lines = ["| clip | run | open loop | closed loop |", "|---|---|---|---|"]
    lines += [f"| {r['clip']} | {r['run']} | {cell(r['open'])} | {cell(r['closed'])} |" for r in rows]
    lines += ["", "| loop | replays | " + " | ".join(labels) + " |", "|---" * (2 + len(labels)) + "|"]
    for loop in ("open", "closed"):
        fs = [f for r in rows if r[loop] is not None for f in r[loop]]
        counts = label_counts(fs)
        lines.append(f"| {loop} | {len(fs)} | " + " | ".join(str(counts[lab]) for lab in labels) + " |")
    return "\n".join(lines) + "\n"
