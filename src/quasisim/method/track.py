"""Closed-loop tracking of a finished result: the plan's PD targets, corrected from the observed state.

An open-loop trajectory through contact is chaotic: in a world a little different from the one it was planned
in (mass, friction, gains, the object's start) its replays part from the plan by millimetres once the hand
touches the object. :class:`Tracker` closes the loop. It drives a world it knows only through
:meth:`~quasisim.targets.base.Target.observe` (the hands' joints and velocities, the object's pose and twist)
and acts on it with PD targets, frame by frame:

1. **Shift** (frame 0): the object's observed position minus its nominal start, ``d`` (x, y), moves the plan's
   hand bases and the reference by ``w_t d`` from frame 1 on (the object where it is, not where it was planned).
   ``w_t`` = 1 throughout by default; with ``shift_fade`` = s > 0 it fades as the plan carries the object away
   from its start, ``w_t = min_{u <= t} max(0, 1 - |p_u - p_0| / s)`` (``p``: the object's position in the
   plan's nominal rollout), so the hands reach for the object where it is and bring it back to the demo's path
   once they hold it.
2. **Follow**: between re-plans, apply the plan's next PD targets ``q*_{t+1}``.
3. **Re-plan** every ``every`` frames from the observed state: put the observation into the tracker's **model**,
   a target of the nominal scene (:meth:`~quasisim.targets.base.Target.sync`; the world's hidden parameters are
   never read), roll ``samples`` windows of the next ``horizon`` frames out in it (the current plan's window,
   the untouched plan's window, and Gaussian perturbations of the current one on ``knots`` knots, the sampling
   stage's noise, :func:`quasisim.method.stages.sampling.sample_windows`; with ``grip``, also the current one
   pressing harder where the object holds fingers back) and keep the cheapest as the plan
   (receding horizon, warm-started). The cost (:func:`quasisim.method.stages.sampling.window_costs`) measures
   the distance to the plan's own **nominal rollout** (object pose, metric keypoints; shifted by ``d``), not to
   the demo, so in the nominal world the tracker reproduces the plan; ``strict_weight`` > 0 adds the hinge on
   the demo's strict limits (2 cm, 30 deg) from ``strict_margin`` of them.

**Weighing several worlds** (``worlds``): the re-plan's windows are also rolled out, from the same observed
state, in models of named worlds (:func:`quasisim.targets.perturb.named_world`: ``corner``, the hard corner of
the robust ranges, mass high, friction low, gains low; ``thin``, contacts ``world_thin`` m thinner;
``corner-thin``), each scored against the same plan's nominal rollout, and a window is chosen by its costs
in the nominal model and those worlds aggregated by ``world_risk`` (``worst``, ``mean``, ``cvar`` of the worst
``world_cvar`` fraction; the sampling stage's :func:`~quasisim.method.stages.sampling.robust_scores`), so a
plan chosen to hold in the corner is not re-planned back to the nominal model's cheapest. Each world costs one
more rollout of the windows per re-plan.

**Grasp margin** (``grasp_weight`` > 0): the windows are rolled out with each hand's ``grasp_slots`` strongest
contacts with the object, in the nominal model and every world's, and the cost adds ``grasp_weight`` x the
window mean of the load they carry beyond friction cones shrunk by ``grasp_margin`` (the sampling stage's
grasp term, :func:`quasisim.method.stages.sampling.grasp_term`), so the tracker keeps the margin a plan was
made with instead of re-planning to the nominal model's cheapest grasp at the rim of its cones.

An observation that carries a time stamp ``frame`` older than ``t`` (a late sensor,
:class:`~quasisim.targets.perturb.Sensor`) is brought up to date in the model first: synced there, then advanced
through the targets the tracker applied since (a Smith predictor); the re-plan starts from that prediction.

**Planning beside the controller** (``lead`` > 0): a robot's planner runs in its own thread while the
controller applies the plan, so a re-plan may take several frame periods. With ``lead`` = L, the re-plan that
starts at frame ``t`` plans from the state predicted at ``t + L`` (the observation advanced in the model through
the targets already committed for frames ``t + 1 .. t + L``) and changes the plan from frame ``t + L + 1`` on;
the controller meanwhile applies the committed targets. With ``every`` = ``lead``, one core keeps up when a
re-plan takes at most ``every`` frame periods (``replan_ms_p95`` against ``every / fps``), whatever a single
control step costs; the simulation runs the re-plan inside :meth:`Tracker.act` but lets its result act only
where a concurrent planner's could.

**Filtering noisy observations** (``obs_gain`` < 1): the state the tracker re-plans from is its own estimate: the
previous estimate advanced in the model through the target applied since, moved toward the (latency-corrected)
observation by ``obs_gain`` (positions and velocities linearly, the object's orientation by spherical
interpolation): a fixed-gain observer. 1 (default) takes every observation as it is.

**Learning the sensors** (``obs_adapt``): the same observer with a gain per observed number, learned from the
innovations ``e_t`` (the latency-corrected observation minus the model's prediction from the last estimate;
the object's orientation as a rotation vector in its predicted frame). An observer with the optimal (Kalman)
gain leaves white innovations; one that trusts a noisy sensor too much leaves them negatively correlated from
frame to frame (the noise it took into its estimate returns with the opposite sign), one that trusts its model
too much positively (its estimate lags). So each gain starts at 1 and moves by the innovations' correlation at
lag 1, ``k <- k exp(ADAPT_RATE rho)`` in [:data:`MIN_GAIN`, 1], the averages decaying by ``obs_adapt_decay`` per
frame, after :data:`WARMUP` frames (Mehra's whiteness test of an adaptive Kalman filter, used as a gradient).
An exact sensor keeps its gain near 1; a noisy one's falls as far as its noise exceeds the model's error.

**Learning the world** (``adapt``): the paper's stage 3, fitting the model to the target, done inside the loop.
Beside the nominal model the tracker holds six more, each with one hidden parameter at an end of the training
ranges (``configs/robust.yaml``: object mass, friction, PD gains, each times ``1 -+ range``). After every frame
each model is synced to the previous observation and advanced through the targets applied since; its error
against the new observation (object position in mm plus the hands' joints in 0.01 rad, mean) is added to an
exponentially decaying score (``adapt_decay``), and every re-plan runs in the model with the lowest score. The
world's parameters are never read: only observed transitions choose the model.

Settings: ``configs/track.yaml`` (:class:`TrackOptions`). Cost per replay: about ``T / every`` re-plans of
``samples`` x ``horizon`` frames in the model. Time-varying linear feedback around the plan (finite-difference
Jacobians, a Riccati pass) was measured by a prototype (``docs/transfer.md``: 0 % robust strict, contact makes
the Jacobians useless) and is not built.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from quasisim.config import apply_overrides, build, read_yaml
from quasisim.data.demo import Demo
from quasisim.errors import InputError
from quasisim.optim.objective import Weights, padded
from quasisim.targets import Observation, Target, TargetRollout, make_target
from quasisim.targets.perturb import finger_columns, named_world
from quasisim.targets.scene import Scene

TRACK_PATH = Path(__file__).resolve().parent.parent / "configs" / "track.yaml"
MIN_GAIN, WARMUP, ADAPT_RATE = 0.05, 5, 0.5  # obs_adapt: the lowest gain; frames before it learns; its rate
LINEAR = ("qpos", "qvel", "obj_pos", "obj_vel", "obj_angvel")  # the observer's channels besides the orientation


@dataclass(frozen=True)
class TrackOptions:
    """The tracker's settings (``configs/track.yaml``; see the module docstring).

    Attributes:
        every: frames between re-plans (0: never re-plan; the shift alone).  samples: candidate windows per
            re-plan (>= 2: the current and the untouched plan's window).  horizon: frames per window.
        knots: noise knots per window.  noise_base_pos (m), noise_base_rot (rad), noise_joints (rad):
            noise std per dof group.  noise_scales: per-candidate std multipliers, cycled.
        shift: move the plan by the object's observed start offset (step 1).
        shift_fade: the object's travel in the plan's nominal rollout (m) over which that shift fades back to
            none (0: it never fades).
        follow: fractions ``f``: at each re-plan, candidates with the hands' bases moved by ``f`` x the object's
            offset from the plan's nominal rollout (``f > 0`` follows the object, ``f < 0`` pushes it back); when
            one is kept, the rest of the plan moves with it.
        grip: closures ``g`` (rad, or m for slide joints): at each re-plan, candidates that are the current
            window pressed harder where the object holds fingers back (``g sign(q* - q)`` added to every finger
            joint more than ``grip_gap`` from its target, as the sampling stage's ``grip``), so that a grasp
            slipping in the world can be tightened in one step, not only by chance in the random windows.
        strict_weight, strict_margin: the hinge on the demo's strict limits in the cost (0: none).
        object_weight: the window cost's object terms (translation, rotation) times this against the hand's
            keypoints (1: the objective's own weights).
        seed: noise seed.  threads: the model's rollout threads.
        model_dt: the model's physics step (s; 0: the scene's own): a coarser step re-plans faster and predicts
            less exactly.
        adapt: choose the model among 7 by how well each predicted the observed transitions.  adapt_decay: the
            weight of the older errors in that score, in [0, 1).
        obs_gain: how far each observation moves the tracker's state estimate from its model's prediction, in
            (0, 1] (1: the observation as it is).  obs_adapt: a gain per observed number learned from the
            innovations instead ("Learning the sensors").  obs_adapt_decay: the weight of older innovations.
        lead: frames a re-plan takes to act (0: within its control step; see "Planning beside the controller").
        keep: a candidate replaces the current plan's window only where its cost is below ``1 - keep`` times the
            current window's (0: the cheapest always), so that differences the model cannot resolve do not move
            the plan.
        worlds: named worlds whose models score every re-plan's windows too ("Weighing several worlds"; empty:
            the nominal model alone).  world_thin: the ``thin`` worlds' contact depth (m).  world_risk: how a
            window's costs over the models are aggregated (``worst``, ``mean``, ``cvar``).  world_cvar: the
            fraction of the worst costs ``cvar`` averages.
        grasp_weight, grasp_margin, grasp_slots: the grasp margin in the window cost ("Grasp margin"; weight 0:
            none), as the sampling stage's options of those names.
    """

    every: int = 1
    samples: int = 16
    horizon: int = 6
    knots: int = 3
    noise_base_pos: float = 0.004
    noise_base_rot: float = 0.04
    noise_joints: float = 0.08
    noise_scales: tuple[float, ...] = (0.5, 1.0, 2.0)
    shift: bool = True
    shift_fade: float = 0.0
    follow: tuple[float, ...] = ()
    grip: tuple[float, ...] = ()
    grip_gap: float = 0.02
    strict_weight: float = 0.0
    strict_margin: float = 0.75
    object_weight: float = 1.0
    seed: int = 0
    threads: int = 1
    model_dt: float = 0.0
    adapt: bool = False
    adapt_decay: float = 0.8
    obs_gain: float = 1.0
    obs_adapt: bool = False
    obs_adapt_decay: float = 0.9
    lead: int = 0
    keep: float = 0.0
    worlds: tuple[str, ...] = ()
    world_thin: float = 0.001
    world_risk: str = "worst"
    world_cvar: float = 0.5
    grasp_weight: float = 0.0
    grasp_margin: float = 0.2
    grasp_slots: int = 8
    path: str = ""

    def __post_init__(self) -> None:
        where = self.path or None
        for name, lo in (("every", 0), ("samples", 2), ("horizon", 1), ("knots", 1), ("threads", 1), ("seed", 0),
                         ("lead", 0), ("grasp_slots", 1)):  # fmt: skip
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < lo:
                raise InputError(where, name, f"an integer >= {lo}", repr(v))
        for name in ("noise_base_pos", "noise_base_rot", "noise_joints", "strict_weight", "strict_margin", "model_dt",
                     "shift_fade", "grip_gap", "object_weight", "grasp_weight"):  # fmt: skip
            v = getattr(self, name)
            if not isinstance(v, int | float) or isinstance(v, bool) or not 0 <= v < float("inf"):
                raise InputError(where, name, "a finite number >= 0", repr(v))
        if not self.noise_scales or not all(isinstance(s, int | float) and s >= 0 for s in self.noise_scales):
            raise InputError(where, "noise_scales", "a non-empty list of numbers >= 0", repr(self.noise_scales))
        if not all(isinstance(f, int | float) and abs(f) <= 2 for f in self.follow):
            raise InputError(where, "follow", "a list of fractions in [-2, 2]", repr(self.follow))
        if not all(isinstance(g, int | float) and not isinstance(g, bool) and 0 < g <= 0.5 for g in self.grip):
            raise InputError(where, "grip", "a list of closures in (0, 0.5]", repr(self.grip))
        if self.samples < 2 + len(self.follow) + len(self.grip):
            want = f"at least 2 + len(follow) + len(grip) = {2 + len(self.follow) + len(self.grip)}"
            raise InputError(where, "samples", want, repr(self.samples))
        for name in ("shift", "adapt", "obs_adapt"):
            if not isinstance(getattr(self, name), bool):
                raise InputError(where, name, "true or false", repr(getattr(self, name)))
        if isinstance(self.obs_gain, bool) or not isinstance(self.obs_gain, int | float) or not 0 < self.obs_gain <= 1:
            raise InputError(where, "obs_gain", "a gain in (0, 1]", repr(self.obs_gain))
        for name in ("keep", "grasp_margin"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not 0 <= v < 1:
                raise InputError(where, name, "a fraction in [0, 1)", repr(v))
        from quasisim.method.options import RISK_MEASURES
        from quasisim.targets.perturb import NAMED_WORLDS

        for w in self.worlds:
            if w not in NAMED_WORLDS:
                raise InputError(where, "worlds", f"a list of {', '.join(NAMED_WORLDS)}", repr(w))
        if self.world_risk not in RISK_MEASURES:
            raise InputError(where, "world_risk", f"one of {', '.join(RISK_MEASURES)}", repr(self.world_risk))
        for name, hi in (("world_thin", 0.01), ("world_cvar", 1.0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not 0 < v <= hi:
                raise InputError(where, name, f"a number in (0, {hi}]", repr(v))
        for name in ("adapt_decay", "obs_adapt_decay"):
            if not 0 <= getattr(self, name) < 1:
                raise InputError(where, name, "a weight in [0, 1)", repr(getattr(self, name)))

    @property
    def filters(self) -> bool:
        """Whether the tracker re-plans from its own state estimate (an observer) rather than the observation."""
        return self.obs_gain < 1 or self.obs_adapt

    @classmethod
    def from_yaml(cls, path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> TrackOptions:
        """The settings in ``path`` (default ``configs/track.yaml``) with ``overrides`` (name -> value)."""
        path = Path(path or TRACK_PATH)
        data = apply_overrides(read_yaml(path), overrides)
        for key in ("noise_scales", "follow", "grip", "worlds"):
            if isinstance(data.get(key), list):
                data[key] = tuple(data[key])
        return build(cls, {**data, "path": str(path)}, path)

    @classmethod
    def preset(cls, name: str, overrides: dict[str, Any] | None = None) -> TrackOptions:
        """The settings of a file of ``configs/`` (``track.yaml``, ``track_fast.yaml``) or of a path."""
        from quasisim.method.options import tracker_file

        return cls.from_yaml(tracker_file(name), overrides)

    def sampling(self) -> Any:
        """The :class:`~quasisim.method.options.SamplingOptions` whose noise this tracker draws."""
        from quasisim.method.options import SamplingOptions

        return SamplingOptions(
            samples=self.samples, horizon=self.horizon, knots=self.knots, noise_base_pos=self.noise_base_pos,
            noise_base_rot=self.noise_base_rot, noise_joints=self.noise_joints, noise_scales=self.noise_scales,
            mode="predictive", temperature=1.0, seed=self.seed, threads=self.threads, kinematic_alternative=False,
        )  # fmt: skip


def shift_bases(scene: Scene, q: np.ndarray, d: np.ndarray) -> np.ndarray:
    """PD targets ``q`` (..., D) with every hand's base moved by ``d`` (3,) m in the world, or per row by ``d``
    (..., 3): the first three base coordinates of each hand are slides along world x, y, z (:mod:`quasisim.targets.mujoco_target`)."""
    q = np.array(q, np.float64)
    for sl in scene.dof_slices:
        q[..., sl.start : sl.start + 3] += d
    return q


def shift_weights(object_pos: np.ndarray, fade: float) -> np.ndarray:
    """(T,) the weight ``w_t`` of the start shift at each frame: 1 while the object (``object_pos``, (T, 3) m,
    the plan's nominal rollout) has not left its start, falling linearly to 0 as it travels ``fade`` m from it,
    never rising again; all 1 for ``fade`` 0."""
    if fade == 0:
        return np.ones(len(object_pos))
    travel = np.linalg.norm(object_pos - object_pos[0], axis=-1)
    return np.minimum.accumulate(np.clip(1 - travel / fade, 0, 1))


class Innovations(NamedTuple):
    """One observed quantity's innovations, per component (``obs_adapt``): the last one, the exponential
    averages ``lag0`` ~ ``E[e_t^2]`` and ``lag1`` ~ ``E[e_t e_(t-1)]``, the gain ``k`` in use, ``n`` seen."""

    last: np.ndarray
    lag0: np.ndarray
    lag1: np.ndarray
    k: np.ndarray
    n: int


def learn_innovation(s: Innovations | None, e: np.ndarray, decay: float) -> Innovations:
    """``s`` after innovation ``e`` (a new channel, gain 1, where ``s`` is None), its gain moved by the
    innovations' correlation at lag 1, ``k <- k exp(ADAPT_RATE rho)``: a filter with the optimal gain leaves
    white innovations (rho = 0); one trusting a noisy sensor too much leaves them negatively correlated (each
    frame's noise, taken into the estimate, returns with the opposite sign in the next innovation), one
    trusting its model too much positively (the estimate lags)."""
    e = np.asarray(e, np.float64)
    if s is None:
        return Innovations(e, np.square(e), np.zeros_like(e), np.ones_like(e), 1)
    mix = lambda old, new: decay * old + (1 - decay) * new  # noqa: E731
    lag0, lag1 = mix(s.lag0, np.square(e)), mix(s.lag1, e * s.last)
    k = s.k
    if s.n >= WARMUP:
        with np.errstate(divide="ignore", invalid="ignore"):
            rho = np.where(lag0 > 0, lag1 / lag0, 0.0)
        k = np.clip(k * np.exp(ADAPT_RATE * rho), MIN_GAIN, 1.0)
    return Innovations(e, lag0, lag1, k, s.n + 1)


def candidate_scenes(scene: Scene) -> list[Scene]:
    """The models of ``adapt``: ``scene`` first, then one hidden parameter at a time at either end of the training
    ranges (``configs/robust.yaml``): object mass, friction, PD gains times ``1 -+ range``."""
    from quasisim.targets.perturb import RobustConfig, scaled_scene

    r = RobustConfig.from_yaml()
    out = [scene]
    for name, rng in (("mass", r.mass), ("friction", r.friction), ("gains", r.pd_gains)):
        out += [scaled_scene(scene, **{name: 1 + sign * rng}) for sign in (-1.0, 1.0)]
    return out


def model_scene(scene: Scene, dt: float) -> Scene:
    """``scene`` with the physics step ``dt`` (s) in either simulator (``scene`` itself for 0)."""
    if dt == 0:
        return scene
    return dataclasses.replace(scene, physics=dataclasses.replace(scene.physics, mujoco_dt=dt, pybullet_dt=dt))


class Tracker:
    """A closed-loop policy around a plan (see the module docstring): :meth:`start` on the world's first
    observation, then :meth:`act` once per frame. Built from the **nominal** scene only.

    Args:
        demo: the clip (its strict limits, when ``opts.strict_weight`` > 0).  scene: the nominal scene the plan
            was made in; the model is built from it.  plan: (T, D) PD targets.  opts: :class:`TrackOptions`.
        weights: the objective weights of the window cost.  target: the model's simulator (``mujoco`` or
            ``pybullet``; the world may be either).  nominal: the plan's rollout in the nominal scene (computed
            here when None).
    """

    def __init__(
        self, demo: Demo, scene: Scene, plan: np.ndarray, opts: TrackOptions, weights: Weights, target: str = "mujoco",
        nominal: TargetRollout | None = None,
    ) -> None:  # fmt: skip
        from quasisim.method.stages.sampling import scene_sampler

        ow = opts.object_weight
        weights = dataclasses.replace(weights, obj_pos=weights.obj_pos * ow, obj_rot=weights.obj_rot * ow)
        self.demo, self.scene, self.opts, self.weights = demo, scene, opts, weights
        self.plan = np.asarray(plan, np.float64)
        self.models: list[Target] = [
            make_target(target, model_scene(sc, opts.model_dt), threads=opts.threads)
            for sc in (candidate_scenes(scene) if opts.adapt else [scene])
        ]
        self.model = self.models[0]  # the nominal scene's; with adapt, the one that predicts the world best
        self.world_models: list[Target] = [
            make_target(
                target, model_scene(named_world(scene, w, opts.world_thin), opts.model_dt), threads=opts.threads
            )
            for w in opts.worlds
        ]  # "Weighing several worlds"
        self.scores = np.zeros(len(self.models))
        self.nominal = nominal if nominal is not None else self.model.rollout(self.plan)
        self._sample = scene_sampler(opts.sampling(), scene)
        base = np.concatenate([np.arange(s.start, s.start + 6) for s in scene.dof_slices])
        self._base_cols = base if len(scene.hands) > 1 else None  # window_costs' smoothness split (one hand: None)
        self._fingers = finger_columns(scene)  # grip: the hands' finger joints
        self._contacts = opts.grasp_slots if opts.grasp_weight > 0 else 0  # "Grasp margin": contact slots per hand
        self.replans, self.physics_steps, self.seconds = 0, 0, 0.0
        self.step_seconds: list[float] = []  # wall time of every act() (s)
        self.replan_seconds: list[float] = []  # wall time of every re-plan (s)
        self.offset = np.zeros(3)  # the start shift of step 1 (m), set by start()
        self._gains: list[dict[str, float]] = []  # obs_adapt: each frame's mean gain per channel
        self._work: np.ndarray | None = None

    def start(self, obs: Observation) -> None:
        """Frame 0: the shift of step 1 from the object's observed position; the plan and references set up."""
        H, nom = self.opts.horizon, self.nominal
        d = np.zeros(3)
        if self.opts.shift:
            d[:2] = (np.asarray(obs["obj_pos"]) - nom.object_pos[0])[:2]
        self.offset = d
        shifts = shift_weights(nom.object_pos, self.opts.shift_fade)[:, None] * d  # (T, 3) the shift per frame
        moved = shift_bases(self.scene, self.plan[1:], shifts[1:])
        self._planned = padded(np.concatenate([self.plan[:1], moved]), H)  # the untouched plan (shifted)
        self._work = self._planned.copy()  # the plan as re-planning changes it
        kp = nom.robot_keypoints + shifts[:, None, :]
        self._ref = [padded(nom.object_pos + shifts, H), padded(nom.object_quat, H), padded(kp, H)]
        self._demo_ref = [padded(self.demo.object_pos, H), padded(self.demo.object_quat, H)]
        self._rng = np.random.default_rng(self.opts.seed)
        self._applied = self.plan[0].copy()
        self._history = [self._applied]  # the targets at the end of frames 0, 1, ... (as applied)
        self._last = obs  # the observation the models' next prediction starts from (adapt)
        self._est = obs  # the state estimate (obs_gain < 1, obs_adapt)
        self._innov: dict[str, Innovations] = {}  # obs_adapt: per channel
        self._gains: list[dict[str, float]] = []  # obs_adapt: each frame's mean gain per channel
        for m in (*self.models, *self.world_models):
            m.reset(self.plan[0])

    def act(self, t: int, obs: Observation) -> np.ndarray:
        """The PD targets (D,) for the end of frame ``t + 1``, from the world's observation ``obs`` at frame ``t``."""
        if self._work is None:
            raise RuntimeError("tracker: call start(obs) with the world's first observation before act")
        every, t0 = self.opts.every, time.perf_counter()
        if self.opts.adapt and t > 0:
            self._learn(t, obs)
        if self.opts.filters:
            self._est = self._filtered(t, self._now(t, obs))
        lead = self.opts.lead
        if every and t % every == 0 and t + lead < len(self.plan) - 1:
            state = self._est if self.opts.filters else self._now(t, obs)
            if lead:  # the state when the re-plan will act, through the targets committed until then
                state = self._predicted(self.model, state, t, t + lead, self._work)
            t1 = time.perf_counter()
            self._replan(t + lead, state)
            self.replan_seconds.append(time.perf_counter() - t1)
            self.seconds += time.perf_counter() - t0
        self._applied = self._work[t + 1].copy()
        self._history.append(self._applied)
        self.step_seconds.append(time.perf_counter() - t0)
        return self._applied

    def _learn(self, t: int, obs: Observation) -> None:
        """``adapt``: score every model by its prediction of the last observed transition, from the previous
        observation through the targets applied since, and re-plan in the best."""
        prev, self._last = self._last, obs
        a, b = int(prev.get("frame", t - 1)), int(obs.get("frame", t))
        if b <= a:
            return
        err = np.empty(len(self.models))
        for k, m in enumerate(self.models):
            got = self._predicted(m, prev, a, b)
            err[k] = (
                np.linalg.norm(got["obj_pos"] - obs["obj_pos"]) / 1e-3 + np.abs(got["qpos"] - obs["qpos"]).mean() / 1e-2
            )
        self.scores = self.opts.adapt_decay * self.scores + err
        self.model = self.models[int(np.argmin(self.scores))]

    def _filtered(self, t: int, now: Observation) -> Observation:
        """The estimate at frame ``t``: the last one advanced in the model through the target applied since, moved
        toward the (latency-corrected) observation ``now`` by ``obs_gain``, or by the gains learned from the
        innovations (``obs_adapt``); the orientation turned by the gain times its innovation's rotation vector
        (``obs_gain``: the spherical interpolation)."""
        if t == 0:
            return now
        from scipy.spatial.transform import Rotation

        xyzw = lambda q: Rotation.from_quat(np.roll(np.asarray(q, np.float64), -1))  # noqa: E731
        pred = self._predicted(self.model, self._est, t - 1, t)
        e = {key: np.asarray(now[key], np.float64) - pred[key] for key in LINEAR}
        e["obj_rot"] = (xyzw(pred["obj_quat"]).inv() * xyzw(now["obj_quat"])).as_rotvec()
        if self.opts.obs_adapt:
            decay = self.opts.obs_adapt_decay
            self._innov = {c: learn_innovation(self._innov.get(c), v, decay) for c, v in e.items()}
            k = {c: s.k for c, s in self._innov.items()}
            self._gains.append({c: float(np.mean(v)) for c, v in k.items()})
        else:
            k = dict.fromkeys(e, self.opts.obs_gain)
        est = {key: pred[key] + k[key] * e[key] for key in LINEAR}
        turn = xyzw(pred["obj_quat"]) * Rotation.from_rotvec(k["obj_rot"] * e["obj_rot"])
        est["obj_quat"] = np.roll(turn.as_quat(), 1)
        return {**pred, **est}

    def _now(self, t: int, obs: Observation) -> Observation:
        """The state at frame ``t``: ``obs`` itself, or, where it was taken at an earlier ``obs["frame"]``, its
        prediction in the model through the targets applied since."""
        taken = int(obs.get("frame", t))
        if taken >= t:
            return obs
        return self._predicted(self.model, obs, max(taken, 0), t)

    def _predicted(self, model: Target, obs: Observation, a: int, b: int, targets: Any = None) -> Observation:
        """``obs``, the state at frame ``a``, synced into ``model`` and advanced there through the targets
        applied since (``targets``: the targets at the end of each frame; default the applied ones): the
        model's state at frame ``b``."""
        targets = self._history if targets is None else targets
        model.sync(obs)
        for j in range(a, b):
            model.advance(targets[j], targets[j + 1])
        self.physics_steps += (b - a) * model.substeps
        return model.observe()

    def _replan(self, t: int, obs: Observation) -> None:
        """Step 3: windows from the observed state rolled out in the model, the cheapest kept as the plan."""
        from quasisim.method.stages.sampling import grip_bias, window_costs

        o, H, T = self.opts, self.opts.horizon, len(self.plan)
        current = self._work[t : t + H + 1].copy()  # its first row: the target at the end of frame t, committed
        untouched = self._planned[t : t + H + 1].copy()
        untouched[0] = current[0]
        wins = self._sample(self._rng, current)
        wins[-1] = untouched  # the plan as made is always a candidate
        offset = np.asarray(obs["obj_pos"]) - self._ref[0][t]  # the object against the plan's nominal rollout
        shifts = [f * offset for f in o.follow]
        for k, d in enumerate(shifts):  # the window with the hands moved with (f > 0) or against (f < 0) it
            wins[-2 - k, 1:] = shift_bases(self.scene, current[1:], d)
        for k, g in enumerate(o.grip):  # the window pressing harder where the object holds fingers back
            bias = grip_bias(current[0], np.asarray(obs["qpos"]), self._fingers, g, o.grip_gap)
            wins[-2 - len(shifts) - k, 1:] = current[1:] + bias
        self.model.sync(obs)
        pred = self.model.rollout_windows(wins, None, None, self._contacts)
        w = slice(t + 1, t + H + 1)
        ref_pos, ref_quat, ref_kp = (r[w] for r in self._ref)
        frame_w = (np.arange(t + 1, t + H + 1) < T).astype(np.float64)
        dp, dq = (r[w] for r in self._demo_ref)

        def score(p: Any) -> np.ndarray:  # the window cost of predictions ``p``, with the hinge where asked
            c = window_costs(wins, p, ref_pos, ref_quat, ref_kp, frame_w, self.weights, self._base_cols,
                             grasp=(o.grasp_weight, o.grasp_margin))  # fmt: skip
            if o.strict_weight > 0:
                from quasisim.method.stages.sampling import strict_hinge

                c = c + o.strict_weight * strict_hinge(p.obj_pos, p.obj_quat, dp, dq, frame_w, o.strict_margin)
            return c

        costs = score(pred)
        costs = np.where(np.isfinite(costs), costs, np.inf)
        costs = self._weighed(wins, obs, costs, score)
        best = int(np.argmin(costs))
        if not costs[best] < (1 - o.keep) * costs[0]:  # row 0: the current plan's window
            best = 0
        self._work[t : t + H + 1] = wins[best]
        k = len(wins) - 2 - best
        if 0 <= k < len(shifts):  # a moved window: the rest of the plan moves with it
            self._work[t + H + 1 :] = shift_bases(self.scene, self._work[t + H + 1 :], shifts[k])
        self.replans += 1
        self.physics_steps += pred.n_steps

    def _weighed(self, wins: np.ndarray, obs: Observation, costs: np.ndarray, score: Any) -> np.ndarray:
        """The windows' nominal ``costs`` aggregated with their costs (``score``: predictions -> costs, as the
        nominal's) in the named worlds' models, rolled out from the same observed state (``world_risk``), or
        ``costs`` itself without worlds."""
        if not self.world_models:
            return costs
        from quasisim.method.stages.sampling import robust_scores

        others = []
        for m in self.world_models:
            m.sync(obs)
            pred = m.rollout_windows(wins, None, None, self._contacts)
            self.physics_steps += pred.n_steps
            others.append(score(pred))
        everyone = np.arange(len(wins))
        return robust_scores(costs, others, everyone, self.opts.world_risk, self.opts.world_cvar)

    def cost(self) -> dict[str, float]:
        """What tracking cost so far: seconds re-planning, re-plans, the share of the clip's steps that
        re-planned, physics steps in the model, and the median and 95th percentile of the time per control
        step (ms, :meth:`act`'s wall time) and of the time per re-plan (ms); with ``obs_adapt``, each channel's
        learned gain (``gain_<channel>``, its components' mean over the frames)."""
        ms = 1e3 * np.asarray(self.step_seconds or [0.0])
        rp = 1e3 * np.asarray(self.replan_seconds or [0.0])
        learned = {f"gain_{c}": float(np.mean([g[c] for g in self._gains])) for c in (self._gains or [{}])[0]}
        return learned | {
            "replan_seconds": self.seconds, "replans": float(self.replans),
            "replan_share": self.replans / max(len(self.plan) - 1, 1), "physics_steps": float(self.physics_steps),
            "step_ms_p50": float(np.median(ms)), "step_ms_p95": float(np.percentile(ms, 95)),
            "replan_ms_p50": float(np.median(rp)), "replan_ms_p95": float(np.percentile(rp, 95)),
        }  # fmt: skip

    def close(self) -> None:
        for m in (*self.models, *self.world_models):
            m.close()

    def __enter__(self) -> Tracker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def closed_loop(opts: TrackOptions | None = None, weights: Weights | None = None) -> Any:
    """The controller maker of closed-loop robust success (:data:`quasisim.eval.evaluate.PolicyMaker`):
    ``maker(demo, scene, plan, target)`` computes the plan's nominal rollout once and returns a function that
    builds a fresh :class:`Tracker` per replay. Defaults: ``configs/track.yaml``, the weights of
    ``configs/transfer.yaml``."""
    from quasisim.method.config import TransferConfig

    opts = opts or TrackOptions.from_yaml()
    weights = weights or TransferConfig.from_yaml().weights

    def maker(demo: Demo, scene: Scene, plan: np.ndarray, target: str) -> Any:
        with make_target(target, scene) as tgt:
            nominal = tgt.rollout(plan)
        return lambda: Tracker(demo, scene, plan, opts, weights, target, nominal)

    return maker
