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
  (gain ``kp``, bias ``-kp q - kv qd``) plus one feed-forward actuator (``kv qd*``). Within a control
  frame the targets are interpolated linearly and ``qd*`` is the frame-to-frame velocity of the targets.
* Object: free body with the asset's mass, centre of mass and inertia; collision from its convex parts.
"""

from __future__ import annotations

import time
from typing import Any

import mujoco
import numpy as np

from quasisim.assets.hand import HandModel
from quasisim.rotations import np_mat_to_quat, np_quat_to_mat, sign_continuous
from quasisim.targets import TargetRollout
from quasisim.targets.scene import Scene

HAND_PREFIX = "hand/"  # the one hand of a one-hand scene (Scene.prefixes: two hands are rhand/ and lhand/)
# collision bits: hand (type 2, affinity 1) touches object/table (type 1, affinity 3), not itself.
HAND_CONTYPE, HAND_CONAFFINITY = 2, 1
# MuJoCo's warnings that mean the simulation went wrong (counted per run in ``data.warning``)
UNSTABLE_WARNINGS = ("BADQPOS", "BADQVEL", "BADQACC", "BADCTRL", "CONTACTFULL", "CNSTRFULL")
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
        _add_hand_geoms(spec, hand, prefix, bodies, visual, fr)
    _add_object(spec, scene, visual, fr)
    for hand, prefix in zip(scene.hands, scene.prefixes, strict=True):
        _add_actuators(spec, hand, prefix)
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
    pd, wb = hand.config.pd, spec.worldbody
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
                    damping=pd.joint_damping, armature=pd.joint_armature,
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


def _add_hand_geoms(spec: Any, hand: HandModel, prefix: str, bodies: list[Any], visual: bool, fr: list[float]) -> None:
    """Collision geoms (and visual ones when ``visual``) and the keypoint sites of the hand (names start with ``prefix``)."""
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
            kw.update(contype=HAND_CONTYPE, conaffinity=HAND_CONAFFINITY, friction=fr, group=3, condim=3)
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
    evals, evecs = np.linalg.eigh(obj.inertia)
    if np.linalg.det(evecs) < 0:
        evecs[:, 0] *= -1
    ob.mass = float(obj.mass)
    ob.ipos = obj.com.tolist()
    ob.iquat = np_mat_to_quat(evecs).tolist()
    ob.inertia = np.maximum(evals, 1e-9).tolist()
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


def _add_actuators(spec: Any, hand: HandModel, prefix: str) -> None:
    """PD position + velocity feed-forward actuators on every dof of the hand with name prefix ``prefix``."""
    pd = hand.config.pd
    for i, jn in enumerate(hand_dof_names(hand, prefix)):
        gains = pd.base_pos if i < 3 else pd.base_rot if i < 6 else pd.joint
        limit = None if i < 6 else pd.joint_force_limit
        for kind in ("pd", "ff"):
            act = spec.add_actuator(name=f"{kind}/{jn}", target=jn, trntype=mujoco.mjtTrn.mjTRN_JOINT)
            act.gaintype = mujoco.mjtGain.mjGAIN_FIXED
            act.biastype = mujoco.mjtBias.mjBIAS_AFFINE
            gp = np.zeros(10)
            bp = np.zeros(10)
            if kind == "pd":
                gp[0], bp[1], bp[2] = gains.kp, -gains.kp, -gains.kv
            else:
                gp[0] = gains.kv
            act.gainprm = gp.tolist()
            act.biasprm = bp.tolist()
            act.ctrllimited = False
            if limit is not None and kind == "pd":
                act.forcelimited = True
                act.forcerange = [-limit, limit]


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
        oj = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "object_free")
        self.obj_qpos = int(m.jnt_qposadr[oj])
        self.obj_dof = int(m.jnt_dofadr[oj])
        self.obj_body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "object")

    def set_state(self, data: Any, qfull: np.ndarray, obj_pos: np.ndarray, obj_quat: np.ndarray) -> None:
        data.qpos[self.hand_qpos] = qfull
        data.qpos[self.obj_qpos : self.obj_qpos + 3] = obj_pos
        data.qpos[self.obj_qpos + 3 : self.obj_qpos + 7] = obj_quat
        mujoco.mj_forward(self.model, data)


class MujocoTarget:
    """Roll PD targets out in MuJoCo. See the module docstring for the set-up."""

    name = "mujoco"

    def __init__(self, scene: Scene) -> None:
        self.scene = scene
        self.mm = MujocoModel(scene, visual=False)

    @property
    def substeps(self) -> int:
        return max(1, round(1.0 / (self.scene.fps * self.scene.physics.mujoco_dt)))

    def rollout(self, q_targets: np.ndarray, init_qvel: bool = True) -> TargetRollout:
        """Run the PD targets ``q_targets`` (T, D) from the demo's initial object pose (D = 6 + J per hand,
        the hands concatenated).

        The hands start at ``q_targets[0]`` (with the targets' initial velocity when ``init_qvel``).
        """
        q_targets = np.asarray(q_targets, dtype=np.float64)
        D = self.scene.n_dof
        if q_targets.ndim != 2 or q_targets.shape[1] != D:
            raise ValueError(f"q_targets must have shape (T, {D}), got {q_targets.shape}")
        T = len(q_targets)
        qd0 = (q_targets[1] - q_targets[0]) * self.scene.fps if init_qvel and T > 1 else None
        sess = self.session(q_targets[0], qd0)
        t0 = time.perf_counter()
        for t in range(T):
            sess.record()
            if t < T - 1:
                sess.advance(q_targets[t], q_targets[t + 1])
        return sess.result(time.perf_counter() - t0)

    def session(self, q0: np.ndarray, qd0: np.ndarray | None = None) -> MujocoSession:
        """A step-by-step run (closed-loop control): the hands at ``q0`` (D,) with velocity ``qd0``,
        the object at the demo's initial pose, at rest."""
        return MujocoSession(self, np.asarray(q0, np.float64), qd0)


class MujocoSession:
    """One MuJoCo run advanced frame by frame: :meth:`observe` the state, :meth:`advance` one control frame."""

    def __init__(self, target: MujocoTarget, q0: np.ndarray, qd0: np.ndarray | None) -> None:
        self.target = target
        mm = target.mm
        self.data = mujoco.MjData(mm.model)
        mm.set_state(self.data, q0, target.scene.object_pos0, target.scene.object_quat0)
        if qd0 is not None:
            self.data.qvel[mm.hand_dof] = qd0
        self._rec: dict[str, list[np.ndarray]] = {"qpos": [], "opos": [], "oquat": [], "kps": []}

    def observe(self) -> dict[str, np.ndarray]:
        """Hands' ``qpos``/``qvel`` (D,), object origin ``obj_pos``, ``obj_quat`` (w x y z), world linear
        velocity of the centre of mass ``obj_vel`` and world angular velocity ``obj_angvel``, ``keypoints``."""
        mm, d = self.target.mm, self.data
        self._sync()
        o = mm.obj_qpos
        quat = d.qpos[o + 3 : o + 7].copy()
        R = np_quat_to_mat(quat)
        w = R @ d.qvel[mm.obj_dof + 3 : mm.obj_dof + 6]  # free joint: angular velocity in the body frame
        com = R @ np.asarray(self.target.scene.obj.com)
        v = d.qvel[mm.obj_dof : mm.obj_dof + 3] + np.cross(w, com)  # free joint: velocity of the frame origin
        return {
            "qpos": d.qpos[mm.hand_qpos].copy(), "qvel": d.qvel[mm.hand_dof].copy(),
            "obj_pos": d.qpos[o : o + 3].copy(), "obj_quat": quat, "obj_vel": v, "obj_angvel": w,
            "keypoints": d.site_xpos[mm.kp_site].copy(),
        }  # fmt: skip

    def advance(self, qa: np.ndarray, qb: np.ndarray) -> None:
        """One control frame: PD targets interpolated from ``qa`` to ``qb`` with their velocity fed forward."""
        mm, d, m = self.target.mm, self.data, self.target.mm.model
        fps, n = self.target.scene.fps, self.target.substeps
        d.ctrl[mm.ff_act] = (qb - qa) * fps
        for k in range(n):
            s = (k + 1) / n
            d.ctrl[mm.pd_act] = (1 - s) * qa + s * qb
            mujoco.mj_step(m, d)

    def _sync(self) -> None:
        """Positions of bodies and sites for the current ``qpos`` (``mj_step`` leaves them one step behind)."""
        mujoco.mj_kinematics(self.target.mm.model, self.data)

    def record(self) -> None:
        """Append the current frame (hand qpos, object pose, keypoint sites) to the run's record."""
        mm, d = self.target.mm, self.data
        self._sync()
        self._rec["qpos"].append(d.qpos[mm.hand_qpos].copy())
        self._rec["opos"].append(d.qpos[mm.obj_qpos : mm.obj_qpos + 3].copy())
        self._rec["oquat"].append(d.qpos[mm.obj_qpos + 3 : mm.obj_qpos + 7].copy())
        self._rec["kps"].append(d.site_xpos[mm.kp_site].copy())

    def result(self, wall_s: float) -> TargetRollout:
        """The recorded frames as a :class:`TargetRollout`."""
        scene = self.target.scene
        return TargetRollout(
            target=self.target.name,
            qpos=np.array(self._rec["qpos"]),
            object_pos=np.array(self._rec["opos"]),
            object_quat=sign_continuous(np.array(self._rec["oquat"])),
            keypoints=np.array(self._rec["kps"]),
            kp_human=scene.kp_human,
            kp_metric=scene.kp_metric,
            dt=float(self.target.mm.model.opt.timestep),
            substeps=self.target.substeps,
            wall_s=wall_s,
            extras={"sim_warnings": self.warnings()},
        )

    def warnings(self) -> dict[str, int]:
        """How often MuJoCo raised each warning of :data:`UNSTABLE_WARNINGS` in this run."""
        w = self.data.warning
        return {k: int(w[int(getattr(mujoco.mjtWarning, f"mjWARN_{k}"))].number) for k in UNSTABLE_WARNINGS}
