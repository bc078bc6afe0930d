"""The one interface of the target simulators (:class:`Target`), the PD law they share, what they produce.

Light on purpose (numpy only at import): the simulators themselves load in their own modules
(:mod:`quasisim.targets.mujoco_target`, :mod:`quasisim.targets.pybullet_target`).

* :func:`pd_gains`: per dof of a hand, ``kp``, ``kv``, the PD force limit and the joint damping (once per hand);
* :func:`pd_schedule`: within a control frame from targets ``qa`` to ``qb``, the PD target of every physics
  step and the fed-forward target velocity; every backend's :meth:`Target.advance` and the batched window
  rollouts apply exactly these numbers;
* :class:`Target`: reset, observe, save and restore the state, set it from an observation (:meth:`Target.sync`),
  advance one frame, roll a whole clip out
  (:meth:`Target.rollout`, written once here), roll candidate windows out (:meth:`Target.rollout_windows`),
  judge a clip (:meth:`Target.judge`).
"""

from __future__ import annotations

import abc
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from quasisim.files import save_npz_atomic

if TYPE_CHECKING:
    from quasisim.assets.hand import HandModel
    from quasisim.data.demo import Demo
    from quasisim.optim.objective import Weights
    from quasisim.targets.scene import Scene

# A rollout faster than this is a numerical blow-up, not a manipulation (a dropped object reaches ~4 m/s).
MAX_OBJECT_SPEED = 10.0  # m/s, object origin between two frames
MAX_HAND_SPEED = 30.0  # m/s, any robot keypoint between two frames

Observation = dict[str, np.ndarray]
"""A target's state now (:meth:`Target.observe`), keys :data:`OBS_KEYS`: ``qpos``, ``qvel`` (D,) hands (m, rad;
per s), ``obj_pos`` (3,) object origin (m), ``obj_quat`` (4,) w x y z, ``obj_vel`` (3,) world linear velocity
of the object's centre of mass (m/s), ``obj_angvel`` (3,) world angular velocity (rad/s), ``keypoints``
(K, 3) every robot keypoint of every hand (m)."""
OBS_KEYS = ("qpos", "qvel", "obj_pos", "obj_quat", "obj_vel", "obj_angvel", "keypoints")


@dataclass(frozen=True, eq=False)
class TargetRollout:
    """What a target simulator produced, sampled at the control frames (T frames).

    Attributes:
        target: ``"mujoco"`` or ``"pybullet"``.
        qpos: (T, D) measured hand generalized positions (base coordinates + joints; D = 6 + J per hand,
            the hands concatenated, right then left).
        object_pos: (T, 3) m.  object_quat: (T, 4) w x y z.
        keypoints: (T, K, 3) all robot keypoints of every hand (m).
        kp_human: (K,) index of each robot keypoint into the human keypoints of all hands
            (``Demo.human_joints``: the left hand's are 21..41).  kp_metric: (K,) used in MPJPE.
        dt: physics step (s); substeps: physics steps per control frame; wall_s: wall time of the rollout.
        extras: ``sim_warnings`` (name -> count) where the simulator reports numerical trouble (MuJoCo).
    """

    target: str
    qpos: np.ndarray
    object_pos: np.ndarray
    object_quat: np.ndarray
    keypoints: np.ndarray
    kp_human: np.ndarray
    kp_metric: np.ndarray
    dt: float
    substeps: int
    wall_s: float
    extras: dict[str, Any] = field(default_factory=dict)

    @property
    def robot_keypoints(self) -> np.ndarray:
        """(T, K_metric, 3) the keypoints used by the metrics."""
        return self.keypoints[:, self.kp_metric]

    @property
    def human_keypoint_index(self) -> np.ndarray:
        return self.kp_human[self.kp_metric]

    @property
    def instability(self) -> str:
        """Why this rollout is numerically unstable (the simulator's warnings, NaN or inf, an energy blow-up:
        speeds no hand or held object reaches), or "" when it is not."""
        warned = {k: int(n) for k, n in self.extras.get("sim_warnings", {}).items() if n}
        if warned:
            return f"{self.target} warned: " + ", ".join(f"{k} x{n}" for k, n in warned.items())
        for name, a in (("hand qpos", self.qpos), ("object pose", self.object_pos), ("keypoints", self.keypoints)):
            if not np.isfinite(a).all():
                return f"NaN or inf in the {name} from frame {int(np.argwhere(~np.isfinite(a))[0][0])}"
        frame_dt = self.dt * self.substeps
        v_obj = np.linalg.norm(np.diff(self.object_pos, axis=0), axis=-1) / frame_dt
        v_kp = np.linalg.norm(np.diff(self.keypoints, axis=0), axis=-1).max(axis=-1, initial=0.0) / frame_dt
        for what, v, vmax in (("object", v_obj, MAX_OBJECT_SPEED), ("hand keypoint", v_kp, MAX_HAND_SPEED)):
            if len(v) and v.max() > vmax:
                t = int(np.argmax(v > vmax))
                return f"energy blow-up: {what} speed {v[t]:.3g} m/s (limit {vmax:g}) at frame {t + 1}"
        return ""

    def save(self, path: str | Path) -> Path:
        """``rollout.npz``: object_pos, object_quat, robot_keypoints, human_keypoint_index (+ full state)."""
        return save_npz_atomic(
            path,
            target=np.array(self.target),
            object_pos=self.object_pos.astype(np.float64),
            object_quat=self.object_quat.astype(np.float64),
            robot_keypoints=self.robot_keypoints.astype(np.float64),
            human_keypoint_index=self.human_keypoint_index.astype(np.int64),
            qpos=self.qpos.astype(np.float64),
            all_keypoints=self.keypoints.astype(np.float64),
            all_human_keypoint_index=self.kp_human.astype(np.int64),
            dt=np.array(self.dt),
            substeps=np.array(self.substeps),
            instability=np.array(self.instability),
        )


@dataclass(frozen=True, eq=False)
class Prediction:
    """Candidate rollouts sampled at the window's frames ``t+1 .. t+H`` (N candidates).

    Attributes:
        qpos: (N, H, D) hands.  obj_pos: (N, H, 3) m.  obj_quat: (N, H, 4) w x y z.
        keypoints: (N, H, K_metric, 3) metric keypoints (m).  n_steps: physics steps simulated.
        qvel: (N, H, D) hands' velocities.  obj_vel, obj_angvel: (N, H, 3) the object's centre-of-mass linear
            and angular velocity, world axes (m/s, rad/s); as :meth:`Target.observe` gives them.
        cones: (N, H, C, 2) with ``contacts=C`` only: the C strongest hand-object contacts of each hand (all
            hands' slots concatenated), each as its friction-cone radius and tangential load in object weights
            (:func:`quasisim.targets.grasp.cone_loads`, the world's own friction and mass; empty slots 0).
    """

    qpos: np.ndarray
    obj_pos: np.ndarray
    obj_quat: np.ndarray
    keypoints: np.ndarray
    n_steps: int
    qvel: np.ndarray | None = None
    obj_vel: np.ndarray | None = None
    obj_angvel: np.ndarray | None = None
    cones: np.ndarray | None = None


class Prune(NamedTuple):
    """Early exit for candidate windows (:meth:`Target.rollout_windows`): every candidate runs the first
    ``frames`` frames of its window; ``keep`` gets their :class:`Prediction` of those frames (N candidates,
    ``frames`` frames) and returns the indices of the candidates that run the rest."""

    frames: int
    keep: Callable[[Prediction], np.ndarray]


def _head(out: dict[str, np.ndarray], frames: int) -> Prediction:
    """The :class:`Prediction` of the first ``frames`` frames of per-candidate arrays ``out`` (N, H, ...)."""
    return Prediction(**{k: v[:, :frames] for k, v in out.items()}, n_steps=0)


# ---- the PD law ---------------------------------------------------------------------------------------


class PDGains(NamedTuple):
    """Per dof of one hand (6 + J each, base then joints): the PD law ``tau = clip(kp (q* - q) + kv (qd* - qd),
    +-force_limit) - damping qd``.

    Attributes:
        kp: N/m (base position), N m/rad.  kv: N s/m, N m s/rad.  force_limit: N m on the joints' PD part,
            inf on the base.  damping: joint damping (N m s/rad), 0 on the base.
    """

    kp: np.ndarray
    kv: np.ndarray
    force_limit: np.ndarray
    damping: np.ndarray


def pd_gains(hand: HandModel, scale: float = 1.0) -> PDGains:
    """The PD gains of every dof of ``hand`` (its config's ``pd``: ``base_pos`` on the 3 base translations,
    ``base_rot`` on the 3 base angles, ``joint`` on the J joints), ``kp`` and ``kv`` times ``scale``
    (:attr:`~quasisim.targets.scene.PhysicsOptions.gain_scale`: 1 but in a perturbed target)."""
    pd, J = hand.config.pd, hand.n_joints
    kp = scale * np.array([pd.base_pos.kp] * 3 + [pd.base_rot.kp] * 3 + [pd.joint.kp] * J)
    kv = scale * np.array([pd.base_pos.kv] * 3 + [pd.base_rot.kv] * 3 + [pd.joint.kv] * J)
    limit = np.r_[np.full(6, np.inf), np.full(J, pd.joint_force_limit)]
    damping = np.r_[np.zeros(6), np.full(J, pd.joint_damping)]
    return PDGains(kp, kv, limit, damping)


def pd_schedule(qa: np.ndarray, qb: np.ndarray, substeps: int, fps: float) -> tuple[np.ndarray, np.ndarray]:
    """The PD targets of one control frame from targets ``qa`` to ``qb`` (..., D), physics step by step.

    Returns:
        targets: (..., substeps, D) the PD target of physics step ``k``, ``(1 - s) qa + s qb`` with
            ``s = (k + 1) / substeps`` (the frame ends at ``qb``);
        velocity: (..., D) the fed-forward target velocity ``(qb - qa) fps`` (m/s, rad/s), the same at every step.
    """
    qa, qb = np.asarray(qa), np.asarray(qb)
    s = ((np.arange(substeps) + 1) / substeps)[:, None]
    return (1 - s) * qa[..., None, :] + s * qb[..., None, :], (qb - qa) * fps


def feed_forward(kv: np.ndarray, qa: np.ndarray, qb: np.ndarray, fps: float) -> np.ndarray:
    """``kv qd*``: the feed-forward force of :func:`pd_schedule`'s velocity, as ``kv (qb - qa) fps`` evaluated
    left to right (the order the PyBullet law has always used: the same bits)."""
    return kv * (qb - qa) * fps


# ---- the interface --------------------------------------------------------------------------------------


class Target(abc.ABC):
    """A target simulator of a :class:`~quasisim.targets.scene.Scene`, advanced one control frame at a time.

    A run: :meth:`reset`, then :meth:`observe` and :meth:`advance` in turn. :meth:`rollout` is that loop over a
    whole clip; :meth:`rollout_windows` tries candidate windows from the current state; :meth:`judge` scores a
    clip. A capability a backend lacks raises ``NotImplementedError`` saying why. Release with :meth:`close`
    (or ``with``).
    """

    name: str
    scene: Scene

    # ---- what every backend implements ----

    @property
    @abc.abstractmethod
    def dt(self) -> float:
        """Physics step (s)."""

    @abc.abstractmethod
    def reset(self, q0: np.ndarray, qd0: np.ndarray | None = None) -> None:
        """Start a run: the hands at ``q0`` (D,) with velocity ``qd0`` (D,; default 0), the object at the
        scene's initial pose, at rest."""

    @abc.abstractmethod
    def observe(self) -> Observation:
        """The state now (:data:`Observation`)."""

    @abc.abstractmethod
    def save_state(self) -> object:
        """An exact copy of the simulation state (for :meth:`restore_state`)."""

    @abc.abstractmethod
    def restore_state(self, state: object) -> None:
        """Put the simulation back into ``state`` (of :meth:`save_state`): advancing from it again gives the
        same numbers."""

    @abc.abstractmethod
    def advance(self, qa: np.ndarray, qb: np.ndarray) -> None:
        """One control frame (:attr:`substeps` physics steps) with the PD targets of :func:`pd_schedule` from
        ``qa`` to ``qb`` (D each)."""

    # ---- optional hooks ----

    def release_state(self, state: object) -> None:
        """Free ``state`` (of :meth:`save_state`) where the simulator holds it; by default nothing to do."""
        return None

    def set_hands(self, q: np.ndarray, qd: np.ndarray) -> None:
        """Put the hands at ``q`` (D,) with velocity ``qd`` (D,), the object untouched."""
        raise NotImplementedError(f"target {self.name}: setting the hands' state mid-run is not implemented")

    def sync(self, obs: Observation) -> None:
        """Put the simulation into the observed state ``obs`` (:data:`Observation`: the hands' ``qpos``, ``qvel``;
        the object's pose and its centre of mass's linear and angular velocity, world axes), as a model is
        re-synced to a measured world (:mod:`quasisim.method.track`). Only what ``obs`` holds is set: the
        solver's warm start and contact history are cleared, so advancing from it may differ from the
        observed world's own next frame in the solver's last digits. Needs a run (:meth:`reset`) first."""
        raise NotImplementedError(f"target {self.name}: setting the state from an observation is not implemented")

    def set_world(self, scene: Scene) -> bool:
        """Simulate ``scene`` from the next :meth:`reset` on without building the simulator again, where
        ``scene`` is this target's scene with other physical parameters only (a world of
        :func:`~quasisim.targets.perturb.perturbed_scene`: the object's mass and inertia, friction, the PD gains,
        the object's initial pose), exactly as a target built for ``scene`` would. Returns False where it cannot
        (another structure, or a backend without it; the caller builds a target for ``scene``): by default."""
        return False

    def contact_forces(self, slots: int) -> np.ndarray:
        """(n_hands, slots, 3) the hand-object contacts now, per hand its ``slots`` strongest
        (:func:`quasisim.targets.grasp.strongest`): the force the hand exerts on the object in each contact's
        frame (normal, pressing > 0; the two tangential components), N; empty slots 0."""
        raise NotImplementedError(f"target {self.name}: contact forces are not reported (mujoco and pybullet do)")

    def body_contact_forces(self) -> np.ndarray:
        """(n_hand_bodies,) per hand body (each hand's ``body_names`` in order, the hands concatenated) the summed
        normal force of its contacts with the object during the last physics step (N; pressing > 0; 0: none)."""
        raise NotImplementedError(
            f"target {self.name}: per-body contact forces are not reported (mujoco and pybullet do)"
        )

    def contact_cones(self, slots: int) -> np.ndarray:
        """(n_hands * slots, 2) :meth:`contact_forces` as friction-cone radii and tangential loads in object
        weights (:func:`quasisim.targets.grasp.cone_loads`) in this target's world."""
        from quasisim.targets.grasp import cone_loads

        phys = self.scene.physics
        f = self.contact_forces(slots).reshape(-1, 3)
        return cone_loads(f, phys.friction, self.scene.obj.mass * phys.gravity)

    def extras(self) -> dict[str, Any]:
        """:attr:`TargetRollout.extras` of the run so far (the simulator's warnings, where it counts them)."""
        return {}

    # ---- written once ----

    @property
    def substeps(self) -> int:
        """Physics steps per control frame: ``round(1 / (fps dt))``, at least 1."""
        return max(1, round(1.0 / (self.scene.fps * self.dt)))

    def rollout(self, q_targets: np.ndarray, init_qvel: bool = True) -> TargetRollout:
        """Run the PD targets ``q_targets`` (T, D) from the scene's initial object pose (D = 6 + J per hand,
        the hands concatenated): the hands start at ``q_targets[0]``, with the targets' initial velocity
        ``(q_targets[1] - q_targets[0]) fps`` when ``init_qvel``; every frame observed, then advanced."""
        q_targets = np.asarray(q_targets, dtype=np.float64)
        D = self.scene.n_dof
        if q_targets.ndim != 2 or q_targets.shape[1] != D:
            raise ValueError(f"q_targets must have shape (T, {D}), got {q_targets.shape}")
        T = len(q_targets)
        self.reset(q_targets[0], (q_targets[1] - q_targets[0]) * self.scene.fps if init_qvel and T > 1 else None)
        frames = []
        t0 = time.perf_counter()
        for t in range(T):
            frames.append(self.observe())
            if t < T - 1:
                self.advance(q_targets[t], q_targets[t + 1])
        return self.recorded(frames, time.perf_counter() - t0)

    def recorded(self, frames: list[Observation], wall_s: float) -> TargetRollout:
        """The observed ``frames`` (T observations of this run) as a :class:`TargetRollout`."""
        from quasisim.rotations import sign_continuous

        scene = self.scene
        return TargetRollout(
            target=self.name,
            qpos=np.array([f["qpos"] for f in frames]),
            object_pos=np.array([f["obj_pos"] for f in frames]),
            object_quat=sign_continuous(np.array([f["obj_quat"] for f in frames])),
            keypoints=np.array([f["keypoints"] for f in frames]),
            kp_human=scene.kp_human,
            kp_metric=scene.kp_metric,
            dt=float(self.dt),
            substeps=self.substeps,
            wall_s=wall_s,
            extras=self.extras(),
        )

    def rollout_windows(
        self, wins: np.ndarray, qd0: np.ndarray | None = None, prune: Prune | None = None, contacts: int = 0
    ) -> Prediction:
        """Roll candidate windows (N, H + 1, D) out from the current state, each for H frames, and leave the
        state as it was; ``qd0`` (N, D) replaces each candidate's initial hand velocity (its hands then start
        at the window's frame 0). With ``prune`` (:class:`Prune`), every candidate runs ``prune.frames``
        frames, then only those ``prune.keep`` picks run on (the others' later frames are NaN). With
        ``contacts`` > 0 also :attr:`Prediction.cones` (:meth:`contact_cones`, that many slots per hand). Here:
        one candidate after the other from :meth:`save_state`."""
        N, H, D = len(wins), wins.shape[1] - 1, wins.shape[2]
        metric = np.flatnonzero(self.scene.kp_metric)
        shapes = {"qpos": (D,), "obj_pos": (3,), "obj_quat": (4,), "keypoints": (len(metric), 3), "qvel": (D,),
                  "obj_vel": (3,), "obj_angvel": (3,)}  # fmt: skip
        if contacts > 0:
            shapes["cones"] = (len(self.scene.hands) * contacts, 2)
        out = {k: np.full((N, H, *s), np.nan) for k, s in shapes.items()}
        split = H if prune is None else min(max(prune.frames, 1), H)

        def run(i: int, frames: range) -> None:
            for f in frames:
                self.advance(wins[i, f], wins[i, f + 1])
                o = self.observe()
                if contacts > 0:
                    o = {**o, "cones": self.contact_cones(contacts)}
                for k in shapes:
                    out[k][i, f] = o[k][metric] if k == "keypoints" else o[k]

        state = self.save_state()
        heads = []  # with pruning: each candidate's state after the first `split` frames
        for i in range(N):
            self.restore_state(state)
            if qd0 is not None:
                self.set_hands(wins[i, 0], qd0[i])
            run(i, range(split))
            if prune is not None:
                heads.append(self.save_state())
        kept = np.arange(N) if prune is None else np.asarray(prune.keep(_head(out, split)), dtype=int)
        for i, head in enumerate(heads):
            if i in kept:
                self.restore_state(head)
                run(i, range(split, H))
            self.release_state(head)
        self.restore_state(state)
        self.release_state(state)
        return Prediction(**out, n_steps=(N * split + len(kept) * (H - split)) * self.substeps)

    def judge(self, demo: Demo, q_targets: np.ndarray, weights: Weights) -> float:
        """The whole-clip objective J of :meth:`rollout` of ``q_targets`` (T, D) against ``demo``
        (:func:`quasisim.optim.objective.clip_cost`; infinity when the rollout is unstable)."""
        from quasisim.optim.objective import clip_cost

        return clip_cost(demo, self.rollout(q_targets), weights)

    # ---- lifetime ----

    def close(self) -> None:
        """Release the simulator's resources (idempotent); by default nothing to release."""
        return None

    def __enter__(self) -> Target:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
