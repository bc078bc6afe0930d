"""A left hand from a right hand (and back): the reflection of a robot model across a plane.

Let ``M`` be the reflection across the plane normal to one axis (``x``: M = diag(-1, 1, 1)). A reflected
rigid frame ``M R`` would be left-handed, so every frame ``(R, p)`` of the model becomes the proper frame
``(M R M, M p)``: in each frame's own coordinates a point ``x`` becomes ``M x``. Since ``M M = I`` this
composes through the tree: the world pose of every body of the mirrored model is the reflected world
pose of the original's, for the same joint angles, once

* positions (bodies, geoms, sites, joints, centres of mass, cameras, lights, mesh vertices) map by ``M``;
* orientations (quaternions of bodies, geoms, sites, inertia frames, cameras) map by ``q -> (w, -M v)``:
  a rotation by angle a about axis n becomes a rotation by a about ``-M n``;
* hinge axes map by ``-M`` (an angular quantity), so the same positive angle turns the mirrored joint
  the mirrored way: joint ranges, ``ref``, tendons and actuators on joints stay as they are;
  slide axes map by ``M``;
* sizes of primitives and principal inertias are unchanged (their frames carry the reflection); mesh
  faces are reversed (a reflection turns the winding, and outward normals with it).

Which plane makes a right hand a left one depends on the model's frames: the hand YAML's ``mirror_axis``
(docs/hands.md). Any plane through the origin gives the same hand up to a rotation.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from quasisim.assets.model_edit import canonicalize, compile_spec, read_spec, set_mesh_data, write_mjcf

AXES = ("x", "y", "z")


def reflection(axis: str) -> np.ndarray:
    """(3, 3) reflection across the plane normal to ``axis`` (``x``, ``y`` or ``z``)."""
    M = np.eye(3)
    M[AXES.index(axis), AXES.index(axis)] = -1.0
    return M


def mirror_quat(q: np.ndarray, M: np.ndarray) -> np.ndarray:
    """The quaternion (w x y z) of ``M R M`` for the rotation ``R`` of ``q``."""
    q = np.asarray(q, dtype=np.float64)
    return np.concatenate([q[..., :1], -q[..., 1:] @ M.T], axis=-1)


def mirror_spec(spec: Any, axis: str) -> Any:
    """Reflect a canonical spec (:func:`quasisim.assets.model_edit.canonicalize`) across the plane normal
    to ``axis``, in place; returns it."""
    M = reflection(axis)

    def pos(v: Any) -> np.ndarray:
        return M @ np.asarray(v, dtype=np.float64)

    def quat(q: Any) -> np.ndarray:
        return mirror_quat(np.asarray(q), M)

    for b in spec.bodies[1:]:
        b.pos, b.quat, b.ipos, b.iquat = pos(b.pos), quat(b.quat), pos(b.ipos), quat(b.iquat)
    for j in spec.joints:
        j.pos = pos(j.pos)
        j.axis = -pos(j.axis) if j.type == mujoco.mjtJoint.mjJNT_HINGE else pos(j.axis)
    for e in [*spec.geoms, *spec.sites, *spec.cameras]:
        e.pos, e.quat = pos(e.pos), quat(e.quat)
    for lt in spec.lights:
        lt.pos, lt.dir = pos(lt.pos), pos(lt.dir)
    for m in spec.meshes:
        verts = np.asarray(m.uservert, dtype=np.float64).reshape(-1, 3) @ M.T
        faces = np.asarray(m.userface).reshape(-1, 3)[:, ::-1]
        set_mesh_data(m, verts, faces)
    return spec


def mirror_mjcf(src: str | Path, dst: str | Path, axis: str = "x") -> Path:
    """Write the mirror image of the MJCF/URDF model ``src`` as an MJCF file ``dst`` (meshes as STL beside it)."""
    spec = read_spec(Path(src))
    canonicalize(spec, compile_spec(spec, src), src)
    return write_mjcf(mirror_spec(spec, axis), dst)
