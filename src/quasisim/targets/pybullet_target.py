"""PyBullet target: the MuJoCo target's scene rebuilt from the parsed hand model with ``createMultiBody``.

PyBullet cannot load the Shadow MJCF, so the hand is assembled link by link from
:class:`~quasisim.assets.hand.HandModel`. Set-up (stated once, used for every figure):

* ``timeStep`` 0.5 ms (``PhysicsOptions.pybullet_dt``; ``round(1 / (fps dt))`` substeps per control frame,
  100 at 20 fps), 100 solver iterations, gravity -9.81 m/s^2 along z, one ``DIRECT`` client per target.
* Hand: a fixed world base, 3 prismatic links along world x, y, z and 3 revolute links about the axes of
  ``Placement.base_rot`` (intrinsic x-y-z); all are 1e-4 kg dummies except the last, the hand's root body. One
  link per hand body: a body without joints is a fixed link, a body with several joints a chain of dummy
  links. PyBullet rotates a link about its frame origin, MuJoCo a body about the joint anchor, so a body's
  link frame sits at its (last) joint anchor and its shapes, inertial frame, children and keypoints are
  shifted by minus the anchor. No hand self-collision; the hand collides with the object and the table.
* PD control per dof as in the MuJoCo target, applied as ``TORQUE_CONTROL`` at every physics step:
  ``tau = clip(kp (q* - q) - kv v) + kv qd* - damping v`` for finger joints (clip at
  +-``pd.joint_force_limit`` N m on the PD part, like MuJoCo's force range; ``pd.joint_damping``) and
  ``kp (q* - q) + kv (qd* - v)`` (N, N m) for the base (:func:`~quasisim.targets.base.pd_gains`); targets
  interpolated linearly within a frame, ``qd*`` the frame-to-frame target velocity
  (:func:`~quasisim.targets.base.pd_schedule`). Velocity terms are linearly implicit, as in MuJoCo's
  ``implicitfast``: ``v`` is the end-of-step velocity from ``(M + dt diag(kv + damping)) v = M qd + dt (kp
  (q* - q) + kv qd*)`` with the joint-space mass matrix ``M`` (``calculateMassMatrix``, every step), so the
  torque yields exactly that ``v`` up to gravity, Coriolis and contact forces. An explicit ``-kv qd``
  diverged on the base hinges (``kv dt / I > 2`` once the middle base angle tilts the outer hinge axes
  together; seen at 50 deg). At exactly +-90 deg (gimbal lock) their difference carries only the dummy
  inertia; ``Placement.base_rot`` is chosen per clip to stay far from it (tracking is tested up to 85 deg).
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
* Two hands (a demo with ``left_joints``): one multibody per hand as above, each with its own ``base_rot``
  and PD law (mass matrix per hand); the hands collide with the object and the table, not with each other
  (``setCollisionFilterPair``). States and targets are ``[right (6 + J), left (6 + J)]``.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from scipy.spatial import ConvexHull

from quasisim.assets.hand import HINGE, Geom, HandModel
from quasisim.errors import QuasisimError
from quasisim.rotations import np_mat_to_quat, np_quat_to_mat
from quasisim.targets.base import Observation, Target, feed_forward, pd_gains, pd_schedule
from quasisim.targets.grasp import strongest
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


@dataclass
class _HandBody:
    """One hand as a PyBullet multibody: its links (:func:`hand_links`), the PyBullet joint of each of its dofs
    (``dof_joint``, 6 + J, our order), its bodies' links and offsets, and the multibody's id once built."""

    hand: HandModel
    links: list[_Link]
    dof_joint: np.ndarray
    body_link: np.ndarray
    body_off: np.ndarray
    id: int = -1

    @classmethod
    def make(cls, scene: Scene, hand: HandModel, base_rot: np.ndarray) -> _HandBody:
        links, dof_link, body_link, body_off = hand_links(scene, hand, base_rot)
        return cls(hand, links, np.asarray(dof_link), body_link, body_off)

    @property
    def mm_order(self) -> np.ndarray:
        """PyBullet's dof order (= joint index order) -> ours."""
        return np.argsort(self.dof_joint)


class _PDLaw(NamedTuple):
    """One hand's PD law during one control frame, per dof in PyBullet's dof order (6 + J each): the multibody,
    its dof joints, the dofs' columns in the state vector, :class:`PDGains`' arrays, the feed-forward ``kv qd*``,
    the physics step ``dt`` (s) and the implicit diagonal ``dt (kv + damping)``."""

    body: int
    joints: list[int]
    cols: np.ndarray
    kp: np.ndarray
    kv: np.ndarray
    limit: np.ndarray
    damping: np.ndarray
    ff: np.ndarray
    dt: float
    implicit: np.ndarray


def hand_links(scene: Scene, hand: HandModel | None = None, base_rot: np.ndarray | None = None) -> tuple[
    list[_Link], list[int], np.ndarray, np.ndarray
]:  # fmt: skip
    """The hand as PyBullet links: ``hand`` on base frame ``base_rot`` (default: the scene's first placement).

    Returns:
        links; ``dof_link`` (6 + J): the link (= PyBullet joint index) of every hand dof in our order;
        ``body_link`` (B,): the link of every body; ``body_off`` (B, 3): the link frame in the body frame
        (link frame = body frame translated by ``body_off``, in body axes; m).
    """
    hand = scene.hands[0] if hand is None else hand
    base_rot = scene.base_rots[0] if base_rot is None else base_rot
    arm = hand.config.pd.joint_armature
    eye = np.eye(3)
    links = [_Link(parent=k, pos=np.zeros(3), rot=eye, joint="prismatic", axis=eye[k]) for k in range(3)]
    for k in range(3):  # the base hinges; the first link frame carries base_rot
        rot = base_rot if k == 0 else eye
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


class PybulletTarget(Target):
    """Roll PD targets out in PyBullet. See the module docstring for the set-up.

    Owns one ``DIRECT`` physics client (``self.client``); release it with :meth:`close` (or ``with``).
    :meth:`rollout_windows` is :class:`~quasisim.targets.base.Target`'s: one candidate after the other from
    ``saveState``.
    """

    name = "pybullet"

    def __init__(self, scene: Scene, threads: int = 1) -> None:
        """``threads`` is accepted for the common constructor (:func:`~quasisim.targets.make_target`); PyBullet
        steps one client on one thread."""
        if scene.physics.contact_margin != 0:
            raise QuasisimError(
                f"pybullet target: physics.contact_margin {scene.physics.contact_margin:g} m is MuJoCo's (a negative "
                "geom margin); expected 0 with --target pybullet (the sampler's 'thin' world: mujoco only)"
            )
        self.scene = scene
        self.pb = _pybullet()
        self.client = self.pb.connect(self.pb.DIRECT)
        self.parts = [_HandBody.make(scene, h, R) for h, R in zip(scene.hands, scene.base_rots, strict=True)]
        self._fresh = False
        self._files = itertools.count()
        self._build()

    # the first (one-hand: the only) hand's multibody
    @property
    def hand_id(self) -> int:
        return self.parts[0].id

    @property
    def links(self) -> list[_Link]:
        return self.parts[0].links

    @property
    def body_link(self) -> np.ndarray:
        return self.parts[0].body_link

    @property
    def body_off(self) -> np.ndarray:
        return self.parts[0].body_off

    @property
    def dof_joint(self) -> np.ndarray:
        return self.parts[0].dof_joint

    def _slices(self) -> list[tuple[_HandBody, slice]]:
        """Each hand's multibody and its columns in the state and target vectors."""
        return list(zip(self.parts, self.scene.dof_slices, strict=True))

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
            frames = [self._add_hand(part, tmp) for part in self.parts]
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
        for part, part_frames in zip(self.parts, frames, strict=True):
            self._hand_dynamics(part, part_frames)
        for a, b in itertools.combinations(self.parts, 2):  # the hands do not touch each other (as in MuJoCo)
            for i, j in itertools.product(range(-1, len(a.links)), range(-1, len(b.links))):
                pb.setCollisionFilterPair(a.id, b.id, i, j, enableCollision=0, **kw)
        self._fresh = True

    def _add_hand(self, part: _HandBody, tmp: Path) -> list[tuple[np.ndarray, np.ndarray]]:
        """Create ``part``'s multibody (sets ``part.id``); returns its links' principal inertia frames."""
        pb, kw, L = self.pb, self._kw(), part.links
        shape_ids = [self._shape_array(lk.shapes, tmp) if lk.shapes else -1 for lk in L]
        frames = [_principal(lk.inertia) for lk in L]
        jtype = {"fixed": pb.JOINT_FIXED, "revolute": pb.JOINT_REVOLUTE, "prismatic": pb.JOINT_PRISMATIC}
        part.id = pb.createMultiBody(
            baseMass=0.0, basePosition=[0, 0, 0], linkMasses=[lk.mass for lk in L],
            linkCollisionShapeIndices=shape_ids, linkVisualShapeIndices=[-1] * len(L),
            linkPositions=[lk.pos.tolist() for lk in L], linkOrientations=[_xyzw(lk.rot) for lk in L],
            linkInertialFramePositions=[lk.com.tolist() for lk in L],
            linkInertialFrameOrientations=[_xyzw(f[1]) for f in frames],
            linkParentIndices=[lk.parent for lk in L], linkJointTypes=[jtype[lk.joint] for lk in L],
            linkJointAxis=[lk.axis.tolist() for lk in L], **kw,
        )  # fmt: skip
        return frames

    def _hand_dynamics(self, part: _HandBody, frames: list[tuple[np.ndarray, np.ndarray]]) -> None:
        """Friction, inertia, joint limits of ``part``'s links; its velocity motors off."""
        pb, kw = self.pb, self._kw()
        for i, (lk, (moments, _)) in enumerate(zip(part.links, frames, strict=True)):
            self._dynamics(part.id, i, moments + 1e-12)  # strict triangle inequality for the rotor disc
            pb.changeDynamics(part.id, i, maxJointVelocity=MAX_JOINT_VELOCITY, **kw)
            if lk.limit is not None:
                lo, hi = lk.limit
                pb.changeDynamics(part.id, i, jointLowerLimit=lo, jointUpperLimit=hi, **kw)
        movable = [i for i, lk in enumerate(part.links) if lk.joint != "fixed"]
        zero = [0.0] * len(movable)
        pb.setJointMotorControlArray(part.id, movable, pb.VELOCITY_CONTROL, forces=zero, **kw)

    # ---- state -----------------------------------------------------------------------------------

    def set_state(self, qfull: np.ndarray, qvel: np.ndarray | None = None) -> None:
        """Reset the hands to ``qfull`` (D,) with velocity ``qvel`` (m/s, rad/s; default 0)."""
        qvel = np.zeros(len(qfull)) if qvel is None else qvel
        for part, sl in self._slices():
            for j, q, v in zip(part.dof_joint, qfull[sl], qvel[sl], strict=True):
                self.pb.resetJointState(part.id, int(j), float(q), float(v), **self._kw())

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
        """Measured hands' ``qfull`` (D,) and its velocity, in our dof order."""
        q, v = zip(*(self._joint_states(p.id, p.dof_joint.tolist()) for p in self.parts), strict=True)
        return (q[0], v[0]) if len(q) == 1 else (np.concatenate(q), np.concatenate(v))

    def _joint_states(self, body: int, joints: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """Positions and velocities of multibody ``body``'s ``joints``, in that order."""
        st = self.pb.getJointStates(body, joints, **self._kw())
        return np.array([s[0] for s in st]), np.array([s[1] for s in st])

    def body_poses(self, part: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """World poses of hand ``part``'s bodies from PyBullet's links: positions (B, 3) m, rotations (B, 3, 3)."""
        h = self.parts[part]
        st = self.pb.getLinkStates(h.id, h.body_link.tolist(), computeForwardKinematics=1, **self._kw())
        rot = np.stack([_mat(s[5]) for s in st])
        pos = np.array([s[4] for s in st]) - np.einsum("bij,bj->bi", rot, h.body_off)
        return pos, rot

    def keypoints(self) -> np.ndarray:
        """Keypoints (K, 3) of every hand from PyBullet's link poses and the hand models' offsets (m)."""
        out = []
        for i, part in enumerate(self.parts):
            pos, rot = self.body_poses(i)
            h = part.hand
            out.append(pos[h.kp_body] + np.einsum("kij,kj->ki", rot[h.kp_body], h.kp_pos))
        return out[0] if len(out) == 1 else np.concatenate(out)

    # ---- the Target interface ----------------------------------------------------------------------

    @property
    def dt(self) -> float:
        return float(self.scene.physics.pybullet_dt)

    def reset(self, q0: np.ndarray, qd0: np.ndarray | None = None) -> None:
        """Start a run: rebuild the world when a previous run used it (so runs are reproducible), put the hands
        at ``q0`` (D,) with velocity ``qd0`` (default 0) and the object at the demo's initial pose, at rest."""
        if not self._fresh:
            self._build()
        self._fresh = False
        self.set_state(np.asarray(q0, dtype=np.float64), qd0)
        self.set_object_pose(self.scene.object_pos0, self.scene.object_quat0)

    def observe(self) -> Observation:
        """As :meth:`Target.observe`; the object's velocities from ``getBaseVelocity`` (PyBullet's base frame
        is the object's inertial frame: the centre of mass's linear velocity, world axes)."""
        qpos, qvel = self.joint_states()
        opos, oquat = self.object_pose()
        v, w = self.pb.getBaseVelocity(self.obj_id, **self._kw())
        return {
            "qpos": qpos, "qvel": qvel, "obj_pos": opos, "obj_quat": oquat, "obj_vel": np.asarray(v, np.float64),
            "obj_angvel": np.asarray(w, np.float64), "keypoints": self.keypoints(),
        }  # fmt: skip

    def contact_forces(self, slots: int) -> np.ndarray:
        """As :meth:`Target.contact_forces`: per hand its ``slots`` strongest contact points with the object of
        the last ``stepSimulation`` (``getContactPoints``: ``normalForce``, ``lateralFriction1``,
        ``lateralFriction2``; N)."""
        kw = self._kw()
        out = []
        for part in self.parts:
            pts = self.pb.getContactPoints(bodyA=part.id, bodyB=self.obj_id, **kw)
            out.append(strongest(np.array([(c[9], c[10], c[12]) for c in pts], np.float64), slots))
        return np.stack(out)

    def body_contact_forces(self) -> np.ndarray:
        """As :meth:`Target.body_contact_forces`: the ``normalForce`` of every contact point of a hand with the
        object in the last ``stepSimulation`` (``getContactPoints``), summed per body: a point's ``linkIndexA`` is
        the link that carries its body's shapes (:attr:`_HandBody.body_link`)."""
        out = []
        for part in self.parts:
            body_of_link = {int(link): b for b, link in enumerate(part.body_link)}
            f = np.zeros(part.hand.n_bodies)
            for c in self.pb.getContactPoints(bodyA=part.id, bodyB=self.obj_id, **self._kw()):
                f[body_of_link[c[3]]] += c[9]
            out.append(f)
        return np.concatenate(out)

    def save_state(self) -> int:
        """``saveState``: the id of an in-memory copy of the world (free it with :meth:`release_state`)."""
        return int(self.pb.saveState(**self._kw()))

    def restore_state(self, state: object) -> None:
        self.pb.restoreState(stateId=state, **self._kw())

    def release_state(self, state: object) -> None:
        self.pb.removeState(state, **self._kw())

    def set_hands(self, q: np.ndarray, qd: np.ndarray) -> None:
        self.set_state(q, qd)

    def sync(self, obs: Observation) -> None:
        """The observed state: the hands' joints (``resetJointState``), the object's pose, then its centre of
        mass's velocities (``resetBaseVelocity``: PyBullet's base frame is the object's inertial frame)."""
        self.set_state(np.asarray(obs["qpos"], np.float64), np.asarray(obs["qvel"], np.float64))
        self.set_object_pose(obs["obj_pos"], obs["obj_quat"])
        v, w = (np.asarray(obs[k], np.float64).tolist() for k in ("obj_vel", "obj_angvel"))
        self.pb.resetBaseVelocity(self.obj_id, v, w, **self._kw())

    def advance(self, qa: np.ndarray, qb: np.ndarray) -> None:
        """One control frame (``substeps`` physics steps): the PD targets of :func:`pd_schedule` from ``qa`` to
        ``qb`` (D each) with their velocity fed forward; the PD law of the module docstring, per hand."""
        pb, kw = self.pb, self._kw()
        targets, _ = pd_schedule(qa, qb, self.substeps, self.scene.fps)
        laws = [self._pd_law(part, sl, qa, qb) for part, sl in self._slices()]
        for target in targets:
            for law in laws:
                tau = self._pd_torque(law, target[law.cols])
                pb.setJointMotorControlArray(law.body, law.joints, pb.TORQUE_CONTROL, forces=tau, **kw)
            pb.stepSimulation(**kw)

    def _pd_law(self, part: _HandBody, sl: slice, qa: np.ndarray, qb: np.ndarray) -> _PDLaw:
        """One hand's PD law for the frame from ``qa`` to ``qb``, every per-dof array in PyBullet's dof order."""
        g = pd_gains(part.hand, self.scene.physics.gain_scale)
        order = part.mm_order
        cols = np.arange(sl.start, sl.stop)[order]
        kp, kv, lim, damp = (x[order] for x in g)
        ff = feed_forward(kv, qa[cols], qb[cols], self.scene.fps)  # kv qd*
        dt = self.scene.physics.pybullet_dt
        return _PDLaw(part.id, part.dof_joint[order].tolist(), cols, kp, kv, lim, damp, ff, dt, dt * (kv + damp))

    def _pd_torque(self, law: _PDLaw, target: np.ndarray) -> list[float]:
        """A hand's PD torques (6 + J, PyBullet's dof order) towards its PD ``target`` (same order): the
        linearly implicit law of the module docstring, with ``M`` from ``calculateMassMatrix``."""
        q, qd = self._joint_states(law.body, law.joints)
        M = np.array(self.pb.calculateMassMatrix(law.body, q.tolist(), **self._kw()))
        e = law.kp * (target - q)
        A = M + np.diag(law.implicit)
        v = np.linalg.solve(A, M @ qd + law.dt * (e + law.ff))  # end-of-step velocity
        return (np.clip(e - law.kv * v, -law.limit, law.limit) + law.ff - law.damping * v).tolist()

    # ---- lifetime --------------------------------------------------------------------------------

    def close(self) -> None:
        """Disconnect the physics client (idempotent)."""
        if getattr(self, "client", None) is not None:
            with contextlib.suppress(Exception):
                self.pb.disconnect(physicsClientId=self.client)
            self.client = None

    def __del__(self) -> None:
        self.close()
