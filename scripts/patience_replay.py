"""Replay the early exit of stages 1 and 2 on recorded loss curves: what a smaller ``patience`` would save.

    python scripts/patience_replay.py benchmarks/runs/grab25-shadow-mujoco-hull default+sample+select 3,12 4,8

For every checkpoint of stages 1 and 2 of every clip of a ``quasisim bench transfer`` folder (its ``.work``
folder, kept on the machine that ran it), the control-optimisation loss curve is fed, in order, to
``quasisim.optim.adam.adam_steps`` itself, whose early exit decides (stop after ``patience`` evaluations
without a relative improvement of ``min_rel_improvement``, or at ``steps``). Up to the stop, a run with the
smaller patience takes exactly the recorded steps, so its best loss is the best recorded loss up to there.
Prints, per checkpoint and setting, the mean and largest ratio of that loss to the recorded best, and the
evaluations taken against recorded.
"""

from __future__ import annotations

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from quasisim.optim.adam import adam_steps


def replay(losses: np.ndarray, patience: int, steps: int, rel: float = 1e-3) -> tuple[float, int]:
    """(best loss, evaluations) of ``adam_steps``' early exit on a recorded curve ``losses``: the optimiser
    itself, fed the recorded losses in order (zero gradients; past the curve's end a non-finite loss ends it)."""
    recorded = iter(losses)

    def value_and_grad(x: jax.Array) -> tuple[tuple[float, dict[str, float]], jax.Array]:
        return (float(next(recorded, np.inf)), {}), jnp.zeros_like(x)

    _, log = adam_steps(value_and_grad, jnp.zeros(1), steps, 0.0, patience, rel)
    return log.best, len(log.losses)


def main(folder: str, run: str, settings: list[str]) -> None:
    clips = sorted((Path(folder) / ".work").glob(f"*/runs/{run}/checkpoints"))
    if not clips:
        raise SystemExit(f"{folder}/.work holds no checkpoints of run {run!r}")
    names = sorted({p.stem for c in clips for p in c.glob("stage[12]_*.npz")})
    print(f"{len(clips)} clips of {folder} ({run})")
    print(
        "| checkpoint | patience, steps | best loss / recorded best (mean, max) | evaluations (replayed / recorded) |"
    )
    print("|---|---|---|---|")
    for name in names:
        curves = []
        for c in clips:
            with np.load(c / f"{name}.npz") as z:
                n_sysid = int(z["n_sysid"]) if "n_sysid" in z.files else 0
                curves.append(np.asarray(z["losses"][n_sysid:], np.float64))
        for s in settings:
            patience, steps = (int(x) for x in s.split(","))
            runs = [replay(L, patience, steps) for L in curves]
            ratio = np.array([b / L.min() for (b, _), L in zip(runs, curves, strict=True)])
            evals = np.mean([e for _, e in runs])
            print(
                f"| {name} | {patience}, {steps} | {ratio.mean():.3f}, {ratio.max():.2f} | "
                f"{evals:.1f} / {np.mean([len(L) for L in curves]):.1f} |"
            )


if __name__ == "__main__":
    if len(sys.argv) < 4:
        raise SystemExit(__doc__)
    main(sys.argv[1], sys.argv[2], sys.argv[3:])
