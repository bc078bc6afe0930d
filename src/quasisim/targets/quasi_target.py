"""One simulator of the physics curriculum behind the :class:`~quasisim.targets.base.Target` interface, so that a
policy can be trained in it (DGrasp-Tracking w/ curriculum, :mod:`quasisim.policy.train`).

Not a target in the sense of :data:`~quasisim.targets.TARGETS`: nothing is judged in it (success is judged in
MuJoCo or PyBullet); it is what ``quasisim/Track-v0`` steps when it is given a curriculum stage
(``physics=...``). One control frame is :func:`~quasisim.sim.step.rollout` of one frame of the quasi-physical
simulator of the scene (:func:`~quasisim.sim.build.build_model`, the hands as one hand set, ``substeps`` per
frame, the ``n_candidates`` nearest hand points tested for contact) with
the curriculum stage's contact settings (``alpha``, ``d_c``, ``k_n``, ``k_f``, ``k_d``, ``mu``), driven as
stage 2 drives it from PD targets (:func:`~quasisim.optim.trajectory.sim_controls`: the hand roots follow the
bases kinematically, the joints obey the PD law towards the interpolated targets). Residual physics is not
part of it (a curriculum's last, residual simulator is the target itself).

Observed like a target (:data:`~quasisim.targets.base.Observation`): the joints, the object's pose and twist
and the robot keypoints from the simulator's state; the bases (kinematic) are the commanded ones, their
velocity the commanded frame-to-frame velocity. A perturbed world (:meth:`set_world`) scales the object's mass
and inertia, the friction coefficient ``mu`` and the joints' PD gains, and moves the object's start, as in the
targets.
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import numpy as np

from quasisim.targets.base import Observation, Target
from quasisim.targets.scene import Scene

if TYPE_CHECKING:
    from quasisim.sim.types import Model

F32 = jnp.float32
STAGE_KEYS = ("alpha", "d_c", "k_n", "k_f", "k_d", "mu")  # a curriculum stage's contact settings


@functools.partial(jax.jit, static_argnames=("fps",))
def _frame(model: Any, params: Any, state: Any, traj: Any, base_quat: jax.Array, fps: float) -> Any:
    """The state after one control frame along ``traj`` (a two-frame :class:`~quasisim.optim.trajectory.Trajectory`
    of PD targets)."""
    from quasisim.optim.trajectory import sim_controls
    from quasisim.sim.step import rollout

    states = rollout(model, params, state, sim_controls(traj, base_quat, fps), checkpoint=False)
    return jax.tree.map(lambda x: x[0], states)


@jax.jit
def _observe(model: Any, state: Any) -> tuple[jax.Array, jax.Array, jax.Array]:
    from quasisim.optim.objective import hand_keypoints
    from quasisim.sim.step import object_pose

    s = jax.tree.map(lambda x: x[None], state)
    pos, quat = object_pose(model, s)
    return pos[0], quat[0], hand_keypoints(model, s)[0]


def scene_model(
    scene: Scene, substeps: int, n_candidates: int, origin: np.ndarray, table_points: str = "hull"
) -> Model:  # fmt: skip
    """The quasi-physical simulator of ``scene``: its hands as one hand set,
    ``substeps`` per frame of ``scene.fps``, the ``n_candidates`` nearest hand points tested for contact, the
    origin at ``origin`` (3,). The one builder of a scene's simulator (stages 1-3 via
    :func:`~quasisim.method.problem.make_problem`, and :class:`QuasiTarget`)."""
    from quasisim.assets.hand import join_hands
    from quasisim.sim.build import SimOptions, build_model, hand_set_points

    opts = SimOptions.for_fps(scene.fps, substeps, n_candidates=n_candidates, table_points=table_points)
    points = hand_set_points(scene.hands, opts)
    return build_model(join_hands(scene.hands), scene.obj, scene.table, opts, origin, points)


class QuasiTarget(Target):
    """The quasi-physical simulator of ``scene`` with the contact settings ``stage`` (:data:`STAGE_KEYS`, and
    ``substeps`` per frame, 20 where it does not say; see the module docstring)."""

    name = "quasisim"

    def __init__(self, scene: Scene, stage: dict[str, float], n_candidates: int = 128) -> None:
        missing = set(STAGE_KEYS) - set(stage)
        if missing:
            raise ValueError(f"a curriculum stage needs {list(STAGE_KEYS)}; missing {sorted(missing)}")
        self.scene, self.stage, self.nominal = scene, {k: float(stage[k]) for k in STAGE_KEYS}, scene
        self.model = scene_model(scene, int(stage.get("substeps", 20)), n_candidates, scene.object_pos0)
        self.base_quat = jnp.asarray(scene.base_quat, F32)
        self.params = self._params(scene)
        self.state: Any = None
        self._q = self._qd = np.zeros(scene.n_dof)  # the commanded PD targets (bases) and their velocity

    def _params(self, scene: Scene) -> Any:
        """The simulator's parameters for ``scene``: its object's mass and inertia, friction and PD gains
        scaled as ``scene``'s against the scene this target was built for."""
        from quasisim.assets.hand import join_hands
        from quasisim.sim.build import default_params

        ratio_mu = scene.physics.friction / self.nominal.physics.friction
        gains = scene.physics.gain_scale / self.nominal.physics.gain_scale
        hand = join_hands(scene.hands)
        p = default_params(self.model, scene.obj.mass, scene.obj.inertia, self.stage | {"mu": self.stage["mu"] * ratio_mu},
                           hand=hand)  # fmt: skip
        return p.replace(joint_kp=p.joint_kp * gains, joint_kv=p.joint_kv * gains)

    @property
    def dt(self) -> float:
        return self.model.dt

    def reset(self, q0: np.ndarray, qd0: np.ndarray | None = None) -> None:
        from quasisim.optim.trajectory import observed_state

        qd0 = np.zeros_like(q0) if qd0 is None else qd0
        z = np.zeros(3)
        obs = {"qpos": q0, "qvel": qd0, "obj_pos": self.scene.object_pos0, "obj_quat": self.scene.object_quat0,
               "obj_vel": z, "obj_angvel": z}  # fmt: skip
        self.state = observed_state(self.model, obs, self.base_quat)
        self._q, self._qd = np.array(q0, np.float64), np.array(qd0, np.float64)

    def advance(self, qa: np.ndarray, qb: np.ndarray) -> None:
        from quasisim.optim.trajectory import Trajectory

        traj = Trajectory.from_q(np.stack([qa, qb]), self.model.n_points, self.model.hand.hand_joints)
        self.state = _frame(self.model, self.params, self.state, traj, self.base_quat, float(self.scene.fps))
        self._q, self._qd = np.array(qb, np.float64), (np.asarray(qb) - np.asarray(qa)) * self.scene.fps

    def observe(self) -> Observation:
        from quasisim.optim.trajectory import join_q, split_q

        if self.state is None:
            raise RuntimeError("quasisim target: call reset() before observe()")
        hj = self.model.hand.hand_joints
        s = self.state
        pos, quat, kp = _observe(self.model, s)
        base, _ = split_q(self._q, hj)
        base_v, _ = split_q(self._qd, hj)
        f64 = lambda x: np.asarray(x, np.float64)  # noqa: E731
        return {"qpos": join_q(base, f64(s.q), hj), "qvel": join_q(base_v, f64(s.qd), hj), "obj_pos": f64(pos),
                "obj_quat": f64(quat), "obj_vel": f64(s.obj_vel), "obj_angvel": f64(s.obj_angvel),
                "keypoints": f64(kp)}  # fmt: skip

    def save_state(self) -> object:
        return (self.state, self._q.copy(), self._qd.copy())

    def restore_state(self, state: object) -> None:
        self.state, q, qd = state  # type: ignore[misc]
        self._q, self._qd = q.copy(), qd.copy()

    def set_world(self, scene: Scene) -> bool:
        """``scene``'s mass, inertia, friction, PD gains and object start (a perturbed copy of this target's
        scene, the same hands and object); the run ends (:meth:`reset` next)."""
        same = lambda s: ([h.name for h in s.hands], s.obj.name, s.table)  # noqa: E731
        if same(scene) != same(self.nominal):
            return False
        self.scene, self.params, self.state = scene, self._params(scene), None
        return True
