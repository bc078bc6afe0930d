"""``quasisim bench predict``: open-loop prediction error of the quasi-physical simulators against MuJoCo."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from quasisim.data.demo import load_demo
from quasisim.errors import QuasisimError
from quasisim.eval.tables import clips, header, prediction_summary, publish
from quasisim.method.config import TransferConfig
from quasisim.method.curriculum import Curriculum, load_curriculum
from quasisim.method.problem import kinematic_problem
from quasisim.method.replay import collect, prediction_errors, windows
from quasisim.runtime import free_compiled_programs


def _simulators(cur: Curriculum, sims: tuple[int, ...], mus: tuple[float, ...]) -> list[tuple[int, float]]:
    """(curriculum index, friction coefficient) pairs to compare; errors name the valid choices."""
    rigid = cur.rigid
    if sims:
        bad = [n for n in sims if n - 1 not in rigid]
        if bad:
            valid = ", ".join(str(i + 1) for i in rigid)
            raise QuasisimError(f"--sim {bad[0]}: not a rigid simulator of curriculum {cur.name!r}; valid: {valid}")
        rigid = [n - 1 for n in sims]
    if any(not (np.isfinite(m) and m > 0) for m in mus):
        raise QuasisimError(f"--mu: friction coefficients must be positive numbers, got {list(mus)}")
    return [(i, m) for i in rigid for m in (mus or (cur.mu,))]


def run_predict_bench(
    data_dir: Path, clip_names: tuple[str, ...], pattern: str, horizon: int, curriculum: str, hand_name: str,
    out: Path, sims: tuple[int, ...] = (), mus: tuple[float, ...] = (),
) -> str:  # fmt: skip
    """Open-loop ``horizon``-frame prediction error of the quasi-physical simulator against MuJoCo (no
    residual physics, nominal S) under the kinematic retarget's PD targets, for each rigid simulator of
    ``curriculum`` (or those numbered in ``sims``, 1-based), beside the zero-motion predictor; with ``mus``,
    each simulator once per friction coefficient instead of the curriculum's. See :mod:`quasisim.method.replay`."""
    cur = load_curriculum(curriculum)
    pairs = _simulators(cur, sims, mus)
    paths = clips(data_dir, pattern, clip_names)
    bud = TransferConfig.from_yaml().budget("fast")
    rows: list[dict[str, Any]] = []
    for p in tqdm(paths, desc="clips", unit="clip"):
        free_compiled_programs()
        demo = load_demo(p)
        prob, q_kin = kinematic_problem(demo, hand_name, bud.substeps, bud.n_candidates)
        params = {
            f"sim {i + 1} (d_c {100 * cur.stages[i].d_c:g} cm{f', mu {m:g}' if mus else ''})": prob.params(
                {**cur.contact(i), "mu": m}
            )
            for i, m in pairs
        }
        t0 = time.perf_counter()
        buf = collect(prob.scene, [q_kin], demo.fps)
        w = windows(prob.model, buf, [(0, t) for t in range(demo.n_frames - horizon)], horizon, prob.base_quat)
        for name, par in params.items():
            e = prediction_errors(prob.model, par, w, demo.fps, prob.base_quat)
            rows.append({"clip": p.stem, "simulator": name, **e.summary(), "wall_s": time.perf_counter() - t0})
    return publish(out, "predict", rows, _markdown(rows, horizon, hand_name))


def _markdown(rows: list[dict[str, Any]], horizon: int, hand: str) -> list[str]:
    lines = [
        header(f"{horizon}-frame prediction error against MuJoCo ({hand}, kinematic retarget's PD targets)"),
        f"Mean over clips and start frames, after {horizon} frames; zero-motion: the object stays where it was; "
        "diverged: windows whose prediction became non-finite (left out of the means).",
        "",
    ]
    return lines + prediction_summary(rows)
