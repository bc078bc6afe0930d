"""``quasisim bench policy``: learned tracking policies beside our results, clip by clip, in one table.

For every clip: ``ours+residual`` (PPO residual on our result, :mod:`quasisim.policy`), ``dgrasp-tracking``
(PPO from scratch, the kinematic retarget observed) and, where asked, ``dgrasp-base`` (PPO from scratch, the
first grasp then only the root guided, :mod:`quasisim.policy.dgrasp`) and ``dgrasp-tracking-curriculum``
(``dgrasp-tracking`` trained through the physics curriculum's simulators first) trained to ``steps`` env steps in
``OUT/<clip>/<method>/train`` (resumed where a checkpoint is, skipped where finished) and judged in
``OUT/<clip>/<method>/eval`` (the best validated model) and ``eval-final`` (the last one); our result (``RUNS/<clip>/<run>``) open loop (its metrics.json) and closed loop
(the tracker of :mod:`quasisim.method.track`, cached beside the run by :func:`quasisim.bench.closed_loop.add_closed_loop`).
All four meet the same seeded perturbed worlds (``configs/robust.yaml``, seed 0, ``robust`` replays).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from quasisim.errors import QuasisimError
from quasisim.eval.robust import CLOSED_LOOP_SUFFIX, ROBUST_KEY
from quasisim.eval.tables import header, publish

POLICY_METHODS = ("ours+residual", "dgrasp-tracking", "dgrasp-base", "dgrasp-tracking-curriculum")  # --methods
# (default: the first two)


Overrides = tuple[dict[str, Any], dict[str, Any]]  # (env, ppo) settings of every policy (--set)
MODELS = (("best", "eval"), ("final", "eval-final"))  # each policy's model judged, and the folder of its judgement


def _train(clip: Path, folder: Path, method: str, ours: Path, steps: int, seed: int, sets: Overrides) -> dict[str, Any]:
    """Train (or resume, or skip where finished) one policy; its ``training.json``. A folder trained with other
    settings than ``sets`` is refused."""
    from quasisim.policy.train import CHECKPOINT, SETUP, TrainSetup, prepare, train

    if (folder / SETUP).is_file():
        old = TrainSetup.read(folder)
        if (old.env_overrides, old.ppo_overrides) != sets:
            raise QuasisimError(f"{folder}: trained with --set {old.env_overrides} {old.ppo_overrides}, not "
                                f"{sets[0]} {sets[1]}; another --out for other settings")  # fmt: skip
    done = folder / "training.json"
    if done.is_file() and json.loads(done.read_text())["env_steps"] >= steps:
        return json.loads(done.read_text())
    resume = (folder / CHECKPOINT).is_file()
    if not resume:
        residual = ours if method == "ours+residual" else None
        prepare(clip, folder, residual, "shadow", "mujoco", seed, *sets, "dgrasp-tracking" if residual else method)
    print(f"{clip.stem}: {method}, {'resumed' if resume else 'from the start'}, up to {steps} env steps", flush=True)
    return train(folder, steps, resume=resume, progress=False)


def _evaluate(train_dir: Path, eval_dir: Path, robust: int, which: str) -> dict[str, Any]:
    """The metrics of the policy's model ``which`` (judged again only where the policy changed since)."""
    from quasisim.policy.evaluate import evaluate_policy

    m = eval_dir / "metrics.json"
    steps = json.loads((train_dir / "training.json").read_text())["env_steps"]
    if m.is_file():
        old = json.loads(m.read_text())
        if (
            old["policy"]["training"].get("env_steps") == steps
            and old.get(ROBUST_KEY + CLOSED_LOOP_SUFFIX, {}).get("n") == robust
        ):
            return old
    return evaluate_policy(train_dir, eval_dir, robust, which=which).metrics


def _finished(folder: Path, steps: int, robust: int) -> tuple[dict[str, Any], dict[str, Any]] | None:
    """A policy trained to ``steps`` and judged at that step count in ``robust`` worlds: its ``training.json``
    and the metrics of its best and final models; None where it is not (yet)."""
    try:
        info = json.loads((folder / "train" / "training.json").read_text())
        ms = {w: json.loads((folder / sub / "metrics.json").read_text()) for w, sub in MODELS}
    except FileNotFoundError:
        return None
    judged = all(m["policy"]["training"].get("env_steps") == info["env_steps"]
                 and m.get(ROBUST_KEY + CLOSED_LOOP_SUFFIX, {}).get("n") == robust for m in ms.values())  # fmt: skip
    return (info, ms) if info["env_steps"] >= steps and judged else None


def run_policy_bench(
    data_dir: Path, clips: list[str], runs: Path, run: str, steps: int, robust: int, workers: int, out: Path,
    methods: tuple[str, ...] = POLICY_METHODS[:2], seed: int = 0, overrides: Overrides = ({}, {}),
    report_only: bool = False,
) -> list[dict[str, Any]]:  # fmt: skip
    """Train, judge and tabulate (see the module docstring); returns the rows (also ``OUT/policy.json``).
    ``report_only``: nothing is trained or judged; the policies finished and judged at ``steps`` are tabulated."""
    from quasisim.bench.closed_loop import add_closed_loop

    for c in clips:
        if not (runs / c / run / "controls.npz").is_file():
            raise QuasisimError(f"{runs / c / run}: no controls.npz (our result for clip {c}; --runs and --run)")
    rows: list[dict[str, Any]] = []
    for method in methods:
        for c in clips:
            folder = out / c / method
            if report_only:
                if (done := _finished(folder, steps, robust)) is None:
                    continue
                info, ms = done
            else:
                info = _train(data_dir / f"{c}.npz", folder / "train", method, runs / c / run, steps, seed, overrides)
                ms = {w: _evaluate(folder / "train", folder / sub, robust, w) for w, sub in MODELS}
            for which, label in (("best", method), ("final", f"{method} (final model)")):
                rows.append(_row(c, label, ms[which], ms[which][ROBUST_KEY + CLOSED_LOOP_SUFFIX], info))
    ours = [{"clip": c, "method": run} | _our_metrics(runs / c, run) for c in clips]
    ours = add_closed_loop(ours, runs, {c: data_dir / f"{c}.npz" for c in clips}, robust, ("default",), "mujoco",
                           workers)  # fmt: skip
    for m in ours:
        if m.get(ROBUST_KEY, {}).get("n") != robust:
            raise QuasisimError(f"{runs / m['clip'] / run}: judged with other robust replays than --robust {robust}")
        rows.append(_row(m["clip"], f"ours ({run}) open loop", m, m[ROBUST_KEY], None))
        rows.append(_row(m["clip"], f"ours ({run}) closed loop", None, m[ROBUST_KEY + CLOSED_LOOP_SUFFIX], None))
    publish(out, "policy", rows, _markdown(rows, steps, robust))
    return rows


def _our_metrics(clip_dir: Path, run: str) -> dict[str, Any]:
    """Our result's metrics: the run's ``metrics.json``, else its row in the clip's ``clip.json`` (a folder of
    ``quasisim bench transfer`` whose outputs stayed on another machine keeps only that and the plan)."""
    from quasisim.batch import CLIP_FILE

    m, c = clip_dir / run / "metrics.json", clip_dir / CLIP_FILE
    if m.is_file():
        return json.loads(m.read_text())
    if c.is_file() and run in (runs := json.loads(c.read_text())["runs"]):
        return runs[run]["row"]["metrics"]
    raise QuasisimError(f"{clip_dir / run}: no metrics.json, and {c} holds no run {run!r} (--runs and --run)")


def _row(clip: str, method: str, m: dict | None, robust: dict, info: dict | None) -> dict[str, Any]:
    return {
        "clip": clip, "method": method,
        "strict": None if m is None else bool(m["success"]["strict"]),
        "20deg_20cm": None if m is None else bool(m["success"]["20deg_20cm"]),
        "robust_strict": robust["strict"], "robust_20deg_20cm": robust["20deg_20cm"],
        "env_steps": info["env_steps"] if info else None, "train_s": info["wall_s"] if info else None,
    }  # fmt: skip


def _markdown(rows: list[dict[str, Any]], steps: int, robust: int) -> list[str]:
    yn = lambda b: "-" if b is None else ("y" if b else "n")  # noqa: E731
    pct = lambda v: f"{100 * v:.0f}"  # noqa: E731
    lines = [header(f"Learned tracking policies ({steps} env steps each) beside ours, {robust} perturbed worlds"),
             "| method | clips | strict (%) | 20/20 (%) | robust strict (%) | robust 20/20 (%) | env steps | train min/clip |",
             "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    methods = list(dict.fromkeys(r["method"] for r in rows))
    for meth in methods:
        rs = [r for r in rows if r["method"] == meth]
        nominal = [r for r in rs if r["strict"] is not None]
        cells = [pct(np.mean([r[k] for r in nominal])) if nominal else "-" for k in ("strict", "20deg_20cm")]
        trained = [r for r in rs if r["env_steps"] is not None]
        cost = (f"{np.mean([r['env_steps'] for r in trained]):.0f} | {np.mean([r['train_s'] for r in trained]) / 60:.1f}"
                if trained else "- | -")  # fmt: skip
        lines.append(f"| {meth} | {len(rs)} | {' | '.join(cells)} | {pct(np.mean([r['robust_strict'] for r in rs]))} "
                     f"| {pct(np.mean([r['robust_20deg_20cm'] for r in rs]))} | {cost} |")  # fmt: skip
    lines += ["", "| clip | method | strict | 20/20 | robust strict (%) | robust 20/20 (%) | env steps | train min |",
              "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for r in sorted(rows, key=lambda r: (r["clip"], methods.index(r["method"]))):
        t = "-" if r["train_s"] is None else f"{r['train_s'] / 60:.1f}"
        lines.append(f"| {r['clip']} | {r['method']} | {yn(r['strict'])} | {yn(r['20deg_20cm'])} "
                     f"| {pct(r['robust_strict'])} | {pct(r['robust_20deg_20cm'])} | {r['env_steps'] or '-'} | {t} |")  # fmt: skip
    return lines
