"""Offscreen MuJoCo rendering of the reference (human keypoints + demo object) beside a result rollout.

Rendering uses ``MUJOCO_GL`` (``egl`` by default, set by ``import quasisim``; ``osmesa`` also works).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np
from PIL import Image, ImageDraw, ImageFont
from tqdm import tqdm

from quasisim.data.demo import BONES, N_KEYPOINTS, Demo
from quasisim.targets.mujoco_target import MujocoModel
from quasisim.targets.scene import Scene

SKIN = np.array([0.93, 0.72, 0.6, 1.0], dtype=np.float32)
GHOST = np.array([0.2, 0.5, 0.95, 0.6], dtype=np.float32)


@dataclass(frozen=True)
class Camera:
    lookat: np.ndarray
    distance: float
    azimuth: float
    elevation: float


def default_camera(demo: Demo) -> Camera:
    """Look at the object's mean position from the side of the approaching hand; with two hands, from behind
    them (along the mean wrist-to-middle-knuckle direction), so that both stand beside the object."""
    obj = demo.object_pos.mean(axis=0)
    wrists = np.concatenate([demo.joints_of(s)[:, 0] for s in demo.sides])
    if len(demo.sides) > 1:
        j = demo.human_joints.reshape(demo.n_frames, -1, N_KEYPOINTS, 3)
        d = (j[:, :, 9] - j[:, :, 0]).mean(axis=(0, 1))  # forward: wrists to knuckles, away from the body
        az = float(np.degrees(np.arctan2(d[1], d[0])))
    else:
        d = obj - wrists.mean(axis=0)
        az = float(np.degrees(np.arctan2(d[1], d[0]))) + 90.0
    span = float(np.ptp(np.concatenate([demo.object_pos, wrists]), axis=0).max())
    return Camera(lookat=obj, distance=float(np.clip(0.45 + 0.8 * span, 0.5, 1.4)), azimuth=az, elevation=-25.0)


def _add_sphere(mujoco: Any, scn: Any, pos: np.ndarray, r: float, rgba: np.ndarray) -> None:
    if scn.ngeom >= scn.maxgeom:
        return
    g = scn.geoms[scn.ngeom]
    mujoco.mjv_initGeom(g, mujoco.mjtGeom.mjGEOM_SPHERE, np.array([r, 0, 0]), pos, np.eye(3).ravel(), rgba)
    scn.ngeom += 1


def _add_capsule(mujoco: Any, scn: Any, a: np.ndarray, b: np.ndarray, r: float, rgba: np.ndarray) -> None:
    if scn.ngeom >= scn.maxgeom:
        return
    g = scn.geoms[scn.ngeom]
    mujoco.mjv_initGeom(g, mujoco.mjtGeom.mjGEOM_CAPSULE, np.zeros(3), np.zeros(3), np.eye(3).ravel(), rgba)
    mujoco.mjv_connector(g, mujoco.mjtGeom.mjGEOM_CAPSULE, r, a, b)
    scn.ngeom += 1


def _add_skeleton(mujoco: Any, scn: Any, joints: np.ndarray, rgba: np.ndarray, r: float = 0.007) -> None:
    """Capsules and spheres of the human keypoint skeleton(s) ``joints`` (21 H, 3): H hands one after the other."""
    for hand in joints.reshape(-1, N_KEYPOINTS, 3):
        for a, b in BONES:
            _add_capsule(mujoco, scn, hand[a], hand[b], r, rgba)
        for p in hand:
            _add_sphere(mujoco, scn, p, r * 1.15, rgba)


class SideBySide:
    """Renders frame ``t`` of the reference and of a result with the same camera."""

    def __init__(
        self, scene: Scene, demo: Demo, width: int = 400, height: int = 300, camera: Camera | None = None
    ) -> None:
        self.mujoco = mujoco
        self.mm = MujocoModel(scene, visual=True)
        self.demo = demo
        self.renderer = mujoco.Renderer(self.mm.model, height=height, width=width, max_geom=4000)
        self.data = mujoco.MjData(self.mm.model)
        cam = camera or default_camera(demo)
        self.cam = mujoco.MjvCamera()
        self.cam.type = mujoco.mjtCamera.mjCAMERA_FREE
        self.cam.lookat[:] = cam.lookat
        self.cam.distance = cam.distance
        self.cam.azimuth = cam.azimuth
        self.cam.elevation = cam.elevation
        self.opt_ref = mujoco.MjvOption()
        self.opt_res = mujoco.MjvOption()
        # group 1: visual meshes (object, hand); group 3: collision shapes (hand without visual meshes)
        for opt in (self.opt_ref, self.opt_res):
            opt.geomgroup[:] = [1, 1, 0, 1, 0, 0]
        self._hide_hand_q = None

    def _render(
        self, qfull: np.ndarray, opos: np.ndarray, oquat: np.ndarray, joints: np.ndarray | None, ghost: bool
    ) -> np.ndarray:
        mujoco = self.mujoco
        self.mm.set_state(self.data, qfull, opos, oquat)
        self.renderer.update_scene(self.data, camera=self.cam, scene_option=self.opt_res)
        if joints is not None:
            _add_skeleton(mujoco, self.renderer.scene, joints, GHOST if ghost else SKIN, r=0.004 if ghost else 0.007)
        return self.renderer.render().copy()

    def reference(self, t: int) -> np.ndarray:
        far = np.zeros(self.mm.scene.n_dof)
        for sl in self.mm.scene.dof_slices:
            far[sl.start + 2] = -50.0  # park the robot hands out of view
        d = self.demo
        return self._render(far, d.object_pos[t], d.object_quat[t], d.human_joints[t], ghost=False)

    def result(
        self, t: int, qpos: np.ndarray, opos: np.ndarray, oquat: np.ndarray, show_human: bool = True
    ) -> np.ndarray:
        joints = self.demo.human_joints[t] if show_human else None
        return self._render(qpos[t], opos[t], oquat[t], joints, ghost=True)

    def close(self) -> None:
        self.renderer.close()


class RenderedFrames(Sequence[np.ndarray]):
    """The labelled side-by-side images [reference | result] (H, 2W, 3) of a rollout, rendered when read: a
    video is written frame by frame, so memory does not grow with the clip's length (a 10,000-frame clip held
    as images would take about 13 GB). Iterating shows a progress bar with ``progress``; :meth:`close` frees
    the renderer."""

    def __init__(
        self, scene: Scene, demo: Demo, qpos: np.ndarray, opos: np.ndarray, oquat: np.ndarray,
        labels: tuple[str, ...], width: int = 400, height: int = 300, progress: bool = False,
    ) -> None:  # fmt: skip
        self._r = SideBySide(scene, demo, width, height)
        self._rollout, self._labels, self._progress = (qpos, opos, oquat), labels, progress
        self._n, self._fps = demo.n_frames, demo.fps

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, t: int) -> np.ndarray:  # type: ignore[override]
        if not -self._n <= t < self._n:
            raise IndexError(f"frame {t} of {self._n}")
        t %= self._n
        img = np.concatenate([self._r.reference(t), self._r.result(t, *self._rollout)], axis=1)
        return label_frame(img, t, self._n, self._labels, self._fps)

    def __iter__(self) -> Iterator[np.ndarray]:
        for t in tqdm(range(self._n), desc="render", disable=not self._progress, leave=False):
            yield self[t]

    def close(self) -> None:
        self._r.close()


def label_frame(frame: np.ndarray, t: int, n: int, labels: tuple[str, ...], fps: float) -> np.ndarray:
    """``frame`` (H, W, 3) with a label burnt into each of its equally wide panels (e.g. ``("reference
    (demo)", "result (mujoco)")``) and frame ``t`` of ``n`` and its time into the top-right corner."""
    h, w = frame.shape[:2]
    font = ImageFont.load_default(size=max(12, h // 20))
    panel = w // len(labels)
    img = Image.fromarray(frame)
    draw = ImageDraw.Draw(img, "RGBA")
    texts = [((i * panel + 6, 6), lab) for i, lab in enumerate(labels)]
    stamp = f"frame {t} / {n - 1}   {t / fps:.2f} s"  # top right: the player's controls cover the bottom
    texts.append(((w - 6 - draw.textlength(stamp, font=font), 6), stamp))
    for xy, text in texts:
        box = draw.textbbox(xy, text, font=font)
        draw.rectangle((box[0] - 4, box[1] - 3, box[2] + 4, box[3] + 3), fill=(20, 20, 20, 170))
        draw.text(xy, text, font=font, fill=(255, 255, 255, 255))
    return np.asarray(img)


def annotate(frames: list[np.ndarray], labels: tuple[str, ...], fps: float) -> list[np.ndarray]:
    """:func:`label_frame` on every frame of ``frames``."""
    return [label_frame(f, t, len(frames), labels, fps) for t, f in enumerate(frames)]
