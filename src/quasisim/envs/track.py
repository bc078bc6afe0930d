"""``quasisim/Track-v0``: a Gymnasium environment that tracks one demonstration in a target simulator.

One episode is one clip: the hands start at the reference's first PD targets with its initial velocity, the
object at the scene's initial pose (as every replay of :mod:`quasisim.eval.robust` starts); each step is one
control frame (:meth:`~quasisim.targets.base.Target.advance`). What the policy observes, how its action
becomes PD targets, the reward and the termination are :class:`~quasisim.envs.task.TrackTask`'s. On reset,
with ``randomize``, the world is a perturbed copy of the scene (:func:`~quasisim.targets.perturb.perturbed_scene`,
the ranges of ``configs/robust.yaml``) seeded from ``(world_seed, a draw of the env's generator)``: seeded resets
give the same worlds, and never the evaluation's (seed 0). MuJoCo compiles its model at the first reset only and
later sets each world's parameters on it (:meth:`~quasisim.targets.base.Target.set_world`; the same numbers as a
model compiled for the world); PyBullet builds each world anew. :attr:`TrackEnv.worlds_drawn` counts the draws
since the generator was seeded, and ``reset(seed=s, options={"skip_worlds": n})`` goes on after the first ``n``
worlds of seed ``s``: a resumed training continues its sequence of worlds (:mod:`quasisim.policy.train`).

For learning (``configs/track_env.yaml``; each off by default): ``start: random`` starts each episode at a frame
``k`` of the clip drawn from the env's generator, in the state the reference's replay in the nominal scene
reaches there (reference state initialisation); ``limits_start``/``limits_steps`` end episodes outside limits
that shrink from loose ones to the strict limits over the env's first steps (:attr:`TrackEnv.steps_taken`,
:meth:`TrackEnv.set_steps_taken` for a resumed training); ``observe_hand_frame`` adds the object's pose in each
hand's frame to the observation (:class:`~quasisim.envs.task.TrackTask`). ``reward_form: dgrasp`` rewards each
step with DGrasp's terms (:meth:`~quasisim.envs.task.TrackTask.dgrasp_terms`, each in the step's info as ``r_*``),
reading the world's contacts (:meth:`TrackEnv._contacts`). ``action_form: dgrasp`` (not residual) acts in DGrasp's
form (:meth:`~quasisim.envs.task.TrackTask.dgrasp_targets`) and advances each frame with its targets held, no
velocity fed forward (:meth:`~quasisim.envs.task.TrackTask.schedule_from`).

    import gymnasium as gym, quasisim.envs
    env = gym.make("quasisim/Track-v0", clip="grab_s1_cup_lift.npz", reference="out/cup/controls.npz",
                   residual=True)
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from quasisim.data.controls import Controls, load_controls
from quasisim.data.demo import Demo, load_demo
from quasisim.envs.config import TrackEnvConfig
from quasisim.envs.task import Contacts, TrackTask
from quasisim.errors import InputError
from quasisim.targets import TARGETS, Target, make_target
from quasisim.targets.base import Observation
from quasisim.targets.scene import Scene


def load_reference(path: str | Path) -> tuple[Controls, Path]:
    """The controls of a result: ``path`` is a ``controls.npz`` or a run folder holding one."""
    p = Path(path)
    if p.is_dir():
        p = p / "controls.npz"
        if not p.is_file():
            raise InputError(path, None, "a run folder with controls.npz, or a controls .npz file", "no controls.npz")
    return load_controls(p), p


def task_for(
    demo: Demo, controls: Controls, cfg: TrackEnvConfig, residual: bool, controls_path: Path | None = None
) -> TrackTask:
    """The tracking task of ``demo`` with ``controls`` as the reference (their hands, base frames, targets)."""
    from quasisim.eval.evaluate import check_controls, hands_of
    from quasisim.targets.build import scene_for
    from quasisim.targets.scene import place_hands

    hands = hands_of(controls, controls_path)
    check_controls(demo, controls, hands, controls_path)
    scene = scene_for(demo, place_hands(hands, controls.base_rots))
    return TrackTask(demo, scene, controls.q_targets, cfg, residual)


def world_config(cfg: TrackEnvConfig) -> Any:
    """The perturbation ranges of the training worlds: ``cfg.ranges`` with the training seed."""
    from quasisim.eval.robust import replays

    return dataclasses.replace(replays(None, cfg.ranges), seed=cfg.world_seed)


def _count(n: Any, option: str, what: str = "a count of worlds >= 0", top: int | None = None) -> int:
    """``n`` as a count (a reset option) in ``[0, top]``, or a one-line error naming the option."""
    if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 0 or (top is not None and n > top):
        raise ValueError(f"quasisim/Track-v0: {option}: expected {what}, got {n!r}")
    return int(n)


class TrackEnv(gym.Env):
    """Track a clip (see the module docstring).

    Args:
        clip: the demo (.npz, docs/demo_format.md).
        reference: our result to track (run folder or ``controls.npz``); its hands and base frames are the
            robot's. Required: ``quasisim policy train`` writes the kinematic retarget as the reference when
            it is given no result.
        residual: actions add to the reference's PD targets (else they move the measured pose, DGrasp's form;
            ``action_form: dgrasp`` needs ``residual=False``).
        target: the simulator (``mujoco`` or ``pybullet``).
        config: a :class:`TrackEnvConfig` (default ``configs/track_env.yaml`` with ``overrides``).
        physics: a simulator of the physics curriculum to step instead of ``target`` (its contact settings,
            :data:`~quasisim.targets.quasi_target.STAGE_KEYS`; :class:`~quasisim.targets.quasi_target.QuasiTarget`):
            for training through the curriculum (DGrasp-Tracking w/ curriculum); success is only judged in
            ``target``.

    ``reset(options={"world": i})`` uses training world ``i``; ``options={"world": None}`` the nominal scene;
    ``options={"skip_worlds": n}`` skips the generator's next ``n`` draws first (with ``seed``: goes on after
    that seed's first ``n``); ``options={"start": k}`` starts at frame ``k`` in [0, T - 2] (0: the reset of
    ``start: first``; the evaluation starts at 0). :attr:`worlds_drawn`: the draws since the generator was seeded,
    one per reset that draws a world or a start frame (each draw takes both a world and, with ``start: random``,
    a start frame, used or not, so that skipping ``n`` draws replays ``n`` resets whatever their options). The
    info of ``reset`` holds ``world`` (-1: the nominal scene) and ``start`` (the frame). Each step's ``info``
    holds the frame, the errors against the demo (:meth:`TrackTask.errors`; with ``reward_form: dgrasp`` also
    DGrasp's weighted terms ``r_*``, :meth:`TrackTask.reward`), ``limits`` (the termination limits in force,
    [cm, deg]) and, at the episode's end, ``tracked`` (strict success,
    :func:`quasisim.limits.strict_success`, as the evaluation judges it: the clip's end reached within the strict
    limits at every frame and the object moved as in the demo; judged on the episode's object poses, so an
    episode that started after frame 0 is never ``tracked``) and ``frames`` (frames reached).

    With ``start: random`` (or a ``start`` option above 0) the reference's PD targets are replayed once in the
    nominal scene on the env's simulator (the curriculum's cannot be put into a state: refused) and the replay's
    observations kept; a reset at frame ``k`` resets the world and then syncs it
    (:meth:`~quasisim.targets.base.Target.sync`) to the replay's frame ``k``, whatever the world's parameters.
    With ``limits_steps`` > 0 the termination limits follow :attr:`steps_taken`, the env's steps since it was
    made (or :meth:`set_steps_taken`), not the seed: a seed then repeats the worlds and starts, not the endings.
    """

    metadata = {"render_modes": []}  # noqa: RUF012  (Gymnasium's class attribute)

    def __init__(
        self, clip: str | Path, reference: str | Path, residual: bool = False, target: str = "mujoco",
        config: TrackEnvConfig | None = None, overrides: dict[str, Any] | None = None,
        physics: dict[str, float] | None = None,
    ) -> None:  # fmt: skip
        if target not in TARGETS:
            from quasisim.errors import choice_error

            raise choice_error("target", target, tuple(TARGETS))
        cfg = config or TrackEnvConfig.from_yaml(None, overrides)
        controls, path = load_reference(reference)
        self.task = task_for(load_demo(clip), controls, cfg, residual, path)
        self.target, self.physics = target, physics
        self._worlds = world_config(cfg)
        if cfg.start == "random" and physics is not None:
            raise ValueError(
                "quasisim/Track-v0: start: random puts the world into the reference replay's state "
                "(Target.sync), which the curriculum's simulator (physics) cannot; use start: first"
            )
        if cfg.reward_form == "dgrasp" and physics is not None:
            raise ValueError(
                "quasisim/Track-v0: reward_form: dgrasp reads each hand body's contact forces "
                "(Target.body_contact_forces), which the curriculum's simulator (physics) does not report"
            )
        if cfg.action_form == "dgrasp" and physics is not None:
            raise ValueError(
                "quasisim/Track-v0: action_form: dgrasp holds each frame's targets, and the curriculum's "
                "simulator (physics) reports the hands' velocity as the targets' change (0 when held); use "
                "action_form: default"
            )
        D = self.task.scene.n_dof
        self.action_space = gym.spaces.Box(-1.0, 1.0, (D,), np.float32)
        self.observation_space = gym.spaces.Box(-100.0, 100.0, (self.task.observation_size,), np.float32)
        self._world: Target | None = None
        self._t, self._obs, self._prev = 0, None, None
        self.worlds_drawn = 0  # draws of the generator since it was seeded (a resumed training skips them)
        self._poses: list[tuple[np.ndarray, np.ndarray]] = []  # the object's pose at every frame of the episode
        self._start = 0  # the episode's first frame
        self._replay: list[Observation] | None = None  # the reference's nominal replay, frames 0..T-2 (start)
        self.steps_taken = 0  # env steps since construction (or set_steps_taken): the limits' schedule

    def world_scene(self, i: int | None) -> Scene:
        """Training world ``i`` (None: the nominal scene)."""
        from quasisim.targets.perturb import perturbed_scene

        return self.task.scene if i is None else perturbed_scene(self.task.scene, self._worlds, i)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        options = options or {}
        if seed is not None:
            self.worlds_drawn = 0
        for _ in range(_count(options.get("skip_worlds", 0), "reset option skip_worlds")):
            self._draw()
        cfg, T = self.task.cfg, self.task.n_frames
        draw_world, draw_start = "world" not in options and cfg.randomize, "start" not in options
        world, start = self._draw() if draw_world or (draw_start and cfg.start == "random") else (None, None)
        i = options["world"] if "world" in options else world if draw_world else None
        if "start" in options:
            k = _count(options["start"], "reset option start", f"a frame in [0, {T - 2}]", T - 2)
        else:
            k = start or 0
        scene = self.world_scene(i)
        if self._world is None or not self._world.set_world(scene):  # MuJoCo: the parameters, not a new model
            if self._world is not None:
                self._world.close()
            self._world = self._make_world(scene)
        q = self.task.reference
        self._world.reset(q[0], (q[1] - q[0]) * self.task.scene.fps)
        if k:
            self._world.sync(self._reference_replay()[k])
        self._t, self._prev, self._start = k, q[k], k
        self._obs = self._world.observe()
        self._poses = [(self._obs["obj_pos"], self._obs["obj_quat"])]
        return self.task.observation(k, self._obs), {"world": -1 if i is None else i, "start": k}

    def _reference_replay(self) -> list[Observation]:
        """The observations of the reference's PD targets replayed in the nominal scene on the env's simulator,
        frames 0..T-2 (as :meth:`~quasisim.targets.base.Target.rollout` runs them); replayed once, then kept."""
        if self._replay is None:
            q, T = self.task.reference, self.task.n_frames
            with self._make_world(self.task.scene) as world:
                world.reset(q[0], (q[1] - q[0]) * self.task.scene.fps)
                frames = [world.observe()]
                for t in range(T - 2):
                    world.advance(q[t], q[t + 1])
                    frames.append(world.observe())
            self._replay = frames
        return self._replay

    def _make_world(self, scene: Scene) -> Target:
        """The simulator of ``scene``: the target, or the curriculum's simulator :attr:`physics`."""
        if self.physics is None:
            return make_target(self.target, scene)
        from quasisim.targets.quasi_target import QuasiTarget

        return QuasiTarget(scene, self.physics)

    def _draw(self) -> tuple[int, int | None]:
        """The generator's next draw: a training world and, with ``start: random``, a start frame in [0, T - 2]
        (with ``start: first`` the world alone, as before there were start frames)."""
        self.worlds_drawn += 1
        world = int(self.np_random.integers(2**31))
        if self.task.cfg.start != "random":
            return world, None
        return world, int(self.np_random.integers(self.task.n_frames - 1))

    def set_steps_taken(self, n: int) -> None:
        """Set :attr:`steps_taken`, the env steps the limits' schedule counts (a resumed training's so far)."""
        self.steps_taken = _count(n, "set_steps_taken", "a count of env steps >= 0")

    @property
    def limits(self) -> tuple[float, float]:
        """The termination limits (cm, deg) in force now (:meth:`TrackEnvConfig.limits` of :attr:`steps_taken`)."""
        return self.task.cfg.limits(self.steps_taken)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self._world is None or self._obs is None:
            raise RuntimeError("quasisim/Track-v0: call reset() before step()")
        task, t, limits = self.task, self._t, self.limits
        self.steps_taken += 1
        q = task.targets(t, action, self._obs)
        self._world.advance(task.schedule_from(self._prev, q), q)
        self._t, self._prev = t + 1, q
        self._obs = obs = self._world.observe()
        self._poses.append((obs["obj_pos"], obs["obj_quat"]))
        warned = any(self._world.extras().get("sim_warnings", {}).values())  # MuJoCo resets a blown-up state
        if warned or task.unstable(obs):
            info = {"frame": t + 1, "unstable": True, "tracked": False, "frames": t + 1, "limits": list(limits)}
            return np.zeros(self.observation_space.shape, np.float32), 0.0, True, False, info
        contacts = self._contacts() if task.cfg.reward_form == "dgrasp" else None
        r, errors = task.reward(t + 1, obs, np.clip(action, -1, 1), contacts)
        end = t + 1 == task.n_frames - 1
        done = end or (not task.within(errors, limits) and task.cfg.terminate == "strict")
        info: dict[str, Any] = {"frame": t + 1, **errors, "limits": list(limits)}
        if done:
            info |= {"tracked": end and self._strict_success(), "frames": t + 1}
        return task.observation(t + 1, obs), r, done, False, info

    def _contacts(self) -> Contacts:
        """What DGrasp's reward reads of the world now (:class:`~quasisim.envs.task.Contacts`): each hand body's
        normal force on the object in the last physics step, the control frame's duration (physics step x
        substeps) and the object's weight in this world (its perturbed mass)."""
        world = self._world
        assert world is not None
        phys = world.scene.physics
        return Contacts(world.body_contact_forces(), world.dt * world.substeps, world.scene.obj.mass * phys.gravity)

    def _strict_success(self) -> bool:
        """Strict success of the episode's object poses (every frame of the clip) against the demo's; an episode
        that started after frame 0 (``start``) has not tracked the clip: never."""
        from quasisim.limits import strict_success

        if self._start:
            return False
        pos, quat = (np.array(x) for x in zip(*self._poses, strict=True))
        return strict_success(self.task.demo.object_pos, self.task.demo.object_quat, pos, quat)

    def close(self) -> None:
        if self._world is not None:
            self._world.close()
            self._world = None
