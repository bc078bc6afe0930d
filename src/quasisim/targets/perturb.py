"""Perturbed copies of a scene: the worlds of robust success (:mod:`quasisim.eval.robust`) and of the sampling
stage's robust scoring (:mod:`quasisim.method.stages.sampling`, step 7).

:class:`RobustConfig` holds the ranges (``configs/robust.yaml``, or the wider ``configs/robust_wide.yaml``
with a push mid-clip); :func:`perturbed_scene` draws replay ``i``'s copy of a scene (object mass and
inertia, friction, PD gains, the object's initial position) and :func:`push_of` its push, each from a
generator seeded with ``(seed, i)``, the same on every machine and in every run. The method's own worlds
(:class:`TrainingWorlds`: the cascade's gate and selection, the sampling stage's copies) draw from a stream of
their own, so that no choice of seeds makes a world a plan was chosen in a world it is judged in.
:class:`Sensor` is what a
closed-loop controller sees of replay ``i``'s world: its observations late by ``latency`` frames and noisy
(``obs_pos``, ``obs_rot``, ``obs_joints``), drawn from a generator of their own; the world itself is never touched.
:func:`replay` runs a clip in one such world, open loop or with a closed-loop :class:`Policy` (robust success,
:mod:`quasisim.eval.robust`; the cascade's gate, :mod:`quasisim.method.stages.selection`).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from quasisim.config import load
from quasisim.errors import InputError, QuasisimError
from quasisim.targets.scene import Scene

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
ROBUST_PATH = CONFIGS / "robust.yaml"
ROBUST_KEY = "robust"  # metrics.json (the default ranges; the wide ones: "robust_wide")
CLOSED_LOOP_SUFFIX = "_closed_loop"  # metrics.json: "robust_closed_loop", "robust_wide_closed_loop"
# the spawn key of the method's worlds (TrainingWorlds): "plan" in ASCII; the judging worlds have none
PLAN_KEY = int.from_bytes(b"plan", "big")
SEED_LIMIT = 2**32  # the method's seeds are below it (a judging world then never repeats one: TrainingWorlds)


@dataclass(frozen=True)
class RobustConfig:
    """Perturbed replays (``configs/robust.yaml``): ``n`` replays seeded with ``(seed, i)``; relative ranges
    ``mass`` (mass and inertia), ``friction``, ``pd_gains`` (kp and kv); ``object_pos`` (m, along x and y);
    ``push`` (m/s) added to the object's velocity, horizontally, at frame ``round(push_at (T - 1))`` (0: none).
    Sensing (closed loop only, :class:`Sensor`): Gaussian noise of std ``obs_pos`` (m) on the object's observed
    position, ``obs_rot`` (rad, about each axis) on its observed orientation, ``obs_joints`` (rad, or m for slide
    joints) on the hands' observed finger joints; observations ``latency`` frames old.
    ``name``: the metrics key of the open-loop results (``name + "_closed_loop"`` closed loop)."""

    n: int = 0
    seed: int = 0
    mass: float = 0.15
    friction: float = 0.20
    object_pos: float = 0.003
    pd_gains: float = 0.10
    push: float = 0.0
    push_at: float = 0.5
    obs_pos: float = 0.0
    obs_rot: float = 0.0
    obs_joints: float = 0.0
    latency: int = 0
    name: str = ROBUST_KEY
    path: str = ""

    def __post_init__(self) -> None:
        where = self.path or None
        if self.n < 0:
            raise InputError(where, "n", "a count >= 0 (0: no robust replays)", str(self.n))
        for name in ("mass", "friction", "pd_gains"):
            v = getattr(self, name)
            if not 0 <= v < 1:
                raise InputError(where, name, "a relative range in [0, 1)", repr(v))
        if not 0 <= self.object_pos <= 0.05:
            raise InputError(where, "object_pos", "a distance in [0, 0.05] m", repr(self.object_pos))
        if not 0 <= self.push <= 2.0:
            raise InputError(where, "push", "a speed in [0, 2] m/s", repr(self.push))
        if not 0 <= self.push_at <= 1:
            raise InputError(where, "push_at", "a fraction of the clip in [0, 1]", repr(self.push_at))
        for name, hi in (("obs_pos", 0.05), ("obs_rot", 0.5), ("obs_joints", 0.5)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not 0 <= v <= hi:
                raise InputError(where, name, f"a noise std in [0, {hi}]", repr(v))
        if isinstance(self.latency, bool) or not isinstance(self.latency, int) or not 0 <= self.latency <= 20:
            raise InputError(where, "latency", "a whole number of frames in [0, 20]", repr(self.latency))
        if not self.name.isidentifier():
            raise InputError(where, "name", "a metrics key (letters, digits, _)", repr(self.name))

    @classmethod
    def from_yaml(cls, path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> RobustConfig:
        return load(cls, Path(path or ROBUST_PATH), overrides)

    @property
    def closed_loop_key(self) -> str:
        return self.name + CLOSED_LOOP_SUFFIX

    @property
    def senses(self) -> bool:
        """Whether a controller sees the worlds through noise or latency (:class:`Sensor`)."""
        return bool(self.obs_pos or self.obs_rot or self.obs_joints or self.latency)

    def rng(self, *words: int) -> np.random.Generator:
        """The generator of world ``words`` (replay ``i``: ``(i,)``; its sensor: ``(i, 1)``): the judging worlds'
        ``default_rng([seed, *words])``, as it always was."""
        return np.random.default_rng([self.seed, *words])


@dataclass(frozen=True)
class TrainingWorlds(RobustConfig):
    """The worlds the method chooses plans in (``robust_select.seed``, ``sampling.robust_seed``): the same ranges,
    drawn from ``SeedSequence([seed, *words], spawn_key=(PLAN_KEY,))``. The judging worlds' entropy is the words
    ``[seed, i]`` alone; these are ``[seed, i, 0, 0, PLAN_KEY]`` (the spawn key pads the words to 4 first). With
    ``seed`` and ``i`` below :data:`SEED_LIMIT`, a judging world has the same words only if its replay index is at
    least ``PLAN_KEY * 2**32`` (about 8e18): no integer seed makes ``--robust-set seed=N`` judge a plan in the worlds
    it was chosen in."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or not 0 <= self.seed < SEED_LIMIT:
            raise InputError(self.path or None, "seed", "a training-world seed in [0, 2**32)", repr(self.seed))

    def rng(self, *words: int) -> np.random.Generator:
        return np.random.default_rng(np.random.SeedSequence([self.seed, *words], spawn_key=(PLAN_KEY,)))


def training_worlds(seed: int, n: int = 0) -> TrainingWorlds:
    """``n`` of the method's worlds (:class:`TrainingWorlds`), the ranges of ``configs/robust.yaml`` drawn with
    ``seed``."""
    return TrainingWorlds.from_yaml(None, {"n": n, "seed": seed})


def _draws(cfg: RobustConfig, i: int) -> np.ndarray:
    """Replay ``i``'s 6 uniform draws in [-1, 1): mass, friction, gains, object x, object y (the first five,
    as they always were), then the push's direction."""
    return cfg.rng(i).uniform(-1.0, 1.0, size=6)


def perturbed_scene(scene: Scene, cfg: RobustConfig, i: int) -> Scene:
    """Replay ``i``'s copy of ``scene``: every factor drawn uniformly within its range from ``cfg``'s generator
    of world ``i`` (:meth:`RobustConfig.rng`; the same copy on every machine and in every run)."""
    u = _draws(cfg, i)
    scaled = scaled_scene(scene, 1 + cfg.mass * u[0], 1 + cfg.friction * u[1], 1 + cfg.pd_gains * u[2])
    return dataclasses.replace(scaled, object_pos0=scene.object_pos0 + cfg.object_pos * np.array([u[3], u[4], 0.0]))


def scaled_scene(scene: Scene, mass: float = 1.0, friction: float = 1.0, gains: float = 1.0) -> Scene:
    """``scene`` with the object's mass and inertia times ``mass``, every contact's sliding friction times
    ``friction`` and every PD gain (kp, kv) times ``gains``."""
    obj = dataclasses.replace(scene.obj, mass=scene.obj.mass * mass, inertia=scene.obj.inertia * mass)
    object.__setattr__(obj, "_memo", scene.obj._memo)  # the mesh, its SDF and convex parts are unchanged
    physics = dataclasses.replace(
        scene.physics, friction=scene.physics.friction * friction, gain_scale=scene.physics.gain_scale * gains
    )
    return dataclasses.replace(scene, obj=obj, physics=physics)


NAMED_WORLDS = ("corner", "thin", "corner-thin")  # named_world's names


def named_world(scene: Scene, name: str, thin: float = 0.001, cfg: RobustConfig | None = None) -> Scene:
    """A world the method plans for by name (the sampling stage's ``robust_worlds``, the tracker's ``worlds``):
    ``corner``, the hard corner of ``cfg``'s ranges (default ``configs/robust.yaml``) for the quantities that act
    one way on a grasp: the object's mass and inertia times ``1 + mass``, friction times ``1 - friction``, PD gains
    times ``1 - pd_gains``, the object where it starts; ``thin``, contacts that push only once a hand's shape is
    ``thin`` m inside the object (``physics.contact_margin`` = ``-thin``: a grasp that squeezes less; MuJoCo);
    ``corner-thin``, both. A one-line error listing the names otherwise."""
    if name not in NAMED_WORLDS:
        raise QuasisimError(f"unknown world {name!r}; valid options: {', '.join(NAMED_WORLDS)}")
    r = cfg or RobustConfig.from_yaml()
    out = scene
    if name.startswith("corner"):
        out = scaled_scene(scene, 1 + r.mass, 1 - r.friction, 1 - r.pd_gains)
    if name.endswith("thin"):
        out = dataclasses.replace(out, physics=dataclasses.replace(out.physics, contact_margin=-thin))
    return out


def push_of(cfg: RobustConfig, i: int, n_frames: int) -> tuple[int, np.ndarray] | None:
    """Replay ``i``'s push: the frame after which it acts and the velocity (3,) m/s added to the object's
    centre of mass (horizontal, direction drawn with the replay's generator); None without a push."""
    if cfg.push == 0 or n_frames < 2:
        return None
    a = np.pi * _draws(cfg, i)[5]
    return max(1, round(cfg.push_at * (n_frames - 1))), cfg.push * np.array([np.cos(a), np.sin(a), 0.0])


class Sensor:
    """What a closed-loop controller observes of replay ``i``'s world (``cfg``'s sensing settings): at frame
    ``t`` the world's observation of frame ``max(0, t - latency)``, with Gaussian noise on the object's position
    (std ``obs_pos`` m), on its orientation (a rotation by a vector of std ``obs_rot`` rad per axis, applied on
    the world side) and on every hand's finger joints (std ``obs_joints``; the hands' bases, read from the arm,
    are exact). Velocities are passed as observed (late, without noise). Each observation carries ``frame``, the
    frame it was taken at (a sensor's time stamp), so a controller can tell how old it is. The noise is drawn from a generator
    seeded with ``(seed, i, 1)``, apart from the world's draws, so a set with and without sensing meets the same
    worlds. Call :meth:`see` once per frame, in order, with the world's observation.

    Args:
        cfg: the perturbation set.  i: the replay.  finger_cols: (D,) bool, the hands' joint columns (not base).
    """

    def __init__(self, cfg: RobustConfig, i: int, finger_cols: np.ndarray) -> None:
        self.cfg, self.fingers = cfg, np.asarray(finger_cols, bool)
        self._rng = cfg.rng(i, 1)
        self._past: list[dict[str, np.ndarray]] = []
        self._frames = 0  # observations seen so far

    def see(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The controller's view of this frame's observation ``obs`` (the world's; not modified)."""
        c = self.cfg
        self._past.append(obs)
        seen = dict(self._past[max(0, len(self._past) - 1 - c.latency)])
        del self._past[: max(0, len(self._past) - 1 - c.latency)]
        self._frames += 1
        seen["frame"] = np.array(max(0, self._frames - 1 - c.latency))
        e_pos, e_rot = self._rng.standard_normal((2, 3))  # drawn every frame, whichever std is 0
        e_q = self._rng.standard_normal(len(seen["qpos"]))
        if c.obs_pos:
            seen["obj_pos"] = np.asarray(seen["obj_pos"]) + c.obs_pos * e_pos
        if c.obs_rot:
            seen["obj_quat"] = rotated(seen["obj_quat"], c.obs_rot * e_rot)
        if c.obs_joints:
            seen["qpos"] = np.asarray(seen["qpos"]) + np.where(self.fingers, c.obs_joints * e_q, 0.0)
        return seen


def rotated(quat: np.ndarray, rotvec: np.ndarray) -> np.ndarray:
    """The orientation ``quat`` (w x y z) turned by the rotation vector ``rotvec`` (3,) rad on the world side."""
    from scipy.spatial.transform import Rotation

    r = Rotation.from_rotvec(rotvec) * Rotation.from_quat(np.roll(np.asarray(quat, np.float64), -1))
    return np.roll(r.as_quat(), 1)


class Policy(Protocol):
    """A closed-loop controller (:class:`quasisim.method.track.Tracker`): ``start`` on the world's first
    observation, ``act(t, obs)`` -> the PD targets (D,) for frame ``t + 1``; ``cost()`` what it spent
    (numbers, averaged over replays); ``close()``. Optional: ``schedule_from(prev, q)`` -> the targets the
    frame's PD schedule starts from (:meth:`~quasisim.targets.base.Target.advance`; without it ``prev``, the
    previous frame's, with their velocity fed forward; a policy trained with DGrasp's held targets returns
    ``q``, :meth:`quasisim.envs.task.TrackTask.schedule_from`)."""

    def start(self, obs: dict[str, np.ndarray]) -> None: ...
    def act(self, t: int, obs: dict[str, np.ndarray]) -> np.ndarray: ...
    def cost(self) -> dict[str, float]: ...
    def close(self) -> None: ...


def replay(world: Any, q_targets: np.ndarray, policy: Policy | None = None,
           push: tuple[int, np.ndarray] | None = None, qd0: np.ndarray | None = None,
           sensor: Sensor | None = None) -> Any:  # fmt: skip
    """Run a clip in ``world`` (a :class:`~quasisim.targets.base.Target`) as a robust replay does: the hands
    start at ``q_targets[0]`` with the targets' initial velocity (or ``qd0``); open loop (no ``policy``) frame
    ``t + 1``'s targets are ``q_targets[t + 1]``, closed loop ``policy.act(t, observation at t)`` (as ``sensor``
    shows it, where given; the rollout records the world's own states); ``push`` (frame, dv) adds ``dv`` to the
    object's velocity after that frame. Returns the :class:`TargetRollout`."""
    q = np.asarray(q_targets, np.float64)
    if policy is None and push is None and qd0 is None:
        return world.rollout(q)
    T, fps = len(q), world.scene.fps
    world.reset(q[0], qd0 if qd0 is not None else (q[1] - q[0]) * fps if T > 1 else None)
    t0, frames, prev = time.perf_counter(), [], q[0]
    obs = world.observe()
    seen = obs if sensor is None else sensor.see(obs)
    if policy is not None:
        policy.start(seen)
    start_of = getattr(policy, "schedule_from", None)  # as the policy was trained to drive the world
    for t in range(T):
        frames.append(obs)
        if t == T - 1:
            break
        nxt = q[t + 1] if policy is None else np.asarray(policy.act(t, seen), np.float64)
        world.advance(prev if start_of is None else start_of(prev, nxt), nxt)
        prev = nxt
        obs = world.observe()
        if push is not None and t + 1 == push[0]:
            world.sync({**obs, "obj_vel": obs["obj_vel"] + push[1]})
            obs = world.observe()
        seen = obs if sensor is None else sensor.see(obs)
    return world.recorded(frames, time.perf_counter() - t0)


def finger_columns(scene: Scene) -> np.ndarray:
    """(D,) bool: the columns of the hands' finger joints (every hand's columns after its 6 base coordinates)."""
    cols = np.zeros(sum(sl.stop - sl.start for sl in scene.dof_slices), bool)
    for sl in scene.dof_slices:
        cols[sl.start + 6 : sl.stop] = True
    return cols


def world_replays(
    scene: Scene, q_targets: np.ndarray, target: str, cfg: RobustConfig, policy: Callable[[], Policy] | None = None
) -> Iterator[tuple[Any, dict[str, float] | None, float]]:
    """Replay ``i`` of ``cfg`` for ``i`` in ``range(cfg.n)``: ``q_targets`` (T, D) run in ``target`` in the
    perturbed copy of ``scene`` (:func:`perturbed_scene`, :func:`push_of`), open loop or with a fresh
    :class:`Policy` from ``policy`` (built from the nominal ``scene`` only; it sees the world through a
    :class:`Sensor` where ``cfg`` senses). Yields ``(rollout, the policy's cost() or None, seconds)``."""
    from quasisim.targets import make_target

    for i in range(cfg.n):
        ctl = policy() if policy is not None else None
        t0, cost = time.perf_counter(), None
        try:
            with make_target(target, perturbed_scene(scene, cfg, i)) as world:
                sensor = Sensor(cfg, i, finger_columns(scene)) if ctl is not None and cfg.senses else None
                rollout = replay(world, q_targets, ctl, push_of(cfg, i, len(q_targets)), sensor=sensor)
        finally:
            if ctl is not None:
                cost = ctl.cost()
                ctl.close()
        yield rollout, cost, time.perf_counter() - t0


RANGES = {  # --ranges NAME
    "default": ROBUST_PATH, "wide": CONFIGS / "robust_wide.yaml", "sensing": CONFIGS / "robust_sensing.yaml",
}  # fmt: skip
ROBUST_SET_FIXED = ("n", "name", "path")  # not settable by --robust-set (n: --robust N)


def resolve_ranges(name: str) -> str:
    """``name`` if it is a shipped set of :data:`RANGES`, else the absolute path of a perturbation-set YAML file
    of the user's own (the keys of ``configs/robust.yaml``); a one-line error listing the options otherwise."""
    if name in RANGES:
        return name
    p = Path(name).expanduser()
    if p.suffix in (".yaml", ".yml") and p.is_file():
        return str(p.resolve())
    raise QuasisimError(
        f"unknown perturbation ranges {name!r}; valid options: {', '.join(RANGES)}, or the path of an existing "
        "YAML file with the keys of configs/robust.yaml"
    )


def replays(n: int | None, ranges: str = "default", overrides: dict[str, Any] | None = None) -> RobustConfig:
    """The settings of ``ranges`` (a shipped set of :data:`RANGES`, or a YAML file of the user's own:
    :func:`resolve_ranges`) with ``overrides`` (``--robust-set seed=7``) and ``n`` replays where given
    (``--robust N``). A file of the user's own without a ``name`` reports under ``robust_<file stem>``."""
    over = dict(overrides or {})
    if fixed := sorted(set(over) & set(ROBUST_SET_FIXED)):
        hint = "use --robust N for the number of replays" if fixed[0] == "n" else "a set's name is its file's"
        raise QuasisimError(f"--robust-set {fixed[0]}: not settable ({hint})")
    path = resolve_ranges(ranges)
    if path not in RANGES:
        import yaml

        data = yaml.safe_load(Path(path).read_text()) or {}
        if isinstance(data, dict) and "name" not in data:
            over["name"] = "robust_" + "".join(ch if ch.isalnum() else "_" for ch in Path(path).stem)
    if n is not None:
        over["n"] = n
    return RobustConfig.from_yaml(RANGES.get(path, path), over or None)
