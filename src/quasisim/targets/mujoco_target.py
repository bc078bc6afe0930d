"""MuJoCo target: the hand(s) on PD-driven floating bases, the object as convex pieces, a finite table.

Set-up (stated once, used for every figure):

* ``timestep`` 2 ms (``PhysicsOptions.mujoco_dt``), ``implicitfast`` integrator, elliptic friction cones,
  ``impratio`` 10, sliding friction 1 on every contact, gravity -9.81 m/s^2 along z.
* Hand base: 3 slide joints along world x, y, z and 3 hinges about the axes of ``Placement.base_rot``
  (intrinsic x-y-z), all on the hand's root body. Finger joints as in the hand model, with the hand
  config's damping and armature. No hand self-collision; the hand collides with the object and the table.
* Two hands (a demo with ``left_joints``): each hand as above under its own name prefix (``rhand/``,
  ``lhand/``; one hand: ``hand/``) with its own ``base_rot``; both collide with the object and the table,
  not with each other. The control vector and ``qpos`` of the hands are ``[right (6 + J), left (6 + J)]``.
* PD control per degree of freedom, ``tau = kp (q* - q) + kv (qd* - qd)``: one position actuator
  (gain ``kp``, bias ``-kp q - kv qd``) plus one feed-forward actuator (``kv qd*``); gains, force limits and
  joint damping of :func:`~quasisim.targets.base.pd_gains`. Within a control frame the targets follow
  :func:`~quasisim.targets.base.pd_schedule` (interpolated linearly, ``qd*`` the frame-to-frame velocity).
* Object: free body with the asset's mass, centre of mass and inertia; collision from its convex parts.

:class:`MujocoTarget` implements :class:`~quasisim.targets.base.Target`: a run is one ``MjData``; its state is
``mj_getState(..., mjSTATE_FULLPHYSICS)`` plus ``qacc_warmstart``; candidate windows run in ``mujoco.rollout``
on a copy of the scene with ``framepos`` sensors on the metric keypoint sites.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any

import mujoco
import numpy as np

from quasisim.assets.hand import HandModel
from quasisim.errors import QuasisimError
from quasisim.rotations import np_mat_to_quat, np_quat_to_mat
from quasisim.targets.base import Observation, Prediction, Prune, Target, pd_gains, pd_schedule
from quasisim.targets.grasp import cone_loads, strongest
from quasisim.targets.scene import Scene

if TYPE_CHECKING:
    from quasisim.assets.object import ObjectAsset

HAND_PREFIX = "hand/"  # the one hand of a one-hand scene (Scene.prefixes: two hands are rhand/ and lhand/)
# collision bits: hand (type 2, affinity 1) touches object/table (type 1, affinity 3), not itself.
HAND_CONTYPE, HAND_CONAFFINITY = 2, 1
# MuJoCo's warnings that mean the simulation went wrong (counted per run in ``data.warning``)
UNSTABLE_WARNINGS = ("BADQPOS", "BADQVEL", "BADQACC", "BADCTRL", "CONTACTFULL", "CNSTRFULL")
STATE_SPEC = int(mujoco.mjtState.mjSTATE_FULLPHYSICS)  # what save_state copies (with qacc_warmstart)
WORLD_CONTYPE, WORLD_CONAFFINITY = 1, 3


def _geom_type(name: str) -> Any:
    return getattr(mujoco.mjtGeom, f"mjGEOM_{name.upper()}")


def build_spec(scene: Scene, visual: bool = True) -> Any:
    """An ``mujoco.MjSpec`` of the scene (compile with ``.compile()``): options, world (floor, table),
    the hand on its floating base, the object, the PD actuators."""
    spec = mujoco.MjSpec()
    spec.modelname = "quasisim_" + "+".join(h.name for h in scene.hands)
    spec.compiler.degree = False
    spec.option.timestep = scene.physics.mujoco_dt
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    spec.option.impratio = 10.0
    spec.option.gravity = [0.0, 0.0, -scene.physics.gravity]
    spec.visual.global_.offwidth = 1280
    spec.visual.global_.offheight = 960
    spec.visual.quality.shadowsize = 2048
    fr = [scene.physics.friction, 0.005, 0.0001]
    _add_world(spec, scene, visual, fr)
    for hand, base_rot, prefix in zip(scene.hands, scene.base_rots, scene.prefixes, strict=True):
        bodies = _add_hand_bodies(spec, hand, base_rot, prefix)
        _add_hand_geoms(spec, hand, prefix, bodies, visual, fr, scene.physics.contact_margin)
    _add_object(spec, scene, visual, fr)
    for hand, prefix in zip(scene.hands, scene.prefixes, strict=True):
        _add_actuators(spec, hand, prefix, scene.physics.gain_scale)
    return spec


def hand_dof_names(hand: HandModel, prefix: str) -> list[str]:
    """The MJCF joint names of one hand's 6 base coordinates and its joints, in control order."""
    names = [f"{prefix}base_t{a}" for a in "xyz"] + [f"{prefix}base_r{a}" for a in "xyz"]
    return names + [prefix + n for n in hand.joint_names]


def dof_names(scene: Scene) -> list[str]:
    """The MJCF joint names of the whole control vector (every hand, in order)."""
    return [n for h, p in zip(scene.hands, scene.prefixes, strict=True) for n in hand_dof_names(h, p)]


def _add_world(spec: Any, scene: Scene, visual: bool, fr: list[float]) -> None:
    """Sky (visual only), light, floor (no collision) and the table box."""
    if visual:
        spec.add_texture(
            name="sky",
            type=mujoco.mjtTexture.mjTEXTURE_SKYBOX,
            builtin=mujoco.mjtBuiltin.mjBUILTIN_GRADIENT,
            rgb1=[0.75, 0.82, 0.9],
            rgb2=[0.95, 0.96, 0.98],
            width=64,
            height=64,
        )
    wb = spec.worldbody
    wb.add_light(
        pos=[0, 0, scene.table.top + 2.0],
        dir=[0, 0, -1],
        type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL,
        diffuse=[0.7, 0.7, 0.7],
    )
    floor_z = 0.0
    wb.add_geom(
        name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[5, 5, 0.1], pos=[0, 0, floor_z],
        rgba=[0.85, 0.85, 0.82, 1], contype=0, conaffinity=0,
    )  # fmt: skip
    t = scene.table
    wb.add_geom(
        name="table", type=mujoco.mjtGeom.mjGEOM_BOX, size=t.half_size.tolist(), pos=t.center.tolist(),
        rgba=[0.62, 0.5, 0.38, 1], contype=WORLD_CONTYPE, conaffinity=WORLD_CONAFFINITY, friction=fr,
    )  # fmt: skip


def _add_hand_bodies(spec: Any, hand: HandModel, base_rot: np.ndarray, prefix: str) -> list[Any]:
    """The hand's bodies and joints below a root on 3 slide + 3 hinge base joints about the axes of
    ``base_rot`` (3, 3), named with ``prefix``; returns the bodies."""
    damping, arm, wb = pd_gains(hand).damping, hand.config.pd.joint_armature, spec.worldbody
    bodies: list[Any] = []
    for b in range(hand.n_bodies):
        if b == 0:
            body = wb.add_body(name=prefix + hand.body_names[0], pos=[0, 0, 0], quat=np_mat_to_quat(base_rot).tolist())
            for k, ax in enumerate(("x", "y", "z")):
                body.add_joint(
                    name=f"{prefix}base_t{ax}", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=base_rot[k].tolist(),
                    limited=False, armature=0.0, damping=0.0,
                )  # fmt: skip
            for k, ax in enumerate(("x", "y", "z")):
                e = np.eye(3)[k]
                body.add_joint(
                    name=f"{prefix}base_r{ax}", type=mujoco.mjtJoint.mjJNT_HINGE, axis=e.tolist(),
                    limited=False, armature=0.0, damping=0.0,
                )  # fmt: skip
        else:
            parent = bodies[hand.body_parent[b]]
            body = parent.add_body(
                name=prefix + hand.body_names[b], pos=hand.body_pos[b].tolist(), quat=hand.body_quat[b].tolist()
            )
            for j in hand.body_joints(b):
                body.add_joint(
                    name=prefix + hand.joint_names[j],
                    type=mujoco.mjtJoint.mjJNT_HINGE if hand.joint_type[j] == 0 else mujoco.mjtJoint.mjJNT_SLIDE,
                    axis=hand.joint_axis[j].tolist(), pos=hand.joint_pos[j].tolist(),
                    limited=bool(hand.joint_limited[j]), range=hand.joint_range[j].tolist(),
                    damping=float(damping[6 + j]), armature=arm,
                )  # fmt: skip
        if hand.body_mass[b] > 0 or b == 0 or len(hand.body_joints(b)):
            # moving bodies need positive mass and inertia; massless fixed links (URDF frames) stay massless
            body.mass = float(max(hand.body_mass[b], 1e-6))
            body.ipos = hand.body_ipos[b].tolist()
            body.iquat = hand.body_iquat[b].tolist()
            body.inertia = np.maximum(hand.body_inertia[b], 1e-9).tolist()
            body.explicitinertial = True
        bodies.append(body)
    return bodies


def _add_hand_geoms(
    spec: Any, hand: HandModel, prefix: str, bodies: list[Any], visual: bool, fr: list[float], margin: float = 0.0
) -> None:
    """Collision geoms (and visual ones when ``visual``; collision margin ``margin``, m) and the keypoint sites of
    the hand (names start with ``prefix``)."""
    for gi, g in enumerate(hand.geoms):
        if not g.collision and not visual:
            continue
        kw: dict[str, Any] = {
            "name": f"{prefix}{g.name or gi}",
            "type": _geom_type(g.type),
            "size": g.size.tolist(),
            "pos": g.pos.tolist(),
            "quat": g.quat.tolist(),
            "rgba": g.rgba.tolist(),
        }
        if g.type == "mesh":
            mname = f"{prefix}mesh{gi}"
            spec.add_mesh(name=mname, uservert=g.vertices.ravel().tolist(), userface=g.faces.ravel().tolist())
            kw["meshname"] = mname
        if g.collision:
            kw.update(contype=HAND_CONTYPE, conaffinity=HAND_CONAFFINITY, friction=fr, group=3, condim=3,
                      margin=margin)  # fmt: skip
            if visual and any(not h.collision for h in hand.geoms if h.body == g.body):
                kw["rgba"] = [0, 0, 0, 0]  # the body has visual meshes; keep collision shapes invisible
        else:
            kw.update(contype=0, conaffinity=0, group=1)
        bodies[g.body].add_geom(**kw)
    for k, name in enumerate(hand.kp_names):
        bodies[hand.kp_body[k]].add_site(
            name=f"{prefix}kp/{name}", pos=hand.kp_pos[k].tolist(), size=[0.004, 0, 0], group=4
        )


def _add_object(spec: Any, scene: Scene, visual: bool, fr: list[float]) -> None:
    """The object as a free body: its inertia, its convex parts for collision, its mesh for the eye."""
    wb = spec.worldbody
    obj = scene.obj
    ob = wb.add_body(name="object", pos=scene.object_pos0.tolist(), quat=scene.object_quat0.tolist())
    ob.add_freejoint(name="object_free")
    ob.mass, ipos, iquat, inertia = object_inertial(obj)
    ob.ipos, ob.iquat, ob.inertia = ipos.tolist(), iquat.tolist(), inertia.tolist()
    ob.explicitinertial = True
    for i, (v, f) in enumerate(obj.convex_parts()):
        spec.add_mesh(name=f"object_part{i}", uservert=v.ravel().tolist(), userface=f.ravel().tolist())
        ob.add_geom(
            name=f"object_part{i}", type=mujoco.mjtGeom.mjGEOM_MESH, meshname=f"object_part{i}",
            contype=WORLD_CONTYPE, conaffinity=WORLD_CONAFFINITY, friction=fr, group=3, rgba=[0, 0, 0, 0],
            density=0.0, condim=3,
        )  # fmt: skip
    if visual:
        spec.add_mesh(name="object_visual", uservert=obj.vertices.ravel().tolist(), userface=obj.faces.ravel().tolist())
        ob.add_geom(
            name="object_visual", type=mujoco.mjtGeom.mjGEOM_MESH, meshname="object_visual",
            contype=0, conaffinity=0, group=1, rgba=[0.85, 0.35, 0.25, 1], density=0.0,
        )  # fmt: skip


def object_inertial(obj: ObjectAsset) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """The object body's mass, centre of mass (3,), principal axes (4,; w x y z) and principal moments (3,)."""
    evals, evecs = np.linalg.eigh(obj.inertia)
    if np.linalg.det(evecs) < 0:
        evecs[:, 0] *= -1
    return float(obj.mass), np.asarray(obj.com, np.float64), np_mat_to_quat(evecs), np.maximum(evals, 1e-9)


def same_structure(a: Scene, b: Scene) -> bool:
    """Whether scenes ``a`` and ``b`` compile to models that differ in physical parameters only (those of
    :meth:`MujocoModel.set_physics`): the same hands on the same bases, object mesh, centre of mass and initial
    orientation, table, frame rate, time step and gravity."""
    pa, pb = a.physics, b.physics
    return (
        a.placements == b.placements and a.table == b.table and a.fps == b.fps
        and a.obj.content_hash == b.obj.content_hash and np.array_equal(a.obj.com, b.obj.com)
        and np.array_equal(a.object_quat0, b.object_quat0)
        and (pa.mujoco_dt, pa.gravity) == (pb.mujoco_dt, pb.gravity)
    )  # fmt: skip


def _add_actuators(spec: Any, hand: HandModel, prefix: str, gain_scale: float = 1.0) -> None:
    """PD position + velocity feed-forward actuators on every dof of the hand with name prefix ``prefix``
    (gains and force limits of :func:`~quasisim.targets.base.pd_gains`)."""
    g = pd_gains(hand, gain_scale)
    for i, jn in enumerate(hand_dof_names(hand, prefix)):
        kp, kv, limit = float(g.kp[i]), float(g.kv[i]), float(g.force_limit[i])
        for kind in ("pd", "ff"):
            act = spec.add_actuator(name=f"{kind}/{jn}", target=jn, trntype=mujoco.mjtTrn.mjTRN_JOINT)
            act.gaintype = mujoco.mjtGain.mjGAIN_FIXED
            act.biastype = mujoco.mjtBias.mjBIAS_AFFINE
            gp = np.zeros(10)
            bp = np.zeros(10)
            if kind == "pd":
                gp[0], bp[1], bp[2] = kp, -kp, -kv
            else:
                gp[0] = kv
            act.gainprm = gp.tolist()
            act.biasprm = bp.tolist()
            act.ctrllimited = False
            if np.isfinite(limit) and kind == "pd":  # the joints' PD part (the base is unlimited)
                act.forcelimited = True
                act.forcerange = [-limit, limit]


def object_twist(quat: np.ndarray, qvel: np.ndarray, com: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The object's world linear velocity of its centre of mass (m/s) and world angular velocity (rad/s),
    (..., 3) each, from its free joint's orientation ``quat`` (..., 4) w x y z and velocity ``qvel`` (..., 6)
    (MuJoCo: the frame origin's world linear velocity, then the angular velocity in the body frame), with
    the centre of mass ``com`` (3,) in the object frame: ``w = R w_body``, ``v = v_origin + w x (R com)``."""
    R = np_quat_to_mat(quat)
    w = np.einsum("...ij,...j->...i", R, qvel[..., 3:6])
    return qvel[..., 0:3] + np.cross(w, R @ np.asarray(com)), w


def _normalized(quat: np.ndarray) -> np.ndarray:
    """``quat`` (4,) normalised as MuJoCo's compiler does (``mju_normalize4``)."""
    q = np.array(quat, np.float64)
    mujoco.mju_normalize4(q)
    return q


class MujocoModel:
    """A compiled scene with index maps for the hand dofs, keypoint sites and the object."""

    def __init__(self, scene: Scene, visual: bool = True) -> None:
        self.scene = scene
        self.model = build_spec(scene, visual=visual).compile()
        m = self.model
        names = dof_names(scene)
        sites = [f"{p}kp/{n}" for h, p in zip(scene.hands, scene.prefixes, strict=True) for n in h.kp_names]
        bodies = [p + n for h, p in zip(scene.hands, scene.prefixes, strict=True) for n in h.body_names]
        jid = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n) for n in names]
        self.hand_qpos = np.array([m.jnt_qposadr[j] for j in jid])
        self.hand_dof = np.array([m.jnt_dofadr[j] for j in jid])
        self.pd_act = np.array([mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, f"pd/{n}") for n in names])
        self.ff_act = np.array([mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, f"ff/{n}") for n in names])
        self.kp_site = np.array([mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, n) for n in sites])
        self.hand_body = np.array([mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, n) for n in bodies])
        self.hand_of_body = np.full(m.nbody, -1)  # body -> the hand it belongs to (-1: none)
        self.hand_of_body[self.hand_body] = np.repeat(
            np.arange(len(scene.hands)), [len(h.body_names) for h in scene.hands]
        )
        # each hand's root: its one body whose parent is no body of that hand (the subtree of its contact sensor)
        self.hand_root = [
            next(b for b in np.flatnonzero(self.hand_of_body == i) if self.hand_of_body[m.body_parentid[b]] != i)
            for i in range(len(scene.hands))
        ]
        oj = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "object_free")
        self.obj_qpos = int(m.jnt_qposadr[oj])
        self.obj_dof = int(m.jnt_dofadr[oj])
        self.obj_body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "object")
        self.contact_geoms = np.flatnonzero((m.geom_contype != 0) | (m.geom_conaffinity != 0))  # friction fr
        self.grip_geoms = self.contact_geoms[np.isin(m.geom_bodyid[self.contact_geoms], self.hand_body)]  # margin

    def set_physics(self, scene: Scene) -> None:
        """Give the compiled model the physical parameters of ``scene`` (of the model's structure,
        :func:`same_structure`) as compiling it would: the object's mass, inertia and initial position, the sliding
        friction of every colliding geom, the PD gains (kp, kv); then the constants derived from them
        (``mj_setConst``) and the statistics the compiler computes (``meanmass``, ``meaninertia``, which scales
        the solver's tolerance), which ``mj_setConst`` leaves. Also the hand geoms' contact margin."""
        m, b, o = self.model, self.obj_body, self.obj_qpos
        m.body_mass[b], m.body_ipos[b], iquat, m.body_inertia[b] = object_inertial(scene.obj)
        m.body_iquat[b] = _normalized(iquat)
        m.body_pos[b] = m.qpos0[o : o + 3] = m.qpos_spring[o : o + 3] = scene.object_pos0  # the free joint's origin
        m.geom_friction[self.contact_geoms, 0] = scene.physics.friction
        m.geom_margin[self.grip_geoms] = scene.physics.contact_margin
        gains = [pd_gains(h, scene.physics.gain_scale) for h in scene.hands]
        kp, kv = np.concatenate([g.kp for g in gains]), np.concatenate([g.kv for g in gains])
        m.actuator_gainprm[self.pd_act, 0], m.actuator_biasprm[self.pd_act, 1] = kp, -kp
        m.actuator_biasprm[self.pd_act, 2], m.actuator_gainprm[self.ff_act, 0] = -kv, kv
        d = mujoco.MjData(m)
        mujoco.mj_setConst(m, d)
        d.qpos[:] = m.qpos0
        mujoco.mj_forward(m, d)
        m.stat.meanmass = sum(float(x) for x in m.body_mass[1:]) / (m.nbody - 1)
        diag = d.M[m.M_rowadr + m.M_rownnz - 1]
        m.stat.meaninertia = sum(float(x) for x in diag) / m.nv
        self.scene = scene

    def set_state(self, data: Any, qfull: np.ndarray, obj_pos: np.ndarray, obj_quat: np.ndarray) -> None:
        data.qpos[self.hand_qpos] = qfull
        data.qpos[self.obj_qpos : self.obj_qpos + 3] = obj_pos
        data.qpos[self.obj_qpos + 3 : self.obj_qpos + 7] = obj_quat
        mujoco.mj_forward(self.model, data)


def _state_offset(model: Any, spec: int, component: int) -> int:
    """Offset of state ``component`` (one ``mjtState`` bit) inside a state vector of ``spec``."""
    off, bit = 0, 1
    while bit < component:
        if spec & bit:
            off += mujoco.mj_stateSize(model, bit)
        bit <<= 1
    return off


CONTACT_FORCE_DATA = 2  # mjtConDataField: the contact sensor's data "force" (bit 1)
CONTACT_REDUCE_MAXFORCE = 2  # its reduce="maxforce": the contacts with the largest force, largest first


class _WindowModel:
    """The scene with ``framepos`` sensors on the metric keypoint sites, and a ``mujoco.rollout`` pool: the
    batched candidate rollouts of :meth:`MujocoTarget.rollout_windows` (same layout as the target's model)."""

    def __init__(self, scene: Scene, target_model: Any, threads: int, roots: list[str], contacts: int = 0) -> None:
        from mujoco import rollout

        spec = build_spec(scene, visual=False)
        for hand, prefix in zip(scene.hands, scene.prefixes, strict=True):  # scene.kp_metric's order
            for k in np.flatnonzero(hand.kp_metric):
                spec.add_sensor(
                    name=f"kp_metric/{prefix}{hand.kp_names[k]}", type=mujoco.mjtSensor.mjSENS_FRAMEPOS,
                    objtype=mujoco.mjtObj.mjOBJ_SITE, objname=f"{prefix}kp/{hand.kp_names[k]}",
                )  # fmt: skip
        self.contacts = contacts
        for root in roots if contacts > 0 else []:  # per hand: its `contacts` strongest contacts with the object
            spec.add_sensor(
                name=f"contacts/{root}", type=mujoco.mjtSensor.mjSENS_CONTACT, objtype=mujoco.mjtObj.mjOBJ_XBODY,
                objname=root, reftype=mujoco.mjtObj.mjOBJ_BODY, refname="object",
                intprm=[CONTACT_FORCE_DATA, CONTACT_REDUCE_MAXFORCE, contacts],
            )  # fmt: skip
        self.model = spec.compile()
        self.n_kp = int(np.sum(scene.kp_metric)) * 3  # the keypoint sensors' columns come first
        m0 = target_model
        if (self.model.nq, self.model.nv, self.model.nu) != (m0.nq, m0.nv, m0.nu):
            raise QuasisimError("mujoco target: the sensor model's layout differs from the target's")
        self.qpos_off = _state_offset(self.model, STATE_SPEC, int(mujoco.mjtState.mjSTATE_QPOS))
        self.qvel_off = _state_offset(self.model, STATE_SPEC, int(mujoco.mjtState.mjSTATE_QVEL))
        self.datas = [mujoco.MjData(self.model) for _ in range(threads)]
        self.pool = rollout.Rollout(nthread=threads if threads > 1 else 0)


def _joined(head: Prediction, tail: Prediction, kept: np.ndarray, frames: int) -> Prediction:
    """Every candidate's first frames (``head``, N candidates) followed by the later frames of the candidates
    ``kept`` (``tail``); the others' later frames NaN. ``frames``: the window's frames in all."""
    parts = {}
    for f in dataclasses.fields(Prediction):
        a, b = getattr(head, f.name), getattr(tail, f.name)
        if f.name == "n_steps" or a is None:
            continue
        full = np.full((len(a), frames, *a.shape[2:]), np.nan)
        full[:, : a.shape[1]] = a
        full[kept, a.shape[1] :] = b
        parts[f.name] = full
    return Prediction(**parts, n_steps=head.n_steps + tail.n_steps)


class MujocoTarget(Target):
    """Roll PD targets out in MuJoCo. See the module docstring for the set-up.

    A run lives in ``self.data`` (a fresh ``MjData`` at every :meth:`reset`). :meth:`rollout_windows` uses
    ``mujoco.rollout`` with ``threads`` threads on a copy of the scene with keypoint sensors (built on first use).
    """

    name = "mujoco"

    def __init__(self, scene: Scene, threads: int = 1) -> None:
        self.scene = scene
        self.threads = threads
        self.mm = MujocoModel(scene, visual=False)
        self.data: Any = None
        self._windows: _WindowModel | None = None

    @property
    def dt(self) -> float:
        return float(self.mm.model.opt.timestep)

    def _run(self) -> Any:
        if self.data is None:
            raise RuntimeError("mujoco target: no run yet (call reset first)")
        return self.data

    def reset(self, q0: np.ndarray, qd0: np.ndarray | None = None) -> None:
        mm = self.mm
        self.data = mujoco.MjData(mm.model)
        mm.set_state(self.data, np.asarray(q0, np.float64), self.scene.object_pos0, self.scene.object_quat0)
        if qd0 is not None:
            self.data.qvel[mm.hand_dof] = qd0

    def observe(self) -> Observation:
        mm, d = self.mm, self._run()
        mujoco.mj_kinematics(mm.model, d)  # site positions of the current qpos (mj_step leaves them one step behind)
        o = mm.obj_qpos
        quat = d.qpos[o + 3 : o + 7].copy()
        R = np_quat_to_mat(quat)  # object_twist's formula, kept in this form for one state (MPC's bits)
        w = R @ d.qvel[mm.obj_dof + 3 : mm.obj_dof + 6]  # free joint: angular velocity in the body frame
        com = R @ np.asarray(self.scene.obj.com)
        v = d.qvel[mm.obj_dof : mm.obj_dof + 3] + np.cross(w, com)  # free joint: velocity of the frame origin
        return {
            "qpos": d.qpos[mm.hand_qpos].copy(), "qvel": d.qvel[mm.hand_dof].copy(),
            "obj_pos": d.qpos[o : o + 3].copy(), "obj_quat": quat, "obj_vel": v, "obj_angvel": w,
            "keypoints": d.site_xpos[mm.kp_site].copy(),
        }  # fmt: skip

    def save_state(self) -> tuple[np.ndarray, np.ndarray]:
        """``mj_getState(..., mjSTATE_FULLPHYSICS)`` and ``qacc_warmstart`` (the solver's warm start)."""
        d = self._run()
        state = np.zeros(mujoco.mj_stateSize(self.mm.model, STATE_SPEC))
        mujoco.mj_getState(self.mm.model, d, state, STATE_SPEC)
        return state, d.qacc_warmstart.copy()

    def restore_state(self, state: object) -> None:
        full, warm = state  # type: ignore[misc]
        d = self._run()
        mujoco.mj_setState(self.mm.model, d, full, STATE_SPEC)
        d.qacc_warmstart[:] = warm

    def advance(self, qa: np.ndarray, qb: np.ndarray) -> None:
        mm, d, m = self.mm, self._run(), self.mm.model
        targets, velocity = pd_schedule(qa, qb, self.substeps, self.scene.fps)
        d.ctrl[mm.ff_act] = velocity
        for pd in targets:
            d.ctrl[mm.pd_act] = pd
            mujoco.mj_step(m, d)

    def set_hands(self, q: np.ndarray, qd: np.ndarray) -> None:
        mm, d = self.mm, self._run()
        d.qpos[mm.hand_qpos] = q
        d.qvel[mm.hand_dof] = qd

    def sync(self, obs: Observation) -> None:
        """The observed state into the run: hands' ``qpos``, ``qvel``; the object's free joint from its pose and
        its centre of mass's world velocities (inverse of :func:`object_twist`: ``w_body = R^T w``,
        ``v_origin = v - w x (R com)``); ``qacc_warmstart`` zeroed; ``mj_forward``."""
        mm, d = self.mm, self._run()
        quat = np.asarray(obs["obj_quat"], np.float64)
        R = np_quat_to_mat(quat)
        w = np.asarray(obs["obj_angvel"], np.float64)
        o, od = mm.obj_qpos, mm.obj_dof
        d.qpos[mm.hand_qpos] = obs["qpos"]
        d.qvel[mm.hand_dof] = obs["qvel"]
        d.qpos[o : o + 3] = obs["obj_pos"]
        d.qpos[o + 3 : o + 7] = quat / np.linalg.norm(quat)
        d.qvel[od : od + 3] = np.asarray(obs["obj_vel"]) - np.cross(w, R @ np.asarray(self.scene.obj.com))
        d.qvel[od + 3 : od + 6] = R.T @ w
        d.qacc_warmstart[:] = 0.0
        mujoco.mj_forward(mm.model, d)

    def rollout_windows(
        self, wins: np.ndarray, qd0: np.ndarray | None = None, prune: Prune | None = None, contacts: int = 0
    ) -> Prediction:
        """The candidate windows (N, H + 1, D) rolled out from the run's current state with ``mujoco.rollout``
        on the sensor model (``mj_getState(..., mjSTATE_FULLPHYSICS)`` and ``qacc_warmstart`` copied, the
        controls of :func:`pd_schedule`); with ``qd0`` (N, D) each candidate's hands start at its window's
        frame 0 with velocity ``qd0``, as in :meth:`Target.rollout_windows`. With ``prune``, the candidates
        ``prune.keep`` picks go on from their states after ``prune.frames`` frames, with the solver's warm
        start of the step (``mujoco.rollout`` does not return it), so their later frames may differ from an
        unbroken rollout's in the solver's last digits. With ``contacts`` > 0: :attr:`Prediction.cones` from a
        MuJoCo contact sensor per hand (the hand's subtree against the object, ``reduce="maxforce"``, that many
        slots)."""
        if self._windows is None or self._windows.contacts != contacts:
            self.close()
            roots = [mujoco.mj_id2name(self.mm.model, mujoco.mjtObj.mjOBJ_BODY, b) for b in self.mm.hand_root]
            self._windows = _WindowModel(self.scene, self.mm.model, self.threads, roots, contacts)
        wm, mm = self._windows, self.mm
        N, H = len(wins), wins.shape[1] - 1
        state = np.repeat(self.save_state()[0][None], N, axis=0)
        if qd0 is not None:
            state[:, wm.qpos_off + mm.hand_qpos] = wins[:, 0]
            state[:, wm.qvel_off + mm.hand_dof] = qd0
        split = H if prune is None else min(max(prune.frames, 1), H)
        out, ends = self._windows_from(state, wins[:, : split + 1])
        n_steps = N * (split * self.substeps + 1)
        if split < H:
            kept = np.asarray(prune.keep(out), dtype=int)  # type: ignore[union-attr]
            tail, _ = self._windows_from(ends[kept], wins[kept, split:])
            out = _joined(out, tail, kept, H)
            n_steps += len(kept) * ((H - split) * self.substeps + 1)
        return dataclasses.replace(out, n_steps=n_steps)

    def _windows_from(self, state: np.ndarray, wins: np.ndarray) -> tuple[Prediction, np.ndarray]:
        """Windows (N, F + 1, D) rolled out from full-physics states (N, nstate) on the sensor model: their
        :class:`Prediction` at frames 1..F and the states (N, nstate) after frame F."""
        wm, mm, d = self._windows, self.mm, self._run()
        assert wm is not None
        N, F, n = len(wins), wins.shape[1] - 1, self.substeps
        pd, ff = pd_schedule(wins[:, :-1], wins[:, 1:], n, self.scene.fps)
        ctrl = np.zeros((N, F * n + 1, wm.model.nu))  # one more step: sensors lag one step behind qpos
        ctrl[:, :-1, mm.pd_act] = pd.reshape(N, F * n, -1)
        ctrl[:, :-1, mm.ff_act] = np.repeat(ff, n, axis=1)
        ctrl[:, -1] = ctrl[:, -2]
        warm = np.repeat(d.qacc_warmstart[None], N, axis=0)
        states, sens = wm.pool.rollout(wm.model, wm.datas, state, ctrl, initial_warmstart=warm)
        ends = np.arange(1, F + 1) * n  # the state after frame f is step f n - 1; its sensors are step f n
        qpos = states[:, ends - 1, wm.qpos_off : wm.qpos_off + wm.model.nq]
        qvel = states[:, ends - 1, wm.qvel_off : wm.qvel_off + wm.model.nv]
        o, od = mm.obj_qpos, mm.obj_dof
        obj_vel, obj_angvel = object_twist(qpos[..., o + 3 : o + 7], qvel[..., od : od + 6], self.scene.obj.com)
        cones = None
        if wm.contacts > 0:
            phys = self.scene.physics
            # the forces of each frame's last step (its sensors are computed in that step, before it integrates)
            force = sens[:, ends - 1, wm.n_kp :].reshape(N, F, -1, 3)  # hands x slots, each (normal, t1, t2)
            cones = cone_loads(force, phys.friction, self.scene.obj.mass * phys.gravity)
        pred = Prediction(
            qpos=qpos[..., mm.hand_qpos], obj_pos=qpos[..., o : o + 3], obj_quat=qpos[..., o + 3 : o + 7],
            keypoints=sens[:, ends, : wm.n_kp].reshape(N, F, -1, 3), n_steps=N * (F * n + 1),
            qvel=qvel[..., mm.hand_dof], obj_vel=obj_vel, obj_angvel=obj_angvel, cones=cones,
        )  # fmt: skip
        return pred, states[:, ends[-1] - 1]

    def extras(self) -> dict[str, Any]:
        return {"sim_warnings": self.warnings()}

    def _object_contacts(self) -> list[tuple[int, np.ndarray]]:
        """(body, force) of every contact between a hand body and the object during the last physics step
        (``mj_contactForce`` of the run's data after ``mj_step``: the contacts and constraint forces of that step,
        under its controls): the hand body's id and the force (3,) in the contact frame (normal, t1, t2; N)."""
        mm, d = self.mm, self._run()
        out, f6 = [], np.zeros(6)
        for i in range(d.ncon):
            b1, b2 = mm.model.geom_bodyid[d.contact.geom1[i]], mm.model.geom_bodyid[d.contact.geom2[i]]
            body = b1 if b2 == mm.obj_body else b2 if b1 == mm.obj_body else -1
            if body >= 0 and mm.hand_of_body[body] >= 0:
                mujoco.mj_contactForce(mm.model, d, i, f6)
                out.append((int(body), f6[:3].copy()))
        return out

    def contact_forces(self, slots: int) -> np.ndarray:
        """(n_hands, slots, 3) per hand its ``slots`` strongest contacts with the object during the last physics
        step (:meth:`_object_contacts`), as the window rollouts' contact sensors report a frame (N)."""
        per_hand: list[list[np.ndarray]] = [[] for _ in self.scene.hands]
        for body, f in self._object_contacts():
            per_hand[self.mm.hand_of_body[body]].append(f)
        return np.stack([strongest(np.reshape(f, (-1, 3)), slots) for f in per_hand])

    def body_contact_forces(self) -> np.ndarray:
        """As :meth:`Target.body_contact_forces`: the normal forces of :meth:`_object_contacts` summed per body,
        in the order of :attr:`MujocoModel.hand_body`."""
        mm = self.mm
        index = np.full(mm.model.nbody, -1)
        index[mm.hand_body] = np.arange(len(mm.hand_body))
        out = np.zeros(len(mm.hand_body))
        for body, f in self._object_contacts():
            out[index[body]] += f[0]
        return out

    def warnings(self) -> dict[str, int]:
        """How often MuJoCo raised each warning of :data:`UNSTABLE_WARNINGS` in this run."""
        w = self._run().warning
        return {k: int(w[int(getattr(mujoco.mjtWarning, f"mjWARN_{k}"))].number) for k in UNSTABLE_WARNINGS}

    def set_world(self, scene: Scene) -> bool:
        """``scene``'s physical parameters on the compiled model (:meth:`MujocoModel.set_physics`): a world of
        the same structure (:func:`same_structure`) without compiling again; the run ends (:meth:`reset` next)
        and the window model, compiled from the old parameters, is dropped (built again on first use)."""
        if not same_structure(self.scene, scene):
            return False
        self.mm.set_physics(scene)
        self.scene, self.data = scene, None
        self.close()
        return True

    def close(self) -> None:
        """Close the rollout pool (idempotent)."""
        if self._windows is not None:
            self._windows.pool.close()
            self._windows = None


def hand_object_contacts(mm: MujocoModel, qpos: np.ndarray, obj_pos: np.ndarray, obj_quat: np.ndarray) -> np.ndarray:
    """(T,) the number of contacts between any hand body and the object at each frame of a recorded run
    (hand ``qpos`` (T, D), object pose (T, 3), (T, 4) w x y z) in the compiled scene ``mm``. Contacts depend on
    the geometry alone, so a perturbed world's run may be read in its nominal scene."""
    data = mujoco.MjData(mm.model)
    hand = np.zeros(mm.model.nbody, bool)
    hand[mm.hand_body] = True
    out = np.zeros(len(qpos), np.int64)
    for t in range(len(qpos)):
        mm.set_state(data, qpos[t], obj_pos[t], obj_quat[t])
        out[t] = object_contacts(mm.model, data, mm.obj_body, hand)
    return out


def object_contacts(model: Any, data: Any, obj_body: int, hand: np.ndarray) -> int:
    """The contacts of ``data`` (after collision detection) between body ``obj_body`` and the bodies marked in
    ``hand`` ((nbody,) bool)."""
    b1 = model.geom_bodyid[data.contact.geom1[: data.ncon]]
    b2 = model.geom_bodyid[data.contact.geom2[: data.ncon]]
    return int(np.sum((hand[b1] & (b2 == obj_body)) | (hand[b2] & (b1 == obj_body))))
