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
from quasisim.eval.replay_failures import AFTER, DROP_CM
from quasisim.limits import STRICT_CM, STRICT_DEG, object_errors
from quasisim.rotations import np_quat_to_mat

SYMMETRIC_MM = 1.0  # mean surface distance (mm) under which a rotation error is a symmetry of the shape
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
    from quasisim.targets.mujoco_target import object_contacts

    data, obj = mujoco.MjData(model), mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "object")
    hand = np.arange(model.nbody) > 0  # every body but the world's (table, floor) and the object
    hand[obj] = False
    out = np.zeros(len(qpos), int)
    for t, q in enumerate(qpos):
        data.qpos[:] = q
        mujoco.mj_forward(model, data)
        out[t] = object_contacts(model, data, obj, hand)
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
