"""Stage 3's replay buffer and prediction windows: how well the quasi-physical simulator predicts the target.

* :class:`ReplayBuffer` (:func:`collect`): PD-target trajectories rolled out in a target (MuJoCo by default),
  every frame's observation (:data:`~quasisim.targets.base.Observation`: hand joints and velocities, object
  pose and twist, robot keypoints) and the PD targets.
* :class:`Windows` (:func:`windows`): from a recorded frame ``t`` the target's state is put into the
  quasi-physical simulator (contacts start fresh) and the recorded PD targets of frames ``t+1 .. t+H`` are
  applied (open loop; paper appendix, transition prediction analysis).
* :func:`prediction_errors`: the predicted object pose and robot keypoints against the target's after
  ``h = 1 .. H`` frames, beside a zero-motion predictor (the object stays where it is at ``t``), so that an
  error has a scale: a model that predicts worse than "nothing moves" has not learned the contact dynamics.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from quasisim.optim.objective import hand_keypoints
from quasisim.optim.trajectory import Trajectory, observed_state, sim_controls
from quasisim.rotations import quat_angle_deg
from quasisim.sim.step import object_pose, rollout
from quasisim.sim.types import Model, Params, State, pytree
from quasisim.targets import OBS_KEYS, Observation, Target, TargetRollout, make_target
from quasisim.targets.scene import Scene

Array = jax.Array
F32 = jnp.float32


def record_target(target: Target, q_targets: np.ndarray, fps: float) -> tuple[list[Observation], TargetRollout]:
    """Replay ``q_targets`` (T, D) in ``target`` from the scene's start, the hands with the targets' initial
    velocity ``(q[1] - q[0]) fps``: every frame's observation and the recorded rollout (wall time 0)."""
    q = np.asarray(q_targets, np.float64)
    target.reset(q[0], (q[1] - q[0]) * fps)
    obs = []
    for t in range(len(q)):
        obs.append(target.observe())
        if t < len(q) - 1:
            target.advance(q[t], q[t + 1])
    return obs, target.recorded(obs, 0.0)


@dataclass(frozen=True, eq=False)
class ReplayBuffer:
    """``R`` rollouts of ``T`` frames in the target.

    Attributes:
        q_targets: (R, T, 6 + J) the PD targets applied.  qpos, qvel: (R, T, 6 + J) hand (m, rad; per s).
        obj_pos: (R, T, 3) m.  obj_quat: (R, T, 4) w x y z.  obj_vel, obj_angvel: (R, T, 3) world (m/s, rad/s).
        keypoints: (R, T, K, 3) all robot keypoints (m).
    """

    q_targets: np.ndarray
    qpos: np.ndarray
    qvel: np.ndarray
    obj_pos: np.ndarray
    obj_quat: np.ndarray
    obj_vel: np.ndarray
    obj_angvel: np.ndarray
    keypoints: np.ndarray

    @property
    def n_rollouts(self) -> int:
        return len(self.q_targets)

    def arrays(self) -> dict[str, np.ndarray]:
        """The buffer as named arrays (for a checkpoint)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    def extended(self, other: ReplayBuffer, capacity: int) -> ReplayBuffer:
        """This buffer and ``other``, keeping the newest ``capacity`` rollouts."""
        return ReplayBuffer(**{k: np.concatenate([v, getattr(other, k)])[-capacity:] for k, v in self.arrays().items()})

    def observation(self, r: int, t: int) -> Observation:
        """Frame ``t`` of rollout ``r`` as a target observation (:meth:`~quasisim.targets.base.Target.observe`)."""
        return {k: getattr(self, k)[r, t] for k in OBS_KEYS}


def collect(scene: Scene, controls: list[np.ndarray], fps: float, target: str = "mujoco") -> ReplayBuffer:
    """Roll each PD-target trajectory (T, D) of ``controls`` out in ``target`` (one of
    :data:`~quasisim.targets.TARGETS`, built once for ``scene``) and record every frame."""
    frames: dict[str, list[np.ndarray]] = {k: [] for k in ("q_targets", *OBS_KEYS)}
    with make_target(target, scene) as tgt:
        for q in controls:
            obs, _ = record_target(tgt, q, fps)
            frames["q_targets"].append(np.asarray(q, np.float64))
            for k in OBS_KEYS:
                frames[k].append(np.stack([o[k] for o in obs]))
    return ReplayBuffer(**{k: np.stack(v) for k, v in frames.items()})


@pytree
class Windows:
    """``B`` H-frame prediction windows (array leaves batched over B; see module docstring).

    Attributes:
        s0: the target's state at each window's start, as a simulator :class:`State` (leading axis B).
        wins: the window's PD targets, H + 1 frames each, as a :class:`Trajectory` (leading axis B).
        obj_pos, obj_quat: (B, H, ...) what the target's object did.  keypoints: (B, H, K, 3) its keypoints.
        start_pos, start_quat: (B, 3), (B, 4) the object at each window's start (zero-motion predictor).
    """

    s0: State
    wins: Trajectory
    obj_pos: Array
    obj_quat: Array
    keypoints: Array
    start_pos: Array
    start_quat: Array

    def __len__(self) -> int:
        return len(self.obj_pos)

    def take(self, idx: Array) -> Windows:
        """The windows ``idx`` (traceable)."""
        return jax.tree_util.tree_map(lambda x: x[idx], self)


def windows(
    model: Model, buf: ReplayBuffer, starts: list[tuple[int, int]], horizon: int, base_quat: np.ndarray
) -> Windows:
    """The windows starting at frame ``t`` of rollout ``r`` for each ``(r, t)`` of ``starts``."""
    if not starts:
        raise ValueError("no window starts given")
    T = buf.q_targets.shape[1]
    late = [(r, t) for r, t in starts if t + horizon >= T]
    if late:
        raise ValueError(
            f"a {horizon}-frame window needs {horizon} frames after its start; {late[0]} is too late (T = {T})"
        )
    bq = jnp.asarray(base_quat, F32)
    s0 = [observed_state(model, buf.observation(r, t), bq) for r, t in starts]
    wins = [
        Trajectory.from_q(buf.q_targets[r, t : t + horizon + 1], model.n_points, model.hand.hand_joints)
        for r, t in starts
    ]
    stack = lambda xs: jax.tree_util.tree_map(lambda *a: jnp.stack(a), *xs)  # noqa: E731
    sl = [(r, slice(t + 1, t + horizon + 1)) for r, t in starts]
    arr = lambda xs: jnp.asarray(np.stack(xs), F32)  # noqa: E731
    return Windows(
        stack(s0), stack(wins), arr([buf.obj_pos[r, s] for r, s in sl]), arr([buf.obj_quat[r, s] for r, s in sl]),
        arr([buf.keypoints[r, s] for r, s in sl]), arr([buf.obj_pos[r, t] for r, t in starts]),
        arr([buf.obj_quat[r, t] for r, t in starts]),
    )  # fmt: skip


def split_starts(
    n_rollouts: int, T: int, horizon: int, held_out: float
) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """Training and held-out window starts: a window is held out when it starts in the last ``held_out``
    fraction of the clip; training windows end before the first held-out start (they never see its frames)."""
    cut = round((T - horizon) * (1.0 - held_out))
    train = [(r, t) for r in range(n_rollouts) for t in range(0, cut - horizon + 1)]
    test = [(r, t) for r in range(n_rollouts) for t in range(cut, T - horizon)]
    return train, test


def predict(model: Model, params: Params, w: Windows, fps: float, base_quat: np.ndarray) -> tuple[Array, Array, Array]:
    """The simulator's predictions of all windows: object positions (B, H, 3), quaternions (B, H, 4) and
    keypoints (B, H, K, 3)."""
    bq = jnp.asarray(base_quat, F32)

    def one(s0: State, win: Trajectory) -> tuple[Array, Array, Array]:
        states = rollout(model, params, s0, sim_controls(win, bq, fps))
        pos, quat = object_pose(model, states)
        return pos, quat, hand_keypoints(model, states)

    return jax.vmap(one)(w.s0, w.wins)


_predict_jit = jax.jit(predict, static_argnames=("fps",))


@dataclass(frozen=True, eq=False)
class WindowErrors:
    """Mean errors after h = 1..H frames over windows (non-finite predictions left out and counted).

    Attributes: obj_pos_cm, obj_rot_deg, keypoints_mm: (H,).  static_pos_cm, static_rot_deg: (H,) of the
    zero-motion predictor.  n_windows, n_diverged: counts.
    """

    obj_pos_cm: np.ndarray
    obj_rot_deg: np.ndarray
    keypoints_mm: np.ndarray
    static_pos_cm: np.ndarray
    static_rot_deg: np.ndarray
    n_windows: int
    n_diverged: int


def prediction_errors(
    model: Model, params: Params, w: Windows, fps: float, base_quat: np.ndarray, chunk: int = 16
) -> WindowErrors:
    """H-frame prediction errors of the simulator ``params`` on windows ``w`` (see :class:`WindowErrors`)."""
    bq = jnp.asarray(base_quat, jnp.float32)
    n, chunk = len(w), min(chunk, len(w))
    # every chunk of one size (the last one padded with its final window, then trimmed): one compiled program
    idx = [np.minimum(np.arange(i, i + chunk), n - 1) for i in range(0, n, chunk)]
    outs = [_predict_jit(model, params, w.take(jnp.asarray(i)), fps, bq) for i in idx]
    pos, quat, kp = (np.concatenate([np.asarray(o[k], np.float64) for o in outs])[:n] for k in range(3))
    w = jax.tree_util.tree_map(lambda x: np.asarray(x, np.float64), w)
    pos_e = np.linalg.norm(pos - w.obj_pos, axis=-1) * 100.0
    rot_e = quat_angle_deg(quat, w.obj_quat)
    kp_e = np.linalg.norm(kp - w.keypoints, axis=-1).mean(-1) * 1000.0
    ok = np.isfinite(pos_e).all(1) & np.isfinite(kp_e).all(1) & np.isfinite(rot_e).all(1)
    mean = lambda x: x[ok].mean(0) if ok.any() else np.full(x.shape[1], np.nan)  # noqa: E731
    static_pos = np.linalg.norm(w.obj_pos - w.start_pos[:, None], axis=-1) * 100.0
    static_rot = quat_angle_deg(np.broadcast_to(w.start_quat[:, None], w.obj_quat.shape), w.obj_quat)
    return WindowErrors(
        mean(pos_e), mean(rot_e), mean(kp_e), static_pos.mean(0), static_rot.mean(0), len(w), int((~ok).sum())
    )
