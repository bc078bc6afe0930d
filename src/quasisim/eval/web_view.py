"""A finished run in the browser: ``quasisim view RUN_DIR --web`` (3D, built on viser; works on a headless server).

What it shows, per frame of the run (a slider, play/pause and one-frame steps):

* the robot hand(s), the object, the table and the floor: the visible geoms (meshes and primitives) of the
  MuJoCo model in ``scene.xml``, posed by :func:`mujoco.mj_forward` on the frame's row of ``trajectory.npz``;
* the contacts MuJoCo finds at that pose (red points: ``data.contact`` positions);
* the robot's keypoints from ``rollout.npz`` (``all_keypoints``: the points matched to the human keypoints);
* the demo: its human keypoints and skeleton (blue) and its object pose (a translucent blue copy of the
  object). A run folder does not hold the demo's keypoints, only its name and hashes (``checkpoints/run.json``,
  ``controls.npz``); the demo is read from ``--demo`` or found by that name beside the run folder, above it,
  or in ``$QUASISIM_DATA``, and used only when its hash matches (:func:`find_demo`).

viser is an optional dependency (``pip install 'quasisim[viewer]'``); it is imported here only, and this
module only by the ``view`` command.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import socket
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import mujoco
import numpy as np

from quasisim.errors import InputError, QuasisimError
from quasisim.eval.export import SCENE_FILE, TRAJECTORY_FILE, load_export
from quasisim.files import MANIFEST, npz_member, open_npz, read_manifest

if TYPE_CHECKING:
    import viser

    from quasisim.data.demo import Demo

INSTALL_HINT = "pip install 'quasisim[viewer]'"
ROLLOUT_FILE = "rollout.npz"
SPEEDS = ("0.25x", "0.5x", "1x", "2x")
DEFAULT_HDRI = "city"  # viser's default environment map
FAST_HINT = "No shadows or environment lighting: smooth in a browser without a GPU (WebGL in software)"
PORT_WANTED = "a free port (choose another with --port)"
HOST_WANTED = "an address of this machine to listen on (e.g. 127.0.0.1, or 0.0.0.0 for all)"
DEMO_BLUE, ROBOT_ORANGE, CONTACT_RED = (40, 110, 235), (245, 150, 30), (230, 30, 30)


def import_viser() -> Any:
    """The viser module, or a one-line :class:`QuasisimError` saying how to install it."""
    try:
        import viser
    except ImportError:
        raise QuasisimError(f"the web viewer needs viser, which is not installed: {INSTALL_HINT}") from None
    return viser


# ---- the run folder ------------------------------------------------------------------------------


def check_run_dir(run_dir: Path) -> None:
    """:class:`InputError` unless ``run_dir`` is a finished run folder (scene.xml, trajectory.npz and a
    manifest that matches its files, as ``quasisim transfer`` and ``evaluate`` leave it)."""
    what = "a finished run folder (written by `quasisim transfer` or `quasisim evaluate`)"
    if not run_dir.is_dir():
        raise InputError(run_dir, None, what, "a file" if run_dir.exists() else "no such folder")
    for name in (SCENE_FILE, TRAJECTORY_FILE, MANIFEST):
        if not (run_dir / name).is_file():
            raise InputError(run_dir / name, None, f"the {name} of {what}", "no such file (not a finished run)")
    if read_manifest(run_dir) is None:
        raise InputError(
            run_dir / MANIFEST, None, f"the file list of {what}",
            "files missing or changed since it was written (an interrupted or running run?)",
        )  # fmt: skip


def robot_keypoints(run_dir: Path, n_frames: int) -> np.ndarray | None:
    """(T, K, 3) the rollout's robot keypoints (``rollout.npz`` ``all_keypoints``), or None when absent."""
    path = run_dir / ROLLOUT_FILE
    if not path.is_file():
        return None
    with open_npz(path, "rollout", "rollout file") as z:
        if "all_keypoints" not in z.files:
            return None
        kp = np.asarray(npz_member(z, "all_keypoints", path), dtype=np.float64)
    if kp.ndim != 3 or kp.shape[0] != n_frames or kp.shape[2] != 3:
        raise InputError(path, "all_keypoints", f"an array of shape ({n_frames}, K, 3)", str(kp.shape))
    return kp


def find_demo(run_dir: Path, explicit: Path | None, n_frames: int) -> tuple[Demo | None, str]:
    """The run's demo (for its keypoints and object pose) and a note on where it came from or why there is
    none. ``explicit`` (``--demo``) must exist and have the run's frame count; a found one must also be the
    recorded one and have that frame count (:class:`~quasisim.data.run_demo.RunDemos`)."""
    from quasisim.data.run_demo import RunDemos, recorded

    rec, demos = recorded(run_dir), RunDemos(check_mesh=False)
    if explicit is not None:
        demo = demos.load(explicit)
        if demo.n_frames != n_frames:
            raise InputError(explicit, "right_joints", f"the run's {n_frames} frames", f"{demo.n_frames} frames")
        note = f"demo: {explicit}"
        if rec.name and not demos.is_recorded(explicit, rec):
            note += f" (warning: not the demo the run was made from, {rec.name!r})"
        return demo, note
    if not rec.name:
        return None, "demo: not recorded in the run folder (pass --demo DEMO.npz to show it)"
    try:
        for path, demo in demos.matches(run_dir, rec):
            if demo.n_frames == n_frames:
                return demo, f"demo: {path}"
    except InputError as e:
        return None, f"demo: {e} (pass --demo DEMO.npz to show another)"
    return None, f"demo: {rec.name}.npz not found beside the run or in $QUASISIM_DATA (pass --demo DEMO.npz to show it)"


# ---- geometry and per-frame poses ----------------------------------------------------------------


@dataclass(frozen=True)
class GeomMesh:
    """One visible geom as a triangle mesh in its own frame, placed in its body's frame."""

    geom: int
    body: int
    vertices: np.ndarray
    faces: np.ndarray
    pos: np.ndarray
    quat: np.ndarray
    rgba: np.ndarray


def primitive_mesh(kind: int, size: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(vertices, faces) of a MuJoCo primitive geom of type ``kind`` and ``size``; None for height fields
    and SDFs (not drawn)."""
    import trimesh

    g = mujoco.mjtGeom
    if kind == g.mjGEOM_PLANE:
        hx, hy = (s if s > 0 else 2.0 for s in size[:2])  # 0: an infinite plane, drawn 4 m wide
        v = np.array([[-hx, -hy, 0.0], [hx, -hy, 0.0], [hx, hy, 0.0], [-hx, hy, 0.0]])
        return v, np.array([[0, 1, 2], [0, 2, 3]])
    if kind in (g.mjGEOM_SPHERE, g.mjGEOM_ELLIPSOID):
        m = trimesh.creation.icosphere(subdivisions=2)
        scale = size[:1] if kind == g.mjGEOM_SPHERE else size[:3]
        return np.asarray(m.vertices) * scale, np.asarray(m.faces)
    if kind == g.mjGEOM_CAPSULE:
        m = trimesh.creation.capsule(height=2 * size[1], radius=size[0], count=[16, 16])
    elif kind == g.mjGEOM_CYLINDER:
        m = trimesh.creation.cylinder(radius=size[0], height=2 * size[1], sections=24)
    elif kind == g.mjGEOM_BOX:
        m = trimesh.creation.box(extents=2 * size[:3])
    else:
        return None
    return np.asarray(m.vertices), np.asarray(m.faces)


def geom_meshes(model: mujoco.MjModel) -> list[GeomMesh]:
    """The visible geoms of ``model`` (groups 0-2 with some opacity; the collision copies in group 3 are
    transparent) as meshes."""
    out = []
    for g in range(model.ngeom):
        rgba = model.mat_rgba[model.geom_matid[g]] if model.geom_matid[g] >= 0 else model.geom_rgba[g]
        if model.geom_group[g] > 2 or rgba[3] <= 0:
            continue
        if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH:
            m = model.geom_dataid[g]
            v0, nv, f0, nf = model.mesh_vertadr[m], model.mesh_vertnum[m], model.mesh_faceadr[m], model.mesh_facenum[m]
            mesh = (model.mesh_vert[v0 : v0 + nv].astype(np.float64), model.mesh_face[f0 : f0 + nf].astype(np.int32))
        else:
            mesh = primitive_mesh(int(model.geom_type[g]), model.geom_size[g])
        if mesh is not None:
            body = int(model.geom_bodyid[g])
            out.append(GeomMesh(g, body, *mesh, model.geom_pos[g].copy(), model.geom_quat[g].copy(), np.array(rgba)))
    return out


@dataclass(frozen=True)
class Frames:
    """Everything the viewer draws per frame, computed once: body poses (T, nbody, 3 | 4, quaternions w x y
    z), contact positions (one (n, 3) array per frame), robot keypoints (T, K, 3) or None."""

    body_pos: np.ndarray
    body_quat: np.ndarray
    contacts: list[np.ndarray]
    robot_keypoints: np.ndarray | None


def pose_frames(model: mujoco.MjModel, qpos: np.ndarray, keypoints: np.ndarray | None) -> Frames:
    """Run :func:`mujoco.mj_forward` on each row of ``qpos``: the bodies' world poses and the contacts."""
    data = mujoco.MjData(model)
    pos, quat, contacts = [], [], []
    for q in qpos:
        data.qpos[:] = q
        mujoco.mj_forward(model, data)
        pos.append(data.xpos.copy())
        quat.append(data.xquat.copy())
        contacts.append(np.array([data.contact[i].pos for i in range(data.ncon)]).reshape(-1, 3))
    return Frames(np.array(pos), np.array(quat), contacts, keypoints)


def bone_segments(joints: np.ndarray) -> np.ndarray:
    """(B H, 2, 3) the skeleton's bones of the human keypoints ``joints`` (21 H, 3)."""
    from quasisim.data.demo import BONES, N_KEYPOINTS

    hands = joints.reshape(-1, N_KEYPOINTS, 3)
    return np.concatenate([np.stack([h[[a for a, _ in BONES]], h[[b for _, b in BONES]]], axis=1) for h in hands])


# ---- the server ----------------------------------------------------------------------------------


def check_port(host: str, port: int) -> None:
    """:class:`InputError` naming ``--host``/``--port`` when ``host`` is unknown or ``port`` is taken there."""
    try:
        family, kind, proto, _, addr = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
    except (socket.gaierror, UnicodeError, OverflowError) as e:
        raise InputError(None, "--host", HOST_WANTED, f"{host!r} ({e})") from None
    with socket.socket(family, kind, proto) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(addr)
        except OSError as e:
            if e.errno == errno.EADDRINUSE:
                raise InputError(f"{host}:{port}", "--port", PORT_WANTED, f"in use ({e.strerror})") from None
            raise InputError(None, "--host", HOST_WANTED, f"{host!r} ({e.strerror or e})") from None


@contextlib.contextmanager
def quiet() -> Iterator[None]:
    """Send what viser prints (with rich, to ``sys.stdout``) nowhere for the block."""
    with open(os.devnull, "w") as null, contextlib.redirect_stdout(null):
        yield


def url_of(host: str, port: int) -> str:
    """The address a browser on this machine (or at the end of an SSH tunnel) opens."""
    shown = "localhost" if host in ("", "0.0.0.0", "::") else f"[{host}]" if ":" in host else host
    return f"http://{shown}:{port}"


class WebView:
    """A viser server showing one run folder; :meth:`set_frame` poses the scene, a thread plays it."""

    def __init__(self, run_dir: Path, host: str, port: int, demo_path: Path | None = None) -> None:
        viser = import_viser()
        check_run_dir(run_dir)
        self.run_dir = run_dir
        self.model, qpos, self.fps = load_export(run_dir)
        self.n_frames = len(qpos)
        self.demo, self.demo_note = find_demo(run_dir, demo_path, self.n_frames)
        self.frames = pose_frames(self.model, qpos, robot_keypoints(run_dir, self.n_frames))
        check_port(host, port)
        with quiet():  # viser prints a banner of its own; serve() prints the one-line URL
            self.server = viser.ViserServer(host=host, port=port, label=f"quasisim: {run_dir.name}", verbose=False)
        if port and self.server.get_port() != port:  # taken between the check and the start
            with quiet():
                self.server.stop()
            raise InputError(f"{host}:{port}", "--port", PORT_WANTED, "in use")
        self.url = url_of(host, self.server.get_port())
        self.frame = -1  # nothing shown yet
        self._lock = threading.RLock()
        self._playing = threading.Event()
        self._stopped = threading.Event()
        self._speed = 1.0
        self.bodies: dict[int, viser.FrameHandle] = {}
        self._build_scene(viser)
        self._build_gui(viser)
        self.set_frame(0)
        self._player = threading.Thread(target=self._play_loop, name="quasisim-web-view-player", daemon=True)
        self._player.start()

    # -- scene --

    def _build_scene(self, viser: Any) -> None:
        scene = self.server.scene
        scene.set_up_direction("+z")
        meshes = geom_meshes(self.model)
        for b in sorted({m.body for m in meshes if m.body != 0}):
            self.bodies[b] = scene.add_frame(f"/bodies/b{b}", show_axes=False)
        self.mesh_nodes: list[str] = []  # the scene names of the model's geoms
        for m in meshes:
            name = f"/bodies/b{m.body}/g{m.geom}" if m.body else f"/world/g{m.geom}"
            self._add_mesh(name, m, tuple(int(c) for c in 255 * m.rgba[:3]), float(m.rgba[3]))
            self.mesh_nodes.append(name)
        self.contacts = scene.add_point_cloud(
            "/contacts", np.zeros((0, 3)), CONTACT_RED, point_size=0.008, point_shape="circle", precision="float32"
        )
        self.robot_kp = None
        if self.frames.robot_keypoints is not None:
            self.robot_kp = scene.add_point_cloud(
                "/robot_keypoints", self.frames.robot_keypoints[0], ROBOT_ORANGE, point_size=0.007,
                point_shape="circle", precision="float32",
            )  # fmt: skip
        self.fast_light = scene.add_light_ambient("/fast_light", intensity=1.5, visible=False)
        self.demo_nodes: list[Any] = []
        if self.demo is not None:
            self._build_demo(scene)
        self._place_camera()

    def _add_mesh(self, name: str, m: GeomMesh, color: tuple[int, ...], opacity: float) -> Any:
        return self.server.scene.add_mesh_simple(
            name, m.vertices.astype(np.float32), m.faces, color=color, opacity=None if opacity >= 1 else opacity,
            position=m.pos, wxyz=m.quat, side="double" if len(m.faces) <= 2 else "front",
        )  # fmt: skip

    def _build_demo(self, scene: Any) -> None:
        assert self.demo is not None
        obj = self.model.body("object").id
        self.demo_object = scene.add_frame("/demo/object", show_axes=False)
        for m in geom_meshes(self.model):
            if m.body == obj:
                self.demo_nodes.append(self._add_mesh(f"/demo/object/g{m.geom}", m, DEMO_BLUE, 0.35))
        joints = self.demo.human_joints
        self.demo_kp = scene.add_point_cloud(
            "/demo/keypoints", joints[0], DEMO_BLUE, point_size=0.008, point_shape="circle", precision="float32"
        )
        self.demo_bones = scene.add_line_segments("/demo/bones", bone_segments(joints[0]), DEMO_BLUE, thickness=0.002)
        self.demo_nodes += [self.demo_object, self.demo_kp, self.demo_bones]

    def _place_camera(self) -> None:
        """Look at the middle of the object's path from the front and above, far enough to see the path and
        a hand beside it (a hand's long approach may start out of view; the mouse zooms out)."""
        path = self.frames.body_pos[:, self.model.body("object").id]
        lo, hi = path.min(axis=0), path.max(axis=0)
        centre, size = (lo + hi) / 2, float(np.linalg.norm(hi - lo)) + 0.3  # m, about a hand's span
        self.server.initial_camera.look_at = tuple(centre)
        direction = np.array([0.6, -0.6, 0.5]) / np.linalg.norm([0.6, -0.6, 0.5])
        self.server.initial_camera.position = tuple(centre + direction * 1.6 * size)

    # -- gui --

    def _build_gui(self, viser: Any) -> None:
        gui, icon = self.server.gui, viser.Icon
        gui.add_markdown(self._header())
        self.slider = gui.add_slider("Frame", 0, max(self.n_frames - 1, 1), 1, 0, disabled=self.n_frames < 2)
        self.slider.on_update(lambda _: self.set_frame(int(self.slider.value)))
        self.play_button = gui.add_button("Play", icon=icon.PLAYER_PLAY)
        self.play_button.on_click(lambda _: self._playing.set())
        self.pause_button = gui.add_button("Pause", icon=icon.PLAYER_PAUSE)
        self.pause_button.on_click(lambda _: self.pause())
        self.prev_button = gui.add_button("Previous frame", icon=icon.PLAYER_TRACK_PREV)
        self.prev_button.on_click(lambda _: self.step(-1))
        self.next_button = gui.add_button("Next frame", icon=icon.PLAYER_TRACK_NEXT)
        self.next_button.on_click(lambda _: self.step(1))
        speed = gui.add_dropdown("Speed", SPEEDS, initial_value="1x")
        speed.on_update(lambda _: setattr(self, "_speed", float(speed.value.rstrip("x"))))
        self.readout = gui.add_markdown("")
        self.toggles: dict[str, Any] = {}
        with gui.add_folder("Show"):
            self._toggle(gui, "Contacts", [self.contacts])
            if self.robot_kp is not None:
                self._toggle(gui, "Robot keypoints", [self.robot_kp])
            if self.demo_nodes:
                self._toggle(gui, "Demo (keypoints, object)", self.demo_nodes)
            self.fast = gui.add_checkbox("Fast rendering", False, hint=FAST_HINT)
            self.fast.on_update(lambda _: self.set_fast(bool(self.fast.value)))

    def set_fast(self, fast: bool) -> None:
        """Without shadows and environment lighting (WebGL in software draws ~30 frames a second instead of 1-2)."""
        scene = self.server.scene
        scene.configure_environment_map(None if fast else DEFAULT_HDRI)
        scene.configure_default_lights(True, cast_shadow=not fast)
        self.fast_light.visible = fast  # stands in for the environment's light

    def _toggle(self, gui: Any, label: str, nodes: list[Any]) -> None:
        """A check box ``label`` that shows or hides ``nodes`` (kept in ``self.toggles``)."""
        box = self.toggles[label] = gui.add_checkbox(label, True)

        def flip(_: Any) -> None:
            for n in nodes:
                n.visible = bool(box.value)

        box.on_update(flip)

    def _header(self) -> str:
        lines = [f"**{self.run_dir.name}**: {self.n_frames} frames at {self.fps:g} fps"]
        try:
            m = json.loads((self.run_dir / "metrics.json").read_text())
            lines.append(
                f"R_err {m['R_err_deg']:.1f} deg, T_err {m['T_err_cm']:.2f} cm, MPJPE {m['MPJPE_mm']:.1f} mm, "
                f"strict success: {'yes' if m['success']['strict'] else 'no'}"
            )
        except (OSError, ValueError, KeyError, TypeError):
            pass
        legend = ["red: contacts"] + ["orange: robot keypoints"] * (self.robot_kp is not None)
        legend += ["blue: the demo (human keypoints, object)"] * (self.demo is not None)
        lines.append("; ".join(legend))
        lines.append(self.demo_note)
        return "\n\n".join(lines)

    # -- frames --

    def set_frame(self, t: int) -> None:
        """Pose everything at frame ``t`` (clipped to the run) and move the slider there."""
        t = int(np.clip(t, 0, self.n_frames - 1))
        f = self.frames
        with self._lock, self.server.atomic():
            if t == self.frame:  # e.g. the slider's callback when set_frame moved it
                return
            self.frame = t
            for b, h in self.bodies.items():
                h.position, h.wxyz = f.body_pos[t, b], f.body_quat[t, b]
            self.contacts.points = f.contacts[t].astype(np.float32)
            if self.robot_kp is not None and f.robot_keypoints is not None:
                self.robot_kp.points = f.robot_keypoints[t].astype(np.float32)
            if self.demo is not None:
                self.demo_object.position, self.demo_object.wxyz = self.demo.object_pos[t], self.demo.object_quat[t]
                self.demo_kp.points = self.demo.human_joints[t].astype(np.float32)
                self.demo_bones.points = bone_segments(self.demo.human_joints[t]).astype(np.float32)
            n = len(f.contacts[t])
            self.readout.content = (
                f"frame {t} / {self.n_frames - 1} ({t / self.fps:.2f} s); {n} contact{'s' * (n != 1)}"
            )
            if int(self.slider.value) != t:
                self.slider.value = t  # calls set_frame(t) again, which returns at once

    @property
    def playing(self) -> bool:
        return self._playing.is_set()

    def pause(self) -> None:
        """Stop playing; once this returns, the frame stays."""
        with self._lock:  # not while the player moves a frame
            self._playing.clear()

    def step(self, d: int) -> None:
        """Pause and move ``d`` frames (clipped)."""
        with self._lock:
            self.pause()
            self.set_frame(self.frame + d)

    def _play_loop(self) -> None:
        """While playing, the next frame (looping) at the run's frame rate times the speed."""
        while not self._stopped.is_set():
            if not self._playing.wait(timeout=0.2):
                continue
            with self._lock:
                if self._playing.is_set():
                    self.set_frame((self.frame + 1) % self.n_frames)
            self._stopped.wait(1.0 / (self.fps * self._speed))

    def stop(self) -> None:
        """Stop playing and serving."""
        self._stopped.set()
        self.pause()
        self._player.join(timeout=2.0)
        with quiet():  # viser says "Server stopped"
            self.server.stop()


def serve(run_dir: str | Path, host: str = "127.0.0.1", port: int = 8080, demo: str | Path | None = None) -> None:
    """Serve ``run_dir`` at ``host:port``: print the URL (one line on stdout, a hint on stderr) and serve
    until Ctrl-C."""
    run_dir = Path(run_dir)
    view = WebView(run_dir, host, port, None if demo is None else Path(demo))
    try:  # from the first line printed on: a client may connect and Ctrl-C may come at once
        print(view.url, flush=True)
        p = view.server.get_port()
        print(
            f"serving {run_dir} until Ctrl-C; {view.demo_note}; from another machine: ssh -L {p}:localhost:{p} "
            f"{socket.gethostname()}, then open http://localhost:{p}",
            file=sys.stderr,
            flush=True,
        )
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        view.stop()
