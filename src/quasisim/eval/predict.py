"""How well the quasi-physical simulator predicts the target: the measure of stage 3's fitting.

Stage 3 of the paper fits residual physics and S so that the quasi-physical simulator's multi-step
predictions match transitions recorded in the target. This module holds what that fitting is judged by,
the open-loop ``H``-step prediction error (paper appendix, transition prediction analysis):

1. replay PD targets in MuJoCo frame by frame and record every frame's full state (hand joints and
   velocities, object pose and twist) and the robot keypoints;
2. from each recorded frame ``t``, put the state into the quasi-physical simulator (contacts start fresh),
   apply the same PD targets for frames ``t+1 .. t+H`` and compare the predicted object pose and robot
   keypoints with MuJoCo's after ``h = 1 .. H`` frames.

A zero-motion predictor (the object stays where it is at ``t``) is reported beside it, so that an error
has a scale: a model that predicts worse than "nothing moves" has not learned the contact dynamics.
The residual networks are not fitted yet (see the README status).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from quasisim.optim.objective import hand_keypoints
from quasisim.optim.trajectory import Trajectory, observed_state, sim_controls
from quasisim.rotations import quat_angle_deg
from quasisim.sim.step import object_pose, rollout
from quasisim.sim.types import Model, Params, State
from quasisim.targets import TargetRollout
from quasisim.targets.mujoco_target import MujocoTarget
from quasisim.targets.scene import Scene

F32 = jnp.float32


@dataclass(frozen=True, eq=False)
class PredictionError:
    """Errors of ``H``-step open-loop predictions, averaged over the windows of one clip.

    Attributes:
        horizon: H (frames).  n_windows: windows (start frames ``0 .. T - H - 1``).
        n_diverged: windows whose prediction became non-finite (left out of the means).
        obj_pos_cm: (H,) object position error after h = 1..H frames (cm).
        obj_rot_deg: (H,) object rotation error (deg).
        keypoints_mm: (H,) mean robot-keypoint error (mm).
        static_pos_cm, static_rot_deg: (H,) the same for the zero-motion predictor.
    """

    horizon: int
    n_windows: int
    n_diverged: int
    obj_pos_cm: np.ndarray
    obj_rot_deg: np.ndarray
    keypoints_mm: np.ndarray
    static_pos_cm: np.ndarray
    static_rot_deg: np.ndarray

    def summary(self) -> dict[str, float]:
        """The figures after the last frame of the horizon."""
        return {
            "horizon": self.horizon,
            "n_windows": self.n_windows,
            "n_diverged": self.n_diverged,
            "obj_pos_cm": float(self.obj_pos_cm[-1]),
            "obj_rot_deg": float(self.obj_rot_deg[-1]),
            "keypoints_mm": float(self.keypoints_mm[-1]),
            "static_pos_cm": float(self.static_pos_cm[-1]),
            "static_rot_deg": float(self.static_rot_deg[-1]),
        }


def record_target(scene: Scene, q_targets: np.ndarray, fps: float) -> tuple[list[dict[str, np.ndarray]], TargetRollout]:
    """Replay ``q_targets`` (T, 6 + J) in MuJoCo: every frame's observation and the recorded rollout."""
    q = np.asarray(q_targets, np.float64)
    sess = MujocoTarget(scene).session(q[0], (q[1] - q[0]) * fps)
    obs = []
    for t in range(len(q)):
        sess.record()
        obs.append(sess.observe())
        if t < len(q) - 1:
            sess.advance(q[t], q[t + 1])
    return obs, sess.result(0.0)


def prediction_error(
    model: Model, params: dict[str, Params], base_quat: np.ndarray, fps: float, q_targets: np.ndarray,
    obs: list[dict], ro: TargetRollout, horizon: int = 10,
) -> dict[str, PredictionError]:  # fmt: skip
    """Open-loop ``horizon``-frame predictions of the quasi-physical simulator ``model`` under each of the
    named parameter sets ``params`` (S already applied), from the target's recorded states ``obs`` under
    ``q_targets``; ``ro`` is the target's rollout of the same run (see :func:`record_target`). One compiled
    prediction serves every parameter set (they are array leaves)."""
    T = len(q_targets)
    if T <= horizon:
        raise ValueError(f"a {horizon}-frame prediction needs more than {horizon} frames, the clip has {T}")
    bq = jnp.asarray(base_quat, F32)

    @jax.jit
    def predict(p: Params, s0: State, win: Trajectory) -> tuple[jax.Array, jax.Array, jax.Array]:
        states = rollout(model, p, s0, sim_controls(win, bq, fps))
        pos, quat = object_pose(model, states)
        return pos, quat, hand_keypoints(model, states)

    starts = range(T - horizon)
    s0s = [observed_state(model, obs[t], bq) for t in starts]
    wins = [Trajectory.from_q(q_targets[t : t + horizon + 1], model.n_points) for t in starts]
    spos_e, srot_e = [], []
    for t in starts:
        sl = slice(t + 1, t + horizon + 1)
        spos_e.append(np.linalg.norm(ro.object_pos[t] - ro.object_pos[sl], axis=-1) * 100.0)
        srot_e.append(quat_angle_deg(ro.object_quat[t][None], ro.object_quat[sl]))
    m = lambda x: np.mean(np.stack(x), 0)  # noqa: E731
    out = {}
    mf = lambda x, ok: np.mean(np.stack(x)[ok], 0) if ok.any() else np.full(horizon, np.nan)  # noqa: E731
    for name, p in params.items():
        pos_e, rot_e, kp_e = [], [], []
        for t, s0, win in zip(starts, s0s, wins, strict=True):
            pos, quat, kp = (np.asarray(x, np.float64) for x in predict(p, s0, win))
            sl = slice(t + 1, t + horizon + 1)
            pos_e.append(np.linalg.norm(pos - ro.object_pos[sl], axis=-1) * 100.0)
            rot_e.append(quat_angle_deg(quat, ro.object_quat[sl]))
            kp_e.append(np.linalg.norm(kp - ro.keypoints[sl], axis=-1).mean(-1) * 1000.0)
        ok = np.isfinite(np.stack(pos_e)).all(1) & np.isfinite(np.stack(kp_e)).all(1)
        out[name] = PredictionError(
            horizon, len(starts), int((~ok).sum()), mf(pos_e, ok), mf(rot_e, ok), mf(kp_e, ok), m(spos_e), m(srot_e)
        )
    return out
