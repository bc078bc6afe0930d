"""Sampling MPC in the target: predictive sampling with the target simulator itself as the model (stage
``sample``, :data:`STAGE`, around the PD targets of the stages before it; settings ``sampling:`` in
``configs/transfer.yaml``, :class:`~quasisim.method.options.SamplingOptions`; from the kinematic retarget
alone it is the ``sample-target`` baseline).

At every control frame ``t`` of a clip with ``T`` frames:

1. take the exact current state of the target (MuJoCo: ``mj_getState(..., mjSTATE_FULLPHYSICS)`` plus
   ``qacc_warmstart``; PyBullet: ``saveState``);
2. build ``samples`` candidate windows of the PD targets of frames ``t+1 .. t+horizon``: the nominal plan's
   window and ``samples - 1`` perturbations. The noise is Gaussian on ``knots`` knots spread evenly over
   the window and interpolated linearly to its frames; its std is ``noise_base_pos`` (m) on the base
   position, ``noise_base_rot`` (rad) on the base angles and ``noise_joints`` on the joints, times a
   per-candidate multiplier cycling through ``noise_scales``. Perturbed joint targets are clipped to the
   hand's joint limits (widened to the nominal's own value where the nominal is outside them, so that a
   zero perturbation is the nominal). With ``screen`` > 1, ``screen`` times as many windows are drawn and only
   the nominal and the ``samples - 1`` others cheapest by a kinematic pre-screen go on: the window cost of
   step 4 with the hands exactly at their PD targets (forward kinematics of the robot's keypoints, the same
   sites the target reports) and without the object terms (:func:`kinematic_costs`). No physics: it ranks
   by hand tracking and smoothness, which dominate the window cost (BENCHMARKS.md, "could any simulator
   pre-screen"). A step that starts with the object beyond ``widen_margin`` x the strict limits (2 cm, 30 deg)
   draws ``backtrack_samples`` x the windows, as a re-planned step does (step 6);
3. roll every candidate out in the target from that state with the target's one PD schedule
   (:meth:`~quasisim.targets.base.Target.rollout_windows`, :func:`~quasisim.targets.base.pd_schedule`;
   MuJoCo: ``mujoco.rollout`` on a copy of the scene with ``framepos`` sensors on the metric keypoint sites;
   PyBullet: one candidate after the other from ``restoreState``). Pruning (``prune_frames`` > 0): every
   candidate runs the first ``prune_frames`` frames of its window, and only the ``max(ceil(prune_keep N),
   samples)`` with the lowest lower bound of their window cost (:func:`cost_bounds`: step 4's cost with the later frames' errors
   at 0) run the rest, continued from their own states (MuJoCo: with the step's solver warm start, which
   ``mujoco.rollout`` does not return); the others are never chosen. A recorded run (``--record-transitions``)
   rolls every window out in full;
   With ``grip`` > 0 every window is driven pressing harder where the object holds fingers back: each finger
   joint whose measured position at the step's start is more than ``grip_gap`` from its PD target (rad, or m
   for slide joints) gets ``grip * sign(q* - q)`` added to its targets on the window's frames (``kp grip``
   more torque; :func:`grip_bias`). The plan the loop keeps is without it, so the bias does not add up over
   steps; the applied frames (the run's result) are the chosen window plus its step's bias;
4. score each window with the MPC window objective (:func:`quasisim.optim.objective.window_costs`),
   evaluated on the target's states: mean over the window's frames of ``obj_pos |p - p_ref|`` (m),
   ``obj_rot (1 - |q . q_ref|)`` and ``hand`` x mean metric-keypoint distance (m), plus ``smooth`` x the
   mean squared second differences of the window's base and joint targets (the window includes frame
   ``t``). Frames past the clip's end reuse the last reference frame and are masked out of the means;
   With ``alternatives`` (other nominal plans, e.g. the kinematic retarget beside the curriculum's plan),
   ``samples`` more windows are drawn around each alternative's window (its frame 0 replaced by the
   targets the step starts from), so a step can switch to another plan;
   With ``strict_weight`` > 0 the cost also holds a hinge on the strict limits (2 cm, 30 deg at every frame,
   :mod:`quasisim.eval.metrics`): ``strict_weight`` x the mean over the window's frames of
   ``max(0, e_pos / 2 cm - strict_margin) + max(0, e_rot / 30 deg - strict_margin)``, so that among
   candidates of similar mean error the one that keeps every frame inside the limits wins;
   With ``grasp_weight`` > 0 the cost also holds the grasp margin: every window is rolled out with each hand's
   ``grasp_slots`` strongest contacts with the object (MuJoCo: a contact sensor per hand in the batched
   rollouts; PyBullet: ``getContactPoints``), and ``grasp_weight`` x the mean over the window's frames of
   ``sum_c max(0, |f_t,c| - (1 - grasp_margin) mu f_n,c) / (m g)`` is added (:func:`grasp_term`,
   :mod:`quasisim.targets.grasp`): the load the contacts carry beyond friction cones shrunk by
   ``grasp_margin``, in object weights, in the world of the rollout (a scoring copy's own friction and mass);
5. ``predictive``: keep the cheapest window as the plan; ``mppi``: the plan becomes the
   ``softmax(-cost / temperature)``-weighted mean of the windows. Apply the plan's first ``replan`` frames
   (``t -> t+replan``; 1 on frames re-planned after a back-up, step 6) in the target, recording each frame
   and checking it against the strict limits, then plan again from there. The target is deterministic and
   its state is copied exactly, so the applied frames are what the chosen candidate predicted (predictive
   mode); planning every ``replan`` frames divides the rollouts by about ``replan``. With ``replan_margin``
   a frame after the first is applied only while the chosen candidate predicted the object within
   ``replan_margin`` x the strict limits there (2 cm, 30 deg); otherwise the loop plans that frame afresh, so
   frames near the limits get the full search of every frame.
6. Backing up (``backtrack`` > 0): when the frame just applied leaves the strict limits, the target is put
   back to its saved state ``backtrack`` frames earlier (at least frame 1) and those frames are planned
   again with ``backtrack_samples`` times the samples, around the plan chosen so far; at most
   ``backtrack_budget`` times per clip. A frame that leaves the limits again after a back-up from it backs
   up once more, ``backtrack`` frames further back each time, up to ``backtrack_retries`` times (0: once per
   failing frame). With ``backtrack_strict_weight`` the re-planned frames' window cost holds the hinge of
   step 4 at that weight instead of ``strict_weight``, so the re-planning aims at the limits it left.
   A frame that stays outside the limits (its retries or the budget spent) fails strict success for the
   clip, unless a later back-up reaches back past it: without ``backtrack_after_lost`` no back-up follows
   it (less time, but back-ups after it also keep the object near its path and can re-plan the lost frame).
   With ``backtrack_limit`` < 1 a frame backs up already when it comes closer to the limits than that
   fraction of them (e.g. 0.75: beyond 1.5 cm or 22.5 deg), with the same retries and budget, so the run keeps
   a margin that a slightly different target (robust success) does not eat; only a frame outside the limits
   themselves is lost;
7. Robust scoring (``robust_copies`` > 0 or ``robust_worlds``): beside the target run the named worlds
   ``robust_worlds`` (:func:`quasisim.targets.perturb.named_world`: ``corner``, the hard corner of the robust
   ranges, mass high, friction low, gains low; ``thin``, contacts ``robust_thin`` m thinner; ``corner-thin``)
   and ``robust_copies`` perturbed copies of it
   (:func:`quasisim.targets.perturb.perturbed_scene`: the ranges of ``configs/robust.yaml``, drawn with
   ``robust_seed`` in the method's own stream, never a judging world), each started as the target is and
   advanced with the same applied frames, open loop, as a robust replay would run them. The ``robust_top``
   cheapest candidates in the target are also rolled out from its own state in every copy whose object is
   still within the strict limits (a copy that has lost it no longer tells candidates apart), and the window
   is chosen by its cost averaged over the target and those copies (a copy's unstable rollout costs
   :data:`UNSTABLE_COST`), or by another risk measure (``robust_risk``: ``worst``, the largest of those costs;
   ``cvar``, the mean of the largest ``robust_cvar`` fraction). Back-ups put the copies back with the target; with ``backtrack_copies`` the loop
   also backs up (step 6) when a copy that was within the strict limits before the frame just applied is not
   after it.

The run starts from ``plan[0]``; the hand's initial velocity is that of the applied targets
(``(q[1] - q[0]) fps``, per candidate at ``t = 0``), so the recorded run equals a plain replay of the applied
targets (:meth:`~quasisim.targets.base.Target.rollout`).

Suggested settings (all required; load with ``quasisim.config.build(SamplingOptions, data, path)``)::

    sampling:
      samples: 24              # candidate windows per frame (the nominal + 23 perturbations)
      horizon: 10              # frames per window
      knots: 3                 # noise knots per window, linear in between
      noise_base_pos: 0.004    # m
      noise_base_rot: 0.04     # rad
      noise_joints: 0.08       # rad (m for slide joints)
      noise_scales: [0.5, 1.0, 2.0]  # per-candidate multipliers of the noise std, cycled
      kinematic_alternative: true  # stage sample after other stages: also sample around the kinematic retarget
      mode: predictive         # predictive | mppi
      temperature: 0.003       # mppi only: softmax temperature, in cost units
      seed: 0
      threads: 2               # MuJoCo rollout threads
      strict_weight: 0.0       # hinge on the strict limits in the window cost (0: none)
      strict_margin: 0.75      # ... from this fraction of the limits
      backtrack: 5             # frames to back up when a frame leaves the strict limits (0: never)
      backtrack_samples: 4     # samples multiplier while re-planning those frames
      backtrack_budget: 12     # back-ups per clip at most
      backtrack_retries: 1     # further back-ups from a frame that leaves the limits again (0: none)
      backtrack_strict_weight: null  # the hinge's weight on re-planned frames (null: strict_weight)
      backtrack_after_lost: true  # back up after a frame stayed outside the limits (false: never)
      robust_copies: 0         # perturbed copies of the target that score the best candidates (0: none)
      robust_top: 8            # ... the candidates (cheapest in the target) scored in every copy
      robust_seed: 1           # ... seeds the copies' perturbations
      robust_worlds: []        # named worlds that score them too: corner, thin, corner-thin
      robust_thin: 0.001       # ... thin: contacts this much thinner (m)
      backtrack_copies: false  # ... back up also when a copy leaves the strict limits
      screen: 2                # kinematic pre-screen: draw screen x the windows, roll out the cheapest (1: none)
      replan: 1                # frames of the chosen window applied before planning again
      replan_margin: null      # ... those after the first only while predicted within this fraction of the limits
      widen_margin: null       # steps starting with the object beyond this fraction of the limits: more samples
      prune_frames: 0          # frames every candidate runs before only the cheapest bounds go on (0: all run)
      prune_keep: 0.5          # ... the fraction that goes on
      grip: 0.0                # extra closure of finger joints the object holds back (0: none)
      grip_gap: 0.02           # ... held back: more than this from their targets (rad)
      backtrack_limit: 1.0     # back up when a frame comes closer to the strict limits than this fraction
      grasp_weight: 0.0        # the grasp margin in the window cost (0: none)
      grasp_margin: 0.2        # ... the friction cones shrunk by this fraction
      grasp_slots: 8           # ... each hand's strongest contacts counted
"""

from __future__ import annotations

import dataclasses
import functools
import math
import sys
import time
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from quasisim.assets.hand import HandModel
from quasisim.data.demo import Demo, content_hash
from quasisim.errors import QuasisimError
from quasisim.files import save_npz_atomic
from quasisim.limits import STRICT_CM, STRICT_DEG, object_errors
from quasisim.method.options import SamplingOptions
from quasisim.method.stage import Context, Outcome, Stage
from quasisim.method.stages._common import q_expect
from quasisim.optim import objective
from quasisim.optim.objective import Weights, padded, window_references
from quasisim.sim.kinematics import fk_full, keypoints
from quasisim.targets import Observation, Prediction, Prune, Target, TargetRollout, make_target
from quasisim.targets.grasp import slack_excess
from quasisim.targets.perturb import named_world, perturbed_scene, training_worlds
from quasisim.targets.scene import Scene
from quasisim.tracecache import cached_jit

UNSTABLE_COST = 1.0e3  # a window cost for a copy's rollout that went unstable (finite costs are ~0.01-1)


@dataclass(frozen=True, eq=False)
class SampleResult:
    """Outcome of :func:`run_sampling`.

    Attributes:
        q_targets: (T, 6 + J) the PD targets applied in the target.
        rollout: the target's recorded run (a replay of ``q_targets``).
        window_loss: (T - 1,) per frame, the lowest candidate window cost of the plan that applied it (with
            copies, step 7: the lowest score).
        wall_s: wall time of the control loop (s).
        n_physics_steps: physics steps simulated, candidates and the applied frames together.
        prediction_error: (T - 1,) after each applied frame, the largest difference between the chosen
            candidate's predicted and the measured hand qpos / object position (m, rad); 0 when the target
            is deterministic and its state is copied exactly; NaN in ``mppi`` mode (no candidate applied).
        backup_frames: (B, 2) int, each time the loop backed up to re-plan frames that left the strict limits
            (step 6): the frame that left them and the frame it went back to, in the order they happened.
        stopped_at: with ``stop_when_lost``, the frame that stayed outside the strict limits, where the run
            ended (the later frames hold the plan's targets and are not in ``rollout``); else None.
    """

    q_targets: np.ndarray
    rollout: TargetRollout
    window_loss: np.ndarray
    wall_s: float
    n_physics_steps: int
    prediction_error: np.ndarray
    backup_frames: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 2), np.int64))
    stopped_at: int | None = None

    @property
    def backups(self) -> int:
        """Times the loop backed up (step 6)."""
        return len(self.backup_frames)


# ---- sampling and scoring -------------------------------------------------------------


def knot_basis(horizon: int, knots: int) -> np.ndarray:
    """(H, K) linear-interpolation weights from ``knots`` knots spread evenly over ``horizon`` frames."""
    x = np.arange(horizon, dtype=np.float64)
    at = np.linspace(0.0, horizon - 1.0, knots) if knots > 1 else np.zeros(1)
    return np.stack([np.interp(x, at, np.eye(knots)[k]) for k in range(knots)], axis=1)


def noise_std(opts: SamplingOptions, n_joints: int | tuple[int, ...]) -> np.ndarray:
    """(D,) noise std per dof of hands with ``n_joints`` joints each (one int: one hand): per hand, base
    position (m), base angles (rad), joints; D = sum over hands of 6 + J."""
    counts = (n_joints,) if isinstance(n_joints, int | np.integer) else n_joints
    b = np.r_[np.full(3, opts.noise_base_pos), np.full(3, opts.noise_base_rot)]
    return np.concatenate([np.r_[b, np.full(int(j), opts.noise_joints)] for j in counts])


def sample_windows(
    rng: np.random.Generator, nominal: np.ndarray, opts: SamplingOptions, joint_lo: np.ndarray, joint_hi: np.ndarray,
    std: np.ndarray | None = None,
) -> np.ndarray:  # fmt: skip
    """Candidate windows (N, H + 1, D): row 0 the ``nominal`` window (H + 1, D), rows 1.. perturbed.

    Frame 0 of every window (the targets the step starts from) is never perturbed. ``joint_lo/hi`` bound the
    perturbed targets: (J,) for one hand's joints (columns 6..), or (D,) for every column (-inf/inf for the
    base coordinates and unlimited joints, :meth:`~quasisim.targets.scene.Scene.joint_bounds`); a bound the
    nominal already crosses is widened to the nominal's value. ``std`` (D,): the noise std per column
    (default: one hand's, :func:`noise_std`).
    """
    N, H, D = opts.samples, len(nominal) - 1, nominal.shape[1]
    std = noise_std(opts, D - 6) if std is None else std
    basis = knot_basis(H, opts.knots)
    scales = np.asarray(opts.noise_scales, dtype=np.float64)[np.arange(N - 1) % len(opts.noise_scales)]
    knots = rng.standard_normal((N - 1, opts.knots, D)) * std * scales[:, None, None]
    wins = np.repeat(nominal[None].astype(np.float64), N, axis=0)
    wins[1:, 1:] += np.einsum("hk,nkd->nhd", basis, knots)
    c = D - len(joint_lo)  # the first bounded column
    lo = np.minimum(joint_lo, nominal[1:, c:])
    hi = np.maximum(joint_hi, nominal[1:, c:])
    wins[1:, 1:, c:] = np.clip(wins[1:, 1:, c:], lo, hi)
    return wins


def scene_sampler(opts: SamplingOptions, scene: Scene) -> Callable[[np.random.Generator, np.ndarray], np.ndarray]:
    """:func:`sample_windows` for ``scene``: ``sample(rng, nominal)`` keeps every hand's joints within its
    ranges and uses the noise std of the scene's hands (one or two)."""
    lo, hi = scene.joint_bounds()  # every column of every hand (the base unbounded)
    std = noise_std(opts, tuple(h.n_joints for h in scene.hands))
    return functools.partial(sample_windows, opts=opts, joint_lo=lo, joint_hi=hi, std=std)


def kinematic_keypoints(scene: Scene) -> Callable[[np.ndarray], np.ndarray]:
    """``f(q)``: the metric keypoints (..., K_metric, 3) (m, world) of the scene's hands at ``q`` (..., D) by
    forward kinematics of the hand models: the sites the target reports (tested against MuJoCo)."""
    metric = tuple(int(i) for i in np.flatnonzero(scene.kp_metric))
    cols = tuple((sl.start, sl.stop) for sl in scene.dof_slices)
    rots = tuple(jnp.asarray(R, jnp.float32) for R in scene.base_rots)

    def f(q: np.ndarray) -> np.ndarray:
        flat = jnp.asarray(np.asarray(q, np.float32).reshape(-1, q.shape[-1]))
        out = _metric_keypoints(scene.hands, cols, metric, rots, flat)
        return np.asarray(out, np.float64).reshape(*q.shape[:-1], len(metric), 3)

    return f


@cached_jit(static_argnames=("hands", "cols", "metric"))
def _metric_keypoints(
    hands: tuple[HandModel, ...], cols: tuple[tuple[int, int], ...], metric: tuple[int, ...],
    rots: tuple[jax.Array, ...], q: jax.Array,
) -> jax.Array:  # fmt: skip
    """(N, K_metric, 3) the hands' metric keypoints at ``q`` (N, D), hand ``i`` in columns ``cols[i]`` with
    base rotation ``rots[i]``; a traced program kept on disk (:mod:`quasisim.tracecache`)."""

    def one(x: jax.Array) -> jax.Array:
        kp = [keypoints(h, fk_full(h, R, x[a:b])) for h, R, (a, b) in zip(hands, rots, cols, strict=True)]
        return jnp.concatenate(kp)[np.asarray(metric)]

    return jax.vmap(one)(q)


def kinematic_costs(
    wins: np.ndarray, kp: Callable[[np.ndarray], np.ndarray], ref_pos: np.ndarray, ref_quat: np.ndarray,
    cost: Callable[[np.ndarray, Prediction], np.ndarray],
) -> np.ndarray:  # fmt: skip
    """(N,) the window cost ``cost`` (:func:`window_costs` with its references bound) of candidate windows
    ``wins`` (N, H + 1, D) with the hands exactly at their PD targets (keypoints by ``kp``,
    :func:`kinematic_keypoints`) and the object on its references (``ref_pos`` (H, 3), ``ref_quat`` (H, 4)),
    so that its terms are zero: hand tracking and smoothness only."""
    N, H = len(wins), wins.shape[1] - 1
    pred = Prediction(
        qpos=wins[:, 1:], obj_pos=np.broadcast_to(ref_pos, (N, H, 3)), obj_quat=np.broadcast_to(ref_quat, (N, H, 4)),
        keypoints=kp(wins[:, 1:]), n_steps=0,
    )  # fmt: skip
    return cost(wins, pred)


def cost_bounds(
    head: Prediction, wins: np.ndarray, ref_pos: np.ndarray, ref_quat: np.ndarray, ref_kp: np.ndarray,
    cost: Callable[[np.ndarray, Prediction], np.ndarray],
) -> np.ndarray:  # fmt: skip
    """(N,) lower bounds of the window cost ``cost`` of candidate windows ``wins`` (N, H + 1, D) from their
    rollouts' first F frames ``head``: the cost with the object and the keypoints of frames F+1..H on their
    references (``ref_pos`` (H, 3), ``ref_quat`` (H, 4), ``ref_kp`` (H, K, 3)). Every term of step 4 is a
    mean of non-negative per-frame errors (smoothness needs no rollout), so the later frames can only add."""
    N, F = len(wins), head.obj_pos.shape[1]

    def filled(x: np.ndarray, ref: np.ndarray) -> np.ndarray:
        return np.concatenate([x, np.broadcast_to(ref[F:], (N, *ref[F:].shape))], axis=1)

    pred = Prediction(
        qpos=wins[:, 1:], obj_pos=filled(head.obj_pos, ref_pos), obj_quat=filled(head.obj_quat, ref_quat),
        keypoints=filled(head.keypoints, ref_kp), n_steps=0,
    )  # fmt: skip
    return cost(wins, pred)


def pruner(
    opts: SamplingOptions, wins: np.ndarray, bound: Callable[[Prediction, np.ndarray], np.ndarray]
) -> Prune | None:
    """Step 3's early exit: after ``prune_frames`` frames the ``max(ceil(prune_keep N), samples)`` candidates
    with the lowest ``bound(head, wins)`` (:func:`cost_bounds`) go on, so a step never runs fewer whole windows
    than one plan's ``samples``; None (every window in full) when that is all of them, when ``prune_frames`` is
    0 or when it is not below the horizon."""
    n = max(math.ceil(opts.prune_keep * len(wins)), opts.samples)
    if opts.prune_frames == 0 or opts.prune_frames >= wins.shape[1] - 1 or n >= len(wins):
        return None
    return Prune(opts.prune_frames, lambda head: np.argsort(bound(head, wins), kind="stable")[:n])


def screened(wins: np.ndarray, n: int, costs: np.ndarray) -> np.ndarray:
    """The nominal (row 0) and the ``n - 1`` others of ``wins`` with the lowest pre-screen ``costs``."""
    return wins[np.r_[0, 1 + np.argsort(costs[1:], kind="stable")[: n - 1]]]


def window_costs(
    wins: np.ndarray,
    pred: Prediction,
    ref_pos: np.ndarray,
    ref_quat: np.ndarray,
    ref_kp: np.ndarray,
    frame_w: np.ndarray,
    weights: Weights,
    base_cols: np.ndarray | None = None,
    strict: tuple[float, float] = (0.0, 0.75),
    grasp: tuple[float, float] = (0.0, 0.2),
) -> np.ndarray:
    """(N,) the MPC window objective of every candidate, measured in the target
    (:func:`quasisim.optim.objective.window_costs`, the objective of the gradient-based MPC), plus the hinge
    on the strict limits (:func:`strict_hinge`) with ``strict`` = (weight, margin), plus the grasp margin
    (:func:`grasp_term`) with ``grasp`` = (weight, margin) where the rollouts carry their contacts.

    Args:
        wins: (N, H + 1, D) candidate windows.  pred: their rollouts at frames 1..H of the window.
        ref_pos: (H, 3) m, ref_quat: (H, 4), ref_kp: (H, K_metric, 3) m: references of those frames.
        frame_w: (H,) 1 for frames inside the clip, 0 past its end.  weights: objective weights.
        base_cols: the base-coordinate columns of every hand (two hands: 12 of D); None: one hand, the first
            6 columns. The smoothness term averages the base columns and the joint columns separately.
    """
    n_base = 6
    if base_cols is not None:
        joints = np.setdiff1d(np.arange(wins.shape[-1]), base_cols)
        wins, n_base = wins[..., np.r_[base_cols, joints]], len(base_cols)
    costs = objective.window_costs(
        pred.obj_pos, pred.obj_quat, pred.keypoints, wins, ref_pos, ref_quat, ref_kp, frame_w, weights.arrays(),
        n_base=n_base,
    )  # fmt: skip
    costs = np.asarray(costs, np.float64)
    if strict[0] > 0:
        costs = costs + strict[0] * strict_hinge(pred.obj_pos, pred.obj_quat, ref_pos, ref_quat, frame_w, strict[1])
    if grasp[0] > 0 and pred.cones is not None:
        costs = costs + grasp[0] * grasp_term(pred.cones, frame_w, grasp[1])
    return costs


def grasp_term(cones: np.ndarray, frame_w: np.ndarray, margin: float) -> np.ndarray:
    """(N,) mean over a window's frames (``frame_w`` (H,)) of the load its hand-object contacts ``cones``
    (N, H, C, 2; :attr:`~quasisim.targets.base.Prediction.cones`) carry beyond friction cones shrunk by
    ``margin`` (:func:`quasisim.targets.grasp.slack_excess`, object weights): 0 for a grasp that holds with
    that margin; a frame a pruned candidate did not run (NaN) counts 0, as :func:`cost_bounds` counts it."""
    excess = np.nan_to_num(slack_excess(cones, margin), nan=0.0)
    return np.sum(excess * frame_w, axis=-1) / max(float(np.sum(frame_w)), 1.0)


def strict_fractions(
    pos: np.ndarray, quat: np.ndarray, ref_pos: np.ndarray, ref_quat: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Translation and rotation errors of object poses (..., 3), (..., 4) against references, as fractions
    of the strict limits (2 cm, 30 deg; above 1: over), measured as the metrics measure them."""
    rot_deg, trans_cm = object_errors(ref_pos, ref_quat, pos, quat)
    return trans_cm / STRICT_CM, rot_deg / STRICT_DEG


def strict_hinge(
    pos: np.ndarray, quat: np.ndarray, ref_pos: np.ndarray, ref_quat: np.ndarray, frame_w: np.ndarray, margin: float
) -> np.ndarray:
    """(N,) mean over a window's frames of ``max(0, e_pos / 2 cm - margin) + max(0, e_rot / 30 deg - margin)``
    for predicted object poses ``pos`` (N, H, 3), ``quat`` (N, H, 4) against references (H, 3), (H, 4)."""
    trans, rot = strict_fractions(pos, quat, ref_pos, ref_quat)
    h = np.maximum(trans - margin, 0.0) + np.maximum(rot - margin, 0.0)
    return np.sum(h * frame_w, axis=-1) / max(float(np.sum(frame_w)), 1.0)


def next_plan_window(wins: np.ndarray, costs: np.ndarray, opts: SamplingOptions) -> tuple[np.ndarray, int | None]:
    """The new plan window (H + 1, 6 + J) and the index of the applied candidate (None for ``mppi``)."""
    if opts.mode == "predictive":
        best = int(np.argmin(costs))
        return wins[best].copy(), best
    w = np.exp(-(costs - costs.min()) / opts.temperature)
    return np.einsum("n,nhd->hd", w / w.sum(), wins), None


# ---- the control loop ------------------------------------------------------------------------------


TRANSITIONS_FORMAT = "quasisim-transitions-v1"
STATE_KEYS = ("qpos", "qvel", "obj_pos", "obj_quat", "obj_vel", "obj_angvel")


class Transitions:
    """What the sampling stage rolled out in the target, kept for fitting a simulator to it (opt-in:
    ``quasisim transfer --record-transitions DIR``; the format is in ``docs/transfer.md``).

    Per step ``t`` of the control loop (T - 1 steps, N candidates, windows of H frames, D hand dofs): the
    state every window starts from, the candidate windows of PD targets, every candidate's states at the
    window's frames, its cost and which one was applied; and the applied trajectory's states per frame.
    """

    def __init__(self) -> None:
        self.steps: list[dict[str, np.ndarray]] = []
        self.run: dict[str, np.ndarray] = {}

    def add(
        self, frame: int, start: Observation, wins: np.ndarray, qd0: np.ndarray | None, pred: Prediction,
        costs: np.ndarray, chosen: int | None,
    ) -> None:  # fmt: skip
        """One step, planned from frame ``frame``: the target's state ``start`` before the windows ``wins``
        (N, H + 1, D) were rolled out (with the hands' velocities ``qd0`` (N, D) per candidate where given),
        their rollouts and costs."""
        qvel0 = np.broadcast_to(start["qvel"], wins[:, 0].shape) if qd0 is None else qd0
        row = {f"start_{k}": np.asarray(start[k]) for k in (*STATE_KEYS, "keypoints") if k != "qvel"}
        row |= {
            "start_qvel": np.array(qvel0),
            "windows": wins,
            "costs": costs,
            "chosen": np.array(-1 if chosen is None else chosen),
            "frame": np.array(frame),
        }
        row |= {k: np.asarray(getattr(pred, k)) for k in (*STATE_KEYS, "keypoints")}
        self.steps.append(row)

    def record_step(
        self, frame: int, start: Observation, wins: np.ndarray, qd0: np.ndarray | None, pred: Prediction,
        costs: np.ndarray, best: int | None, blocks: tuple[int, int, int],
    ) -> None:  # fmt: skip
        """One step of the control loop (:meth:`add`) with the same count of windows every step: ``blocks`` =
        (windows drawn per block this step, windows kept per block, blocks), the applied window ``best`` kept
        (:func:`_recorded`)."""
        keep = _recorded(*blocks, best)
        chosen = None if best is None else int(np.flatnonzero(keep == best)[0])
        kept = {k: getattr(pred, k) for k in (*STATE_KEYS, "keypoints")}
        sub = dataclasses.replace(pred, **{k: v[keep] for k, v in kept.items() if v is not None})
        self.add(frame, start, wins[keep], None if qd0 is None else qd0[keep], sub, costs[keep], chosen)

    def finish(self, applied: np.ndarray, frames: list[Observation]) -> None:
        """The applied PD targets (T, D) and the applied run's state at every frame (T observations)."""
        self.run = {"applied": np.asarray(applied, np.float64)}
        self.run |= {f"run_{k}": np.stack([f[k] for f in frames]) for k in (*STATE_KEYS, "keypoints")}

    def save(self, path: Path, meta: dict[str, Any]) -> Path:
        """Write everything to ``path`` atomically; ``meta``: strings and numbers naming the run."""
        stacked = {k: np.stack([r[k] for r in self.steps]) for k in self.steps[0]} if self.steps else {}
        info = {k: np.array(v) for k, v in meta.items()}
        return save_npz_atomic(path, format=np.array(TRANSITIONS_FORMAT), **stacked, **self.run, **info)


def _check_plan(demo: Demo, scene: Scene, plan: np.ndarray) -> np.ndarray:
    plan = np.asarray(plan, dtype=np.float64)
    D = scene.n_dof
    if plan.ndim != 2 or plan.shape != (demo.n_frames, D) or demo.n_frames < 2:
        raise QuasisimError(f"sampling: plan must have shape ({demo.n_frames}, {D}) with >= 2 frames, got {plan.shape}")
    if not np.isfinite(plan).all():
        raise QuasisimError("sampling: plan has NaN or inf values")
    return plan


def run_sampling(
    demo: Demo,
    scene: Scene,
    plan: np.ndarray,
    opts: SamplingOptions,
    weights: Weights,
    target: str = "mujoco",
    progress: bool = True,
    alternatives: tuple[np.ndarray, ...] = (),
    transitions: Transitions | None = None,
) -> SampleResult:
    """Predictive-sampling MPC of ``demo`` in ``target`` from the nominal PD-target ``plan`` (T, 6 + J),
    e.g. the kinematic retarget, with windows also sampled around each of ``alternatives`` (T, 6 + J);
    ``weights`` (:class:`~quasisim.optim.objective.Weights`) gives ``obj_pos``, ``obj_rot``, ``hand`` and
    ``smooth``. Deterministic for a fixed ``opts.seed``. See the module docstring. ``transitions``: where
    every rolled-out window is kept (the result is the same with or without it)."""
    plan = _check_plan(demo, scene, plan)
    alts = tuple(padded(_check_plan(demo, scene, a), opts.horizon) for a in alternatives)
    with ExitStack() as stack:
        tgt = stack.enter_context(make_target(target, scene, threads=opts.threads))
        copies = [stack.enter_context(make_target(target, s, threads=opts.threads)) for s in copy_scenes(scene, opts)]
        return _control_loop(demo, scene, plan, opts, weights, tgt, progress, alts, transitions, copies)


def copy_scenes(scene: Scene, opts: SamplingOptions) -> list[Scene]:
    """The scenes of the perturbed copies that score candidates (step 7): the named worlds ``opts.robust_worlds``
    (:func:`quasisim.targets.perturb.named_world`), then ``opts.robust_copies`` draws of
    :func:`quasisim.targets.perturb.perturbed_scene` with the shipped ranges and ``opts.robust_seed``
    (:class:`~quasisim.targets.perturb.TrainingWorlds`)."""
    cfg = training_worlds(opts.robust_seed)  # the method's stream, never a judging world
    named = [named_world(scene, w, opts.robust_thin) for w in opts.robust_worlds]
    return named + [perturbed_scene(scene, cfg, i) for i in range(opts.robust_copies)]


def robust_scores(
    costs: np.ndarray, copy_costs: Sequence[np.ndarray], top: np.ndarray, risk: str = "mean", cvar: float = 0.5
) -> np.ndarray:
    """(N,) the score step 7 chooses by: for the candidates ``top``, their cost in the target ``costs`` (N,) and
    in the copies (each (len(top),); non-finite: :data:`UNSTABLE_COST`) aggregated by the risk measure ``risk``:
    ``mean``; ``worst``, the largest; ``cvar``, the mean of the largest ``ceil(cvar M)`` of the M costs; every
    other candidate infinity (never chosen, MPPI weight 0)."""
    scores = np.full(len(costs), np.inf)
    rows = np.array([costs[top], *(np.where(np.isfinite(c), c, UNSTABLE_COST) for c in copy_costs)])
    if risk == "mean":
        scores[top] = np.mean(rows, axis=0)
    else:
        k = 1 if risk == "worst" else math.ceil(cvar * len(rows))
        scores[top] = np.mean(np.sort(rows, axis=0)[len(rows) - k :], axis=0)
    return scores


def _control_loop(
    demo: Demo, scene: Scene, plan: np.ndarray, opts: SamplingOptions, weights: Weights, target: Target, progress: bool,
    alts: tuple[np.ndarray, ...], transitions: Transitions | None = None, copies: Sequence[Target] = (),
) -> SampleResult:  # fmt: skip
    """Steps 1-7 from frame 0 to the clip's end: plan a window, apply its frames one by one (each checked
    against the strict limits), re-plan; back up where a frame left the limits (:class:`_Loop`)."""
    loop = _Loop(demo, scene, plan, opts, weights, target, alts, copies, transitions)
    bar = tqdm(total=len(plan) - 1, desc="sampling", unit="frame", disable=not progress, leave=False)
    while loop.t < len(plan) - 1 and not loop.stopped:
        step = loop.plan()
        for j in range(1, 1 + step.frames):
            if j > 1 and not loop.calm(step, j):
                break  # the frame's predicted object error is not well inside the limits: plan it afresh
            back = loop.apply(step, j)
            if loop.stopped:
                break
            bar.update(1)
            if back is not None:
                bar.update(back - loop.t)
                loop.back_up(back)
                break
    bar.close()
    return loop.result()


@dataclass(frozen=True, eq=False)
class _Step:
    """One plan of the control loop, made at frame ``t``: the chosen window ``win`` (H + 1, D) (without the grip
    bias ``bias``), the candidate ``best`` that predicted it (None in ``mppi`` mode), every candidate's
    prediction ``pred`` and score ``score`` (N,), the copies ``live`` on track at ``t``, and how many of its
    ``frames`` may be applied before planning again."""

    t: int
    win: np.ndarray
    best: int | None
    bias: np.ndarray | None
    pred: Prediction
    score: np.ndarray
    live: list[Target]
    frames: int


class _Loop:
    """The control loop's state over one clip: the plan shifted as it goes (``work``), the applied targets,
    the observed frames, the states saved for backing up; :meth:`plan` (steps 1-5), :meth:`apply` (a frame,
    then the strict-limits check of step 6) and :meth:`back_up`. ``observer`` (:class:`Transitions`) is told
    every step's windows and the applied run."""

    def __init__(
        self, demo: Demo, scene: Scene, plan: np.ndarray, opts: SamplingOptions, weights: Weights, target: Target,
        alts: tuple[np.ndarray, ...], copies: Sequence[Target], observer: Transitions | None,
    ) -> None:  # fmt: skip
        H = opts.horizon
        self.opts, self.weights, self.target, self.alts, self.copies = opts, weights, target, alts, list(copies)
        self.observer, self.T, self.fps = observer, len(plan), float(demo.fps)
        self.every = [target, *copies]  # the target first; the copies follow the applied frames open loop
        self.ref_pos, self.ref_quat, self.ref_kp = window_references(
            demo, scene.kp_human, np.flatnonzero(scene.kp_metric), H
        )
        self.sample = scene_sampler(opts, scene)
        self.kp = kinematic_keypoints(scene) if opts.screen > 1 else None  # step 2's pre-screen
        self.wide = dataclasses.replace(opts, samples=opts.samples * opts.backtrack_samples)
        base = np.concatenate([np.arange(sl.start, sl.start + 6) for sl in scene.dof_slices])
        self.base_cols = base if len(scene.hands) > 1 else None  # one hand: the first 6 columns
        self.fingers = np.ones(plan.shape[1], bool)  # the hands' joints: every column but the base dofs
        self.fingers[base] = False
        self.work = padded(plan, H)  # the plan, shifted as we go (without the grip bias)
        self.applied = plan.copy()
        self.rng = np.random.default_rng(opts.seed)
        self.losses, self.pred_err, self.steps = np.zeros(self.T - 1), np.full(self.T - 1, np.nan), 0
        self.frames: list[Observation] = []
        self.saved: dict[int, list[object]] = {}  # frame -> the target's and the copies' states after it
        self.widened = np.zeros(self.T, bool)  # frames planned again with more samples after a back-up
        self.backed_from: dict[int, int] = {}  # frame -> back-ups from it
        self.events: list[tuple[int, int]] = []  # (frame that left the limits, frame gone back to), per back-up
        self.lost = False  # a frame stayed outside the strict limits: the clip cannot pass strict any more
        self.behind = opts.backtrack * (2 + opts.backtrack_retries)  # frames of saved states kept behind t
        self.contacts = opts.grasp_slots if opts.grasp_weight > 0 else 0  # contact slots per hand (step 4)
        self.rehinge = (
            opts.strict_weight if opts.backtrack_strict_weight is None else opts.backtrack_strict_weight,
            opts.strict_margin,
        )
        self.t = 0
        for tg in self.every:
            tg.reset(plan[0], None)
        self.t0 = time.perf_counter()

    @property
    def stopped(self) -> bool:
        """Whether the run ended early (``stop_when_lost`` and a frame stayed outside the strict limits)."""
        return self.lost and self.opts.stop_when_lost

    def plan(self) -> _Step:
        """Steps 1-5 at frame ``t``: draw the windows, roll them out in the target (and the copies on track),
        score them, keep the chosen one in the plan."""
        opts, t, H, fps = self.opts, self.t, self.opts.horizon, self.fps
        ref_pos, ref_quat, ref_kp, frames = self.ref_pos, self.ref_quat, self.ref_kp, self.frames
        strays = bool(frames) and _limit_fraction(frames[-1], ref_pos[t], ref_quat[t]) > (opts.widen_margin or math.inf)
        step_opts = self.wide if self.widened[t] or strays else opts
        w = slice(t + 1, t + H + 1)
        frame_w = (np.arange(t + 1, t + H + 1) < self.T).astype(np.float64)
        cost = functools.partial(
            window_costs, ref_pos=ref_pos[w], ref_quat=ref_quat[w], ref_kp=ref_kp[w], frame_w=frame_w,
            weights=self.weights, base_cols=self.base_cols,
            strict=self.rehinge if self.widened[t] else (opts.strict_weight, opts.strict_margin),
            grasp=(opts.grasp_weight, opts.grasp_margin),
        )  # fmt: skip
        pre = None  # step 2's pre-screen: the cost of windows with the hands at their targets
        if self.kp is not None:
            pre = functools.partial(kinematic_costs, kp=self.kp, ref_pos=ref_pos[w], ref_quat=ref_quat[w], cost=cost)
        wins = _draw(self.sample, self.rng, self.work[t : t + H + 1], step_opts, opts.screen, pre)
        for alt in self.alts:  # windows around another plan, from the targets this step starts from
            nominal = np.concatenate([self.work[t : t + 1], alt[t + 1 : t + H + 1]])
            wins = np.concatenate([wins, _draw(self.sample, self.rng, nominal, step_opts, opts.screen, pre)])
        qd0 = (wins[:, 1] - wins[:, 0]) * fps if t == 0 else None
        # the state the windows start from: the frame just observed (before the first step, the reset state)
        start = frames[-1] if frames else self.target.observe()
        bias = grip_bias(self.work[t], start["qpos"], self.fingers, opts.grip, opts.grip_gap)
        run_wins = wins if bias is None else biased(wins, bias, self.applied[t])  # what the target is driven with
        bound = functools.partial(cost_bounds, ref_pos=ref_pos[w], ref_quat=ref_quat[w], ref_kp=ref_kp[w], cost=cost)
        prune = pruner(opts, wins, bound) if self.observer is None else None  # a recording keeps every frame
        pred = self.target.rollout_windows(run_wins, qd0, prune, self.contacts)
        costs = cost(wins, pred)
        if prune is not None:  # the candidates that stopped early are never chosen
            costs = np.where(np.isnan(pred.obj_pos[:, -1, 0]), np.inf, costs)
        live = [c for c in self.copies if _within_limits(c.observe(), ref_pos[t], ref_quat[t])]
        score, n_copy_steps = _score_in_copies(live, run_wins, qd0, costs, cost, opts, self.contacts)
        self.steps += n_copy_steps
        win, best = next_plan_window(wins, score, opts)
        if self.observer is not None:
            blocks = (step_opts.samples, opts.samples, 1 + len(self.alts))
            self.observer.record_step(t, start, run_wins, qd0, pred, costs, best, blocks)
        self.work[t : t + H + 1] = win
        self.steps += pred.n_steps
        n = 1 if self.widened[t] else min(opts.replan, H, self.T - 1 - t)  # one where re-planned after a back-up
        return _Step(t, win, best, bias, pred, score, live, n)

    def calm(self, step: _Step, j: int) -> bool:
        """Whether frame ``j`` (>= 2) of ``step``'s window may be applied without planning again (step 5)."""
        t = self.t
        return _calm(step.pred, step.best, j, self.ref_pos[t + 1], self.ref_quat[t + 1], self.opts.replan_margin)

    def apply(self, step: _Step, j: int) -> int | None:
        """Apply frame ``j`` of ``step``'s window (``t -> t + 1``) in the target and the copies, then check the
        new frame against the strict limits (step 6): the frame to back up to, or None."""
        opts, t, every, ref_pos, ref_quat = self.opts, self.t, self.every, self.ref_pos, self.ref_quat
        self.applied[t + 1] = step.win[j] if step.bias is None else step.win[j] + step.bias
        if t == 0:  # the run starts with the hand velocity of the applied targets, as a replay of them
            for tg in every:
                tg.reset(self.applied[0], (self.applied[1] - self.applied[0]) * self.fps)
            self.frames.append(self.target.observe())
        for tg in every:
            tg.advance(self.applied[t], self.applied[t + 1])
        self.frames.append(self.target.observe())
        self.losses[t] = step.score.min()
        self.steps += len(every) * self.target.substeps
        if step.best is not None:  # what the chosen candidate predicted against what the target did
            q_now, p_now, pred = self.frames[-1]["qpos"], self.frames[-1]["obj_pos"], step.pred
            self.pred_err[t] = max(
                np.abs(pred.qpos[step.best, j - 1] - q_now).max(), np.abs(pred.obj_pos[step.best, j - 1] - p_now).max()
            )
        self.t = t = t + 1
        over = _limit_fraction(self.frames[-1], ref_pos[t], ref_quat[t])
        off = not over <= 1.0  # outside the strict limits (or not finite)
        if opts.backtrack_copies and step.live:  # a copy on track before this frame and off it after
            off = off or not all(_within_limits(c.observe(), ref_pos[t], ref_quat[t]) for c in step.live)
        near = off or over > opts.backtrack_limit  # outside, or inside by less than the margin asked
        back = None if self.lost and not opts.backtrack_after_lost else _back_up_to(t, near, opts, self.backed_from)
        self.lost = self.lost or (off and back is None)
        if self.stopped:
            return None
        if opts.backtrack > 0:  # the states a back-up may return to
            self.saved[t] = [tg.save_state() for tg in every]
            back, drop = _kept_states(sorted(self.saved), t, back, self.behind)
            for k in drop:
                _release(every, self.saved.pop(k))
        return back

    def back_up(self, back: int) -> None:
        """Put the target and the copies back to their states after frame ``back``, to plan the frames since
        again with more samples (step 6)."""
        t = self.t
        self.backed_from[t] = self.backed_from.get(t, 0) + 1
        self.events.append((t, back))
        for tg, state in zip(self.every, self.saved[back], strict=True):
            tg.restore_state(state)
        del self.frames[back + 1 :]
        self.widened[back:t] = True
        self.t = back

    def result(self) -> SampleResult:
        """The run so far (the saved states released; the observer told the applied run)."""
        for states in self.saved.values():
            _release(self.every, states)
        wall = time.perf_counter() - self.t0
        if self.observer is not None:
            self.observer.finish(self.applied, self.frames)
        backups = np.array(self.events, np.int64).reshape(-1, 2)
        rollout = self.target.recorded(self.frames, wall)
        stopped = self.t if self.stopped else None
        return SampleResult(self.applied, rollout, self.losses, wall, self.steps, self.pred_err, backups, stopped)


def grip_bias(q: np.ndarray, qpos: np.ndarray, fingers: np.ndarray, grip: float, gap: float) -> np.ndarray | None:
    """(D,) step 3's grip bias: ``grip * sign(q - qpos)`` on the ``fingers`` columns whose measured position
    ``qpos`` is more than ``gap`` from its PD target ``q`` (a joint that the object holds back is pressed
    further, ``kp grip`` more torque), 0 elsewhere; None without a grip (``grip`` 0)."""
    if grip == 0:
        return None
    g = np.where(fingers, q - qpos, 0.0)
    return np.where(np.abs(g) > gap, grip * np.sign(g), 0.0)


def biased(wins: np.ndarray, bias: np.ndarray, q_now: np.ndarray) -> np.ndarray:
    """(N, H + 1, D) windows ``wins`` as the target runs them: frame 0 the targets applied last (``q_now``,
    with their own bias), the later frames plus ``bias``."""
    out = wins + bias
    out[:, 0] = q_now
    return out


def _draw(
    sample: Callable[..., np.ndarray], rng: np.random.Generator, nominal: np.ndarray, o: SamplingOptions, screen: int,
    pre: Callable[[np.ndarray], np.ndarray] | None,
) -> np.ndarray:  # fmt: skip
    """Step 2: ``o.samples`` windows around ``nominal``; with a pre-screen ``pre`` (windows -> costs), the
    nominal and the cheapest others of ``screen`` times as many."""
    if pre is None:
        return sample(rng, nominal, opts=o)
    many = sample(rng, nominal, opts=dataclasses.replace(o, samples=o.samples * screen))
    return screened(many, o.samples, pre(many))


def _score_in_copies(
    live: Sequence[Target], wins: np.ndarray, qd0: np.ndarray | None, costs: np.ndarray,
    cost: Callable[[np.ndarray, Prediction], np.ndarray], opts: SamplingOptions, contacts: int = 0,
) -> tuple[np.ndarray, int]:  # fmt: skip
    """Step 7: the ``opts.robust_top`` cheapest candidates (``costs`` in the target) rolled out in the ``live``
    copies too and scored by :func:`robust_scores` with ``opts.robust_risk`` (``costs`` itself without live
    copies); and the physics steps the copies took."""
    if not live:
        return costs, 0
    top = np.argsort(costs, kind="stable")[: opts.robust_top]
    preds = [c.rollout_windows(wins[top], None if qd0 is None else qd0[top], None, contacts) for c in live]
    scores = robust_scores(costs, [cost(wins[top], p) for p in preds], top, opts.robust_risk, opts.robust_cvar)
    return scores, sum(p.n_steps for p in preds)


def _kept_states(frames: list[int], t: int, back: int | None, keep: int) -> tuple[int | None, list[int]]:
    """The back-up bookkeeping after frame ``t``'s state is saved (``frames``: the frames with a saved state):
    the frame to go back to (``back``, or the oldest frame kept when chained back-ups reach past it) and the
    saved frames to release: without a back-up those older than ``t - keep``, with one those after it."""
    if back is None:
        return None, [k for k in frames if k < t - keep]
    back = max(back, frames[0])
    return back, [k for k in frames if k > back]


def _release(targets: Sequence[Target], states: list[object]) -> None:
    for tg, state in zip(targets, states, strict=True):
        tg.release_state(state)


def _recorded(block: int, n: int, blocks: int, best: int | None) -> np.ndarray:
    """Indices of the windows a transitions file keeps of one step: the first ``n`` of each of ``blocks``
    blocks of ``block`` windows (a re-planned step samples more; every step keeps the same count), with the
    applied window ``best`` in place of the last one kept if it is not among them."""
    keep = np.concatenate([k * block + np.arange(n) for k in range(blocks)])
    if best is not None and best not in keep:
        keep[-1] = best
    return keep


def _back_up_to(t: int, off: bool, opts: SamplingOptions, backed_from: dict[int, int]) -> int | None:
    """The frame to go back to when frame ``t`` left the strict limits (``off``; step 6), or None:
    ``backtrack`` frames back, ``backtrack`` further for each back-up from ``t`` before (``backed_from``:
    frame -> back-ups from it), within ``backtrack_retries`` retries and the clip's ``backtrack_budget``."""
    done = backed_from.get(t, 0)
    if not off or opts.backtrack == 0 or sum(backed_from.values()) >= opts.backtrack_budget or t < 2:
        return None
    return None if done > opts.backtrack_retries else max(1, t - (done + 1) * opts.backtrack)


def _calm(
    pred: Prediction, best: int | None, j: int, ref_pos: np.ndarray, ref_quat: np.ndarray, margin: float | None
) -> bool:
    """Whether frame ``j`` (>= 2) of the chosen window may be applied without planning again (step 5): always
    without a ``margin``; otherwise only when the chosen candidate ``best`` predicted the object at that frame
    within ``margin`` x the strict limits of its reference pose (3,), (4,) (never in ``mppi`` mode, where no
    single candidate is applied and nothing predicted the frame)."""
    if margin is None:
        return True
    if best is None:
        return False
    trans, rot = strict_fractions(pred.obj_pos[best, j - 1], pred.obj_quat[best, j - 1], ref_pos, ref_quat)
    return max(float(trans), float(rot)) < margin


def _limit_fraction(obs: Observation, ref_pos: np.ndarray, ref_quat: np.ndarray) -> float:
    """The larger of the object's translation and rotation errors in ``obs`` against its reference pose (3,),
    (4,), as a fraction of the strict limits (above 1: over)."""
    trans, rot = strict_fractions(obs["obj_pos"], obs["obj_quat"], ref_pos, ref_quat)
    return max(float(trans), float(rot))


def _within_limits(obs: Observation, ref_pos: np.ndarray, ref_quat: np.ndarray) -> bool:
    """Whether the object of ``obs`` is within the strict limits of its reference pose (3,), (4,)."""
    return _limit_fraction(obs, ref_pos, ref_quat) <= 1.0


def run(ctx: Context, out: Outcome) -> Outcome:
    """Sampling around the last stage's PD targets (the nominal, kept for the selection as ``sampling
    nominal``) and, after a stage that planned (``kinematic_alternative``), around the kinematic retarget too."""
    prob, cfg, spec = ctx.prob, ctx.cfg, ctx.spec
    nominal = out.q
    alternatives = (ctx.kinematic_q,) if cfg.sampling.kinematic_alternative and out.planned else ()

    kept = Transitions() if ctx.transitions is not None else None

    def sample() -> dict[str, Any]:
        r = run_sampling(
            prob.demo, prob.scene, nominal, cfg.sampling, cfg.weights, spec.target, spec.progress, alternatives, kept
        )
        return {
            "q_targets": r.q_targets, "window_loss": r.window_loss, "wall_s": np.array(r.wall_s),
            "n_physics_steps": np.array(r.n_physics_steps), "backups": np.array(r.backups),
            "backup_frames": r.backup_frames,
        }  # fmt: skip

    d = ctx.ck.get("sample", sample, q_expect(prob))
    if kept is not None:
        _save_transitions(ctx, kept)
    ctx.record.seconds["sample"] = float(d["wall_s"])
    ctx.record.curves["sampling window loss per frame"] = [float(x) for x in d["window_loss"]]
    backups = f", {int(d['backups'])} back-ups" if "backups" in d and int(d["backups"]) else ""
    ctx.progress.write(f"sampling in {spec.target} done in {ctx.record.seconds['sample']:.0f} s{backups}")
    seen = {**out.seen, "sampling nominal": nominal}
    return out.replace(q=np.asarray(d["q_targets"], np.float64), planned=True, seen=seen)


def _save_transitions(ctx: Context, kept: Transitions) -> None:
    """``TRANSITIONS/<demo>.<method>.npz`` (said on the progress output); nothing when the sampling stage's
    checkpoint was reused (it did not run), said in one line on stderr."""
    assert ctx.transitions is not None
    demo, spec = ctx.prob.demo, ctx.spec
    path = ctx.transitions / f"{demo.name}.{spec.method}.npz"
    if not kept.run:
        print(
            f"warning: {path}: not written: the sampling stage was read back from its checkpoint (start the run "
            "afresh to record what it rolls out)",
            file=sys.stderr,
        )
        return
    sc = ctx.prob.scene
    meta = {
        "demo": demo.name, "demo_content": content_hash(demo), "hands": " + ".join(h.name for h in sc.hands),
        "hand_dofs": np.array([6 + h.n_joints for h in sc.hands]), "target": spec.target, "method": spec.method,
        "fps": demo.fps, "horizon": ctx.cfg.sampling.horizon, "base_rots": np.stack(sc.base_rots),
        "object": sc.obj.name, "object_mass": sc.obj.mass, "object_com": np.asarray(sc.obj.com),
        "object_inertia": np.asarray(sc.obj.inertia), "kp_metric_index": np.flatnonzero(sc.kp_metric),
        "kp_human": sc.kp_human,
        "table": np.array([sc.table.xmin, sc.table.xmax, sc.table.ymin, sc.table.ymax, sc.table.top]),
    }  # fmt: skip
    kept.save(path, meta)
    ctx.progress.write(f"recorded {len(kept.steps)} sampling steps in {path}")


# s_per_frame: 0.27 s per frame measured on 60-frame GRAB clips, 0.13-0.15 on the long examples (docs/history "Commands on long clips")
STAGE = Stage(
    name="sample", word="sample", config=("sampling",), s_per_frame=0.19, run=run, plans=True, uses_target=True
)
