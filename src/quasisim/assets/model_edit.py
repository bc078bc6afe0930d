"""Edits of a robot model (MJCF or URDF) as MuJoCo specs: canonical form, scaling a subtree, writing MJCF.

Every edit works on a *canonical* spec: the spec whose bodies, joints, geoms, sites, cameras, lights and
meshes carry the values MuJoCo's compiler resolved (defaults, ``euler``/``axisangle``/``fromto``, frames,
``meshdir``, mesh re-centring, inertias from geoms, angle units). Such a spec compiles to the same model
as the original, and a geometric edit is then a plain change of numbers. Meshes become in-memory vertex
and face arrays (the compiled ones), so an edited model needs no mesh files until it is written out
(:func:`write_mjcf`, meshes as binary STL through trimesh).

The edits of a hand YAML (``edits:``, see docs/hands.md) are applied by :func:`quasisim.assets.hand.apply_edits`:

* ``{mirror: x}``: the reflection across the plane normal to x (or y, z) of every frame
  (:mod:`quasisim.assets.mirror`); a right hand becomes a left hand.
* ``{scale: s, body: NAME}``: the body ``NAME`` and everything below it scaled by ``s`` about the
  body's origin, at the same density: lengths times s (child offsets, geom and site positions and sizes,
  mesh vertices, joint positions, slide ranges, centres of mass), masses times s^3, inertias times s^5.
  The body's own place on its parent and all joint axes and hinge ranges are unchanged. Tendons are not
  rescaled (the hand model ignores them).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from quasisim.errors import InputError, captured_stderr, emit
from quasisim.files import save_text_atomic, write_atomic

QUAT = mujoco.mjtOrientation.mjORIENTATION_QUAT
NAN6 = [float("nan")] * 6


@dataclass(frozen=True)
class ModelEdit:
    """One edit of a hand's model (hand YAML ``edits:``): a mirror or a scaling of a subtree.

    Attributes:
        mirror: ``x``, ``y`` or ``z``: reflect the model across the plane normal to this axis.
        scale: factor for the subtree of ``body`` (lengths; masses s^3, inertias s^5).
        body: the root of the scaled subtree.
    """

    mirror: str = ""
    scale: float = 1.0
    body: str = ""

    def validate(self, path: str | Path | None, field: str) -> None:
        if self.mirror and (self.body or self.scale != 1.0):
            raise InputError(path, field, "either {mirror: AXIS} or {scale: S, body: NAME}", "both")
        if self.mirror and self.mirror not in ("x", "y", "z"):
            raise InputError(path, f"{field}.mirror", "one of x, y, z", repr(self.mirror))
        if not self.mirror and (not self.body or not self.scale > 0):
            raise InputError(path, field, "{mirror: AXIS} or {scale: S > 0, body: NAME}", str(self))


def read_spec(path: Path) -> Any:
    """The spec of an MJCF or URDF file; an :class:`InputError` naming the file when MuJoCo cannot parse it."""
    try:
        with captured_stderr() as said:  # MuJoCo prints warnings that come with its errors: fold them in
            spec = mujoco.MjSpec.from_file(str(path))
    except Exception as e:
        extra = f" (MuJoCo: {said.said()})" if said.said() else ""
        got = " ".join(str(e).split()) + extra
        raise InputError(path, None, "an MJCF or URDF file MuJoCo can parse", got) from None
    emit(said)
    spec.compiler.balanceinertia = True
    spec.compiler.fusestatic = False
    spec.compiler.discardvisual = False
    return spec


def compile_spec(spec: Any, path: str | Path) -> Any:
    """Compile ``spec`` (read from ``path``); an :class:`InputError` naming the file when it fails."""
    try:
        with captured_stderr() as said:
            model = spec.compile()
    except Exception as e:
        extra = f" (MuJoCo: {said.said()})" if said.said() else ""
        raise InputError(path, None, "a model MuJoCo can compile", " ".join(str(e).split()) + extra) from None
    emit(said)
    return model


# ---- canonical form -------------------------------------------------------------------------------


def canonicalize(spec: Any, model: Any, path: str | Path | None = None) -> None:
    """Write the compiled values of ``model`` (compiled from ``spec``) into ``spec``'s elements (see module doc);
    ``path`` names the model in errors."""
    _refuse_unsupported(spec, path)
    for f in spec.frames:
        f.pos, f.quat, f.alt.type = [0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], QUAT
    for b in spec.bodies[1:]:
        i = model.bind(b).id
        b.pos, b.quat, b.alt.type = model.body_pos[i], model.body_quat[i], QUAT
        b.mass, b.ipos, b.iquat, b.inertia = (
            model.body_mass[i],
            model.body_ipos[i],
            model.body_iquat[i],
            model.body_inertia[i],
        )
        b.ialt.type, b.fullinertia, b.explicitinertial = QUAT, NAN6, True
    for j in spec.joints:
        i = model.bind(j).id
        j.pos, j.axis = model.jnt_pos[i], model.jnt_axis[i]
    for g in spec.geoms:
        i = model.bind(g).id
        g.pos, g.quat, g.alt.type, g.fromto = model.geom_pos[i], model.geom_quat[i], QUAT, NAN6
        if g.type != mujoco.mjtGeom.mjGEOM_MESH:
            g.size, g.meshname = model.geom_size[i], ""  # a primitive fitted to a mesh keeps its fitted size
    for s in spec.sites:
        i = model.bind(s).id
        s.pos, s.quat, s.alt.type, s.fromto = model.site_pos[i], model.site_quat[i], QUAT, NAN6
        s.size = model.site_size[i]
    for c in spec.cameras:
        i = model.bind(c).id
        c.pos, c.quat, c.alt.type = model.cam_pos[i], model.cam_quat[i], QUAT
    for lt in spec.lights:
        i = model.bind(lt).id
        lt.pos, lt.dir = model.light_pos[i], model.light_dir[i]
    for m in spec.meshes:
        verts, faces = compiled_mesh(model, model.bind(m).id)
        set_mesh_data(m, verts, faces)


def compiled_mesh(model: Any, i: int) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) and faces (F, 3) of compiled mesh ``i``, in the mesh's compiled frame."""
    va, vn = model.mesh_vertadr[i], model.mesh_vertnum[i]
    fa, fn = model.mesh_faceadr[i], model.mesh_facenum[i]
    return np.array(model.mesh_vert[va : va + vn], dtype=np.float64), np.array(model.mesh_face[fa : fa + fn])


def set_mesh_data(mesh: Any, verts: np.ndarray, faces: np.ndarray) -> None:
    """Make ``mesh`` an in-memory mesh with ``verts`` and ``faces`` (no file, scale 1, no reference frame)."""
    mesh.file, mesh.content_type = "", ""
    mesh.scale, mesh.refpos, mesh.refquat = [1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]
    mesh.uservert = np.asarray(verts, dtype=np.float64).ravel().tolist()
    mesh.userface = np.asarray(faces, dtype=np.int64).ravel().tolist()
    mesh.usernormal, mesh.usertexcoord, mesh.userfacenormal, mesh.userfacetexcoord = [], [], [], []


def _refuse_unsupported(spec: Any, path: str | Path | None) -> None:
    """Elements whose geometry the edits do not transform: refuse rather than produce a wrong model."""
    what = {
        "flexes": len(spec.flexes),
        "skins": len(spec.skins),
        "height fields": len(spec.hfields),
        "connect/weld equality constraints": sum(
            e.type in (mujoco.mjtEq.mjEQ_CONNECT, mujoco.mjtEq.mjEQ_WELD) for e in spec.equalities
        ),
        "site-transmission actuators": sum(a.trntype == mujoco.mjtTrn.mjTRN_SITE for a in spec.actuators),
        "keyframes": len(spec.keys) if any(j.type in _FREE_BALL for j in spec.joints) else 0,
    }
    found = [k for k, n in what.items() if n]
    if found:
        raise InputError(path, None, "a model without " + ", ".join(found) + " (model edits do not transform them)")


_FREE_BALL = (mujoco.mjtJoint.mjJNT_FREE, mujoco.mjtJoint.mjJNT_BALL)


# ---- scaling -------------------------------------------------------------------------------------


def scale_subtree(spec: Any, root: Any, s: float) -> None:
    """Scale ``root`` and its descendants by ``s`` about ``root``'s origin (canonical spec; see module doc)."""
    bodies = [root, *root.find_all(mujoco.mjtObj.mjOBJ_BODY)]
    scaled_meshes: dict[str, str] = {}
    for b in bodies:
        if b is not root:
            b.pos = np.asarray(b.pos) * s
        b.ipos, b.mass, b.inertia = np.asarray(b.ipos) * s, b.mass * s**3, np.asarray(b.inertia) * s**5
        for j in b.joints:
            j.pos = np.asarray(j.pos) * s
            if j.type == mujoco.mjtJoint.mjJNT_SLIDE:
                j.range = np.asarray(j.range) * s
        for g in b.geoms:
            g.pos = np.asarray(g.pos) * s
            if g.type == mujoco.mjtGeom.mjGEOM_MESH:
                g.meshname = _scaled_mesh(spec, g.meshname, s, scaled_meshes)
            else:
                g.size = np.asarray(g.size) * s
        for x in b.sites:
            x.pos, x.size = np.asarray(x.pos) * s, np.asarray(x.size) * s
        for c in [*b.cameras, *b.lights]:
            c.pos = np.asarray(c.pos) * s


def _scaled_mesh(spec: Any, name: str, s: float, done: dict[str, str]) -> str:
    """The name of a copy of mesh ``name`` scaled by ``s`` (added once; the original may be used elsewhere)."""
    if name not in done:
        src = spec.mesh(name)
        new = spec.add_mesh(name=f"{name}_scaled{s:g}", inertia=src.inertia, maxhullvert=src.maxhullvert)
        verts = np.asarray(src.uservert, dtype=np.float64).reshape(-1, 3) * s
        set_mesh_data(new, verts, np.asarray(src.userface).reshape(-1, 3))
        done[name] = new.name
    return done[name]


# ---- writing -------------------------------------------------------------------------------------


def write_mjcf(spec: Any, path: str | Path) -> Path:
    """Write an edited ``spec`` as an MJCF file at ``path`` with its meshes as binary STL files in a
    ``<stem>_meshes/`` folder beside it (trimesh); textures stay where the original model has them."""
    import trimesh

    path = Path(path)
    out = spec.copy()
    mesh_dir = path.parent / f"{path.stem}_meshes"
    mesh_dir.mkdir(parents=True, exist_ok=True)
    for m in out.meshes:
        verts = np.asarray(m.uservert, dtype=np.float64).reshape(-1, 3)
        faces = np.asarray(m.userface, dtype=np.int64).reshape(-1, 3)
        fname = re.sub(r"[^A-Za-z0-9_.-]", "_", m.name) + ".stl"
        tm = trimesh.Trimesh(verts, faces, process=False)
        write_atomic(mesh_dir / fname, lambda p, tm=tm: tm.export(p, file_type="stl"))
        m.file, m.uservert, m.userface = fname, [], []
    if out.texturedir or any(t.file for t in out.textures):
        out.texturedir = str((Path(spec.modelfiledir or ".") / (spec.texturedir or "")).resolve())
    out.meshdir = out.compiler.meshdir = mesh_dir.name
    out.modelfiledir = str(path.parent.resolve())  # to_xml compiles: meshes are read from the new place
    return save_text_atomic(path, out.to_xml())
