"""PyBullet target: the MuJoCo target's scene rebuilt from the parsed hand model with ``createMultiBody``.

PyBullet cannot load the Shadow MJCF, so the hand is assembled link by link from
:class:`~quasisim.assets.hand.HandModel`. Set-up (stated once, used for every figure):

* ``timeStep`` 0.5 ms (``PhysicsOptions.pybullet_dt``; ``round(1 / (fps dt))`` substeps per control frame,
  100 at 20 fps), 100 solver iterations, gravity -9.81 m/s^2 along z, one ``DIRECT`` client per target.
* Hand: a fixed world base, 3 prismatic links along world x, y, z and 3 revolute links about the axes of
  ``scene.base_rot`` (intrinsic x-y-z); all are 1e-4 kg dummies except the last, the hand's root body. One
  link per hand body: a body without joints is a fixed link, a body with several joints a chain of dummy
  links. PyBullet rotates a link about its frame origin, MuJoCo a body about the joint anchor, so a body's
  link frame sits at its (last) joint anchor and its shapes, inertial frame, children and keypoints are
  shifted by minus the anchor. No hand self-collision; the hand collides with the object and the table.
* PD control per dof as in the MuJoCo target, applied as ``TORQUE_CONTROL`` at every physics step:
  ``tau = clip(kp (q* - q) - kv v) + kv qd* - damping v`` for finger joints (clip at
  +-``pd.joint_force_limit`` N m on the PD part, like MuJoCo's force range; ``pd.joint_damping``) and
  ``kp (q* - q) + kv (qd* - v)`` (N, N m) for the base; targets interpolated linearly within a frame, ``qd*``
  the frame-to-frame target velocity. Velocity terms are linearly implicit, as in MuJoCo's
  ``implicitfast``: ``v`` is the end-of-step velocity from ``(M + dt diag(kv + damping)) v = M qd + dt (kp
  (q* - q) + kv qd*)`` with the joint-space mass matrix ``M`` (``calculateMassMatrix``, every step), so the
  torque yields exactly that ``v`` up to gravity, Coriolis and contact forces. An explicit ``-kv qd``
  diverged on the base hinges (``kv dt / I > 2`` once the middle base angle tilts the outer hinge axes
  together; seen at 50 deg). At exactly +-90 deg (gimbal lock) their difference carries only the dummy
  inertia; ``scene.base_rot`` is chosen per clip to stay far from it (tracking is tested up to 85 deg).
  PyBullet's default velocity motors are off; link linear/angular damping is 0.
* Joint armature (``pd.joint_armature``, kg m^2) has no PyBullet counterpart; it is approximated by a thin
  rotor disc on the link that a hinge with axis ``a`` moves: inertia ``armature (a a^T + I) / 2``, exactly
  +armature about the joint axis and +armature/2 about the perpendicular axes (``armature a a^T`` alone
  breaks the triangle inequality, which PyBullet's inverse dynamics rejects). Unlike MuJoCo's armature it is
  also felt by ancestor joints (about +0.01 kg m^2 on the base hinges of a 20-joint hand). Slide-joint
  armature is not modelled.
* Contacts: sliding friction ``scene.physics.friction`` on hand links, object and table (PyBullet multiplies
  the two coefficients: 1 x 1), spinning 0.005, rolling 0.0001; ``contactERP = dt / 0.02 s`` (penetration
  recovered over MuJoCo's default 20 ms; the default 0.2 at 0.5 ms pushes overlapping bodies apart at
  metres per second); collision margin 0.1 mm. Convex meshes (hand mesh geoms, the object's convex parts)
  are hulls loaded from temporary OBJ files (``createCollisionShapeArray`` takes meshes only as files).
* Object: one rigid body with the asset's mass, centre of mass and principal inertia. PyBullet reports a
  base's pose as its inertial frame; it is converted back to the object frame for the readout.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import ConvexHull

from quasisim.assets.hand import HINGE, Geom
from quasisim.errors import QuasisimError
from quasisim.rotations import np_mat_to_quat, np_quat_to_mat, sign_continuous
from quasisim.targets import TargetRollout
from quasisim.targets.scene import Scene

DUMMY_MASS = 1e-4  # kg
DUMMY_INERTIA = 1e-8  # kg m^2
SPINNING_FRICTION, ROLLING_FRICTION = 0.005, 0.0001
SOLVER_ITERATIONS = 100
MAX_JOINT_VELOCITY = 1000.0  # rad/s or m/s; PyBullet clamps at 100 by default
CONTACT_TIMECONST = 0.02  # s, penetration recovery time (MuJoCo's default solref); contactERP = dt / this
COLLISION_MARGIN = 1e-4  # m; PyBullet's default 1 mm on convex hulls would leave a visible gap

_PB: Any = None


def _pybullet() -> Any:
    """Import pybullet once, swallowing the build-time banner its C module prints to stderr."""
    global _PB
    if _PB is None:
        import ctypes
        import sys

        sys.stderr.flush()
        saved = os.dup(2)
        try:
            with open(os.devnull, "w") as null:
                os.dup2(null.fileno(), 2)
                import pybullet

                with contextlib.suppress(Exception):  # flush C stdio while it still points at devnull
                    ctypes.CDLL(None).fflush(None)
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        _PB = pybullet
    return _PB


def _xyzw(R: np.ndarray) -> list[float]:
    """Rotation matrix -> PyBullet quaternion (x, y, z, w)."""
    w, x, y, z = np_mat_to_quat(R)
    return [float(x), float(y), float(z), float(w)]


def _mat(q_xyzw: Any) -> np.ndarray:
    x, y, z, w = q_xyzw
    return np_quat_to_mat(np.array([w, x, y, z]))


def _rotor(armature: float, axis: np.ndarray) -> np.ndarray:
    """Inertia (3, 3) of a thin rotor disc with moment ``armature`` about the unit ``axis`` (kg m^2)."""
    return armature * (0.5 * np.eye(3) + 0.5 * np.outer(axis, axis))


def _principal(inertia: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Symmetric inertia (3, 3) -> principal moments (3,) and a right-handed frame (columns)."""
    evals, evecs = np.linalg.eigh(0.5 * (inertia + inertia.T))
    if np.linalg.det(evecs) < 0:
        evecs[:, 0] *= -1
    return evals, evecs


@dataclass
class _Shape:
    """One collision primitive in its link frame (m)."""

    type: str
    size: np.ndarray
    pos: np.ndarray
    rot: np.ndarray
    vertices: np.ndarray | None = None
    faces: np.ndarray | None = None


@dataclass
class _Link:
    """A PyBullet link: frame relative to its parent's link frame, joint, inertial frame, shapes."""

    parent: int  # PyBullet parent index: 0 = the fixed base, k = link k - 1
    pos: np.ndarray
    rot: np.ndarray
    joint: str = "fixed"  # "fixed", "revolute" or "prismatic"
    axis: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    mass: float = DUMMY_MASS
    com: np.ndarray = field(default_factory=lambda: np.zeros(3))
    inertia: np.ndarray = field(default_factory=lambda: DUMMY_INERTIA * np.eye(3))  # about com, link axes
    shapes: list[_Shape] = field(default_factory=list)
    limit: tuple[float, float] | None = None


def hand_links(scene: Scene) -> tuple[list[_Link], list[int], np.ndarray, np.ndarray]:
    """The hand as PyBullet links.

    Returns:
        links; ``dof_link`` (6 + J): the link (= PyBullet joint index) of every hand dof in our order;
        ``body_link`` (B,): the link of every body; ``body_off`` (B, 3): the link frame in the body frame
        (link frame = body frame translated by ``body_off``, in body axes; m).
    """
    hand = scene.hand
    arm = hand.config.pd.joint_armature
    eye = np.eye(3)
    links = [_Link(parent=k, pos=np.zeros(3), rot=eye, joint="prismatic", axis=eye[k]) for k in range(3)]
    for k in range(3):  # the base hinges; the first link frame carries base_rot
        rot = scene.base_rot if k == 0 else eye
        links.append(_Link(parent=3 + k, pos=np.zeros(3), rot=rot, joint="revolute", axis=eye[k]))
    dof_link = list(range(6)) + [-1] * hand.n_joints
    body_link = np.zeros(hand.n_bodies, dtype=int)
    body_off = np.zeros((hand.n_bodies, 3))
    body_link[0] = 5
    for b in range(1, hand.n_bodies):
        par = hand.body_parent[b]
        parent, prev = int(body_link[par]) + 1, body_off[par]  # PyBullet parent index, parent's link offset
        rot0, pos0 = np_quat_to_mat(hand.body_quat[b]), hand.body_pos[b]
        joints = hand.body_joints(b)
        if len(joints) == 0:
            links.append(_Link(parent=parent, pos=pos0 - prev, rot=rot0))
            body_link[b] = len(links) - 1
            continue
        # MuJoCo: body = parent * T(pos0, rot0) * prod_i [T(jp_i) motion_i T(-jp_i)]. Link i = that chain
        # up to motion_i, ending at anchor i: link_1 = parent_link * T(-prev) T(pos0, rot0) T(jp_1) motion_1,
        # link_i = link_{i-1} * T(jp_i - jp_{i-1}) motion_i, and body = last link * T(-jp_last).
        for i, j in enumerate(joints):
            jp = hand.joint_pos[j]
            if i == 0:
                pos, rot = pos0 - prev + rot0 @ jp, rot0
            else:
                pos, rot = jp - hand.joint_pos[joints[i - 1]], eye
            hinge = hand.joint_type[j] == HINGE
            lim = tuple(hand.joint_range[j]) if hand.joint_limited[j] else None
            link = _Link(parent=parent, pos=pos, rot=rot, joint="revolute" if hinge else "prismatic",
                         axis=hand.joint_axis[j].copy(), limit=lim)  # fmt: skip
            if hinge:
                link.inertia = link.inertia + _rotor(arm, link.axis)
            links.append(link)
            parent = len(links)
            dof_link[6 + j] = len(links) - 1
        body_link[b] = len(links) - 1
        body_off[b] = hand.joint_pos[joints[-1]]
    for b in range(hand.n_bodies):
        link, off = links[body_link[b]], body_off[b]
        Ri = np_quat_to_mat(hand.body_iquat[b])
        inertia = Ri @ np.diag(np.maximum(hand.body_inertia[b], 1e-9)) @ Ri.T
        if b > 0 and link.joint == "revolute":
            inertia = inertia + _rotor(arm, link.axis)
        link.mass, link.inertia = float(max(hand.body_mass[b], 1e-6)), inertia
        link.com = hand.body_ipos[b] - off
    for g in hand.collision_geoms():
        off = body_off[g.body]
        links[body_link[g.body]].shapes.append(_geom_shape(g, off))
    return links, dof_link, body_link, body_off


def _geom_shape(g: Geom, off: np.ndarray) -> _Shape:
    if g.type not in ("sphere", "capsule", "cylinder", "box", "mesh", "ellipsoid"):
        raise QuasisimError(f"pybullet target: geom '{g.name}' of type {g.type} is not supported")
    verts, faces = g.vertices, g.faces
    if g.type == "ellipsoid":  # convex hull of a point cloud on the ellipsoid
        n = np.arange(200) + 0.5
        phi, th = np.arccos(1 - 2 * n / 200), np.pi * (1 + 5**0.5) * n
        verts = np.stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)], 1) * g.size[:3]
        faces = ConvexHull(verts).simplices
    kind = "mesh" if verts is not None else g.type
    return _Shape(kind, g.size.copy(), g.pos - off, np_quat_to_mat(g.quat), verts, faces)


class PybulletTarget:
    """Roll PD targets out in PyBullet. See the module docstring for the set-up.

    Owns one ``DIRECT`` physics client (``self.client``); release it with :meth:`close` (or ``with``).
    """

    name = "pybullet"

    def __init__(self, scene: Scene) -> None:
        self.scene = scene
        self.pb = _pybullet()
        self.client = self.pb.connect(self.pb.DIRECT)
        self.links, dof_link, self.body_link, self.body_off = hand_links(scene)
        self.dof_joint = np.asarray(dof_link)
        self._mm_order = np.argsort(self.dof_joint)  # PyBullet's dof order (= joint index order) -> ours
        self._mm_inv = np.argsort(self._mm_order)
        self._fresh = False
        self._files = itertools.count()
        self._build()

    # ---- construction ----------------------------------------------------------------------------

    def _kw(self) -> dict[str, int]:
        return {"physicsClientId": self.client}

    def _shape_array(self, shapes: list[_Shape], tmp: Path) -> int:
        pb = self.pb
        types, radii, halves, lengths, files, pos, orn = [], [], [], [], [], [], []
        for s in shapes:
            r, h, half, fname = 0.0, 0.0, [0.0] * 3, ""
            if s.type == "mesh":
                fname = str(tmp / f"hull{next(self._files)}.obj")
                lines = [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in np.asarray(s.vertices)]
                lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in np.asarray(s.faces)]
                Path(fname).write_text("\n".join(lines) + "\n")
            elif s.type == "box":
                half = s.size[:3].tolist()
            elif s.type == "sphere":
                r = float(s.size[0])
            else:  # capsule: height = distance between the cap centres; cylinder: full height (see tests)
                r, h = float(s.size[0]), 2.0 * float(s.size[1])
            types.append(getattr(pb, f"GEOM_{s.type.upper()}"))
            radii.append(r)
            lengths.append(h)
            halves.append(half)
            files.append(fname)
            pos.append(s.pos.tolist())
            orn.append(_xyzw(s.rot))
        return pb.createCollisionShapeArray(
            shapeTypes=types, radii=radii, halfExtents=halves, lengths=lengths, fileNames=files,
            meshScales=[[1.0, 1.0, 1.0]] * len(shapes), collisionFramePositions=pos,
            collisionFrameOrientations=orn, **self._kw(),
        )  # fmt: skip

    def _dynamics(self, body: int, link: int, inertia: np.ndarray | None = None) -> None:
        kw = self._kw()
        self.pb.changeDynamics(
            body, link, lateralFriction=self.scene.physics.friction, spinningFriction=SPINNING_FRICTION,
            rollingFriction=ROLLING_FRICTION, linearDamping=0.0, angularDamping=0.0,
            collisionMargin=COLLISION_MARGIN, **kw,
        )  # fmt: skip
        if inertia is not None:  # a separate call: combined with the damping keywords it is silently ignored
            self.pb.changeDynamics(body, link, localInertiaDiagonal=inertia.tolist(), **kw)

    def _build(self) -> None:
        pb, kw, sc = self.pb, self._kw(), self.scene
        pb.resetSimulation(**kw)
        pb.setPhysicsEngineParameter(
            fixedTimeStep=sc.physics.pybullet_dt, numSolverIterations=SOLVER_ITERATIONS, numSubSteps=0,
            contactERP=min(1.0, sc.physics.pybullet_dt / CONTACT_TIMECONST), deterministicOverlappingPairs=1,
            enableFileCaching=0, **kw,
        )  # fmt: skip
        pb.setGravity(0.0, 0.0, -sc.physics.gravity, **kw)
        with tempfile.TemporaryDirectory(prefix="quasisim_pb_") as d:
            tmp = Path(d)
            shape_ids = [self._shape_array(lk.shapes, tmp) if lk.shapes else -1 for lk in self.links]
            frames = [_principal(lk.inertia) for lk in self.links]
            jtype = {"fixed": pb.JOINT_FIXED, "revolute": pb.JOINT_REVOLUTE, "prismatic": pb.JOINT_PRISMATIC}
            L = self.links
            self.hand_id = pb.createMultiBody(
                baseMass=0.0, basePosition=[0, 0, 0], linkMasses=[lk.mass for lk in L],
                linkCollisionShapeIndices=shape_ids, linkVisualShapeIndices=[-1] * len(L),
                linkPositions=[lk.pos.tolist() for lk in L], linkOrientations=[_xyzw(lk.rot) for lk in L],
                linkInertialFramePositions=[lk.com.tolist() for lk in L],
                linkInertialFrameOrientations=[_xyzw(f[1]) for f in frames],
                linkParentIndices=[lk.parent for lk in L], linkJointTypes=[jtype[lk.joint] for lk in L],
                linkJointAxis=[lk.axis.tolist() for lk in L], **kw,
            )  # fmt: skip
            obj = sc.obj
            self.obj_moments, self.obj_axes = _principal(np.asarray(obj.inertia, dtype=np.float64))
            self.obj_com = np.asarray(obj.com, dtype=np.float64)
            parts = [_Shape("mesh", np.zeros(3), np.zeros(3), np.eye(3), v, f) for v, f in obj.convex_parts()]
            self.obj_id = pb.createMultiBody(  # PyBullet reads the OBJ files here, not at shape creation
                baseMass=float(obj.mass), baseCollisionShapeIndex=self._shape_array(parts, tmp),
                basePosition=sc.object_pos0.tolist(), baseOrientation=_xyzw(np_quat_to_mat(sc.object_quat0)),
                baseInertialFramePosition=self.obj_com.tolist(),
                baseInertialFrameOrientation=_xyzw(self.obj_axes), **kw,
            )  # fmt: skip
        self._dynamics(self.obj_id, -1, np.maximum(self.obj_moments, 1e-9))
        t = sc.table
        tshape = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=t.half_size.tolist(), **kw)
        self.table_id = pb.createMultiBody(0.0, tshape, basePosition=t.center.tolist(), **kw)
        self._dynamics(self.table_id, -1)
        for i, (lk, (moments, _)) in enumerate(zip(self.links, frames, strict=True)):
            self._dynamics(self.hand_id, i, moments + 1e-12)  # strict triangle inequality for the rotor disc
            pb.changeDynamics(self.hand_id, i, maxJointVelocity=MAX_JOINT_VELOCITY, **kw)
            if lk.limit is not None:
                lo, hi = lk.limit
                pb.changeDynamics(self.hand_id, i, jointLowerLimit=lo, jointUpperLimit=hi, **kw)
        movable = [i for i, lk in enumerate(self.links) if lk.joint != "fixed"]
        zero = [0.0] * len(movable)
        pb.setJointMotorControlArray(self.hand_id, movable, pb.VELOCITY_CONTROL, forces=zero, **kw)
        self._fresh = True

    # ---- state -----------------------------------------------------------------------------------

    def set_state(self, qfull: np.ndarray, qvel: np.ndarray | None = None) -> None:
        """Reset the hand to ``qfull`` (6 + J) with velocity ``qvel`` (m/s, rad/s; default 0)."""
        qvel = np.zeros(len(qfull)) if qvel is None else qvel
        for j, q, v in zip(self.dof_joint, qfull, qvel, strict=True):
            self.pb.resetJointState(self.hand_id, int(j), float(q), float(v), **self._kw())

    def set_object_pose(self, pos: np.ndarray, quat: np.ndarray) -> None:
        """Place the object frame at ``pos`` (m), ``quat`` (w x y z), at rest."""
        R = np_quat_to_mat(quat)
        self.pb.resetBasePositionAndOrientation(
            self.obj_id, (np.asarray(pos) + R @ self.obj_com).tolist(), _xyzw(R @ self.obj_axes), **self._kw()
        )
        self.pb.resetBaseVelocity(self.obj_id, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], **self._kw())

    def object_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Object frame position (m) and quaternion (w x y z), from PyBullet's inertial-frame pose."""
        p, q = self.pb.getBasePositionAndOrientation(self.obj_id, **self._kw())
        R = _mat(q) @ self.obj_axes.T
        return np.asarray(p) - R @ self.obj_com, np_mat_to_quat(R)

    def joint_states(self) -> tuple[np.ndarray, np.ndarray]:
        """Measured hand ``qfull`` (6 + J) and its velocity, in our dof order."""
        st = self.pb.getJointStates(self.hand_id, self.dof_joint.tolist(), **self._kw())
        return np.array([s[0] for s in st]), np.array([s[1] for s in st])

    def mass_matrix(self, q: np.ndarray) -> np.ndarray:
        """Joint-space mass matrix (6 + J, 6 + J) of the hand at ``q`` in our dof order (kg, kg m, kg m^2)."""
        M = self.pb.calculateMassMatrix(self.hand_id, q[self._mm_order].tolist(), **self._kw())
        return np.asarray(M)[np.ix_(self._mm_inv, self._mm_inv)]

    def body_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """World poses of the hand bodies from PyBullet's links: positions (B, 3) m, rotations (B, 3, 3)."""
        links = self.body_link.tolist()
        st = self.pb.getLinkStates(self.hand_id, links, computeForwardKinematics=1, **self._kw())
        rot = np.stack([_mat(s[5]) for s in st])
        pos = np.array([s[4] for s in st]) - np.einsum("bij,bj->bi", rot, self.body_off)
        return pos, rot

    def keypoints(self) -> np.ndarray:
        """Hand keypoints (K, 3) from PyBullet's link poses and the hand model's offsets (m)."""
        pos, rot = self.body_poses()
        h = self.scene.hand
        return pos[h.kp_body] + np.einsum("kij,kj->ki", rot[h.kp_body], h.kp_pos)

    # ---- rollout ---------------------------------------------------------------------------------

    @property
    def substeps(self) -> int:
        return max(1, round(1.0 / (self.scene.fps * self.scene.physics.pybullet_dt)))

    def rollout(self, q_targets: np.ndarray, init_qvel: bool = True) -> TargetRollout:
        """Run the PD targets ``q_targets`` (T, 6 + J) from the demo's initial object pose.

        The hand starts at ``q_targets[0]`` (with the targets' initial velocity when ``init_qvel``); the
        world is rebuilt first when a previous rollout used it, so rollouts are reproducible.
        """
        q_targets = np.asarray(q_targets, dtype=np.float64)
        hand = self.scene.hand
        if q_targets.ndim != 2 or q_targets.shape[1] != 6 + hand.n_joints:
            raise ValueError(f"q_targets must have shape (T, {6 + hand.n_joints}), got {q_targets.shape}")
        T, fps = len(q_targets), self.scene.fps
        self.reset(q_targets[0], (q_targets[1] - q_targets[0]) * fps if init_qvel and T > 1 else None)
        qpos = np.zeros((T, 6 + hand.n_joints))
        opos, oquat = np.zeros((T, 3)), np.zeros((T, 4))
        kps = np.zeros((T, len(hand.kp_names), 3))
        t0 = time.perf_counter()
        for t in range(T):
            qpos[t], opos[t], oquat[t], kps[t] = self.frame_state()
            if t == T - 1:
                break
            self.advance(q_targets[t], q_targets[t + 1])
        return self.make_rollout(qpos, opos, oquat, kps, time.perf_counter() - t0)

    def reset(self, q0: np.ndarray, qd0: np.ndarray | None = None) -> None:
        """Start a run: rebuild the world when a previous run used it, put the hand at ``q0`` (6 + J) with
        velocity ``qd0`` (default 0) and the object at the demo's initial pose, at rest."""
        if not self._fresh:
            self._build()
        self._fresh = False
        self.set_state(np.asarray(q0, dtype=np.float64), qd0)
        self.set_object_pose(self.scene.object_pos0, self.scene.object_quat0)

    def frame_state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """What a rollout records per frame: hand ``qpos`` (6 + J), object position (3,) m and quaternion
        (4,) w x y z, all keypoints (K, 3) m."""
        qpos = self.joint_states()[0]
        opos, oquat = self.object_pose()
        return qpos, opos, oquat, self.keypoints()

    def _pd_law(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per-dof ``kp``, ``kv``, PD torque limit and joint damping (6 + J each) of the PD law."""
        hand = self.scene.hand
        pd = hand.config.pd
        kp = np.array([pd.base_pos.kp] * 3 + [pd.base_rot.kp] * 3 + [pd.joint.kp] * hand.n_joints)
        kv = np.array([pd.base_pos.kv] * 3 + [pd.base_rot.kv] * 3 + [pd.joint.kv] * hand.n_joints)
        lim = np.r_[np.full(6, np.inf), np.full(hand.n_joints, pd.joint_force_limit)]
        damp = np.r_[np.zeros(6), np.full(hand.n_joints, pd.joint_damping)]
        return kp, kv, lim, damp

    def advance(self, qa: np.ndarray, qb: np.ndarray) -> None:
        """One control frame (``substeps`` physics steps): PD targets interpolated linearly from ``qa`` to
        ``qb`` (6 + J each) with their velocity fed forward; the PD law of the module docstring."""
        pb, kw = self.pb, self._kw()
        fps, n, dt = self.scene.fps, self.substeps, self.scene.physics.pybullet_dt
        kp, kv, lim, damp = self._pd_law()
        D = dt * np.diag(kv + damp)
        joints, torque = self.dof_joint.tolist(), pb.TORQUE_CONTROL
        ff = kv * (qb - qa) * fps  # kv qd*
        for k in range(n):
            s = (k + 1) / n
            q, qd = self.joint_states()
            M = self.mass_matrix(q)
            e = kp * ((1 - s) * qa + s * qb - q)
            v = np.linalg.solve(M + D, M @ qd + dt * (e + ff))  # end-of-step velocity
            tau = np.clip(e - kv * v, -lim, lim) + ff - damp * v
            pb.setJointMotorControlArray(self.hand_id, joints, torque, forces=tau.tolist(), **kw)
            pb.stepSimulation(**kw)

    def make_rollout(
        self, qpos: np.ndarray, opos: np.ndarray, oquat: np.ndarray, kps: np.ndarray, wall_s: float
    ) -> TargetRollout:
        """A :class:`TargetRollout` of recorded frames (the arrays of :meth:`frame_state`, stacked over T)."""
        hand = self.scene.hand
        return TargetRollout(
            target=self.name,
            qpos=np.asarray(qpos),
            object_pos=np.asarray(opos),
            object_quat=sign_continuous(np.asarray(oquat)),
            keypoints=np.asarray(kps),
            kp_human=hand.kp_human.copy(),
            kp_metric=hand.kp_metric.copy(),
            dt=float(self.scene.physics.pybullet_dt),
            substeps=self.substeps,
            wall_s=wall_s,
        )

    # ---- lifetime --------------------------------------------------------------------------------

    def close(self) -> None:
        """Disconnect the physics client (idempotent)."""
        if getattr(self, "client", None) is not None:
            with contextlib.suppress(Exception):
                self.pb.disconnect(physicsClientId=self.client)
            self.client = None

    def __enter__(self) -> PybulletTarget:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        self.close()
