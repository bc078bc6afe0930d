"""``quasisim bench env``: the speed of the tracking environment ``quasisim/Track-v0`` on one clip.

Three timings in one process, after the environment is made and reset once (both timed apart):

* **resets**: ``resets`` resets, each into another training world (``options={"world": k}``, k = 1, 2, ...);
* **steps**: ``steps`` env steps with the actions a fresh policy takes (Gaussian, std ``noise`` in action
  units, seeded), timed apart from the resets that end episodes on the way;
* **training throughput**: env steps per second of that loop with those resets (each into a random training
  world, as in training) counted in: what a PPO environment process delivers, validation and updates aside.
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class EnvSpeed:
    """Seconds of one environment's work: making it, its first reset, ``resets`` resets into training worlds,
    ``steps`` steps and the ``episode_resets`` resets (``episode_s``) that ended episodes among them."""

    make_s: float
    first_reset_s: float
    resets: int
    resets_s: float
    steps: int
    steps_s: float
    episode_resets: int
    episode_s: float

    def row(self) -> str:
        """A markdown table row (:data:`HEAD`)."""
        per_reset, per_step = self.resets_s / max(self.resets, 1), self.steps_s / max(self.steps, 1)
        return (
            f"| {self.make_s:.2f} | {self.first_reset_s * 1e3:.1f} | {self.resets} | {per_reset * 1e3:.2f} | "
            f"{1 / per_reset:.1f} | {self.steps} | {per_step * 1e3:.2f} | {1 / per_step:.0f} | "
            f"{self.episode_resets} | {self.steps / (self.steps_s + self.episode_s):.0f} |"
        )


HEAD = (
    "| make (s) | first reset (ms) | resets | ms/reset | resets/s | steps | ms/step | steps/s | episode resets "
    "| steps/s with resets |\n|---|---|---|---|---|---|---|---|---|---|"
)


def kinematic_reference(clip: Path, hand: str, folder: Path) -> Path:
    """The kinematic retarget of ``clip`` to ``hand`` saved in ``folder`` (what ``policy train`` tracks without
    ``--residual``)."""
    from quasisim.data.demo import load_demo
    from quasisim.method.retarget import kinematic_controls
    from quasisim.targets.build import demo_hands

    demo = load_demo(clip)
    path = folder / "kinematic.npz"
    kinematic_controls(demo_hands(hand, demo.sides), demo, hand).save(path)
    return path


def time_env(clip: Path, reference: Path, target: str, residual: bool, resets: int, steps: int,
             noise: float = 0.1, seed: int = 0) -> EnvSpeed:  # fmt: skip
    """Time ``quasisim/Track-v0`` of ``clip`` tracking ``reference`` (see the module docstring)."""
    import gymnasium as gym

    import quasisim.envs

    t0 = time.perf_counter()
    env = gym.make(quasisim.envs.TRACK_ID, clip=clip, reference=reference, residual=residual, target=target)
    t1 = time.perf_counter()
    env.reset(seed=seed)
    t2 = time.perf_counter()
    for k in range(resets):
        env.reset(options={"world": k + 1})
    t3 = time.perf_counter()
    rng = np.random.default_rng(seed)
    shape = env.action_space.shape
    step_s = episode_s = 0.0
    ended = 0
    env.reset(seed=seed)
    for _ in range(steps):
        a = np.clip(noise * rng.standard_normal(shape), -1, 1).astype(np.float32)
        ts = time.perf_counter()
        _, _, term, trunc, _ = env.step(a)
        te = time.perf_counter()
        step_s += te - ts
        if term or trunc:
            env.reset()
            episode_s += time.perf_counter() - te
            ended += 1
    env.close()
    return EnvSpeed(t1 - t0, t2 - t1, resets, t3 - t2, steps, step_s, ended, episode_s)


def run_env_bench(clip: Path, reference: Path | None, hand: str, target: str, residual: bool, resets: int,
                  steps: int, noise: float) -> str:  # fmt: skip
    """Time the environment of ``clip`` (tracking ``reference``, or the kinematic retarget to ``hand``); returns
    the markdown: the header (date, machine, command) and the table."""
    from quasisim.eval.tables import header

    with tempfile.TemporaryDirectory() as tmp:
        ref = reference or kinematic_reference(clip, hand, Path(tmp))
        speed = time_env(clip, ref, target, residual, resets, steps, noise)
    kind = "residual" if residual else "from scratch (DGrasp's actions)"
    what = f"- clip: {clip.stem}, {target}, {kind}, action noise {noise:g}, reference: {reference or f'kinematic retarget to {hand}'}"
    return "\n".join([header("quasisim/Track-v0 speed"), what, "", HEAD, speed.row(), ""])
