"""Many clips at once: ``quasisim batch DATA_DIR --out DIR`` and the benchmark tables, on Ray.

Each clip is one Ray task (a :class:`Job`: one or more transfer runs of that clip). The driver ships the
demo and its mesh to the worker as bytes, the worker runs the transfers in a scratch folder (their
checkpoints live there, so a retried or resumed clip continues where it stopped) and returns the output
files as bytes; only the driver writes results: each clip's folder ``OUT/<clip>/`` appears at once (written
aside and renamed) with ``clip.json`` (the clip's metrics and settings, and the demo file it ran, relative to
the batch's data folder) in it, and ``OUT/batch.json`` / ``OUT/batch.md`` (per-clip rows, failures and the
summary table) are rewritten atomically after every clip.

- Resumable: a clip whose folder exists is never redone; a clip that was running when the batch was killed
  resumes from its checkpoints in the scratch folder (``OUT/.work/<clip>`` by default, on the node that runs
  it). That folder is removed only once the driver has stored the clip (:func:`remove_scratch`, on its node;
  ``keep_scratch`` keeps it): a clip whose result is lost before (its node lost, the driver stopped) or that
  fails with an error (its failure says so) keeps its checkpoints to resume from.
- A worker that dies (killed, out of memory) has its clip retried (``max_retries``); a clip that fails
  with an error is reported with it and the batch goes on.
- Local by default: a Ray of the batch's own with this machine's cores, whatever other Ray runs here;
  ``ray_address`` (``auto``: the cluster ``ray start`` made on this machine) runs the same tasks on an existing
  Ray cluster (its workers need quasisim installed; scratch paths are per node; a node that dies has its
  clips retried elsewhere). :mod:`quasisim.raycluster` finds and reaches Ray.
- Interrupted (Ctrl-C, SIGTERM), a local batch takes its Ray down with it; the same command resumes.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import json
import os
import resource
import shutil
import time
import traceback
from collections.abc import Generator, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from quasisim.errors import InputError, QuasisimError
from quasisim.files import LOCK, save_json_atomic, save_text_atomic
from quasisim.method.spec import TransferSpec

if TYPE_CHECKING:
    from quasisim.pipeline import PieceHook

CLIP_FILE = "clip.json"  # written last into a clip's folder: its metrics and what made them
BATCH_FILE = "batch.json"
SKIP_OUTPUT = ("checkpoints",)  # stays in the worker's scratch folder


class BatchHooks:
    """Where tests reach into a clip's run on its worker (:func:`run_job`) and into the driver taking the
    results (:func:`_run_group`); here every hook does nothing.

    A batch takes its hooks from :func:`run_batch`'s ``hooks`` (default: :data:`HOOKS`, which a test's
    driver process may replace before the batch starts) and carries them to the workers with each task, so a
    subclass must pickle: a class of a module that the workers can import."""

    def scratch(self, scratch: Path) -> Path:
        """The clip's scratch folder on this worker's node, given the batch's (``OUT/.work/<clip>``)."""
        return scratch

    def starting(self, clip: str) -> None:
        """Called as the clip starts on its worker, before anything of it is written."""

    def piece_hook(self, clip: str, scratch: Path) -> PieceHook | None:
        """``run_transfer``'s ``piece_hook`` for the clip (each checkpointed piece's name and computation
        go through it); None: none."""
        return None

    def waiting(self) -> None:
        """Called on the driver before it waits for the next clip's result (so before it stores any)."""


NO_HOOKS = BatchHooks()
HOOKS: BatchHooks = NO_HOOKS  # a batch's hooks where run_batch is given none


@dataclass(frozen=True)
class Run:
    """One transfer of a clip: ``name`` is its subfolder in the clip's folder ("" for the folder itself);
    ``seed_from`` names an earlier run of the same job whose checkpoints it starts from (``default+mpc``
    reuses the stages 1-2 of ``default``)."""

    name: str
    spec: TransferSpec
    seed_from: str | None = None

    def __post_init__(self) -> None:  # the method and stages resolved (a spec's None: its defaults)
        object.__setattr__(self, "spec", self.spec.checked())


@dataclass(frozen=True)
class Job:
    """The runs of one clip; ``data_dir``: the batch's data folder (None: the demo's folder)."""

    demo_path: Path
    runs: tuple[Run, ...]
    data_dir: Path | None = None

    @property
    def clip(self) -> str:
        return self.demo_path.stem

    @property
    def demo_file(self) -> str:
        """The demo file relative to ``data_dir`` (its name where it is not below it): ``clip.json``'s
        ``demo_file``, where ``export`` looks first (the demo's own name may differ from the file's)."""
        with contextlib.suppress(ValueError):
            if self.data_dir is not None:
                return self.demo_path.relative_to(self.data_dir).as_posix()
        return self.demo_path.name


@dataclass(frozen=True)
class Settings:
    """How the batch runs: Ray address (None: local), workers, threads per worker, scratch folder, config."""

    ray_address: str | None = None
    workers: int = 0  # 0: one per core
    threads: int = 0  # 0: cores // workers
    scratch: Path | None = None  # None: OUT/.work
    config_path: str | None = None
    overrides: dict[str, Any] = field(default_factory=dict)
    max_retries: int = 2
    keep_scratch: bool = False  # keep each clip's checkpoints (later runs of the same clip start from them)
    record_transitions: bool = False  # each run keeps what its sampling stage rolled out (RUN/transitions/)
    pin_cores: bool = True  # each worker on `threads` cores of its own (runtime.pin_to_free_cores)
    # a local batch of pinned workers runs its first clip alone on every core first (:func:`leads`), unless resumed
    lead_clip: bool = True

    def resolved(self) -> Settings:
        cores = os.cpu_count() or 1
        w = self.workers or cores
        return dataclasses.replace(self, workers=w, threads=self.threads or max(1, cores // w))


def identity(run: Run, s: Settings) -> dict[str, Any]:
    """What makes a run's results (recorded in its clip's ``clip.json``; a batch into the same OUT must
    match it), as JSON would give it back: the run, its spec, the config settings its stages read and, for a
    run with a stage in the quasi-physical simulator, the simulator's revision; ``judging``: the worlds its robust
    success was judged in (:func:`quasisim.eval.robust.judged_with`; checked apart, :func:`finished_runs`)."""
    from quasisim.eval.robust import judged_with
    from quasisim.method.stage import simulator_identity

    spec = run.spec.identity() | {"stages": _identity_stages(s, run.spec)}
    d = {"name": run.name, **spec, "seed_from": run.seed_from, "config_sha256": config_hash(s, run.spec)}
    d |= {"judging": judged_with(run.spec.robust_configs())}
    return json.loads(json.dumps(d | simulator_identity(run.spec.stages)))


@functools.cache
def _run_config(path: str | None, overrides: str, method: str) -> Any:
    """The transfer config of a run: the YAML at ``path`` (default the shipped one) with ``overrides`` (JSON) and
    its method's settings."""
    from quasisim.method.config import CONFIG_PATH, TransferConfig
    from quasisim.method.registry import METHODS

    return METHODS[method].config(TransferConfig.from_yaml(path or CONFIG_PATH, json.loads(overrides)))


@functools.cache
def _config_hash(path: str | None, overrides: str, budget: str, stages: tuple[str, ...], method: str) -> str:
    from quasisim.method.stage import declared_stages

    content = _run_config(path, overrides, method).identity(budget, declared_stages(stages))
    content.get("sampling", {}).pop("threads", None)
    return hashlib.sha256(json.dumps(content, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _identity_stages(s: Settings, spec: TransferSpec) -> list[str]:
    """``spec``'s stages as its identity records them (those idle with the run's config left out)."""
    from quasisim.method.stage import identity_stages

    cfg = _run_config(s.config_path, json.dumps(s.overrides, sort_keys=True), spec.method)
    return identity_stages(spec.stages, cfg)


def config_hash(s: Settings, spec: TransferSpec) -> str:
    """Hash of the config settings that determine ``spec``'s results (the YAML with the overrides applied;
    settings of stages the run does not have and rollout threads aside): adding a stage-3 setting does not
    invalidate a finished sample-target run."""
    return _config_hash(
        s.config_path, json.dumps(s.overrides, sort_keys=True), spec.budget, tuple(spec.stages), spec.method
    )


# ---- the worker's side -------------------------------------------------------------------------------


def pack_demo(demo_path: Path) -> dict[str, bytes]:
    """The demo file and its mesh as {relative path: bytes} (what a worker on another machine needs)."""
    import numpy as np

    from quasisim.data.demo import load_demo

    demo = load_demo(demo_path)  # validated here: a bad demo fails its clip before any work
    with np.load(demo_path, allow_pickle=False) as z:
        mesh_name = str(z["object_mesh"])
    return {demo_path.name: demo_path.read_bytes(), f"meshes/{mesh_name}": demo.object_mesh_path.read_bytes()}


def spread_objects(jobs: list[Job]) -> list[Job]:
    """``jobs`` reordered round-robin over their objects (every object's first clip, then every second clip,
    ...), keeping the order within an object. The first clip of an object builds its caches (convex
    decomposition, SDF grid, compiled programs); clips of one object started side by side would each build
    them (measured on the 25 GRAB clips, three per object in name order: see BENCHMARKS.md)."""
    groups: dict[str, list[Job]] = {}
    for j in jobs:
        groups.setdefault(_object_key(j.demo_path), []).append(j)
    rounds = max((len(g) for g in groups.values()), default=0)
    return [g[k] for k in range(rounds) for g in groups.values() if k < len(g)]


def _object_key(demo_path: Path) -> str:
    """The demo's object mesh name, or the file's path when it cannot be read (its clip fails later)."""
    import numpy as np

    try:
        with np.load(demo_path, allow_pickle=False) as z:
            return str(z["object_mesh"])
    except Exception:  # a broken demo is reported by its own clip
        return str(demo_path)


def _write_tree(root: Path, files: dict[str, bytes]) -> None:
    for rel, data in files.items():
        p = root / rel
        if not (p.is_file() and p.read_bytes() == data):
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_bytes(data)


def _read_tree(root: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(root)): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.relative_to(root).parts[0] not in SKIP_OUTPUT
    }


def _node() -> str:
    """The Ray node this worker runs on (its id; the host name outside Ray)."""
    import socket

    try:
        import ray

        return str(ray.get_runtime_context().get_node_id()) if ray.is_initialized() else socket.gethostname()
    except ImportError:
        return socket.gethostname()


def run_job(
    job: Job, files: dict[str, bytes], s: Settings, scratch: Path, hooks: BatchHooks = NO_HOOKS
) -> dict[str, Any]:
    """Run ``job``'s transfers in ``scratch`` (resumed from the checkpoints there); returns their output
    files ({run/relative path: bytes}), a result row per run, the worker's peak memory, its node and the
    scratch folder it used.

    The worker keeps ``scratch``: the driver has it removed on this node once it stored the clip
    (:func:`remove_scratch`), so a result lost on its way (the node lost, the driver stopped) leaves the
    checkpoints to resume from. A clip that fails with an error (for good: Ray retries a clip only when its
    worker dies) keeps them too, and its error says where (a note on the exception): the same command resumes
    it, an out-of-memory error in a late stage keeps the earlier stages."""
    from quasisim.runtime import configure, free_compiled_programs, pin_to_free_cores

    scratch = hooks.scratch(scratch)
    hooks.starting(job.clip)
    cores = pin_to_free_cores(s.threads) if s.pin_cores else None  # before JAX's CPU backend starts
    configure()
    free_compiled_programs()  # a worker runs clip after clip: keep below the kernel's mapping limit
    try:
        out_files, rows = _run_transfers(job, files, s, scratch, hooks.piece_hook(job.clip, scratch))
    except Exception as e:
        e.add_note(f"checkpoints kept in {scratch} on node {_node()}: the same command resumes the clip from them")
        raise
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return {"files": out_files, "rows": rows, "peak_rss_mb": peak_mb, "pid": os.getpid(), "cores": cores,
            "node": _node(), "scratch": str(scratch)}  # fmt: skip


def remove_scratch(scratch: str, s: Settings) -> None:
    """Remove a clip's scratch folder (unless ``s.keep_scratch``), on the node that holds it, once the driver
    has stored the clip (:class:`Removals`)."""
    if not s.keep_scratch:
        shutil.rmtree(scratch, ignore_errors=True)


def _run_transfers(
    job: Job, files: dict[str, bytes], s: Settings, scratch: Path, fault: PieceHook | None
) -> tuple[dict[str, bytes], list[dict[str, Any]]]:
    """:func:`run_job`'s transfers in ``scratch``: their output files and result rows."""
    from quasisim.method.config import CONFIG_PATH, TransferConfig
    from quasisim.pipeline import run_transfer

    cfg = TransferConfig.from_yaml(s.config_path or CONFIG_PATH, {"sampling.threads": s.threads, **s.overrides})
    _write_tree(scratch / "input", files)
    demo = scratch / "input" / job.demo_path.name
    out_files: dict[str, bytes] = {}
    rows = []
    for r in job.runs:
        run_dir = scratch / "runs" / (r.name or "_")
        ck = run_dir / "checkpoints"
        if r.seed_from is not None and not ck.is_dir():
            ck.mkdir(parents=True)
            for f in (scratch / "runs" / (r.seed_from or "_") / "checkpoints").glob("*.npz"):
                shutil.copy2(f, ck / f.name)
        # every checkpoint carries the identity of what made it: pieces made with other settings (an earlier
        # batch) are recomputed, the others reused, so the run's own record of its settings is not needed
        (ck / "run.json").unlink(missing_ok=True)
        # the batch runs one attempt of a clip at a time: a lock here is a killed attempt's, maybe on another host
        (run_dir / LOCK).unlink(missing_ok=True)
        record = run_dir / "transitions" if s.record_transitions and "sample" in r.spec.stages else None
        if record is not None and not any(record.glob("*.npz")):
            (ck / "sample.npz").unlink(missing_ok=True)  # a retried clip samples again, to record it
        t0 = time.perf_counter()
        spec = dataclasses.replace(r.spec, progress=False)
        res = run_transfer(demo, run_dir, spec, cfg, resume=ck.is_dir(), piece_hook=fault, record_transitions=record)
        rows.append({
            "clip": job.clip, "run": r.name or r.spec.method, "metrics": res.metrics,
            "kinematic_metrics": res.kinematic_metrics, "seconds": res.record.seconds,
            "wall_s": time.perf_counter() - t0,
        })  # fmt: skip
        prefix = f"{r.name}/" if r.name else ""
        out_files |= {prefix + k: v for k, v in _read_tree(run_dir).items()}
    return out_files, rows


# ---- the driver's side -------------------------------------------------------------------------------


@dataclass
class BatchResult:
    """Rows (one per clip and run), failures ({clip: error}), timing of a batch, per worker process
    ({pid: ...}) its peak memory and the cores it was pinned to (None: not pinned), and the node of each clip."""

    rows: list[dict[str, Any]]
    failures: dict[str, str]
    wall_s: float
    n_run: int
    workers: int
    peak_rss_mb: dict[str, float]
    cores: dict[str, list[int] | None] = field(default_factory=dict)
    lead: dict[str, Any] | None = None  # the clip run alone on every core first (:func:`leads`): clip, pid
    nodes: dict[str, str] = field(default_factory=dict)  # {clip: the Ray node it ran on}


def finished_runs(out: Path, job: Job, s: Settings, any_revision: bool = False) -> dict[str, dict[str, Any]]:
    """{run name: result row} of ``job``'s runs already in ``OUT/<clip>/clip.json``; an error when one of
    them was made with other settings (``any_revision``: made by any revision of the simulator, for reading
    back finished runs; a batch never extends them) or judged with other robust settings (the option named)."""
    from quasisim.eval.robust import judging_mismatch

    p = out / job.clip / CLIP_FILE
    if not p.is_file():
        return {}
    done = json.loads(p.read_text())["runs"]
    skip = {"judging", *(["simulator_revision"] if any_revision else [])}  # judging: checked apart (older: none)
    drop = lambda d: {k: v for k, v in d.items() if k not in skip}  # noqa: E731
    for r in job.runs:
        differs = r.name in done and judging_mismatch(
            done[r.name]["identity"], done[r.name]["row"], r.spec.robust_configs()
        )
        if differs:
            raise QuasisimError(
                f"{out / job.clip}: run {r.name or job.clip!r} was judged with other robust settings ({differs}; see "
                f"{p}); give the same, or use another --out"
            )
        if r.name in done and drop(done[r.name]["identity"]) != drop(identity(r, s)):
            raise QuasisimError(
                f"{out / job.clip}: run {r.name or job.clip!r} was made with other settings (see {p}); use another "
                "--out or remove that folder"
            )
    return {r.name: done[r.name]["row"] for r in job.runs if r.name in done}


def _check_clip_folder(final: Path) -> None:
    """:class:`InputError` where ``OUT/<clip>`` exists but is no clip folder of a batch (no ``clip.json``: another
    command's run folder, the user's): :func:`_persist` would replace it with the clip's results."""
    if (final.exists() or final.is_symlink()) and not (final / CLIP_FILE).is_file():
        got = "a file" if final.is_file() else "a symbolic link" if final.is_symlink() else "a folder"
        raise InputError(
            final, "--out", f"no file or folder of that name, or a clip folder of quasisim batch (with {CLIP_FILE}); "
            "move it away or choose another --out", f"{got} without {CLIP_FILE}",
        )  # fmt: skip


def _persist(out: Path, job: Job, s: Settings, result: dict[str, Any]) -> None:
    """Write a clip's folder as a whole, with the runs it held before: aside, then swapped into place."""
    final, tmp, old = out / job.clip, out / f".{job.clip}.incoming", out / f".{job.clip}.old"
    shutil.rmtree(tmp, ignore_errors=True)
    runs: dict[str, Any] = {}
    if (final / CLIP_FILE).is_file():
        shutil.copytree(final, tmp)
        runs = json.loads((final / CLIP_FILE).read_text())["runs"]
    _write_tree(tmp, result["files"])
    runs |= {r.name: {"identity": identity(r, s), "row": row} for r, row in zip(job.runs, result["rows"], strict=True)}
    save_json_atomic(tmp / CLIP_FILE, {"clip": job.clip, "demo_file": job.demo_file, "runs": runs})
    if final.exists():
        shutil.rmtree(old, ignore_errors=True)
        os.replace(final, old)
    os.replace(tmp, final)
    shutil.rmtree(old, ignore_errors=True)


def _ray_init(s: Settings) -> Any:
    """``ray`` for this batch: a local Ray of its own, or the cluster of ``s.ray_address``
    (:mod:`quasisim.raycluster`; a failure is one line naming the address)."""
    from quasisim.raycluster import connect, start_local

    # XLA has no flag for a thread count; one core per worker: Eigen's thread pool off (MuJoCo's threads are set apart)
    threads = f"--xla_cpu_multi_thread_eigen={'true' if s.threads > 1 else 'false'}"
    env = {"XLA_FLAGS": f"{os.environ.get('XLA_FLAGS', '')} {threads}".strip()}  # the driver's flags, kept
    if s.ray_address:
        return connect(s.ray_address, env, s.threads)
    return start_local(s.workers * s.threads, env)


def run_batch(
    jobs: list[Job], out: Path, s: Settings, on_clip: Any = None, hooks: BatchHooks | None = None
) -> BatchResult:
    """The runs of ``jobs`` not finished in ``out``, on Ray; ``on_clip(rows, failures)`` after each clip;
    ``hooks``: the workers' (tests; None: :data:`HOOKS`)."""
    s = s.resolved()
    out.mkdir(parents=True, exist_ok=True)
    scratch = (s.scratch or out / ".work").resolve()
    rows: list[dict[str, Any]] = []
    todo: list[Job] = []
    for j in jobs:
        done = finished_runs(out, j, s)
        rows += list(done.values())
        missing = tuple(r for r in j.runs if r.name not in done)
        if missing:
            _check_clip_folder(out / j.clip)
            todo.append(dataclasses.replace(j, runs=missing))
    if rows:  # resumed: its first part filled the persistent caches a lead clip would fill, and a lead clip holds
        s = dataclasses.replace(s, lead_clip=False)  # every core for one clip's whole run (docs/batch.md)
    failures: dict[str, str] = {}
    peak: dict[str, float] = {}
    cores: dict[str, list[int] | None] = {}
    nodes: dict[str, str] = {}
    t0 = time.perf_counter()
    lead = None
    # closed at once when the loop ends early (Ctrl-C, an error): a local Ray goes down with it
    with contextlib.closing(_dispatch(spread_objects(todo), s, scratch, HOOKS if hooks is None else hooks)) as results:
        for job, result in results:
            _take(job, result, out, s, (rows, failures, peak, cores, nodes))
            if isinstance(result, dict) and result.get("lead"):
                lead = {"clip": job.clip, "pid": result["pid"]}
            if on_clip is not None:
                on_clip(rows, failures)
    return BatchResult(rows, failures, time.perf_counter() - t0, len(todo), s.workers, peak, cores, lead, nodes)


def _take(job: Job, result: dict[str, Any] | str, out: Path, s: Settings, acc: tuple[Any, ...]) -> None:
    """One clip's result into the batch: its folder written (or its error kept) and its row, memory, cores
    and node added to ``acc`` (rows, failures, peak, cores, nodes)."""
    rows, failures, peak, cores, nodes = acc
    if isinstance(result, str):
        failures[job.clip] = result
        return
    _persist(out, job, s, result)  # its scratch folder is removed on its node after this (Removals)
    rows.extend(result["rows"])
    peak[str(result["pid"])] = result["peak_rss_mb"]
    cores[str(result["pid"])] = None if result["cores"] is None else list(result["cores"])
    nodes[job.clip] = result.get("node", "")  # "": a worker of an older quasisim


def leads(s: Settings, n_todo: int) -> bool:
    """Whether the batch runs its first clip alone on all ``workers x threads`` cores before the workers
    start: a local batch (``ray_address`` None) of several pinned workers and clips. Every later clip's
    compiled programs then come from the persistent caches that clip filled, and XLA compiles each program
    on every core instead of each worker compiling the same programs side by side on one core each
    (docs/history/benchmarks-2026-11-23-to-12-03.md, "The first clip alone on both cores").
    :func:`run_batch` turns it off for a resumed batch."""
    return s.lead_clip and s.ray_address is None and s.pin_cores and s.workers > 1 and n_todo > 1


def run_lead_job(
    job: Job, files: dict[str, bytes], s: Settings, scratch: Path, hooks: BatchHooks = NO_HOOKS
) -> dict[str, Any]:
    """:func:`run_job` for the lead clip (its own Ray function, so that its worker process, unpinned and
    with XLA's thread pool sized for every core, exits after it instead of running pinned clips)."""
    return {**run_job(job, files, s, scratch, hooks), "lead": True}


def _dispatch(
    todo: list[Job], s: Settings, scratch: Path, hooks: BatchHooks
) -> Iterator[tuple[Job, dict[str, Any] | str]]:
    """Yield (job, result or error text) as the workers finish, with a progress bar over clips; with
    :func:`leads`, the first readable clip runs alone on every core before the others are handed out."""
    from quasisim.raycluster import sigterm_interrupts

    if not todo:
        return
    with sigterm_interrupts():
        yield from _dispatch_on_ray(todo, s, scratch, hooks)


def _dispatch_on_ray(
    todo: list[Job], s: Settings, scratch: Path, hooks: BatchHooks
) -> Iterator[tuple[Job, dict[str, Any] | str]]:
    """:func:`_dispatch` once SIGTERM interrupts: Ray started or reached, the clips run, Ray shut down."""
    from tqdm import tqdm

    ray = _ray_init(s)
    try:
        task = ray.remote(num_cpus=s.threads, max_retries=s.max_retries)(run_job)
        rest, removals = list(todo), Removals(ray, s)
        with tqdm(total=len(todo), desc="clips", unit="clip", dynamic_ncols=True) as bar:
            if leads(s, len(todo)):
                cores = s.workers * s.threads  # the XLA flags (the compilation cache's key) stay the workers'
                lead = ray.remote(num_cpus=cores, max_retries=s.max_retries, max_calls=1)(run_lead_job)
                lead_s = dataclasses.replace(s, threads=cores)
                while rest:  # until one lead clip could be read and submitted
                    first, rest = rest[:1], rest[1:]
                    if (yield from _run_group(ray, lead, lead_s, first, scratch, bar, hooks, removals)):
                        break
            yield from _run_group(ray, task, s, rest, scratch, bar, hooks, removals)
        removals.wait()
    finally:
        ray.shutdown(wait_for_processes=not s.ray_address)  # a local Ray's processes are gone when it returns


class Removals:
    """The removal of each stored clip's scratch folder on its node (:func:`remove_scratch`): by the driver
    itself in a local batch (its node), by a task pinned to the clip's node on a cluster (a node that is gone
    keeps it: its disk went with it, or it is there to resume from should the clip run there again)."""

    def __init__(self, ray: Any, s: Settings) -> None:
        self.ray, self.s = ray, s
        self.tasks: list[Any] = []  # the removals' Ray tasks (a cluster's)
        self.fn = ray.remote(num_cpus=0, max_retries=0)(remove_scratch) if s.ray_address else None

    def stored(self, result: dict[str, Any]) -> None:
        """``result``'s clip is stored: remove its scratch folder (none named: a worker of an older quasisim)."""
        scratch = result.get("scratch")
        if self.s.keep_scratch or not scratch:
            return
        if self.fn is None:
            remove_scratch(scratch, self.s)
            return
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        where = NodeAffinitySchedulingStrategy(result["node"], soft=False)
        self.tasks.append(self.fn.options(scheduling_strategy=where).remote(scratch, self.s))

    def wait(self, timeout_s: float = 120.0) -> None:
        """Until the removals on the cluster's nodes ended (done or failed: a node lost), at most ``timeout_s``."""
        if self.tasks:
            self.ray.wait(self.tasks, num_returns=len(self.tasks), timeout=timeout_s)


def _run_group(
    ray: Any, fn: Any, s: Settings, jobs: list[Job], scratch: Path, bar: Any, hooks: BatchHooks, removals: Removals
) -> Generator[tuple[Job, dict[str, Any] | str], None, int]:
    """Submit ``jobs`` as tasks of the Ray function ``fn``, yield (job, result or error text) as they end
    (the caller stores each before it asks for the next: its scratch folder is removed then); returns how many
    were submitted (a demo that cannot be read is not)."""
    pending = {}
    for j in jobs:
        try:
            pending[fn.remote(j, pack_demo(j.demo_path), s, scratch / j.clip, hooks)] = j
        except QuasisimError as e:  # an unreadable demo fails its clip only
            bar.update(1)
            yield j, str(e)
    submitted = len(pending)
    while pending:
        hooks.waiting()
        ready, _ = ray.wait(list(pending), num_returns=1)
        job = pending.pop(ready[0])
        try:
            result = ray.get(ready[0])
        except Exception as e:  # one clip's failure is reported; the batch goes on
            yield job, _error_text(e)
            bar.set_postfix(failed=job.clip)
        else:
            yield job, result
            removals.stored(result)  # the caller stored it (an error there, an interrupt: kept)
        bar.update(1)
    return submitted


def _error_text(e: BaseException) -> str:
    """The clip's error in one line: a quasisim error's message, else the exception and its last frame; then
    its notes (the worker's: where the clip's checkpoints are kept)."""
    cause = getattr(e, "cause", None) or e
    notes = "".join(f"; {n}" for n in getattr(cause, "__notes__", ()))
    if isinstance(cause, QuasisimError):
        return f"{cause}{notes}"
    tb = traceback.extract_tb(cause.__traceback__)
    where = f" ({tb[-1].filename}:{tb[-1].lineno})" if tb else ""
    text = str(cause).strip().splitlines()
    return f"{type(cause).__name__}: {text[-1] if text else ''}{where}{notes}"


def write_batch_files(
    out: Path, result_rows: list[dict[str, Any]], failures: dict[str, str], meta: dict[str, Any]
) -> str:
    """``OUT/batch.json`` (rows, failures, settings) and ``OUT/batch.md`` (summary + per-clip table)."""
    from quasisim.eval.tables import CLIP_HEAD, SUMMARY_HEAD, clip_row, summary_rows

    first = {r["clip"]: r for r in reversed(result_rows)}  # the kinematic replay once per clip
    rows = [_flat(r, "kinematic") for r in first.values()] + [_flat(r, "method") for r in result_rows]
    lines = [
        f"# batch: {len(result_rows)} runs, {len(failures)} failed clip(s)", "",
        SUMMARY_HEAD.format(g="method"), *summary_rows(rows, "method"), "",
        CLIP_HEAD.format(g="method"), *[clip_row(r, "method") for r in sorted(rows, key=_order)], "",
        *([f"- failed: {c}: {e}" for c, e in sorted(failures.items())] or ["- no failures"]),
    ]  # fmt: skip
    save_json_atomic(out / BATCH_FILE, {**meta, "rows": result_rows, "failures": failures})
    text = "\n".join(lines) + "\n"
    save_text_atomic(out / "batch.md", text)
    return text


def _flat(r: dict[str, Any], which: str) -> dict[str, Any]:
    """A result row as a table row of the run (``method``) or of its kinematic replay."""
    m = r["metrics"] if which == "method" else r["kinematic_metrics"]
    name = r["run"] if which == "method" else "kinematic"
    wall = method_seconds(r["seconds"]) if which == "method" else r["seconds"].get("retarget", 0.0)
    return {"clip": r["clip"], "method": name, **m, "wall_s": wall, "lifted": lifted_as_demo(m)}


def lifted_as_demo(metrics: dict[str, Any]) -> bool:
    """Whether a run's object rose as the demo's did (``metrics.json``'s ``object_motion.lift_ok``: at least the
    set fraction of the demo's lift, or the demo barely lifts it); False for metrics without ``object_motion``."""
    return bool(metrics.get("object_motion", {}).get("lift_ok", False))


def run_batch_command(
    data_dir: Path, names: tuple[str, ...], pattern: str, spec: TransferSpec, out: Path, ray_address: str | None,
    workers: int, threads: int, config_path: Path | None, overrides: dict[str, Any], retries: int = 2,
    record_transitions: bool = False, lead_clip: bool = True,
) -> BatchResult:  # fmt: skip
    """``quasisim batch``: one run per clip into ``OUT/<clip>/``; prints the summary and the throughput;
    ``record_transitions``: each clip keeps what its sampling stage rolled out (``OUT/<clip>/transitions/``)."""
    from quasisim.assets.hand import load_hand
    from quasisim.eval.tables import clips
    from quasisim.method.config import CONFIG_PATH, TransferConfig
    from quasisim.method.curriculum import load_curriculum

    TransferConfig.from_yaml(config_path or CONFIG_PATH, overrides).budget(spec.budget)  # bad settings: fail now
    load_hand(spec.hand)  # so are a bad --hand and --curriculum (not an error in every clip)
    load_curriculum(spec.curriculum)
    paths = clips(data_dir, pattern, names)
    if not paths:
        raise QuasisimError(
            f"{data_dir}: expected clips matching --pattern {pattern!r} (*_long.npz only when the pattern names them), got none"
        )
    cfg_path = str(config_path) if config_path else None
    s = Settings(
        ray_address,
        workers,
        threads,
        None,
        cfg_path,
        overrides,
        max_retries=retries,
        record_transitions=record_transitions,
        lead_clip=lead_clip,
    ).resolved()
    jobs = [Job(p, (Run("", spec),), data_dir) for p in paths]
    meta = {"data_dir": str(data_dir), "spec": dataclasses.asdict(spec), "workers": s.workers, "threads": s.threads,
            "ray": ray_address or "local"}  # fmt: skip
    res = run_batch(jobs, out, s, lambda rows, fails: write_batch_files(out, rows, fails, meta))
    text = write_batch_files(out, res.rows, res.failures, {**meta, **throughput(res)})
    print(text)
    t = throughput(res)
    if res.n_run:
        where = f"on {t['nodes_used']} node(s) of the Ray cluster at {ray_address}" if ray_address else ""
        print(f"{res.n_run} clip(s) in {res.wall_s:.0f} s {where or f'with {s.workers} worker(s)'}: "
              f"{t['clips_per_hour']:.1f} clips/hour")  # fmt: skip
    print(f"wrote {out / BATCH_FILE}, {out / 'batch.md'} and one folder per clip")
    return res


def throughput(res: BatchResult) -> dict[str, Any]:
    """Clips per hour of the clips run now, and the workers' peak memory and cores."""
    return {
        "clips_run": res.n_run, "wall_s": res.wall_s,
        "clips_per_hour": 3600.0 * res.n_run / res.wall_s if res.n_run and res.wall_s > 0 else None,
        "peak_rss_mb_per_worker": res.peak_rss_mb, "cores_per_worker": res.cores, "lead_clip": res.lead,
        "node_per_clip": res.nodes, "nodes_used": len(set(res.nodes.values())),
    }  # fmt: skip


def seconds_keys() -> tuple[str, ...]:
    """The keys of a run's ``seconds`` (``summary.json``) that time its work: the retarget's, then each
    stage's :attr:`~quasisim.method.stage.Stage.word` in run order."""
    from quasisim.method.stage import declared_stages

    return ("retarget", *(st.word for st in declared_stages()))


def method_seconds(seconds: dict[str, float]) -> float:
    """A run's compute time from its stages' own timings (``summary.json`` ``seconds``, :func:`seconds_keys`;
    stages read back from checkpoints keep the time they took), so a resumed or seeded run counts what its
    result cost."""
    return float(sum(seconds.get(k, 0.0) for k in seconds_keys()))


def _order(r: dict[str, Any]) -> tuple[str, bool, str]:
    return r["clip"], r["method"] != "kinematic", r["method"]
