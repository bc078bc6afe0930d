"""The optimisation loop: Adam (optax) with early termination, keeping the best iterate; progress bars."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm import tqdm

Array = jax.Array
ValueAndGrad = Callable[[Any], tuple[tuple[Array, dict[str, Array]], Any]]
OnStep = Callable[[int, float], None]


@dataclass(frozen=True)
class StepBudget:
    """Adam steps for one optimisation (values: ``configs/transfer.yaml``; paper: 100 control and 1000
    identification steps per simulator).

    Attributes:
        control_steps, sysid_steps: maximum steps.  control_lr, sysid_lr: Adam step sizes.
        patience: stop after this many steps without a relative improvement of ``min_rel_improvement``.
    """

    control_steps: int
    sysid_steps: int
    control_lr: float
    sysid_lr: float
    patience: int
    min_rel_improvement: float


@dataclass
class StepLog:
    """Loss history of one optimisation run."""

    losses: list[float] = dataclasses.field(default_factory=list)
    terms: list[dict[str, float]] = dataclasses.field(default_factory=list)
    best: float = float("inf")
    wall_s: float = 0.0
    stopped_early: bool = False


def adam_steps(
    value_and_grad: ValueAndGrad,
    x0: Any,
    steps: int,
    lr: float,
    patience: int,
    min_rel_improvement: float,
    mask: Callable[[Any], Any] | None = None,
    on_step: OnStep | None = None,
) -> tuple[Any, StepLog]:
    """Minimise with Adam; return the best iterate (the loss is evaluated before each update, so the
    returned point is one whose loss was measured) and the loss history. ``mask`` zeroes gradient
    leaves that must stay fixed. Stops early after ``patience`` steps without a relative improvement."""
    tx = optax.adam(lr)
    x, st = x0, tx.init(eqx.filter(x0, eqx.is_array))
    log = StepLog()
    best_x, since = x0, 0
    t0 = time.perf_counter()
    for k in range(steps + 1):
        (loss, terms), g = value_and_grad(x)
        lv = float(loss)
        if not np.isfinite(lv):
            log.stopped_early = True
            break
        log.losses.append(lv)
        log.terms.append({n: float(v) for n, v in terms.items()})
        since = 0 if (lv < log.best * (1.0 - min_rel_improvement) or k == 0) else since + 1
        if lv < log.best:
            log.best, best_x = lv, x
        if on_step is not None:
            on_step(k, lv)
        if k == steps or since >= patience:
            log.stopped_early = k < steps
            break
        if mask is not None:
            g = mask(g)
        upd, st = tx.update(g, st, x)
        x = optax.apply_updates(x, upd)
    log.wall_s = time.perf_counter() - t0
    return best_x, log


@dataclass(frozen=True)
class Progress:
    """Progress output of a long run: a tqdm bar per optimisation and one-line messages (or nothing)."""

    enabled: bool = True

    @contextmanager
    def steps(self, desc: str, total: int) -> Iterator[OnStep | None]:
        """A bar over ``total + 1`` loss evaluations; yields the ``on_step`` callback of :func:`adam_steps`."""
        if not self.enabled:
            yield None
            return
        bar = tqdm(total=total + 1, desc=desc, unit="step", leave=False, dynamic_ncols=True)
        bar.set_postfix_str("first step compiles (JAX), then the rate is the real one")

        def on_step(k: int, loss: float) -> None:
            bar.update(1)
            bar.set_postfix(loss=f"{loss:.5f}")

        try:
            yield on_step
        finally:
            bar.close()

    def write(self, text: str) -> None:
        if self.enabled:
            tqdm.write(text)


def minimise(
    value_and_grad: ValueAndGrad, x0: Any, steps: int, lr: float, budget: StepBudget, progress: Progress, desc: str
) -> tuple[Any, StepLog]:
    """:func:`adam_steps` with ``budget``'s early termination and a progress bar named ``desc``."""
    with progress.steps(desc, steps) as on_step:
        return adam_steps(value_and_grad, x0, steps, lr, budget.patience, budget.min_rel_improvement, on_step=on_step)


def minibatch_adam(
    vg: Any, x0: Any, train: Any, steps: int, lr: float, batch: int, seed: int, check_every: int = 10,
    progress: Progress | None = None, desc: str = "stage 3 fit",
) -> tuple[Any, list[float]]:  # fmt: skip
    """Minibatch Adam (``batch`` random training windows per step; ``vg(x, windows)``; ``train`` has ``len`` and
    ``take(indices)``, e.g. :class:`~quasisim.method.replay.Windows`). Every ``check_every``
    steps the loss on a fixed subset of ``2 batch`` training windows is measured and the best iterate by it
    is returned, so a fit never ends worse on that subset than it started. Returns the iterate and the
    minibatch losses. Batches are taken here, so ``vg`` is compiled for the batch's size alone, whatever
    the number of training windows."""
    rng, n = np.random.default_rng(seed), len(train)
    b = min(batch, n)
    check = rng.choice(n, size=min(2 * batch, n), replace=False)
    # the check subset in batches of the step's own size: one compiled program serves both
    chunks = [train.take(jnp.asarray(check[i : i + b])) for i in range(0, len(check) - b + 1, b)]

    def check_loss(x: Any) -> float:
        return float(np.mean([float(vg(x, c)[0]) for c in chunks]))

    tx = optax.adam(lr)
    x, st = x0, tx.init(eqx.filter(x0, eqx.is_array))
    with (progress or Progress(False)).steps(desc, steps) as on_step:
        best, best_x = check_loss(x), x
        losses: list[float] = []
        for k in range(1, steps + 1):
            idx = jnp.asarray(rng.choice(n, size=b, replace=False))
            loss, g = vg(x, train.take(idx))
            if not np.isfinite(float(loss)):
                break
            losses.append(float(loss))
            if on_step is not None:
                on_step(k, float(loss))
            upd, st = tx.update(g, st, x)
            x = optax.apply_updates(x, upd)
            if k % check_every == 0 or k == steps:
                c = check_loss(x)
                if c < best:
                    best, best_x = c, x
    return best_x, losses
