"""The tracking task, apart from any RL library: what a policy observes, how its action becomes PD targets,
the DGrasp-style reward and the termination. The Gymnasium environment (:mod:`quasisim.envs.track`) and a
trained policy replayed by the evaluation (:mod:`quasisim.policy.evaluate`) both use this one class, so a
policy sees in evaluation exactly what it saw in training.

Frames: the world is at frame ``t`` (observation ``obs``, :data:`quasisim.targets.base.Observation`); the
action chooses the PD targets of frame ``t + 1``; the reward and termination judge frame ``t + 1``.

* **Action** ``a`` (D,) in [-1, 1]: residual, ``q*_{t+1} = q^ref_{t+1} + s_res * a``; otherwise (DGrasp's
  form) ``q*_{t+1} = q_t + s_delta * a`` from the measured pose ``q_t``; clipped to the joint limits. With
  ``action_form: dgrasp`` (not residual; :meth:`TrackTask.dgrasp_targets`) DGrasp's own form: the fingers and
  base hinges step from the measured pose, the base slides from the goal wrist position (the reference's base
  carried rigidly with the object, :meth:`TrackTask.goal_base`), by DGrasp's small scales, and the frame holds
  its targets with no velocity fed forward (:meth:`TrackTask.schedule_from`).
* **Reward** ``r = sum_k w_k exp(-e_k / s_k) - c |a|^2 / D`` with ``e_pos`` the object's position error (cm),
  ``e_rot`` its rotation error (deg) against the demo, ``e_kp`` the mean distance of the robot's keypoints to
  the demo's (cm), ``e_contact`` the mean distance (cm) of the fingertips that touch the object in the demo to
  the demo's fingertips, both in the object's frame.
* **DGrasp's reward** (``reward_form: dgrasp``; :meth:`TrackTask.dgrasp_terms`): DGrasp's own terms (github
  christsa/dgrasp, ``envs/dgrasp/Environment.hpp``), each against this task's reference at the frame reached,
  ``r = max(clip, sum_k c_k term_k)`` with the coefficients of ``dgrasp_reward``; needs of the world what an
  observation lacks, :class:`Contacts`.
* **Hand frame** (``observe_hand_frame``; :func:`hand_frames`): per hand, the frame at its wrist keypoint with
  ``x`` towards the middle of the index and ring finger bases (``index_mcp``, ``ring_mcp``; every robot hand
  has them, the Allegro no little finger), ``z = (index - wrist) x (ring - wrist)`` normalised (the palm's
  normal, either side by the hand's side), ``y = z x x``.
* **Termination**: the first frame outside the strict limits (2 cm, 30 deg; ``terminate: strict``; the env may
  loosen them early in training, ``limits_start``/``limits_steps``), a blow-up
  (object faster than :data:`~quasisim.targets.base.MAX_OBJECT_SPEED`, a state not finite, or a warning of the
  simulator, which for MuJoCo means it has reset the state), the clip's last frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

from quasisim.data.demo import Demo
from quasisim.envs.config import DofScale, TrackEnvConfig
from quasisim.keypoints import FINGERTIPS, KEYPOINT_NAMES, N_KEYPOINTS
from quasisim.limits import STRICT_CM, STRICT_DEG
from quasisim.targets.base import MAX_OBJECT_SPEED, Observation
from quasisim.targets.scene import Scene


def dof_scale(scene: Scene, s: DofScale) -> np.ndarray:
    """(D,) the action scale of every dof of ``scene``'s hands: 3 base slides, 3 base hinges, the joints."""
    return np.concatenate([np.r_[[s.base_pos] * 3, [s.base_rot] * 3, [s.joints] * (sl.stop - sl.start - 6)]
                           for sl in scene.dof_slices])  # fmt: skip


HAND_FRAME_KEYPOINTS = tuple(KEYPOINT_NAMES.index(n) for n in ("wrist", "index_mcp", "ring_mcp"))
"""The human keypoints whose robot keypoints span each hand's frame (:func:`hand_frames`): wrist, two finger bases."""


def hand_frame_keypoints(scene: Scene) -> np.ndarray:
    """(H, 3) for each hand of ``scene``, the robot keypoints (indices into an observation's ``keypoints``) of its
    wrist, index finger base and ring finger base (:data:`HAND_FRAME_KEYPOINTS`); ValueError naming the hand
    where one is missing."""
    kp, rows = scene.kp_human, []
    for i, hand in enumerate(scene.hands):
        row = [np.flatnonzero(kp == N_KEYPOINTS * i + k) for k in HAND_FRAME_KEYPOINTS]
        missing = [KEYPOINT_NAMES[k] for k, r in zip(HAND_FRAME_KEYPOINTS, row, strict=True) if not len(r)]
        if missing:
            raise ValueError(f"observe_hand_frame: hand {hand.name} has no robot keypoint for {', '.join(missing)}")
        rows.append([int(r[0]) for r in row])
    return np.array(rows, dtype=np.int64)


def hand_frames(keypoints: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each hand's frame from the robot ``keypoints`` (K, 3) m and :func:`hand_frame_keypoints` ``idx`` (H, 3):
    origins (H, 3) m, the wrist keypoints, and rotations (H, 3, 3) whose columns are the frame's axes in world
    coordinates: ``x`` from the wrist towards the middle of the two finger bases, ``z`` the normal of the plane
    of the three points (``(index - wrist) x (ring - wrist)``), ``y = z x x``."""
    p = np.asarray(keypoints, np.float64)[idx]  # (H, 3 points, 3)
    a, b = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    x = a + b
    x /= np.linalg.norm(x, axis=-1, keepdims=True)
    z = np.cross(a, b)
    z -= np.sum(z * x, axis=-1, keepdims=True) * x  # orthogonal to x (it is already, but for rounding)
    z /= np.linalg.norm(z, axis=-1, keepdims=True)
    return p[:, 0], np.stack([x, np.cross(z, x), z], axis=-1)


def _rot(quat: np.ndarray) -> Rotation:
    """w x y z -> scipy (x y z w)."""
    q = np.asarray(quat, np.float64)
    return Rotation.from_quat(np.concatenate([q[..., 1:], q[..., :1]], axis=-1))


def demo_contacts(demo: Demo, scene: Scene, radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The demo's fingertip contacts: ``tips`` (F,) the robot keypoints that stand for human fingertips,
    ``touch`` (T, F) whether the human fingertip is within ``radius`` m of the object's surface, ``local``
    (T, F, 3) the human fingertip in the object's frame (m)."""
    kp = scene.kp_human
    tips = np.flatnonzero(np.isin(kp % N_KEYPOINTS, FINGERTIPS))
    human = demo.human_joints[:, kp[tips]]  # (T, F, 3)
    R = _rot(demo.object_quat).as_matrix()  # (T, 3, 3)
    local = np.einsum("tji,tfj->tfi", R, human - demo.object_pos[:, None])
    mesh = scene.obj.to_trimesh()
    _, dist, _ = mesh.nearest.on_surface(local.reshape(-1, 3))
    inside = mesh.contains(local.reshape(-1, 3))
    touch = ((dist < radius) | inside).reshape(local.shape[:2])
    return tips, touch, local


FINGERTIP_WEIGHT = 4.0  # DGrasp's weight of a fingertip keypoint in its position term, against 1 for the others


def keypoint_weights(kp_human: np.ndarray) -> np.ndarray:
    """(K,) DGrasp's weights of the robot keypoints standing for the human keypoints ``kp_human`` (K,; indices
    into the human keypoints of all hands): :data:`FINGERTIP_WEIGHT` for a fingertip, 1 for the others, then
    divided by their mean (DGrasp: 4x on its five fingertip parts, normalised to a mean of 1)."""
    w = np.where(np.isin(np.asarray(kp_human) % N_KEYPOINTS, FINGERTIPS), FINGERTIP_WEIGHT, 1.0)
    return w / w.mean()


class Contacts(NamedTuple):
    """What DGrasp's reward needs of the world beyond an observation; the env reads it from its target.

    Attributes:
        forces: (B,) per hand body (:meth:`~quasisim.targets.base.Target.body_contact_forces`: the scene's hands'
            ``body_names`` in order, concatenated) the summed normal force of its contacts with the object during
            the last physics step, N.
        frame_dt: the control frame's duration in the simulator (physics step x substeps), s.
        weight: the object's weight ``m g`` in this world, N.
    """

    forces: np.ndarray
    frame_dt: float
    weight: float


@dataclass(frozen=True, eq=False)
class TrackTask:
    """One clip's tracking task: the demo, its nominal scene, the reference PD targets (T, D), the settings.

    Built once per environment (or evaluation); its methods are pure functions of their arguments."""

    demo: Demo
    scene: Scene
    reference: np.ndarray
    cfg: TrackEnvConfig
    residual: bool
    # derived in __post_init__: the action scale (D,), the joint bounds, the metric keypoints (Km,) and the demo's
    # keypoints for them (T, Km, 3), the fingertip contacts (demo_contacts), the demo object's rotations
    scale: np.ndarray = field(init=False, repr=False)
    bounds: tuple[np.ndarray, np.ndarray] = field(init=False, repr=False)
    metric: np.ndarray = field(init=False, repr=False)
    human_kp: np.ndarray = field(init=False, repr=False)
    tips: np.ndarray = field(init=False, repr=False)
    touch: np.ndarray = field(init=False, repr=False)
    tips_local: np.ndarray = field(init=False, repr=False)
    demo_rot: Rotation = field(init=False, repr=False)
    frame_kp: np.ndarray | None = field(init=False, repr=False)  # (H, 3) hand_frame_keypoints, observe_hand_frame
    # DGrasp's reward: every robot keypoint's demo position in the demo object's frame (T, K, 3), its weight (K,)
    # and its hand body (K,; index into Contacts.forces); the finger joints' columns (Dj,) and each hand's base
    # columns (H, 6: three slides, three hinges) of the pose vector
    kp_local: np.ndarray = field(init=False, repr=False)
    kp_weight: np.ndarray = field(init=False, repr=False)
    kp_body: np.ndarray = field(init=False, repr=False)
    joint_cols: np.ndarray = field(init=False, repr=False)
    base_cols: np.ndarray = field(init=False, repr=False)
    # action_form: dgrasp: DGrasp's action scale (D,) (dgrasp_action; the observation keeps ``scale``'s units)
    dgrasp_scale: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        ref = np.asarray(self.reference, np.float64)
        if ref.shape != (self.demo.n_frames, self.scene.n_dof):
            raise ValueError(f"reference: expected ({self.demo.n_frames}, {self.scene.n_dof}), got {ref.shape}")
        if self.residual and self.cfg.action_form == "dgrasp":
            raise ValueError(
                "action_form: dgrasp sets the PD targets around the measured pose and the goal wrist position, "
                "not on the reference: it needs residual=False (or action_form: default)"
            )
        set_ = object.__setattr__
        set_(self, "reference", ref)
        set_(self, "scale", dof_scale(self.scene, self.cfg.residual_scale if self.residual else self.cfg.delta_scale))
        set_(self, "bounds", self.scene.joint_bounds())
        set_(self, "metric", np.flatnonzero(self.scene.kp_metric))
        set_(self, "human_kp", self.demo.human_joints[:, self.scene.kp_human[self.metric]])  # (T, Km, 3)
        tips, touch, local = demo_contacts(self.demo, self.scene, self.cfg.contact_radius)
        set_(self, "tips", tips)
        set_(self, "touch", touch)
        set_(self, "tips_local", local)
        set_(self, "demo_rot", _rot(self.demo.object_quat))
        set_(self, "frame_kp", hand_frame_keypoints(self.scene) if self.cfg.observe_hand_frame else None)
        kp, R = self.scene.kp_human, self.demo_rot.as_matrix()
        kp_local = np.einsum("tji,tkj->tki", R, self.demo.human_joints[:, kp] - self.demo.object_pos[:, None])
        set_(self, "kp_local", kp_local)
        set_(self, "kp_weight", keypoint_weights(kp))
        first = np.cumsum([0] + [h.n_bodies for h in self.scene.hands])[:-1]  # each hand's first body
        set_(self, "kp_body", np.concatenate([h.kp_body + b for h, b in zip(self.scene.hands, first, strict=True)]))
        cols = [np.arange(sl.start, sl.stop) for sl in self.scene.dof_slices]
        set_(self, "joint_cols", np.concatenate([c[6:] for c in cols]))
        set_(self, "base_cols", np.stack([c[:6] for c in cols]))
        set_(self, "dgrasp_scale", dof_scale(self.scene, self.cfg.dgrasp_action.scale()))

    @property
    def n_frames(self) -> int:
        return len(self.reference)

    @property
    def observation_size(self) -> int:
        D, H, Km = self.scene.n_dof, self.cfg.horizon, len(self.metric)
        frames = 0 if self.frame_kp is None else 6 * len(self.frame_kp)
        return 1 + 2 * D + 12 + 3 * Km + H * (D + 3) + frames

    def observation(self, t: int, obs: Observation) -> np.ndarray:
        """(observation_size,) float32: the clip's phase; the hands' pose against the reference and their
        velocity (in action units per frame); the object's position (cm) and rotation (deg) errors against
        the demo, its linear and angular velocity per frame, all in units of the strict limits; the robot
        keypoints against the demo's (in 2 cm); then for each of the next ``horizon`` frames the reference's
        change (action units) and the demo object's path from the object now (in 2 cm); with
        ``observe_hand_frame``, for each hand in turn the object's position in the hand's frame
        (:func:`hand_frames`, in 2 cm) and its rotation relative to that frame (``R_hand^T R_object`` as a
        rotation vector, in 30 deg)."""
        T, ref, s, fps = self.n_frames, self.reference, self.scale, self.scene.fps
        future = np.minimum(np.arange(t + 1, t + 1 + self.cfg.horizon), T - 1)
        pos, quat = np.asarray(obs["obj_pos"]), np.asarray(obs["obj_quat"])
        rot_err = (self.demo_rot[t].inv() * _rot(quat)).as_rotvec()
        kp = np.asarray(obs["keypoints"])[self.metric]
        parts = [
            [t / max(T - 1, 1)],
            (obs["qpos"] - ref[t]) / s,
            obs["qvel"] / fps / s,
            100 * (pos - self.demo.object_pos[t]) / STRICT_CM,
            np.degrees(rot_err) / STRICT_DEG,
            100 * np.asarray(obs["obj_vel"]) / fps / STRICT_CM,
            np.degrees(np.asarray(obs["obj_angvel"])) / fps / STRICT_DEG,
            (100 * (kp - self.human_kp[t]) / STRICT_CM).ravel(),
            ((ref[future] - ref[t]) / s).ravel(),
            (100 * (self.demo.object_pos[future] - pos) / STRICT_CM).ravel(),
        ]
        if self.frame_kp is not None:
            origin, R = hand_frames(np.asarray(obs["keypoints"]), self.frame_kp)
            local = np.einsum("hji,hj->hi", R, pos - origin)  # R^T (pos - origin)
            rel = (Rotation.from_matrix(R).inv() * _rot(quat)).as_rotvec()  # (H, 3)
            parts.append(np.concatenate([100 * local / STRICT_CM, np.degrees(rel) / STRICT_DEG], axis=1).ravel())
        return np.clip(np.concatenate([np.ravel(p) for p in parts]), -100.0, 100.0).astype(np.float32)

    def targets(self, t: int, action: np.ndarray, obs: Observation) -> np.ndarray:
        """(D,) the PD targets of frame ``t + 1`` for ``action`` (D,) in [-1, 1] (clipped): the action moves
        them no further out of the joint limits than the pose it starts from (the reference or the measured
        pose, which may lie a hair outside), so a zero residual is the reference exactly. With
        ``action_form: dgrasp``: :meth:`dgrasp_targets`."""
        if self.cfg.action_form == "dgrasp":
            return self.dgrasp_targets(t, action, obs)
        a = np.clip(np.asarray(action, np.float64), -1.0, 1.0)
        base = self.reference[t + 1] if self.residual else np.asarray(obs["qpos"], np.float64)
        lo, hi = self.bounds
        return np.clip(base + self.scale * a, np.minimum(lo, base), np.maximum(hi, base))

    def goal_base(self, t: int, obs: Observation) -> np.ndarray:
        """(H, 3) m, DGrasp's goal wrist position of each hand for frame ``t + 1`` (its wrist guidance): the
        reference's base slides at ``t + 1`` (the hand root's world position, :mod:`quasisim.sim.kinematics`)
        moved rigidly with the object from the demo's pose at ``t + 1`` to the observed pose now,

        ``g_h = x_obj + R_obj R_demo(t+1)^T (p^ref_h(t+1) - x_demo(t+1))``,

        so the wrist is drawn to where the reference grasp would hold the object as it is now."""
        p = self.reference[t + 1, self.base_cols[:, :3]]  # (H, 3)
        local = self.demo_rot[t + 1].inv().apply(p - self.demo.object_pos[t + 1])
        return _rot(obs["obj_quat"]).apply(local) + np.asarray(obs["obj_pos"], np.float64)

    def dgrasp_targets(self, t: int, action: np.ndarray, obs: Observation) -> np.ndarray:
        """(D,) the PD targets of frame ``t + 1`` in DGrasp's form of action (``action_form: dgrasp``; github
        christsa/dgrasp, ``envs/dgrasp/Environment.hpp``: targets ``action * action_std + action_mean``, the
        mean the measured pose, the wrist's translation guided to the goal):

        ``q* = clip(m + s * clip(a, -1, 1), min(lo, m), max(hi, m))``

        with the mean ``m`` the measured pose ``q_t`` (``obs["qpos"]``) on the finger joints and base hinges and
        :meth:`goal_base` on each hand's base slides, ``s`` :attr:`dgrasp_scale` (``dgrasp_action``: fingers
        0.015 rad, hinges 0.01 rad, slides 0.001 m), ``lo``/``hi`` the joint limits (an action moves a target no
        further out of them than its mean, as :meth:`targets`). A zero action holds the measured fingers and
        wrist rotation and puts the wrist at the goal."""
        a = np.clip(np.asarray(action, np.float64), -1.0, 1.0)
        mean = np.array(obs["qpos"], np.float64)
        mean[self.base_cols[:, :3]] = self.goal_base(t, obs)
        lo, hi = self.bounds
        return np.clip(mean + self.dgrasp_scale * a, np.minimum(lo, mean), np.maximum(hi, mean))

    def schedule_from(self, prev: np.ndarray, q: np.ndarray) -> np.ndarray:
        """The PD targets a frame's schedule starts from on its way to ``q`` (:meth:`Target.advance(start, q)
        <quasisim.targets.base.Target.advance>`): the previous frame's ``prev``, with the velocity
        ``(q - prev) fps`` fed forward; with ``action_form: dgrasp`` ``q`` itself, DGrasp's zero velocity
        targets (the target held over the frame, nothing fed forward)."""
        return q if self.cfg.action_form == "dgrasp" else prev

    def errors(self, t: int, obs: Observation) -> dict[str, float]:
        """Frame ``t``'s errors against the demo: ``object_pos`` (cm), ``object_rot`` (deg), ``keypoints``
        (mean, cm), ``contact`` (mean over the demo's touching fingertips, cm; 0 where none touch)."""
        pos, R = np.asarray(obs["obj_pos"]), _rot(obs["obj_quat"])
        kp = np.asarray(obs["keypoints"])
        touch = self.touch[t]
        contact = 0.0
        if touch.any():
            local = R.inv().apply(kp[self.tips[touch]] - pos)
            contact = float(100 * np.linalg.norm(local - self.tips_local[t, touch], axis=-1).mean())
        return {
            "object_pos": float(100 * np.linalg.norm(pos - self.demo.object_pos[t])),
            "object_rot": float(np.degrees((self.demo_rot[t].inv() * R).magnitude())),
            "keypoints": float(100 * np.linalg.norm(kp[self.metric] - self.human_kp[t], axis=-1).mean()),
            "contact": contact,
        }

    def reward(
        self, t: int, obs: Observation, action: np.ndarray, contacts: Contacts | None = None
    ) -> tuple[float, dict[str, float]]:
        """The reward of reaching frame ``t`` (observed ``obs``) with ``action``, and the errors it came from
        (:meth:`errors`, which the termination judges). With ``reward_form: dgrasp``: DGrasp's reward,
        ``max(clip, sum_k c_k term_k)`` over :meth:`dgrasp_terms` (which needs the world's ``contacts``), and
        beside the errors each weighted term ``c_k term_k`` as ``r_<k>`` (``r_pos``, ``r_pose``, ``r_contact``,
        ``r_impulse``, ``r_obj_vel``, ``r_body_vel``, ``r_body_qvel``; ``action`` unused)."""
        e = self.errors(t, obs)
        if self.cfg.reward_form == "dgrasp":
            if contacts is None:
                raise ValueError("reward_form: dgrasp: the reward needs the world's contacts (Contacts)")
            dg = self.cfg.dgrasp_reward
            coeff = dg.coefficients()
            weighted = {f"r_{k}": coeff[k] * v for k, v in self.dgrasp_terms(t, obs, contacts).items()}
            return float(max(dg.clip, sum(weighted.values()))), {**e, **weighted}
        rw = self.cfg.reward
        r = sum(term.weight * np.exp(-e[k] / term.scale) for k, term in rw.terms().items())
        r -= rw.action_cost * float(np.mean(np.square(action)))
        return float(r), e

    def contact_bodies(self, t: int) -> np.ndarray:
        """(n,) DGrasp's target contact parts at frame ``t``: the hand bodies (indices into :attr:`Contacts.forces`)
        that carry a robot fingertip keypoint whose human fingertip touches the object in the demo at ``t``
        (:func:`demo_contacts`, within ``contact_radius`` of its surface). Only fingertips: the demo's contacts
        are judged for them alone, so DGrasp's other contact parts (palm, proximal and middle phalanges) are never
        targets here."""
        return np.unique(self.kp_body[self.tips[self.touch[t]]])

    def dgrasp_terms(self, t: int, obs: Observation, contacts: Contacts) -> dict[str, float]:
        """DGrasp's reward terms at frame ``t`` (observed ``obs``), as its published code records them (github
        christsa/dgrasp, ``envs/dgrasp/Environment.hpp``), each against this task's reference, before the
        coefficients:

        * ``pos``: ``max(-10, -sum_k |w_k d_k|^2)`` (m^2) over every robot keypoint ``k``, ``d_k`` its position
          against the demo's keypoint at ``t``, both in the object's frame (the demo's through the demo object's
          pose, the robot's through the observed object's); ``w`` :func:`keypoint_weights` (fingertips 4x, mean 1).
          DGrasp's 21 hand parts are here the robot's keypoints, one per human keypoint the hand has.
        * ``pose``: ``max(-10, -|q - q*|)`` (rad) over the finger joints, ``q*`` the reference's PD targets at
          ``t`` (DGrasp's pose vector also holds the wrist's rotation in the object's frame; the base is left out
          here).
        * ``contact``: the share of :meth:`contact_bodies` whose contacts with the object press now (``forces`` >
          0); 0 where the demo touches with none.
        * ``impulse``: ``min(sum_b f_b dt, impulse_cap m g)`` over :meth:`contact_bodies` ``b``: each body's normal
          force in the frame's last physics step times the frame's duration ``dt`` (``frame_dt``; N s), capped at
          ``impulse_cap`` object weights (DGrasp: raisim's impulse of the body's contact in the last physics step,
          capped at 5 x the object's mass in kg).
        * ``obj_vel``: ``|v|^2`` of the object's centre of mass (m^2/s^2; DGrasp's velocity relative to the hand is
          the world velocity in the wrist's axes: the same norm).
        * ``body_vel``, ``body_qvel``: the hand bases' three slide and three hinge velocities squared, summed over
          the hands (m^2/s^2, rad^2/s^2; DGrasp's ``gv_`` of its base dofs, the same kind).
        """
        kp = np.asarray(obs["keypoints"], np.float64)
        local = _rot(obs["obj_quat"]).inv().apply(kp - np.asarray(obs["obj_pos"], np.float64))
        d = self.kp_weight[:, None] * (self.kp_local[t] - local)
        q = np.asarray(obs["qpos"], np.float64)[self.joint_cols]
        qvel = np.asarray(obs["qvel"], np.float64)[self.base_cols]  # (H, 6)
        bodies = self.contact_bodies(t)
        forces = np.asarray(contacts.forces, np.float64)[bodies]
        impulse = float(forces.sum()) * contacts.frame_dt
        return {
            "pos": max(-10.0, -float(np.sum(d * d))),
            "pose": max(-10.0, -float(np.linalg.norm(q - self.reference[t, self.joint_cols]))),
            "contact": float(np.mean(forces > 0)) if len(bodies) else 0.0,
            "impulse": min(impulse, self.cfg.dgrasp_reward.impulse_cap * contacts.weight),
            "obj_vel": float(np.sum(np.square(obs["obj_vel"]))),
            "body_vel": float(np.sum(np.square(qvel[:, :3]))),
            "body_qvel": float(np.sum(np.square(qvel[:, 3:]))),
        }

    def unstable(self, obs: Observation) -> bool:
        """The simulation blew up: a state that is not finite or an object faster than MAX_OBJECT_SPEED."""
        v = np.asarray(obs["obj_vel"])
        finite = all(np.isfinite(np.asarray(obs[k])).all() for k in ("qpos", "obj_pos", "obj_quat"))
        return not finite or float(np.linalg.norm(v)) > MAX_OBJECT_SPEED

    def within(self, errors: dict[str, float], limits: tuple[float, float]) -> bool:
        """The object is within ``limits`` (cm, deg) of the demo's pose (:meth:`errors`)."""
        return errors["object_pos"] <= limits[0] and errors["object_rot"] <= limits[1]
