"""The curriculum's hand-off to a simulator with a smaller contact distance: touch instead of hovering.

A point touches the object when its signed distance is below ``d_c`` (:mod:`quasisim.sim.contact`), so a
grasp found in a simulator with ``d_c = 1 cm`` may hold the object from up to 1 cm away. In the next
simulator, with a smaller ``d_c``, those fingers no longer touch, the object drops, and no gradient brings
them back (an untouched point has no force to differentiate), while ten Adam steps of 1e-3 rad cannot move a
finger a centimetre. Measured on the 25 development clips (BENCHMARKS.md): at the step to ``d_c = 0`` the
previous simulator's solution was the best start on 8 of 25 clips only.

The hand-off moves the grasp instead, so that every contact pushes as it did. A point in contact at the
end of frame ``t`` of the previous simulator's rollout, at signed distance ``phi_a`` (m) from the object,
pushes with ``k_n (d_c - phi_a)`` there; in the next simulator (``d_c'``, ``k_n'``) it pushes as hard at
``phi_a' = d_c' - (k_n / k_n') (d_c - phi_a)``. Its PD target moves as far, ``Delta = phi_a - phi_a'``, along
the object's normal (so the PD spring keeps its stretch too): a point that hovered ``phi_a = 1 cm`` away with
``d_c = 1 cm`` moves 1 cm, one that pressed ``phi_a = -5 mm`` into a simulator ten times softer moves 3.5 mm
out. With ``phi`` the object's signed distance at the previous rollout's object pose, ``x_p(q)`` the point
at joint targets ``q`` (the base targets fixed) and ``c_tp`` 1 for a point in contact:

    min_{q'_t}  sum_p c_tp (phi(x_p(q'_t)) - phi(x_p(q_t)) + Delta_tp)^2  +  lambda |q'_t - q_t|^2

one small least-squares problem per frame, solved by Levenberg-Marquardt steps (frame 0, the rest pose the
rollout starts from, is kept). The result is one more start for stage 2's restart guard, which keeps
whichever start scores best in the new simulator, so the hand-off never makes a simulator's start worse.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from quasisim.optim.trajectory import Trajectory, bucket_frames, first_frames, pad_frames, simulate_jit
from quasisim.rotations import quat_to_mat
from quasisim.sim.kinematics import bases_to_roots, forward_kinematics, points_world
from quasisim.sim.step import object_origin, sdf_lookup
from quasisim.sim.types import Model, Params, State
from quasisim.tracecache import cached_jit

Array = jax.Array


@dataclass(frozen=True)
class HandoffOptions:
    """Settings of the hand-off (``configs/transfer.yaml``, key ``stage2``).

    Attributes:
        mode: where the touching start is added: ``stiffest`` (at the hand-off to the curriculum's stiffest
            simulator only), ``every`` (at every simulator whose ``d_c`` is smaller than the previous one's)
            or ``none`` (the paper's hand-off: the previous result as it is).
        iterations: Levenberg-Marquardt steps.  damping: lambda (m^2/rad^2: signed distance against joint motion).
    """

    mode: str
    iterations: int
    damping: float


MODES = ("stiffest", "every", "none")


def touches(mode: str, rigid: list[int], sim: int) -> bool:
    """Whether ``mode`` adds the touching start at stage 2's simulator ``sim`` (an entry of ``rigid``, the
    curriculum's rigid simulators, soft to stiff; the first has no previous simulator to hand off from)."""
    if sim == rigid[0]:
        return False
    return mode == "every" or (mode == "stiffest" and sim == rigid[-1])


def _depths(model: Model, root_pos: Array, root_rot: Array, q: Array, s: State) -> Array:
    """(N,) signed distances (m) of the hand points at root pose (simulator coordinates) and joints ``q`` to
    the object where state ``s`` holds it."""
    p = points_world(
        forward_kinematics(model.hand, root_pos, root_rot, q, model.hand_geom), model.point_body, model.point_local
    )
    origin, R = object_origin(model, s)
    return sdf_lookup(model, (p - origin) @ R)[0]


def target_depths(model: Model, base_rot: Array, base: Array, joints: Array, states: State) -> Array:
    """(T - 1, N) signed distances of the hand points at the PD targets of frames 1..T-1 (``base`` (T - 1, 6 H),
    ``joints`` (T - 1, J)) to the object where ``states`` (the rollout's T - 1 states) hold it."""

    def one(b: Array, q: Array, s: State) -> Array:
        root_pos, root_rot = bases_to_roots(b, base_rot)
        return _depths(model, model.to_sim(root_pos), root_rot, q, s)

    return jax.vmap(one)(base, joints, states)


def state_depths(model: Model, states: State) -> Array:
    """(T - 1, N) signed distances of the hand points where the rollout's ``states`` put them."""
    return jax.vmap(lambda s: _depths(model, s.root_pos, quat_to_mat(s.root_quat), s.q, s))(states)


def force_keeping_shift(phi: Array, d_c: Array, d_c_next: Array, k_ratio: Array) -> Array:
    """``Delta = phi - phi'`` (m): how far a contact at signed distance ``phi`` moves so that it pushes as
    hard in the next simulator, ``phi' = d_c_next - k_ratio (d_c - phi)``, ``k_ratio = k_n / k_n(next)``."""
    return phi - (d_c_next - k_ratio * (d_c - phi))


@cached_jit(static_argnames=("iterations",))
def touching_joints(
    model: Model, base_rot: Array, base: Array, joints: Array, states: State, shift: Array, damping: Array,
    lo: Array, hi: Array, iterations: int,
) -> Array:  # fmt: skip
    """(T - 1, J) joint targets of frames 1..T-1 whose contact points (``states.in_contact``) sit ``shift``
    (T - 1, N) (m) deeper (module docstring), within the joint range [``lo``, ``hi``]."""
    contact = states.in_contact
    goal = target_depths(model, base_rot, base, joints, states) - shift
    eye = jnp.eye(joints.shape[1], dtype=joints.dtype)

    def frame_step(b: Array, q: Array, mu: Array, q0: Array, s: State, c: Array, g: Array) -> tuple[Array, Array]:
        def residual(qq: Array) -> Array:  # (N,) of the points in contact
            one = jax.tree.map(lambda x: x[None], s)
            return c * (target_depths(model, base_rot, b[None], qq[None], one)[0] - g)

        def cost(qq: Array, r: Array) -> Array:  # r: residual(qq)
            return r @ r + damping * jnp.sum((qq - q0) ** 2)

        r, Jr = residual(q), jax.jacfwd(residual)(q)  # (N,), (N, J)
        grad = Jr.T @ r + damping * (q - q0)
        trial = jnp.clip(q - jnp.linalg.solve(Jr.T @ Jr + (damping + mu) * eye, grad), lo, hi)
        # Levenberg-Marquardt: keep a step only if it lowers the cost
        better = cost(trial, residual(trial)) < cost(q, r)
        return jnp.where(better, trial, q), jnp.where(better, mu / 3.0, mu * 4.0)

    def body(carry: tuple[Array, Array], _: None) -> tuple[tuple[Array, Array], None]:
        q, mu = carry
        return jax.vmap(frame_step)(base, q, mu, joints, states, contact, goal), None

    mu0 = jnp.full(joints.shape[0], 1.0e-4, joints.dtype)  # m^2/rad^2; /3 after a kept step, x4 after a refused one
    return jax.lax.scan(body, (joints, mu0), None, length=iterations)[0][0]


def touching(
    model: Model, params: Params, next_params: Params, traj: Trajectory, base_quat: np.ndarray,
    base_rot: np.ndarray, fps: float, obj0: tuple[np.ndarray, np.ndarray], opts: HandoffOptions,
) -> Trajectory:  # fmt: skip
    """``traj`` (found in the simulator ``params``, S applied) with the joint targets moved so that each of
    its contacts pushes in the simulator ``next_params`` as it did in ``params`` (module docstring). Computed
    on the frames padded to :func:`~quasisim.optim.trajectory.bucket_frames` (one program per bucket)."""
    n_frames, traj = traj.base.shape[0], pad_frames(traj, bucket_frames(traj.base.shape[0]))
    states = simulate_jit(model, params, traj, jnp.asarray(base_quat, jnp.float32), fps, obj0)
    shift = force_keeping_shift(state_depths(model, states), params.d_c, next_params.d_c, params.k_n / next_params.k_n)
    hand = model.hand
    lo = np.where(hand.joint_limited, hand.joint_range[:, 0], -np.inf).astype(np.float32)
    hi = np.where(hand.joint_limited, hand.joint_range[:, 1], np.inf).astype(np.float32)
    q = touching_joints(
        model, jnp.asarray(base_rot, jnp.float32), traj.base[1:], traj.joints[1:], states, shift,
        jnp.float32(opts.damping), jnp.asarray(lo), jnp.asarray(hi), opts.iterations,
    )  # fmt: skip
    return first_frames(dataclasses.replace(traj, joints=traj.joints.at[1:].set(q)), n_frames)
