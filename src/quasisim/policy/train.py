"""Train a tracking policy with PPO (stable-baselines3) in ``quasisim/Track-v0``, resumable.

A training folder ``OUT`` holds:

* ``setup.json``: what is trained (:class:`TrainSetup`: the clip, the method, the target, the settings); it marks
  the folder as a training: ``policy train`` refuses a non-empty folder without one (:func:`check_owned`) and
  replaces only what a training wrote (:func:`prepare`);
* ``reference.npz``: the reference PD targets: our result (``ours+residual``) or the kinematic retarget
  (``dgrasp-tracking``, which acts on the measured pose and sees the reference only in its observation;
  ``dgrasp-base``: the retarget of its guide; ``dgrasp-tracking-curriculum``: as ``dgrasp-tracking``, trained
  first in each analytical simulator of the physics curriculum, soft to stiff, then in the target:
  :func:`segments`);
* ``guide.npz`` + ``guide.json`` (``dgrasp-base`` only): the demo as DGrasp sees it, its first grasp carried
  with the object (:mod:`quasisim.policy.dgrasp`), and each hand's grasp frame: the policy trains and is
  observed against the guide, and judged against the clip;
* ``checkpoint.zip`` + ``checkpoint.json``: the model and the steps and seconds so far, written atomically
  every ``checkpoint_every`` env steps and at the end, with the training worlds each environment has drawn;
  ``--resume`` continues from them, each environment's sequence of worlds where it stopped (``PPO.load`` seeds
  the environments again, and would otherwise replay the same worlds);
* ``logs/<segment>/``: ``progress.csv`` and TensorBoard events, one segment per start or resume
  (:mod:`quasisim.policy.curves` reads them);
* ``best.zip`` + ``validation.json``: the model that did best in validation (the nominal world and training
  worlds, never the evaluation's), checked at every checkpoint from the fresh model on (:class:`Selector`);
* ``policy.zip`` + ``training.json``: the final model and the training's cost (env steps, wall time, of which
  validation), with the step and score of the best model.
"""

from __future__ import annotations

import json
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from quasisim.errors import InputError, QuasisimError
from quasisim.files import LOCK, atomic_path, is_orphan, save_json_atomic

METHODS = {"dgrasp-tracking": False, "dgrasp-base": False, "dgrasp-tracking-curriculum": False,
           "ours+residual": True}  # method -> residual actions  # fmt: skip
FROM_SCRATCH = ("dgrasp-tracking", "dgrasp-base", "dgrasp-tracking-curriculum")  # without our result (--method)
CURRICULUM = "dgrasp-tracking-curriculum"  # trained through the physics curriculum, then in the target
SETUP, REFERENCE, CHECKPOINT, POLICY = "setup.json", "reference.npz", "checkpoint.zip", "policy.zip"
GUIDE, GUIDE_INFO = "guide.npz", "guide.json"  # dgrasp-base's demo as DGrasp sees it, and its grasp frames
DGRASP_MU = 1.0  # the friction coefficient of DGrasp-Base's force-closure test: the targets' (PhysicsOptions)
CHECKPOINT_META, TRAINING, LOGS = "checkpoint.json", "training.json", "logs"
BEST, VALIDATION = "best.zip", "validation.json"  # the best validated model (Selector)
OUTPUTS = (SETUP, REFERENCE, GUIDE, GUIDE_INFO, "meshes", CHECKPOINT, CHECKPOINT_META, LOGS, BEST, VALIDATION, POLICY,
           TRAINING)  # all of a run  # fmt: skip


@dataclass(frozen=True)
class TrainSetup:
    """What a training folder trains (``setup.json``)."""

    clip: str
    method: str
    target: str
    reference_source: str
    seed: int = 0
    algo: str = "ppo"
    env_overrides: dict[str, Any] = field(default_factory=dict)
    ppo_overrides: dict[str, Any] = field(default_factory=dict)
    guide: str = ""  # the demo the policy trains against, where not the clip (dgrasp-base: guide.npz)

    @property
    def residual(self) -> bool:
        return METHODS[self.method]

    @property
    def trained_on(self) -> str:
        """The demo the policy trains and is observed against: the guide, else the clip."""
        return self.guide or self.clip

    @classmethod
    def read(cls, out: Path) -> TrainSetup:
        p = out / SETUP
        if not p.is_file():
            raise InputError(out, None, f"a training folder of quasisim policy train (with {SETUP})", f"no {SETUP}")
        try:
            setup = cls(**json.loads(p.read_text()))
        except (json.JSONDecodeError, TypeError) as e:
            raise InputError(p, None, "the setup written by quasisim policy train", str(e)) from None
        if setup.method not in METHODS:
            raise InputError(p, "method", f"one of {', '.join(METHODS)}", repr(setup.method))
        return setup


def check_owned(out: Path, option: str = "--out") -> None:
    """Refuse ``out`` where it is neither missing, empty nor a training folder (:data:`SETUP`): ``policy train``
    replaces only what a training wrote, and never takes over a folder holding files of something else."""
    out = Path(out)
    if not out.is_dir():
        return
    held = sorted(p.name for p in out.iterdir() if p.name != LOCK and not is_orphan(p))
    if held and not (out / SETUP).is_file():
        shown = ", ".join(held[:3]) + (", ..." if len(held) > 3 else "")
        raise InputError(out, option, f"an empty folder or a training folder of quasisim policy train (with {SETUP})",
                         f"a folder holding {shown}")  # fmt: skip
    if held:
        TrainSetup.read(out)  # a damaged or foreign setup.json: refused too


def check_resume(out: Path, setup: TrainSetup, given: dict[str, Any]) -> None:
    """Refuse ``--resume`` with an option whose value differs from the one the training in ``out`` was started
    with (``given``: the options given on the command line, ``CLIP`` included: name -> value): a resumed training
    continues as it was started."""
    stored = {"CLIP": setup.clip, "--residual": setup.reference_source if setup.residual else None,
              "--method": setup.method, "--target": setup.target, "--seed": setup.seed, "--algo": setup.algo}  # fmt: skip
    paths = ("CLIP", "--residual")
    for opt, value in given.items():
        value = str(Path(value).resolve()) if opt in paths else value
        was = _stored_hand(out) if opt == "--hand" else stored[opt]
        if value != was:
            shown = f"no --residual ({setup.method} trains from scratch)" if was is None else was
            leave = "" if opt == "CLIP" else f"leave {opt} out to continue it, or "
            raise QuasisimError(f"{out / SETUP}: --resume with {opt} {value}: expected {shown}, as the training was "
                                f"started ({leave}start again with --overwrite)")  # fmt: skip


def _stored_hand(out: Path) -> str:
    """The robot hand of training folder ``out``: its reference controls'."""
    from quasisim.data.controls import load_controls

    return load_controls(out / REFERENCE).hand


def prepare(
    clip: Path, out: Path, residual_run: Path | None, hand: str, target: str, seed: int,
    env_overrides: dict[str, Any], ppo_overrides: dict[str, Any], method: str = "dgrasp-tracking",
) -> TrainSetup:  # fmt: skip
    """Write ``setup.json`` and ``reference.npz`` into ``out``: our result's controls (``residual_run``, a run
    folder or controls.npz: ``ours+residual``) or, without one, the kinematic retarget to ``hand`` of ``clip``
    (``method`` ``dgrasp-tracking``) or of its DGrasp-Base guide (``dgrasp-base``, with ``guide.npz`` and
    ``guide.json``). Everything is validated and computed first (a guide in a staging folder), before any process
    starts and before ``out`` changes; then the previous training in ``out`` is replaced (:func:`_clear`)."""
    from quasisim.data.demo import load_demo
    from quasisim.envs.config import TrackEnvConfig
    from quasisim.policy.config import PPOConfig

    check_owned(out)
    if method not in FROM_SCRATCH:
        from quasisim.errors import choice_error

        raise choice_error("method", method, FROM_SCRATCH)
    env_cfg = TrackEnvConfig.from_yaml(None, env_overrides)
    ppo = PPOConfig.from_yaml(None, ppo_overrides)
    if method == CURRICULUM:
        from quasisim.method.curriculum import load_curriculum

        load_curriculum(ppo.curriculum)  # refused here (naming the valid ones), before any process starts
    demo = load_demo(clip)
    with tempfile.TemporaryDirectory(prefix="quasisim-guide-") as stage:
        guide = Path(stage) / GUIDE
        if residual_run is not None:
            controls, info = _residual_reference(demo, residual_run), None
            method, source = "ours+residual", str(Path(residual_run).resolve())
        else:
            controls, source, info = _kinematic_reference(demo, hand, method, env_cfg.contact_radius, guide)
        _clear(out)
        setup = TrainSetup(str(Path(clip).resolve()), method, target, source, seed, "ppo", env_overrides,
                           ppo_overrides, str((out / GUIDE).resolve()) if method == "dgrasp-base" else "")  # fmt: skip
        save_json_atomic(out / SETUP, asdict(setup))  # first: the folder stays marked as a training throughout
        if setup.guide:
            _with_mesh_in(load_demo(guide), out / "meshes")
            with atomic_path(out / GUIDE) as tmp:
                shutil.copyfile(guide, tmp)
            save_json_atomic(out / GUIDE_INFO, {"mu": DGRASP_MU, "radius": env_cfg.contact_radius, "hands": info})
        controls.save(out / REFERENCE)
    return setup


def _residual_reference(demo: Any, residual_run: Path) -> Any:
    """Our result's controls (a run folder or controls.npz), checked against ``demo``."""
    from quasisim.envs.track import load_reference
    from quasisim.eval.evaluate import check_controls, hands_of

    controls, path = load_reference(residual_run)
    check_controls(demo, controls, hands_of(controls, path), path)
    return controls


def _kinematic_reference(demo: Any, hand: str, method: str, radius: float, guide: Path) -> tuple[Any, str, Any]:
    """The kinematic retarget to ``hand`` of ``demo`` or (``dgrasp-base``) of its guide, written to ``guide`` (with
    its mesh in ``meshes/`` beside) and read back as the training reads it (float32 on disk); (controls, their
    source, the guide's grasp frames or None)."""
    from quasisim.method.retarget import kinematic_controls
    from quasisim.targets.build import demo_hands

    source, info = f"kinematic retarget to {hand}", None
    if method == "dgrasp-base":
        from quasisim.data.demo import load_demo, save_demo
        from quasisim.policy.dgrasp import grasp_guide

        demo, info = grasp_guide(demo, radius, DGRASP_MU)
        demo = load_demo(save_demo(_with_mesh_in(demo, guide.parent / "meshes"), guide))
        source = f"{source}, of the DGrasp-Base guide ({GUIDE})"
    return kinematic_controls(demo_hands(hand, demo.sides), demo, hand), source, info


def _with_mesh_in(demo: Any, folder: Path) -> Any:
    """``demo`` with its object mesh copied into ``folder`` (a demo .npz finds its mesh in ``meshes/`` beside)."""
    import dataclasses
    import shutil

    folder.mkdir(parents=True, exist_ok=True)
    mesh = folder / demo.object_mesh_path.name
    if not mesh.is_file():
        with atomic_path(mesh) as tmp:
            shutil.copyfile(demo.object_mesh_path, tmp)
    return dataclasses.replace(demo, object_mesh_path=mesh.resolve())


def _clear(out: Path) -> None:
    """Remove what the previous training in ``out`` wrote (:data:`OUTPUTS`, ``meshes/`` only where it trained
    against a guide; ``--overwrite``) but its ``setup.json``, replaced next, so that nothing of it (its best model,
    its validation scores) is taken for the next training's. Nothing where ``out`` holds no training; files of
    other origins stay."""
    if not (out / SETUP).is_file():
        return
    old = TrainSetup.read(out)
    for name in OUTPUTS:
        p = out / name
        if name == SETUP or (name == "meshes" and not old.guide):
            continue
        shutil.rmtree(p) if p.is_dir() and not p.is_symlink() else p.unlink(missing_ok=True)


def make_env(out: Path, setup: TrainSetup, physics: dict[str, float] | None = None) -> Any:
    """A function making one environment of the training (for stable-baselines3's vectorised envs), stepping
    the target or the curriculum's simulator ``physics``."""

    def thunk() -> Any:
        import gymnasium as gym

        import quasisim.envs

        return gym.make(quasisim.envs.TRACK_ID, clip=setup.trained_on, reference=out / REFERENCE,
                        residual=setup.residual, target=setup.target, overrides=setup.env_overrides,
                        physics=physics)  # fmt: skip

    return thunk


Segment = tuple[dict[str, float] | None, int]  # (the simulator's contact settings, None: the target; end step)


def segments(setup: TrainSetup, cfg: Any, steps: int) -> list[Segment]:
    """What a training of ``steps`` env steps trains in, span by span: the target throughout, or (``CURRICULUM``)
    ``cfg.curriculum_stage_steps`` in each analytical simulator of ``cfg.curriculum`` from soft to stiff (its
    residual simulators left out: the target takes their place; each with the substeps per frame stage 2 gives it
    at the ``fast`` budget, ``substeps``), then the target up to ``steps``. A span ends at
    the first whole rollout past its end step."""
    if setup.method != CURRICULUM:
        return [(None, steps)]
    from quasisim.method.config import TransferConfig
    from quasisim.method.curriculum import load_curriculum

    cur, bud = load_curriculum(cfg.curriculum), TransferConfig.from_yaml().budget("fast")
    analytical = [i for i, st in enumerate(cur.stages) if not st.residual]
    ends = [min(steps, (k + 1) * cfg.curriculum_stage_steps) for k in range(len(analytical))]
    step = lambda i: {"substeps": bud.substeps if i == cur.stiffest else bud.soft}  # noqa: E731  (as stage 2 steps)
    return [(cur.contact(i) | step(i), end) for i, end in zip(analytical, ends, strict=True)] + [(None, steps)]


def training_task(out: Path, setup: TrainSetup) -> tuple[Any, Any]:
    """The :class:`~quasisim.envs.task.TrackTask` of training folder ``out`` (on the demo it trains against,
    :attr:`TrainSetup.trained_on`) and its reference controls."""
    from quasisim.data.demo import load_demo
    from quasisim.envs.config import TrackEnvConfig
    from quasisim.envs.track import load_reference, task_for

    controls, path = load_reference(out / REFERENCE)
    cfg = TrackEnvConfig.from_yaml(None, setup.env_overrides)
    return task_for(load_demo(setup.trained_on), controls, cfg, setup.residual, path), controls


class Selector:
    """Validates the model at every checkpoint (:func:`~quasisim.policy.controller.validate`: the nominal world and
    ``validate_worlds`` training worlds) and keeps the best one seen in ``best.zip``, the fresh model included
    (a residual policy's is our result, nearly untouched; among equal scores the later one); ``validation.json``
    holds every score and the seconds spent, across resumes."""

    def __init__(self, out: Path, setup: TrainSetup, worlds: int) -> None:
        from quasisim.envs.track import world_config

        self.task, _ = training_task(out, setup)
        self.out, self.target, self.worlds, self.ranges = out, setup.target, worlds, world_config(self.task.cfg)
        old = out / VALIDATION
        self.state = json.loads(old.read_text()) if old.is_file() else {"history": [], "seconds": 0.0, "best": None}

    def __call__(self, model: Any) -> Any:
        """Validate ``model`` (once per step count); returns its score."""
        from quasisim.policy.controller import Score, validate

        steps = int(model.num_timesteps)
        if self.state["history"] and self.state["history"][-1][0] == steps:
            return Score(*self.state["history"][-1][1:])
        t0 = time.perf_counter()
        score = validate(self.task, model, self.target, self.worlds, self.ranges.seed, self.ranges)
        best = self.state["best"]
        if best is None or score >= Score(*best["score"]):  # a tie: the later, more trained model
            with atomic_path(self.out / BEST) as tmp:
                model.save(tmp)
            self.state["best"] = {"steps": steps, "score": list(score)}
        self.state["history"].append([steps, *score])
        self.state["seconds"] += time.perf_counter() - t0
        save_json_atomic(self.out / VALIDATION, self.state)
        return score


def _callbacks(out: Path, every: int, wall0: float, select: Selector, span: int = 0) -> list[Any]:
    """Checkpoints with validation every ``every`` env steps (atomic) and the tracked fraction of the episodes
    (strict success) in the logs."""
    from stable_baselines3.common.callbacks import BaseCallback

    class Tracked(BaseCallback):
        """Logs ``rollout/tracked``: the share of the episodes ended in the last rollout with strict success
        (the env's ``info["tracked"]``: the clip's end reached within the strict limits, the object moved as in
        the demo; what validation and evaluation count), and ``rollout/frames``: the frames they reached."""

        def _on_rollout_start(self) -> None:
            self.ended: list[tuple[bool, float]] = []

        def _on_step(self) -> bool:
            for info, done in zip(self.locals["infos"], self.locals["dones"], strict=True):
                if done and "frames" in info:
                    self.ended.append((bool(info["tracked"]), float(info["frames"])))
            return True

        def _on_rollout_end(self) -> None:
            if self.ended:
                self.logger.record("rollout/tracked", float(np.mean([e[0] for e in self.ended])))
                self.logger.record("rollout/frames", float(np.mean([e[1] for e in self.ended])))

    class Checkpoint(BaseCallback):
        def _on_training_start(self) -> None:
            self.last = self.num_timesteps
            select(self.model)  # the fresh (or resumed) model is a candidate too

        def _on_step(self) -> bool:
            if self.num_timesteps - self.last >= every:
                self.last = self.num_timesteps
                score = select(self.model)
                for k, v in score._asdict().items():
                    self.logger.record(f"validation/{k}", float(v))
                save_checkpoint(self.model, out, wall0, span)
            return True

    return [Tracked(), Checkpoint()]


def save_checkpoint(model: Any, out: Path, wall0: float, span: int = 0) -> None:
    """``checkpoint.zip`` and ``checkpoint.json`` (steps, wall seconds so far, the span of :func:`segments` and the
    training worlds each of its environments has drawn since it was seeded), each replaced atomically."""
    with atomic_path(out / CHECKPOINT) as tmp:
        model.save(tmp)
    drawn = [int(n) for n in model.get_env().get_attr("worlds_drawn")]
    meta = {"steps": int(model.num_timesteps), "wall_s": time.time() - wall0, "span": span, "worlds_drawn": drawn}
    save_json_atomic(out / CHECKPOINT_META, meta)


def _continue_worlds(venv: Any, meta: dict[str, Any]) -> None:
    """Make the first reset of a resumed training's environments (seeded again by ``PPO.load``) go on after the
    worlds they drew before (``checkpoint.json``); a checkpoint without that count starts them again."""
    drawn = meta.get("worlds_drawn")
    if drawn is None or len(drawn) != venv.num_envs:
        print("checkpoint.json does not say which training worlds were drawn: they start their sequence again",
              flush=True)  # fmt: skip
        return
    venv.set_options([{"skip_worlds": int(n)} for n in drawn])


def _continue_schedule(venv: Any, model: Any) -> None:
    """Set each environment's step count (:meth:`~quasisim.envs.track.TrackEnv.set_steps_taken`: the schedule of
    its termination limits, ``limits_steps``) to the training's steps per environment so far, so that a resumed
    training's (and the next span's new) environments go on with the schedule where it was."""
    venv.env_method("set_steps_taken", int(model.num_timesteps) // venv.num_envs)


def _vec_env(out: Path, setup: TrainSetup, n: int, physics: dict[str, float] | None = None) -> Any:
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecMonitor

    fns = [make_env(out, setup, physics) for _ in range(n)]
    return VecMonitor(SubprocVecEnv(fns, start_method="forkserver") if n > 1 else DummyVecEnv(fns))


def train(out: Path, steps: int, resume: bool = False, progress: bool = True) -> dict[str, Any]:
    """Train (or, with ``resume``, continue) the policy of training folder ``out`` up to ``steps`` env steps;
    returns ``training.json``'s content."""
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.logger import configure

    from quasisim.policy.config import PPOConfig

    setup = TrainSetup.read(out)
    cfg = PPOConfig.from_yaml(None, setup.ppo_overrides)
    torch.set_num_threads(1)  # the env processes have the other cores; more threads only spin against them
    ckpt = out / CHECKPOINT
    meta: dict[str, Any] = {}
    if resume and ckpt.is_file():
        p = out / CHECKPOINT_META  # written after the model: a kill between the two leaves the older one
        meta = json.loads(p.read_text()) if p.is_file() else {}
    elif resume:
        raise QuasisimError(f"{out}: nothing to resume (no {CHECKPOINT}); run without --resume")
    spans = segments(setup, cfg, steps)
    todo = [k for k, (_, end) in enumerate(spans) if end > int(meta.get("steps", 0))] or [len(spans) - 1]
    venv = _vec_env(out, setup, cfg.n_envs, spans[todo[0]][0])
    try:
        if resume:
            model = PPO.load(ckpt, env=venv, device="cpu")
            if todo[0]:
                venv.seed(setup.seed + todo[0])  # span k's worlds: seed + k (as when it started)
            if meta.get("span", 0) == todo[0]:  # else the checkpoint closed the span before: its worlds start
                _continue_worlds(venv, meta)
            _continue_schedule(venv, model)
        else:
            model = PPO("MlpPolicy", venv, seed=setup.seed, device="cpu", verbose=0, **cfg.ppo_kwargs(setup.residual))
        logs = out / LOGS
        segment = logs / f"{len(list(logs.glob('*'))) if logs.is_dir() else 0:03d}"
        model.set_logger(configure(str(segment), ["csv", "tensorboard"]))
        wall0 = time.time() - float(meta.get("wall_s", 0.0))
        select = Selector(out, setup, cfg.validate_worlds)
        for k in todo:
            if spans[k][1] <= model.num_timesteps:  # a span the last rollout already went past
                continue
            if k != todo[0]:  # the next simulator of the curriculum (or the target): new environments
                venv.close()
                venv = _vec_env(out, setup, cfg.n_envs, spans[k][0])
                model.set_env(venv)
                venv.seed(setup.seed + k)
                _continue_schedule(venv, model)
            model.learn(spans[k][1] - model.num_timesteps,
                        callback=_callbacks(out, cfg.checkpoint_every, wall0, select, k),
                        reset_num_timesteps=False, progress_bar=progress)  # fmt: skip
            save_checkpoint(model, out, wall0, k)
        select(model)
        with atomic_path(out / POLICY) as tmp:
            model.save(tmp)
        info = {"method": setup.method, "algo": setup.algo, "env_steps": int(model.num_timesteps),
                "wall_s": time.time() - wall0, "n_envs": cfg.n_envs, "validation_s": select.state["seconds"],
                "best": select.state["best"]}  # fmt: skip
        save_json_atomic(out / TRAINING, info)
        return info
    finally:
        venv.close()
