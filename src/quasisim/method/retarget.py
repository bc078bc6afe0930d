"""Kinematic retargeting: per-frame keypoint IK of the robot hand to the human keypoints (JAX + optax).

For each frame ``t`` (in order, each warm-started from the previous solution):

    minimize_q  sum_k w_k |kp_k(q) - J_t[h_k]|^2  +  lam_smooth |q - q_{t-1}|^2_W  +  lam_rest |q_joints - q_rest|^2
    subject to  joint limits (projected Adam)

where ``kp_k`` are the robot keypoints of the hand config, ``h_k`` their human keypoint indices, ``W``
weights the joint and base-angle terms. The root is first placed by a weighted rigid fit of the robot's
rest-pose wrist/knuckle keypoints onto the human wrist and knuckles (``wrist_fit_human``); the fixed
base frame is the clip's mean root orientation, so base angles stay small.

A demo with two hands is retargeted hand by hand: each robot hand (the right one and its mirror image) to
its own human keypoints (:func:`kinematic_controls`); the controls concatenate them, right then left.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm import tqdm

from quasisim.assets.hand import HandModel
from quasisim.data.controls import Controls
from quasisim.data.demo import Demo, content_hash
from quasisim.rotations import chordal_mean_rotation, kabsch, np_mat_to_euler_xyz
from quasisim.sim.kinematics import HandGeometry, fk_full, geometry_arrays, keypoints
from quasisim.tracecache import cached_jit


@dataclass(frozen=True)
class RetargetOptions:
    """Retargeting settings.

    Attributes:
        iters: Adam iterations per frame (the first frame gets 4x).
        lr: Adam step size (rad or m).
        smooth: weight of |q_t - q_{t-1}|^2 (per rad^2) for joints and base angles.
        rest: weight pulling the finger joints to their rest values (regulariser).
    """

    iters: int = 150
    lr: float = 0.02
    smooth: float = 2e-4
    rest: float = 1e-6


@dataclass(frozen=True, eq=False)
class RetargetResult:
    q: np.ndarray  # (T, 6 + J)
    base_rot: np.ndarray  # (3, 3)
    keypoint_error: np.ndarray  # (T, K) m, all keypoints
    mean_metric_error_mm: float


def rigid_root_fit(hand: HandModel, joints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Root rotations (T, 3, 3) and positions (T, 3) from a rigid fit of the rest-pose wrist/knuckles."""
    idx = [int(np.flatnonzero(hand.kp_human == h)[0]) for h in hand.config.wrist_fit_human]
    rest = jnp.asarray(np.concatenate([np.zeros((1, 6)), hand.rest_q()[None]], axis=1), dtype=jnp.float32)
    src = np.asarray(keypoints_of(hand, rest, jnp.eye(3), None))[0, idx]  # one compiled program, not op by op
    w = hand.kp_weight[idx]
    Rs, ps = [], []
    for Jt in joints:
        R, p = kabsch(src, Jt[list(hand.config.wrist_fit_human)], w)
        Rs.append(R)
        ps.append(p)
    return np.array(Rs), np.array(ps)


# the clip-length warning's estimate of the retarget, per frame (2-core machine; docs/history "Commands on long clips")
RETARGET_S_PER_FRAME, RETARGET_MB_PER_FRAME = 0.008, 0.03


def _keypoints(hand: HandModel, q: jnp.ndarray, base_rot: jnp.ndarray, geom: HandGeometry | None) -> jnp.ndarray:
    """The robot keypoints (K, 3) at ``q`` (6 + J,): base position, base angles about ``base_rot``, joints."""
    return keypoints(hand, fk_full(hand, base_rot, q, geom), geom)


@cached_jit(static_argnames=("hand", "opts"))
def solve_frame(
    hand: HandModel, opts: RetargetOptions, q_init: jnp.ndarray, q_prev: jnp.ndarray, target: jnp.ndarray,
    base_rot: jnp.ndarray, geom: HandGeometry | None,
) -> jnp.ndarray:  # fmt: skip
    """One frame's IK (module docstring): ``opts.iters`` projected Adam steps from ``q_init`` (6 + J,) towards
    the human keypoints ``target`` (21, 3), smooth against ``q_prev``; ``geom``: the hand's geometry
    (:func:`~quasisim.sim.kinematics.geometry_arrays` for a hand built per demo, else None). A traced program
    kept on disk (:mod:`quasisim.tracecache`): a fresh process does not trace it again."""
    kp_human = np.asarray(hand.kp_human)
    w = jnp.asarray(hand.kp_weight, dtype=jnp.float32)
    lo = np.concatenate([np.full(6, -np.inf), np.where(hand.joint_limited, hand.joint_range[:, 0], -np.inf)])
    hi = np.concatenate([np.full(6, np.inf), np.where(hand.joint_limited, hand.joint_range[:, 1], np.inf)])
    smooth_w = np.concatenate([np.zeros(3), np.ones(3 + hand.n_joints)]) * opts.smooth
    q_rest = hand.rest_q()

    def loss(q: jnp.ndarray) -> jnp.ndarray:
        err = jnp.sum(w * jnp.sum((_keypoints(hand, q, base_rot, geom) - target[kp_human]) ** 2, axis=-1))
        return err + jnp.sum(smooth_w * (q - q_prev) ** 2) + opts.rest * jnp.sum((q[6:] - q_rest) ** 2)

    tx = optax.adam(optax.exponential_decay(opts.lr, transition_steps=opts.iters, decay_rate=0.05))

    def body(_: int, carry: tuple) -> tuple:
        q, st = carry
        upd, st = tx.update(jax.grad(loss)(q), st, q)
        return jnp.clip(optax.apply_updates(q, upd), lo, hi), st

    q, _ = jax.lax.fori_loop(0, opts.iters, body, (q_init, tx.init(q_init)))
    return q


@cached_jit(static_argnames=("hand",))
def keypoints_of(hand: HandModel, q: jnp.ndarray, base_rot: jnp.ndarray, geom: HandGeometry | None) -> jnp.ndarray:
    """The robot keypoints (T, K, 3) of every frame of ``q`` (T, 6 + J)."""
    return jax.vmap(lambda x: _keypoints(hand, x, base_rot, geom))(q)


def retarget(
    hand: HandModel, demo: Demo, opts: RetargetOptions | None = None, progress: bool = False, side: str = "right"
) -> RetargetResult:
    """Retarget ``demo``'s keypoints of its ``side`` hand to ``hand`` frame by frame (see module docstring)."""
    opts = opts or RetargetOptions()
    J = np.asarray(demo.joints_of(side), dtype=np.float64)
    Rs, ps = rigid_root_fit(hand, J)
    base_rot = chordal_mean_rotation(Rs)
    eul = np.unwrap(np_mat_to_euler_xyz(np.einsum("ji,tjk->tik", base_rot, Rs)), axis=0)
    base_init = np.concatenate([ps, eul], axis=1)
    geom = geometry_arrays(hand) if hand.config.per_demo else None
    R0 = jnp.asarray(base_rot, dtype=jnp.float32)
    targets = jnp.asarray(J, dtype=jnp.float32)
    q = jnp.asarray(np.concatenate([base_init[0], hand.rest_q()]), dtype=jnp.float32)
    for _ in range(4):  # the first frame has no warm start: give it more iterations
        q = solve_frame(hand, opts, q, q, targets[0], R0, geom)
    qs = [q]
    for t in tqdm(range(1, len(J)), desc="retarget", unit="frame", disable=not progress, leave=False):
        # warm start: previous solution with the root moved by the rigid fit
        q0 = qs[-1].at[:6].set(jnp.asarray(base_init[t], dtype=jnp.float32))
        qs.append(solve_frame(hand, opts, q0, qs[-1], targets[t], R0, geom))
        if t % 64 == 0:  # bounded queue of dispatched solves: memory and time stay linear in the frames
            qs[-1].block_until_ready()
    q_all = np.asarray(jnp.stack(qs), dtype=np.float64)
    kp = np.asarray(keypoints_of(hand, jnp.asarray(q_all, dtype=jnp.float32), R0, geom), dtype=np.float64)
    err = np.linalg.norm(kp - J[:, hand.kp_human], axis=-1)
    return RetargetResult(
        q=q_all, base_rot=base_rot, keypoint_error=err, mean_metric_error_mm=float(err[:, hand.kp_metric].mean() * 1e3)
    )


def retarget_hands(
    hands: tuple[HandModel, ...], demo: Demo, opts: RetargetOptions | None = None, progress: bool = False
) -> tuple[RetargetResult, ...]:
    """Retarget each of ``demo``'s hands (``demo.sides``) to the robot hand of the same position in ``hands``."""
    if len(hands) != len(demo.sides):
        raise ValueError(f"retarget: demo {demo.name} has {len(demo.sides)} hand(s), {len(hands)} robot hand(s) given")
    return tuple(retarget(h, demo, opts, progress, side) for h, side in zip(hands, demo.sides, strict=True))


def kinematic_controls(
    hand: HandModel | tuple[HandModel, ...], demo: Demo, hand_ref: str, opts: RetargetOptions | None = None,
    progress: bool = False,
) -> Controls:  # fmt: skip
    """Retarget and package the result as PD targets (the kinematic-replay baseline); ``hand`` is one robot
    hand, or one per hand of the demo (right, left): their targets are concatenated (T, 2 (6 + J))."""
    hands = (hand,) if isinstance(hand, HandModel) else tuple(hand)
    res = retarget_hands(hands, demo, opts, progress)
    return Controls(
        hand=hand_ref,
        demo=demo.name,
        method="kinematic",
        fps=demo.fps,
        base_rots=tuple(r.base_rot for r in res),
        q_targets=np.concatenate([r.q for r in res], axis=1),
        joint_names=hands[0].joint_names,
        extras={"retarget_keypoint_error": np.concatenate([r.keypoint_error for r in res], axis=1)},
        demo_hash=content_hash(demo),
    )
