"""Export a judged run for MuJoCo's own tools: ``scene.xml`` (the hand on its floating base, the object, the
table and the floor; meshes inline, so the file stands alone) and ``trajectory.npz`` with ``qpos`` (T, nq)
in that model's layout, one row per frame (``quasisim view RUN_DIR`` plays it; so can any MuJoCo script)."""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import mujoco
import numpy as np

from quasisim.errors import InputError, QuasisimError, captured_stderr, emit
from quasisim.files import open_npz, save_npz_atomic, save_text_atomic
from quasisim.targets import TargetRollout
from quasisim.targets.mujoco_target import build_spec, dof_names
from quasisim.targets.scene import Scene

SCENE_FILE, TRAJECTORY_FILE = "scene.xml", "trajectory.npz"
TRAJECTORY_FORMAT = "quasisim-trajectory-v1"


def hand_joint_names(scene: Scene) -> list[str]:
    """The MJCF joint names of each hand's 6 base coordinates and its joints, in controls/rollout order."""
    return dof_names(scene)


def mujoco_qpos(model: mujoco.MjModel, scene: Scene, rollout: TargetRollout) -> np.ndarray:
    """(T, model.nq) the rollout's hand coordinates and object pose in ``model``'s qpos layout."""
    adr = [model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, n)] for n in hand_joint_names(scene)]
    obj = model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, "object_free")]
    qpos = np.tile(model.qpos0, (len(rollout.qpos), 1))
    qpos[:, adr] = rollout.qpos
    qpos[:, obj : obj + 3] = rollout.object_pos
    qpos[:, obj + 3 : obj + 7] = rollout.object_quat
    return qpos


def export_mujoco(scene: Scene, rollout: TargetRollout, out_dir: str | Path) -> tuple[Path, Path]:
    """Write ``out_dir/scene.xml`` and ``out_dir/trajectory.npz`` (``qpos`` (T, nq), ``time`` (T,) s, ``fps``,
    ``scene``); returns their paths. The XML is reloaded to lay out ``qpos``, so the two always agree."""
    out_dir = Path(out_dir)
    spec = build_spec(scene, visual=True)
    spec.compile()
    xml = spec.to_xml()
    model = mujoco.MjModel.from_xml_string(xml)
    qpos = mujoco_qpos(model, scene, rollout)
    scene_path = save_text_atomic(out_dir / SCENE_FILE, xml)
    traj_path = save_npz_atomic(
        out_dir / TRAJECTORY_FILE,
        format=np.array(TRAJECTORY_FORMAT),
        qpos=qpos,
        time=np.arange(len(qpos)) / scene.fps,
        fps=np.array(float(scene.fps)),
        scene=np.array(SCENE_FILE),
        target=np.array(rollout.target),
    )
    return scene_path, traj_path


def load_export(run_dir: str | Path) -> tuple[mujoco.MjModel, np.ndarray, float]:
    """``(model, qpos (T, nq), fps)`` of an exported run folder (:func:`export_mujoco`)."""
    run_dir = Path(run_dir)
    z = open_npz(run_dir / TRAJECTORY_FILE, TRAJECTORY_FORMAT, "exported trajectory")
    scene = run_dir / str(z["scene"])
    try:
        with captured_stderr() as said:
            model = mujoco.MjModel.from_xml_path(str(scene))
    except Exception as e:
        extra = f" (MuJoCo: {said.said()})" if said.said() else ""
        raise InputError(scene, None, "the run's MJCF scene", " ".join(str(e).split()) + extra) from None
    emit(said)
    return model, np.asarray(z["qpos"]), float(z["fps"])


def has_display() -> bool:
    """Whether a window can open here (Linux needs an X or Wayland display; other systems are assumed to)."""
    return not sys.platform.startswith("linux") or bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def view(run_dir: str | Path) -> None:
    """Play an exported run in ``mujoco.viewer`` (looping at the demo's frame rate) until the window closes."""
    run_dir = Path(run_dir)
    model, qpos, fps = load_export(run_dir)
    if not has_display():
        raise QuasisimError(
            f"no display for MuJoCo's viewer (DISPLAY is not set); on a machine with one run "
            f"`quasisim view {run_dir}` or `python -m mujoco.viewer --mjcf {run_dir / SCENE_FILE}`, or open "
            f"{run_dir / 'report.html'} in a browser"
        )
    import mujoco.viewer

    data = mujoco.MjData(model)
    try:
        with mujoco.viewer.launch_passive(model, data) as v:
            t = 0
            while v.is_running():
                data.qpos[:] = qpos[t]
                mujoco.mj_forward(model, data)
                v.sync()
                time.sleep(1.0 / fps)
                t = (t + 1) % len(qpos)
    except RuntimeError as e:  # e.g. macOS without mjpython, or no OpenGL for the window
        raise QuasisimError(f"MuJoCo's viewer could not open: {e}") from None
