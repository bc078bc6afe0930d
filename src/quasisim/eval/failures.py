"""Why a run fails strict success: the first frame over a strict limit, which limit, and what the hand and the
object did there, from the run's own outputs (``rollout.npz``, ``scene.xml``, ``trajectory.npz``) and its demo.

Labels, the first that applies at the first failing frame ``f``:

* ``symmetric``: at every failing frame only the rotation limit is exceeded, and the rotation error moves
  the object's surface by less than :data:`SYMMETRIC_MM` on average (a rotation the shape hides, e.g. about
  a cylinder's axis or a cube's quarter turn);
* ``drop``: within :data:`AFTER` frames of ``f`` the hand touches the object nowhere and the object ends at
  least :data:`DROP_CM` lower than the demo's;
* ``lost contact``: no hand contact at ``f`` (the object was pushed or left behind);
* ``never grasped``: no hand contact at any frame up to ``f``;
* ``slip``: the hand touches the object at ``f``, yet the object drifts off the demo's pose.

Where the run has a sampling stage whose checkpoint recorded its back-ups (``checkpoints/sample.npz``,
``backup_frames``), the failure also says how many back-ups it made and the first and last frame they left
from.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from quasisim.data.demo import Demo
from quasisim.limits import STRICT_CM, STRICT_DEG, object_errors
from quasisim.rotations import np_quat_to_mat

SYMMETRIC_MM = 1.0  # mean surface distance (mm) under which a rotation error is a symmetry of the shape
DROP_CM = 3.0  # the object this much below the demo's, with no hand contact: dropped
AFTER = 10  # frames after the first failing one in which a drop is looked for
SURFACE_POINTS = 400


@dataclass(frozen=True)
class Failure:
    """One run's strict failure (or its pass: ``frame`` -1, ``label`` "pass")."""

    clip: str
    method: str
    label: str
    frame: int  # first frame over a strict limit (-1: none)
    frames: int  # frames of the clip
    over: str  # "translation", "rotation" or "both" at ``frame``
    rot_deg: float  # errors at ``frame``
    trans_cm: float
    surface_mm: float  # how far the rotation error at ``frame`` moves the object's surface (mean, mm)
    contacts: int  # hand-object contacts at ``frame``
    failing_frames: int  # frames over a limit
    max_rot_deg: float
    max_trans_cm: float
    backups: int | None = None  # the sampling stage's back-ups (None: no sampling stage, or not recorded)
    backed_up_from: tuple[int, int] | None = None  # first and last frame a back-up left from


def hand_contacts(scene_xml: Path, qpos: np.ndarray) -> np.ndarray:
    """(T,) number of contacts between the hand(s) and the object at each frame's ``qpos`` (T, nq) of the
    run's exported scene (``scene.xml``: body ``object``; the world's geoms are the table and the floor)."""
    import mujoco

    from quasisim.errors import captured_stderr

    with captured_stderr():
        model = mujoco.MjModel.from_xml_path(str(scene_xml))
    data, obj = mujoco.MjData(model), mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "object")
    out = np.zeros(len(qpos), int)
    for t, q in enumerate(qpos):
        data.qpos[:] = q
        mujoco.mj_forward(model, data)
        b1 = model.geom_bodyid[data.contact.geom1[: data.ncon]]
        b2 = model.geom_bodyid[data.contact.geom2[: data.ncon]]
        out[t] = int(np.sum(((b1 == obj) & (b2 > 0) & (b2 != obj)) | ((b2 == obj) & (b1 > 0) & (b1 != obj))))
    return out


def backups_of(run_dir: Path) -> dict[str, Any]:
    """``{"backups": n, "backed_up_from": (first, last)}`` from the run's sampling checkpoint (its
    ``backup_frames``: the frame each back-up left from, the frame it went back to), or ``{}`` without one."""
    f = run_dir / "checkpoints" / "sample.npz"
    if not f.is_file():
        return {}
    with np.load(f) as z:
        if "backup_frames" not in z:
            return {}
        left = np.asarray(z["backup_frames"]).reshape(-1, 2)[:, 0]
    span = (int(left.min()), int(left.max())) if len(left) else None
    return {"backups": len(left), "backed_up_from": span}


def rotation_distance(mesh: Any, points: np.ndarray, quat_a: np.ndarray, quat_b: np.ndarray) -> float:
    """Mean distance (mm) of the object's surface ``points`` (P, 3; object frame) turned by the rotation from
    pose a to pose b (quaternions w x y z, the same origin) to the object's surface ``mesh`` (a trimesh):
    0 where the rotation is a symmetry of the shape, whatever its angle."""
    R = np_quat_to_mat(quat_a).T @ np_quat_to_mat(quat_b)  # b's frame seen from a's
    _, dist, _ = mesh.nearest.on_surface(points @ R.T)
    return 1000.0 * float(np.mean(dist))


def classify(demo: Demo, run_dir: Path, method: str, mesh: Any, surface: np.ndarray) -> Failure:
    """The :class:`Failure` of the finished run in ``run_dir`` (its ``rollout.npz``, ``scene.xml``,
    ``trajectory.npz``) against ``demo``; ``mesh`` the object's surface (trimesh), ``surface`` (P, 3) points
    on it (object frame)."""
    with np.load(run_dir / "rollout.npz") as z:
        pos, quat = z["object_pos"], z["object_quat"]
    rot, trans = object_errors(demo.object_pos, demo.object_quat, pos, quat)
    bad = (rot > STRICT_DEG) | (trans > STRICT_CM)
    common = {"clip": demo.name, "method": method, "frames": demo.n_frames, "failing_frames": int(bad.sum()),
              "max_rot_deg": float(rot.max()), "max_trans_cm": float(trans.max()), **backups_of(run_dir)}  # fmt: skip
    if not bad.any():
        return Failure(label="pass", frame=-1, over="", rot_deg=0.0, trans_cm=0.0, surface_mm=0.0, contacts=0,
                       **common)  # fmt: skip
    f = int(np.argmax(bad))
    with np.load(run_dir / "trajectory.npz") as z:
        contacts = hand_contacts(run_dir / "scene.xml", z["qpos"])
    over = (
        "both" if rot[f] > STRICT_DEG and trans[f] > STRICT_CM else "rotation" if rot[f] > STRICT_DEG else "translation"
    )
    hidden = [rotation_distance(mesh, surface, demo.object_quat[t], quat[t]) for t in np.flatnonzero(bad)]
    after = slice(f, min(len(pos), f + AFTER + 1))
    below = 100.0 * (demo.object_pos[after, 2] - pos[after, 2])
    if not (trans[bad] > STRICT_CM).any() and max(hidden) < SYMMETRIC_MM:
        label = "symmetric"
    elif (contacts[after] == 0).any() and below.max() >= DROP_CM:
        label = "drop"
    elif not contacts[: f + 1].any():
        label = "never grasped"
    elif contacts[f] == 0:
        label = "lost contact"
    else:
        label = "slip"
    return Failure(label=label, frame=f, over=over, rot_deg=float(rot[f]), trans_cm=float(trans[f]),
                   surface_mm=hidden[0], contacts=int(contacts[f]), **common)  # fmt: skip


def finished_runs(root: Path) -> list[Path]:
    """The finished runs under ``root`` (:func:`quasisim.eval.dataset_export.find_runs`) that were judged in
    MuJoCo's exported scene: with ``rollout.npz``, ``scene.xml``, ``trajectory.npz`` and ``controls.npz``."""
    from quasisim.eval.dataset_export import find_runs

    need = ("rollout.npz", "scene.xml", "trajectory.npz", "controls.npz")
    return [d for d in find_runs(root) if all((d / n).is_file() for n in need)]


def run_method(run_dir: Path) -> str:
    """The method of a finished run (``controls.npz``'s, e.g. ``sample-target``; ``ours`` with its stages)."""
    with np.load(run_dir / "controls.npz") as z:
        return str(z["method"]).split("[")[0] or run_dir.name


def as_rows(failures: list[Failure]) -> list[dict[str, Any]]:
    return [asdict(f) for f in failures]


def markdown(failures: list[Failure]) -> str:
    """Per clip (failures only) and a count of the labels per method."""
    lines = [
        "| clip | method | label | first failing frame | over | rot (deg) | trans (cm) | rot moves surface (mm) | contacts "
        "| frames over | max rot (deg) | max trans (cm) | back-ups (from frames) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for f in failures:
        if f.label != "pass":
            lines.append(
                f"| {f.clip} | {f.method} | {f.label} | {f.frame} of {f.frames} | {f.over} | {f.rot_deg:.1f} | "
                f"{f.trans_cm:.2f} | {f.surface_mm:.1f} | {f.contacts} | {f.failing_frames} | {f.max_rot_deg:.1f} | "
                f"{f.max_trans_cm:.2f} | {_backups_cell(f)} |"
            )
    lines += ["", "| method | runs | strict passes | " + " | ".join(LABELS) + " |", "|---" * (3 + len(LABELS)) + "|"]
    for m in sorted({f.method for f in failures}):
        fs = [f for f in failures if f.method == m]
        counts = [sum(f.label == lab for f in fs) for lab in LABELS]
        lines.append(
            f"| {m} | {len(fs)} | {sum(f.label == 'pass' for f in fs)} | " + " | ".join(map(str, counts)) + " |"
        )
    return "\n".join(lines) + "\n"


def _backups_cell(f: Failure) -> str:
    if f.backups is None:
        return "-"
    return f"{f.backups}" + (f" ({f.backed_up_from[0]}-{f.backed_up_from[1]})" if f.backed_up_from else "")


LABELS = ("symmetric", "drop", "never grasped", "lost contact", "slip")


def analyse(root: Path, data_dir: Path) -> list[Failure]:
    """:func:`classify` every finished run under ``root``; its demo is found by the name and content hash in its
    ``controls.npz``, first in ``data_dir`` (:class:`~quasisim.data.run_demo.RunDemos`)."""
    from quasisim.data.run_demo import RunDemos
    from quasisim.errors import QuasisimError
    from quasisim.targets.build import load_object_for

    runs = finished_runs(root)
    if not runs:
        raise QuasisimError(f"{root}: no finished runs (folders with manifest.json, rollout.npz, scene.xml, "
                            "trajectory.npz, controls.npz)")  # fmt: skip
    out, demos, objects = [], RunDemos((data_dir,), root), {}
    for d in runs:
        demo = demos.find(d)
        if demo.path not in objects:
            obj = load_object_for(demo)
            objects[demo.path] = (obj.to_trimesh(), obj.surface_points(SURFACE_POINTS)[0])
        out.append(classify(demo, d, run_method(d), *objects[demo.path]))
    return out


def write(root: Path, failures: list[Failure], out: Path) -> str:
    from quasisim.eval.tables import header
    from quasisim.files import save_text_atomic

    md = header(f"Strict failures of the runs under {root}") + "\n" + markdown(failures)
    out.mkdir(parents=True, exist_ok=True)
    save_text_atomic(out / "failures.json", json.dumps(as_rows(failures), indent=1))
    save_text_atomic(out / "failures.md", md)
    return md


# ---- perturbed replays (robust success, open and closed loop) ---------------------------------------------

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
    rot = np.einsum("tji,tjk->tik", R, np.stack([np_quat_to_mat(q) for q in rollout.object_quat]))
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
