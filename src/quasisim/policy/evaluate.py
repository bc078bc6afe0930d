"""Judge a trained policy like every other result: replayed closed loop in the target, the same metrics, and
robust success in the same seeded perturbed worlds (:mod:`quasisim.eval.robust`).

The policy acts through :class:`~quasisim.policy.controller.LearnedPolicy` (its mean action, closed loop); it
observes the demo it trained against (DGrasp-Base: its guide), and is judged against the clip.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from quasisim.data.controls import Controls
from quasisim.envs.task import TrackTask
from quasisim.errors import QuasisimError
from quasisim.policy.controller import LearnedPolicy
from quasisim.policy.train import BEST, POLICY, TrainSetup, training_task

MODELS = {"best": BEST, "final": POLICY}  # --model: the best validated checkpoint, or the last one


def load_trained(folder: Path, which: str = "best") -> tuple[TrainSetup, TrackTask, Any, Controls]:
    """The setup, the task, the model ``which`` (:data:`MODELS`) and the reference controls of training
    folder ``folder``."""
    import torch
    from stable_baselines3 import PPO

    setup = TrainSetup.read(folder)
    if which not in MODELS:
        from quasisim.errors import choice_error

        raise choice_error("model", which, tuple(MODELS))
    if not (folder / POLICY).is_file():
        raise QuasisimError(f"{folder}: no {POLICY} (training has not finished: quasisim policy train ... --resume)")
    torch.set_num_threads(1)
    task, controls = training_task(folder, setup)
    return setup, task, PPO.load(folder / MODELS[which], device="cpu"), controls


def evaluate_policy(folder: Path, out: Path | None, robust: int, ranges: str = "default", render: bool = False,
                    progress: bool = False, which: str = "best") -> Any:  # fmt: skip
    """Replay the policy of training folder ``folder`` in its target, nominal and in ``robust`` perturbed worlds
    of ``ranges``; with ``out`` write the outputs of ``quasisim evaluate`` there (metrics.json holds the
    policy's training cost under ``policy``). Returns the :class:`~quasisim.eval.evaluate.Evaluation`."""
    import json

    from quasisim.data.demo import load_demo
    from quasisim.eval.evaluate import Evaluation, mark_stability, scene_surface, write_outputs
    from quasisim.eval.metrics import evaluate_rollout
    from quasisim.eval.robust import replay, replays, robust_success
    from quasisim.files import output_set
    from quasisim.targets import make_target

    setup, task, model, reference = load_trained(folder, which)
    demo, scene = load_demo(setup.clip) if setup.guide else task.demo, task.scene  # judged against the clip
    ctl = LearnedPolicy(task, model)
    with make_target(setup.target, scene) as world:
        rollout = replay(world, task.reference, ctl)
    metrics, pf = evaluate_rollout(demo, rollout, scene_surface(scene, rollout.qpos))
    metrics = mark_stability(metrics, rollout.instability, f"{demo.name} in {setup.target}")
    cfg = replays(robust, ranges)
    if cfg.n:
        metrics[cfg.closed_loop_key] = robust_success(demo, scene, task.reference, setup.target, cfg,
                                           policy=lambda: LearnedPolicy(task, model))  # fmt: skip
    training = folder / "training.json"
    metrics["policy"] = {"method": setup.method, "algo": setup.algo, "model": which, "closed_loop": True,
                         "folder": str(folder),
                         "training": json.loads(training.read_text()) if training.is_file() else {}}  # fmt: skip
    ev = Evaluation(metrics, pf, rollout, scene)
    if out is not None:
        applied = dataclasses.replace(reference, method=setup.method, q_targets=np.asarray(ctl.applied), extras={})
        info = {"policy": f"{setup.method} ({setup.algo}), {metrics['policy']['training'].get('env_steps', '?')} "
                          f"env steps; reference: {setup.reference_source}"}  # fmt: skip
        with output_set(out) as stage:
            write_outputs(ev, demo, applied, setup.target, stage, render, None, info, None, progress)
    return ev
