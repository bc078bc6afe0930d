"""``quasisim fit``: train the world model (:mod:`.world_model`) on the recorded transitions of many clips.

1. Every transitions file under the folder whose clip is not held out (:data:`~.transitions.HELD_OUT`, or
   ``held_out``) gives training pairs (:func:`~.world_model.teacher_forced` on its ``final`` and ``sampled``
   windows in the curriculum's stiffest simulator). Each clip's pairs are kept in ``<out>.parts/<clip>.npz``
   (written atomically, reused when the settings match), so an interrupted fit resumes, and clips run in
   ``workers`` processes.
2. The correction network is trained on all pairs (:func:`~.world_model.train`) and written to ``out`` with
   what it was trained on.
"""

from __future__ import annotations

import concurrent.futures as cf
import hashlib
import json
import multiprocessing
import time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from quasisim.errors import QuasisimError
from quasisim.files import save_npz_atomic
from quasisim.method.transitions import HELD_OUT, clip_problem, load_clip, read_meta, transition_files
from quasisim.method.world_model import Features, WorldModel, WorldModelConfig, init_correction, teacher_forced, train
from quasisim.sim.build import SIMULATOR_REVISION

# the fast budget's stiffest simulator (its revision keys the kept training pairs and is recorded in the file)
SIMULATOR = {"curriculum": "default", "substeps": 20, "n_candidates": 128, "revision": SIMULATOR_REVISION}


def stiffest_params(prob: Any, curriculum: str = SIMULATOR["curriculum"]) -> Any:
    """The nominal stiffest simulator of ``curriculum`` for a clip's problem."""
    from quasisim.method.curriculum import load_curriculum

    cur = load_curriculum(curriculum)
    return prob.params(cur.contact(cur.stiffest))


def _part_key(path: Path, cfg: WorldModelConfig) -> str:
    st = path.stat()
    region = {k: getattr(cfg, k) for k in ("n_object", "n_hand", "radius", "per_step", "seed")}
    blob = json.dumps([str(path.resolve()), st.st_size, st.st_mtime_ns, region, SIMULATOR], sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def clip_pairs(path: Path, data_dir: Path, cfg: WorldModelConfig, parts: Path) -> Path:
    """The training pairs of one transitions file, from ``parts`` when already made with these settings."""
    demo, *_ = read_meta(path)
    out = parts / f"{demo}.{path.stem.split('.')[-1]}.npz"
    key = _part_key(path, cfg)
    if out.is_file():
        with np.load(out) as z:
            if str(z["key"]) == key:
                return out
    prob = clip_problem(path, data_dir, SIMULATOR["substeps"], SIMULATOR["n_candidates"])
    params = stiffest_params(prob)
    got = [teacher_forced(params, load_clip(path, prob, kind, per_step=cfg.per_step, seed=cfg.seed), cfg)
           for kind in ("final", "sampled")]  # fmt: skip
    cat = lambda k: np.concatenate([getattr(f, k) for f, _ in got])  # noqa: E731
    return save_npz_atomic(
        out, key=np.array(key), feats=cat("feats").astype(np.float32), kinds=cat("kinds"), mask=cat("mask"),
        extra=cat("extra").astype(np.float32), target=np.concatenate([y for _, y in got]).astype(np.float32),
    )  # fmt: skip


def _worker(args: tuple[Path, Path, WorldModelConfig, Path]) -> Path:
    return clip_pairs(*args)


def fit_world_model(
    folder: Path, data_dir: Path, out: Path, cfg: WorldModelConfig, held_out: tuple[str, ...] = HELD_OUT,
    workers: int = 1,
) -> WorldModel:  # fmt: skip
    """Steps 1-2 of the module docstring; returns the saved model."""
    meta = {f: read_meta(f)[:2] for f in transition_files(folder)}  # (demo, hand) of each file
    files = [f for f, (demo, _) in meta.items() if demo not in held_out]
    if not files:
        raise QuasisimError(f"{folder}: every recorded clip is held out ({', '.join(held_out)}); nothing to train on")
    hands = sorted({meta[f][1] for f in files})
    if len(hands) > 1:
        raise QuasisimError(f"{folder}: transitions of several hands ({', '.join(hands)}); one world model per hand")
    parts = out.with_name(out.name + ".parts")
    parts.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    jobs = [(f, data_dir, cfg, parts) for f in files]
    if workers > 1:
        ctx = multiprocessing.get_context("spawn")
        with cf.ProcessPoolExecutor(workers, mp_context=ctx) as pool:
            done = list(tqdm(pool.map(_worker, jobs), total=len(jobs), desc="training pairs", unit="clip"))
    else:
        done = [_worker(j) for j in tqdm(jobs, desc="training pairs", unit="clip")]
    t_pairs = time.perf_counter() - t0
    arrays = [dict(np.load(p)) for p in done]
    cat = lambda k: np.concatenate([a[k] for a in arrays])  # noqa: E731
    data = Features(cat("feats"), cat("kinds"), cat("mask"), cat("extra"))
    target = cat("target")
    bar = tqdm(total=cfg.steps, desc="world model", unit="step")

    def progress(i: int, loss: float) -> None:
        bar.n = i
        bar.set_postfix(loss=f"{loss:.3f}")
        bar.refresh()

    t1 = time.perf_counter()
    net, losses = train(init_correction(cfg, data.extra, target), data, target, cfg, progress)
    bar.close()
    info = {
        "hand": hands[0], "simulator": SIMULATOR, "trained_on": sorted({meta[f][0] for f in files}),
        "transition_files": [str(f.relative_to(folder)) for f in files], "held_out": list(held_out),
        "n_pairs": len(target), "losses": losses, "pairs_s": round(t_pairs, 1),
        "train_s": round(time.perf_counter() - t1, 1),
    }  # fmt: skip
    model = WorldModel(net, cfg, info)
    model.save(out)
    return model
