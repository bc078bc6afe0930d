"""The settings of each stage of the method: the sections of ``configs/transfer.yaml`` that belong to one stage
(``stage1``, ``stage2``, ``mpc``, ``sampling``, ``stage3``, ``neural``, ``control_vae``, ``robust_select``), fields of
:class:`~quasisim.method.config.TransferConfig` (light: no JAX or MuJoCo; the stage modules, the config and
the closed-loop tracker read them from here)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from quasisim.errors import QuasisimError, choice_error


@dataclass(frozen=True)
class Stage1Options:
    """Stage 1's settings.

    Attributes:
        human_point_seed: seed of the draw of the human hand's point set (the points the robot's point set
            follows). Any seed is as good as another; runs that differ only in it measure how much a result
            depends on such arbitrary choices (BENCHMARKS.md, run-to-run spread).
    """

    human_point_seed: int


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


HANDOFF_MODES = ("stiffest", "every", "none")


@dataclass(frozen=True)
class MPCOptions:
    """Closed-loop MPC settings (values: ``configs/transfer.yaml``).

    Attributes:
        horizon: frames optimised at each step (H; the paper's q).  steps: Adam steps per frame.  lr: Adam step size.
        soften: number of stiffness samples per gradient (0: plain gradient; mpc-soften uses 4).
        soften_range: relative half-width of the stiffness samples (0.1 = +-10 %).  seed: sampling seed.
    """

    horizon: int
    steps: int
    lr: float
    soften: int
    soften_range: float
    seed: int


RISK_MEASURES = ("mean", "worst", "cvar")  # step 7's aggregation over the target and its perturbed copies
SAMPLING_MODES = ("predictive", "mppi")


@dataclass(frozen=True)
class SamplingOptions:
    """Predictive-sampling settings (see :mod:`quasisim.method.stages.sampling`; no defaults, they come from YAML).

    Attributes:
        samples: candidate windows per frame, the nominal included.  horizon: frames per window.
        knots: noise knots per window.  noise_base_pos (m), noise_base_rot (rad), noise_joints (rad or m):
            noise std per dof group.  noise_scales: per-candidate std multipliers, cycled.
        mode: ``"predictive"`` (take the best window) or ``"mppi"`` (softmax-weighted mean).
        temperature: MPPI softmax temperature (cost units).  seed: noise seed.  threads: rollout threads.
        kinematic_alternative: in stage ``sample`` after other stages, also sample ``samples`` windows around
            the kinematic retarget at every frame (no effect when the plan is the kinematic retarget).
        strict_weight, strict_margin: the hinge on the strict limits in the window cost (step 4; weight 0: none).
        backtrack, backtrack_samples, backtrack_budget: backing up when a frame leaves the strict limits
            (step 6; 0 frames: never).  backtrack_retries: further back-ups from a frame that leaves the
            limits again, each ``backtrack`` frames further back (step 6; 0: none).
            backtrack_strict_weight: the hinge's weight on frames re-planned after a back-up (step 6;
            None: ``strict_weight``).  backtrack_after_lost: go on backing up after a frame has stayed
            outside the limits (step 6).  backtrack_limit: the fraction of the strict limits whose crossing
            backs up (step 6; 1: the limits themselves).
        robust_copies, robust_top, robust_seed: scoring the cheapest ``robust_top`` candidates in
            ``robust_copies`` perturbed copies of the target seeded with ``robust_seed`` (step 7; 0: none; the
            method's own worlds, :class:`~quasisim.targets.perturb.TrainingWorlds`, never a judging world).
        robust_worlds, robust_thin: named worlds scoring the candidates beside the random copies (step 7; each of
            :data:`~quasisim.targets.perturb.NAMED_WORLDS`, :func:`~quasisim.targets.perturb.named_world`:
            ``corner``, ``thin`` with contacts ``robust_thin`` m thinner, ``corner-thin``; empty: none).
        backtrack_copies: back up also when a copy on track leaves the strict limits (step 7).
        robust_risk: how step 7 aggregates a candidate's costs over the target and the copies: ``mean``,
            ``worst`` (the largest), ``cvar`` (the mean of the worst ``robust_cvar`` fraction, at least one).
        screen: draw ``screen`` x the windows and roll out only the kinematic pre-screen's cheapest (step 2;
            1: no pre-screen).
        replan: frames of the chosen window applied before planning again (step 5; at most ``horizon``;
            1 on frames re-planned after a back-up).  replan_margin: frames after the first applied only while
            the chosen candidate predicted the object within this fraction of the strict limits (step 5;
            None: always).  widen_margin: steps that start with the object beyond this fraction of the strict
            limits sample ``backtrack_samples`` x the windows (step 2; None: never).
        prune_frames, prune_keep: every candidate runs the first ``prune_frames`` frames of its window, then
            only the ``prune_keep`` fraction (at least ``samples``) with the lowest cost bound goes on (step 3;
            0 frames: no pruning).
        grip, grip_gap: the extra closure (rad or m) of finger joints held more than ``grip_gap`` from their
            targets at a step's start, added to every window's frames (step 3; 0: none).
        grasp_weight, grasp_margin, grasp_slots: the grasp margin in the window cost (step 4; weight 0: none):
            ``grasp_weight`` x the mean over the window's frames of the hand-object contacts' tangential load
            beyond friction cones shrunk by ``grasp_margin`` (:func:`quasisim.targets.grasp.slack_excess`, in
            object weights), from each hand's ``grasp_slots`` strongest contacts.
        stop_when_lost: end the run at the first frame that stays outside the strict limits (step 6: the clip
            can no longer pass strict success; the frames after it keep the plan's targets). The cascade's
            first step (stage ``quick``) sets it; false in ``configs/transfer.yaml``.
    """

    samples: int
    horizon: int
    knots: int
    noise_base_pos: float
    noise_base_rot: float
    noise_joints: float
    noise_scales: tuple[float, ...]
    mode: str
    temperature: float
    seed: int
    threads: int
    kinematic_alternative: bool
    strict_weight: float = 0.0
    strict_margin: float = 0.75
    backtrack: int = 0
    backtrack_samples: int = 4
    backtrack_budget: int = 6
    robust_copies: int = 0
    robust_top: int = 8
    robust_seed: int = 1
    backtrack_copies: bool = False
    screen: int = 1
    replan: int = 1
    replan_margin: float | None = None
    widen_margin: float | None = None
    backtrack_retries: int = 0
    backtrack_strict_weight: float | None = None
    prune_frames: int = 0
    prune_keep: float = 0.5
    backtrack_after_lost: bool = True
    grip: float = 0.0
    grip_gap: float = 0.02
    backtrack_limit: float = 1.0
    stop_when_lost: bool = False
    robust_risk: str = "mean"
    robust_cvar: float = 0.5
    robust_worlds: tuple[str, ...] = ()
    robust_thin: float = 0.001
    grasp_weight: float = 0.0
    grasp_margin: float = 0.2
    grasp_slots: int = 8

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Raise :class:`QuasisimError` naming the first bad setting."""
        for name in ("samples", "horizon", "knots", "threads", "backtrack_samples", "robust_top", "screen", "replan",
                     "grasp_slots"):  # fmt: skip
            v = getattr(self, name)
            if not _is_int(v) or v < 1:
                raise QuasisimError(f"sampling option '{name}' must be a positive integer, got {v!r}")
        for name in ("backtrack", "backtrack_budget", "robust_copies", "backtrack_retries", "prune_frames"):
            v = getattr(self, name)
            if not _is_int(v) or v < 0:
                raise QuasisimError(f"sampling option '{name}' must be an integer >= 0, got {v!r}")
        if not _is_int(self.seed):
            raise QuasisimError(f"sampling option 'seed' must be an integer, got {self.seed!r}")
        if not _is_int(self.robust_seed) or not 0 <= self.robust_seed < 2**32:  # perturb.TrainingWorlds
            raise QuasisimError(
                f"sampling option 'robust_seed' must be an integer in [0, 2**32), got {self.robust_seed!r}"
            )
        for name in ("noise_base_pos", "noise_base_rot", "noise_joints", "strict_weight", "strict_margin", "grip",
                     "grip_gap", "grasp_weight"):  # fmt: skip
            v = getattr(self, name)
            if not (_is_number(v) and v >= 0):
                raise QuasisimError(f"sampling option '{name}' must be a finite number >= 0, got {v!r}")
        sc = self.noise_scales
        if not isinstance(sc, tuple) or not sc or not all(_is_number(s) and s >= 0 for s in sc):
            raise QuasisimError(f"sampling option 'noise_scales' must be a non-empty tuple of numbers >= 0, got {sc!r}")
        for name in ("kinematic_alternative", "backtrack_copies", "backtrack_after_lost", "stop_when_lost"):
            if not isinstance(getattr(self, name), bool):
                raise QuasisimError(f"sampling option '{name}' must be true or false, got {getattr(self, name)!r}")
        w = self.backtrack_strict_weight
        if w is not None and not (_is_number(w) and w >= 0):
            raise QuasisimError(
                f"sampling option 'backtrack_strict_weight' must be null or a finite number >= 0, got {w!r}"
            )
        for name in ("replan_margin", "widen_margin"):
            m = getattr(self, name)
            if m is not None and not (_is_number(m) and m > 0):
                raise QuasisimError(f"sampling option '{name}' must be null or a finite number > 0, got {m!r}")
        if not (_is_number(self.backtrack_limit) and 0 < self.backtrack_limit <= 1):
            raise QuasisimError(
                f"sampling option 'backtrack_limit' must be a number in (0, 1], got {self.backtrack_limit!r}"
            )
        if not (_is_number(self.prune_keep) and 0 < self.prune_keep <= 1):
            raise QuasisimError(f"sampling option 'prune_keep' must be a number in (0, 1], got {self.prune_keep!r}")
        if self.mode not in SAMPLING_MODES:
            raise choice_error("sampling mode", self.mode, SAMPLING_MODES)
        from quasisim.targets.perturb import NAMED_WORLDS

        for w in self.robust_worlds:
            if w not in NAMED_WORLDS:
                raise choice_error("sampling option 'robust_worlds'", w, NAMED_WORLDS)
        if not (_is_number(self.robust_thin) and 0 < self.robust_thin <= 0.01):
            raise QuasisimError(
                f"sampling option 'robust_thin' must be a depth in (0, 0.01] m, got {self.robust_thin!r}"
            )
        if not (_is_number(self.grasp_margin) and 0 <= self.grasp_margin < 1):
            raise QuasisimError(
                f"sampling option 'grasp_margin' must be a fraction in [0, 1), got {self.grasp_margin!r}"
            )
        if self.robust_risk not in RISK_MEASURES:
            raise choice_error("sampling option 'robust_risk'", self.robust_risk, RISK_MEASURES)
        if not (_is_number(self.robust_cvar) and 0 < self.robust_cvar <= 1):
            raise QuasisimError(f"sampling option 'robust_cvar' must be a number in (0, 1], got {self.robust_cvar!r}")
        if not (_is_number(self.temperature) and self.temperature > 0):
            raise QuasisimError(f"sampling option 'temperature' must be a finite number > 0, got {self.temperature!r}")


def _is_int(v: object) -> bool:
    return isinstance(v, int | np.integer) and not isinstance(v, bool)


def _is_number(v: object) -> bool:
    return isinstance(v, int | float | np.number) and not isinstance(v, bool) and math.isfinite(float(v))


@dataclass(frozen=True)
class FitOptions:
    """Settings of the fit (values: ``configs/transfer.yaml``, ``stage3``).

    Attributes:
        horizon: frames per window (H).  held_out: fraction of the clip's last frames left out of the fit.
        variants: noisy rollouts added to the buffer beside the current controls.  capacity: rollouts kept.
        steps, lr: Adam steps and step size of the constants.  batch: windows per step.
        residual_steps, residual_lr: the same for the residual networks (0 steps: no residual).
        rounds: world-model rounds after the first fit (:func:`world_model_rounds`; 0: fit only).
        seed: window sampling and variant noise.
    """

    horizon: int
    held_out: float
    variants: int
    capacity: int
    steps: int
    lr: float
    batch: int
    residual_steps: int
    residual_lr: float
    rounds: int
    seed: int


@dataclass(frozen=True)
class NeuralOptions:
    """Settings of stage ``neural`` (``configs/transfer.yaml``, ``neural``): a neural model of the target alone
    (:mod:`quasisim.method.world_model`), the paper's ablation "w/o analytical sim".

    Attributes:
        widths: the hidden layers' widths (the paper's world model: 256, six of 512, 256).
        horizon: frames per training window (the model is rolled out that far on its own predictions).
        variants: noisy rollouts added to the buffer beside the current controls each round.
        steps, lr, batch: training steps, step size and windows per step of each round's fit.
        rounds: fit, optimise the controls through the model, roll them out in the target; the best judged there
            is kept.  plan_steps, plan_lr: Adam on the controls through the model per round.
        mpc_horizon, mpc_steps, mpc_lr: closed-loop MPC in the target with the model (0 steps: none).
        trust: the trust region of every optimisation through the model: controls move at most ``trust`` times
            the sampling stage's noise std per column from where it started (``q0 + r tanh(z)``, Adam on ``z``;
            ``plan_lr`` and ``mpc_lr`` are steps in ``z``), so that they stay where the model has data.
        seed: initial weights, window sampling and variant noise.
    """

    widths: tuple[int, ...]
    horizon: int
    variants: int
    steps: int
    lr: float
    batch: int
    rounds: int
    plan_steps: int
    plan_lr: float
    mpc_horizon: int
    mpc_steps: int
    mpc_lr: float
    trust: float
    seed: int


@dataclass(frozen=True)
class ControlVAEOptions:
    """Settings of stage ``control_vae`` (``configs/transfer.yaml``, ``control_vae``): the paper's Control-VAE
    baseline adapted to tracking (:mod:`quasisim.method.control_vae`); its world model is stage ``neural``'s
    (the ``neural`` section's widths, horizon, variants and fit).

    Attributes:
        widths: the hidden layers of the prior, the encoder and the decoder.  latent: the latent size Z.
        sigma: the latent's standard deviation (prior and posterior).  beta: the KL term's weight.
        horizon: frames per training window, acted through the world model.
        steps, lr, batch: the controller's minibatch Adam steps per round, step size and windows per step.
        rounds: train the controller, drive the target with it, refit the model on what it did.
        trust: the controller's PD targets stay within ``trust`` x the sampling noise std of the kinematic
            retarget per column (as stage ``neural``'s trust region).
        seed: initial weights, window noise and variant noise.
    """

    widths: tuple[int, ...]
    latent: int
    sigma: float
    beta: float
    horizon: int
    steps: int
    lr: float
    batch: int
    rounds: int
    trust: float
    seed: int


@dataclass(frozen=True)
class RobustSelectOptions:
    """Choosing plans for the worlds they will meet (``configs/transfer.yaml``, ``robust_select``): the cascade's
    gate (stage ``quick``) and the selection (stage ``select``) replay the plans that pass strict success in the
    nominal target **closed loop** (the tracker of ``tracker``) in ``worlds`` perturbed copies of it (the ranges
    of ``configs/robust.yaml``, drawn with ``seed`` from the method's own stream,
    :class:`~quasisim.targets.perturb.TrainingWorlds`: never a world robust success is judged in). The quick
    result ends the run only where at least ``gate`` of them pass strict success; the selection keeps, among the
    candidates that pass strict nominally, the one passing strict in most worlds (then the objective). ``worlds`` 0: both judge in the nominal target alone, as before.

    ``margin`` > 0 (stage ``margin``, :mod:`quasisim.method.stages.margin`): a plan that passes strict success with
    its largest error above ``margin`` x the limits is sampled again from itself, backing up at ``margin`` x the
    limits, and the result kept where it passes with a smaller largest error.

    Attributes:
        worlds: training worlds per plan (0: off).  seed: their seed, in [0, 2**32) (whatever it is, never a
            judging world's, ``--robust-set seed=N`` included).
        gate: the fraction of worlds the quick result must pass strict in, in [0, 1].
        tracker: the tracker's settings: a file of ``configs/`` (``track_fast.yaml``) or a path.
        margin: the fraction of the strict limits a plan's largest error may reach before stage ``margin``
            samples it again (0: never).
    """

    worlds: int = 0
    seed: int = 1
    gate: float = 0.75
    tracker: str = "track_fast.yaml"
    margin: float = 0.0


def tracker_file(name: str) -> Path:
    """The tracker settings ``name``: a file of ``configs/`` (``track.yaml``, ``track_fast.yaml``) or a path;
    an error lists the shipped ones."""
    from quasisim.errors import InputError

    configs = Path(__file__).resolve().parent.parent / "configs"
    shipped = configs / name
    path = shipped if "/" not in name and shipped.is_file() else Path(name)
    if not path.is_file():
        presets = sorted(p.name for p in configs.glob("track*.yaml") if p.name != "track_env.yaml")
        raise InputError(None, "tracker", f"one of {', '.join(presets)} or a YAML file", repr(name))
    return path
