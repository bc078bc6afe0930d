"""``quasisim batch``: many clips on local Ray workers, resumable, failures reported, a killed worker's clip
retried, results identical to a single transfer."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from batch_hooks import DRIVER, ScriptedHooks, pythonpath
from quasisim.batch import Job, Run, Settings, run_batch, spread_objects
from quasisim.errors import QuasisimError
from quasisim.method.spec import TransferSpec

pytest.importorskip("ray", reason="Ray is installed with the 'cluster' extra (make setup installs it)")

SPEC = TransferSpec(method="sample-target", render=False, progress=False)
FAST = {"sampling.samples": 4, "sampling.horizon": 3, "sampling.backtrack": 0}  # no back-ups: a step per frame


@pytest.fixture(scope="module")
def clips_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two short synthetic clips and a broken one."""
    from quasisim.data.synthetic import EXAMPLES, write_example

    d = tmp_path_factory.mktemp("batch_clips")
    for name in EXAMPLES:
        write_example(name, d, n_frames=12)
    (d / "broken.npz").write_bytes(b"not an npz archive")
    return d


def _jobs(d: Path) -> list[Job]:
    return [Job(p, (Run("", SPEC),)) for p in sorted(d.glob("*.npz"))]


def _batch_cli(clips_dir: Path, out: Path, *extra: str, fault: str = "") -> subprocess.CompletedProcess:
    """``quasisim batch`` in a subprocess (Ray's in-process core worker stays out of the test process);
    ``fault``: the first attempt of that clip kills its worker (:class:`batch_hooks.ScriptedHooks`)."""
    env = {**os.environ, "PYTHONPATH": pythonpath()}
    sets = [a for k, v in FAST.items() for a in ("--set", f"{k}={v}")]
    cli = (
        [sys.executable, str(DRIVER), ScriptedHooks(fault=fault).to_json()]
        if fault
        else [sys.executable, "-m", "quasisim.cli"]
    )
    cmd = [*cli, "batch", str(clips_dir), "--out", str(out), "--method", "sample-target",
           "--workers", "2", "--threads", "1", *sets, *extra]  # fmt: skip
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)


@pytest.mark.slow  # three Ray batches in subprocesses (~50 s cold)
def test_batch_runs_resumes_reports_failures_and_retries(clips_dir: Path, tmp_path: Path) -> None:
    from quasisim.method.config import TransferConfig
    from quasisim.pipeline import run_transfer

    out = tmp_path / "out"
    good = sorted(p.stem for p in clips_dir.glob("*.npz") if p.stem != "broken")
    # the first attempt of this clip kills its worker; every clip keeps what its sampling rolled out
    r = _batch_cli(clips_dir, out, "--record-transitions", fault=good[0])
    assert r.returncode == 0, r.stderr[-2000:]
    res = json.loads((out / "batch.json").read_text())
    assert sorted(row["clip"] for row in res["rows"]) == good
    assert list(res["failures"]) == ["broken"] and "broken.npz" in res["failures"]["broken"]
    assert not (out / ".work" / good[0]).exists()  # scratch removed once the clip is persisted
    # the first readable clip (round-robin over objects) ran alone on every core, in a process of its own that ended
    # after it; each later worker that could pin itself (a parallel test may hold the cores) runs on one core
    lead = res["lead_clip"]
    assert lead["clip"] == next(j.clip for j in spread_objects(_jobs(clips_dir)) if j.clip != "broken")
    workers = {pid: c for pid, c in res["cores_per_worker"].items() if pid != str(lead["pid"])}
    assert len(workers) == len(res["cores_per_worker"]) - 1 and workers  # the lead's process ran no other clip
    pinned = [set(c) for c in workers.values() if c is not None]
    assert all(len(c) == 1 for c in pinned) and len(set().union(*pinned)) == len(pinned)
    for c in good:
        d = json.loads((out / c / "clip.json").read_text())
        assert d["runs"][""]["row"]["metrics"] == json.loads((out / c / "metrics.json").read_text())
        assert (out / c / "controls.npz").is_file() and not (out / c / "checkpoints").exists()
        with np.load(out / c / "transitions" / f"{c}.sample-target.npz") as z, np.load(out / c / "controls.npz") as ctl:
            np.testing.assert_array_equal(z["applied"], ctl["q_targets"])
            assert z["windows"].shape[:2] == (11, FAST["sampling.samples"])  # 12 frames: 11 sampling steps

    # each clip transferred alone, in this process (sampling threads 2): bit-identical controls, the clip whose
    # worker was killed in its middle (after its first checkpointed piece) and retried included
    cfg = TransferConfig.from_yaml(overrides=FAST)
    for c in good[:2]:
        single = run_transfer(clips_dir / f"{c}.npz", tmp_path / f"single_{c}", SPEC, cfg)
        with np.load(out / c / "controls.npz") as z:
            np.testing.assert_array_equal(z["q_targets"], single.controls.q_targets, err_msg=c)

    # resumed: finished clips are not redone (files untouched), the broken clip is tried and reported again
    stamp = (out / good[0] / "controls.npz").stat().st_mtime_ns
    assert _batch_cli(clips_dir, out).returncode == 0
    again = json.loads((out / "batch.json").read_text())
    assert again["clips_run"] == 1 and list(again["failures"]) == ["broken"]
    assert (out / good[0] / "controls.npz").stat().st_mtime_ns == stamp
    assert sorted(row["clip"] for row in again["rows"]) == good

    # without retries the injected kill is a failure of that clip alone: the retry above was real
    r = _batch_cli(clips_dir, tmp_path / "no_retry", "--clips", good[0], "--retries", "0", fault=good[0])
    dead = json.loads((tmp_path / "no_retry" / "batch.json").read_text())
    assert r.returncode == 0 and list(dead["failures"]) == [good[0]] and not dead["rows"]


def _stub_transfer(monkeypatch: pytest.MonkeyPatch, fail: set[str], seen: list[tuple[str, bool, bool]]) -> None:
    """``run_transfer`` replaced by a stand-in that writes a checkpoint and an output, then returns or (for the
    clips in ``fail``) raises; it records (clip, resume, whether the checkpoint was there when it started)."""
    from types import SimpleNamespace

    import quasisim.pipeline

    def transfer(demo: Path, run_dir: Path, spec: TransferSpec, cfg: Any, resume: bool = False, **kw: Any) -> Any:
        assert demo.is_file() and demo.parent == run_dir.parents[1] / "input"
        piece = run_dir / "checkpoints" / "kinematic.npz"
        seen.append((demo.stem, resume, piece.is_file()))
        piece.parent.mkdir(parents=True, exist_ok=True)
        piece.write_bytes(b"piece")
        (run_dir / "controls.npz").write_bytes(b"controls")
        if demo.stem in fail:
            raise RuntimeError("the transfer failed")
        return SimpleNamespace(metrics={"ok": 1}, kinematic_metrics={}, record=SimpleNamespace(seconds={}))

    monkeypatch.setattr(quasisim.pipeline, "run_transfer", transfer)


def test_a_worker_keeps_its_clips_checkpoints_for_the_driver_and_after_an_error(
    clips_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The worker's side of a clip (run_job, here in this process; the transfer a stand-in that writes a
    checkpoint and an output, then returns or fails): its scratch folder (the demo, the checkpoints) is still
    there when run_job returns the clip's outputs (the driver has them on disk only later: it removes the
    folder then, :func:`quasisim.batch.remove_scratch`) and when run_job raises the clip's error, which then
    names the folder kept; keep_scratch keeps it after the driver stored the clip too (bench transfer's later
    runs start from it)."""
    import quasisim.batch as qb
    from quasisim.batch import pack_demo, run_job

    fail: set[str] = set()
    _stub_transfer(monkeypatch, fail, [])
    job = Job(clips_dir / "cube_lift.npz", (Run("", SPEC),))
    files, s = pack_demo(job.demo_path), Settings(workers=1, threads=1, pin_cores=False)
    scratch = tmp_path / ".work" / job.clip
    piece = scratch / "runs" / "_" / "checkpoints" / "kinematic.npz"
    res = run_job(job, files, s, scratch)
    assert res["files"] == {"controls.npz": b"controls"} and res["rows"][0]["metrics"] == {"ok": 1}
    assert piece.is_file() and res["scratch"] == str(scratch)  # kept until the driver stored the clip
    qb.remove_scratch(res["scratch"], s)
    assert not scratch.exists()
    fail.add(job.clip)
    with pytest.raises(RuntimeError, match="the transfer failed") as e:  # an error is final (Ray retries dead workers)
        run_job(job, files, s, scratch)
    assert piece.is_file()  # kept: the same command resumes the clip from it
    assert f"checkpoints kept in {scratch}" in "".join(getattr(e.value, "__notes__", [])), e.value
    fail.clear()
    res = run_job(job, files, dataclasses.replace(s, keep_scratch=True), scratch)
    qb.remove_scratch(res["scratch"], dataclasses.replace(s, keep_scratch=True))
    assert piece.is_file() and (scratch / "input" / "cube_lift.npz").is_file()


class _Ref:
    def __init__(self, result: dict[str, Any] | Exception) -> None:
        self.result = result


class _FakeRay:
    """``ray`` for run_batch without Ray: records each task (its function, clip, Ray options and the threads
    it is given) and answers it at once with a result as a worker's, its pid the task's number; with ``run``,
    runs the task's function here instead (its error raised by ``get``)."""

    def __init__(self, run: bool = False) -> None:
        self.tasks: list[tuple[str, str, dict[str, Any], int]] = []
        self.run = run

    def remote(self, **options: Any) -> Any:
        def wrap(fn: Any) -> Any:
            def submit(job: Job, files: dict[str, bytes], s: Settings, scratch: Path, hooks: Any) -> _Ref:
                self.tasks.append((fn.__name__, job.clip, options, s.threads))
                if self.run:
                    try:
                        return _Ref(fn(job, files, s, scratch, hooks))
                    except Exception as e:
                        return _Ref(e)
                row = {"clip": job.clip, "run": "sample-target", "metrics": {}, "kinematic_metrics": {}, "seconds": {}}
                return _Ref({"files": {}, "rows": [row], "peak_rss_mb": 1.0, "pid": len(self.tasks), "cores": None,
                             "node": "n", **({"lead": True} if fn.__name__ == "run_lead_job" else {})})  # fmt: skip

            return type("RemoteFunction", (), {"remote": staticmethod(submit)})

        return wrap

    def wait(self, refs: list[_Ref], num_returns: int = 1) -> tuple[list[_Ref], list[_Ref]]:
        return refs[:1], refs[1:]

    def get(self, ref: _Ref) -> dict[str, Any]:
        if isinstance(ref.result, Exception):
            raise ref.result
        return ref.result

    def shutdown(self, **kwargs: Any) -> None:
        pass


def test_the_driver_removes_a_clips_checkpoints_once_it_stored_the_clip(
    clips_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """run_batch with Ray a stand-in that runs each task here (run_job, its transfer a stand-in that writes a
    checkpoint): a driver interrupted (Ctrl-C) after a clip's worker returned and before it stored the clip
    leaves the clip's checkpoints where the worker left them, and the same batch again resumes the clip from
    them; once the driver stored the clip (its clip.json), the clip's scratch folder is gone. A clip that fails
    with an error keeps its checkpoints (an out-of-memory error in a late stage keeps the earlier stages) and
    its failure in batch.json says where."""
    import quasisim.batch

    seen: list[tuple[str, bool, bool]] = []
    _stub_transfer(monkeypatch, {"cylinder_lift_turn"}, seen)
    monkeypatch.setattr(quasisim.batch, "_ray_init", lambda s: _FakeRay(run=True))
    persist = quasisim.batch._persist

    def interrupted(*args: Any) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(quasisim.batch, "_persist", interrupted)
    out, s = tmp_path / "out", Settings(workers=1, threads=1, pin_cores=False, overrides=FAST)
    jobs = [j for j in _jobs(clips_dir) if j.clip != "broken"]
    assert [j.clip for j in jobs] == ["cube_lift", "cylinder_lift_turn"]
    with pytest.raises(KeyboardInterrupt):
        run_batch(jobs[:1], out, s)
    work = (out / ".work").resolve()
    assert seen == [("cube_lift", False, False)] and not (out / "cube_lift").exists()
    assert (work / "cube_lift" / "runs" / "_" / "checkpoints" / "kinematic.npz").is_file()  # kept: not stored yet
    monkeypatch.setattr(quasisim.batch, "_persist", persist)
    res = run_batch(jobs, out, s)
    assert seen[1:] == [("cube_lift", True, True), ("cylinder_lift_turn", False, False)]  # resumed from the checkpoint
    assert (out / "cube_lift" / "clip.json").is_file() and not (work / "cube_lift").exists()
    assert (work / "cylinder_lift_turn" / "runs" / "_" / "checkpoints" / "kinematic.npz").is_file()
    err = res.failures["cylinder_lift_turn"]
    assert err.startswith("RuntimeError: the transfer failed"), err
    assert f"checkpoints kept in {work / 'cylinder_lift_turn'} on node " in err, err


def test_export_finds_a_renamed_clips_demo_as_the_file_its_batch_ran(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`quasisim example`, its demo renamed to a.npz (inside it the demo is still named cube_lift), `quasisim
    batch` on that folder (its Ray a stand-in that runs the clip here) and `quasisim export` of the batch: the
    clip's clip.json records the file the batch ran, relative to the batch's data_dir, and export finds the
    demo there (no cube_lift.npz anywhere it searches)."""
    from click.testing import CliRunner

    import quasisim.batch
    import quasisim.runtime
    from quasisim.cli import main

    def cli(*args: Any) -> Any:
        r = CliRunner().invoke(main, [str(a) for a in args])
        assert r.exit_code == 0, r.output
        return r

    data, out = tmp_path / "data", tmp_path / "out"
    cli("example", "--out", data, "--name", "cube_lift", "--frames", "12")
    (data / "cube_lift.npz").rename(data / "a.npz")
    monkeypatch.setenv("QUASISIM_DATA", str(tmp_path / "nothing"))
    monkeypatch.setattr(quasisim.batch, "_ray_init", lambda s: _FakeRay(run=True))
    monkeypatch.setattr(quasisim.runtime, "pin_to_free_cores", lambda n: None)  # the clip runs in this process
    cli("batch", data, "--out", out, "--method", "kinematic", "--robust", "0", "--workers", "1", "--threads", "1")
    r = cli("export", out, "--out", tmp_path / "a.hdf5")
    assert (tmp_path / "a.hdf5").is_file(), r.output
    assert json.loads((out / "a" / "clip.json").read_text())["demo_file"] == "a.npz"


def test_only_a_local_batch_of_pinned_workers_leads_with_one_clip(
    clips_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """What run_batch hands to Ray (a stand-in here, no Ray): a local batch of 2 pinned workers of 1 thread
    runs its first readable clip (broken.npz, first in order, cannot be read) alone, as the lead task on both
    cores with 2 threads, in a process that ends after it, then the other clip as an ordinary task; a batch on a
    cluster, of unpinned workers, of one worker, with --no-lead-clip, of one clip or resumed (a clip finished
    in its folder) has no lead."""
    import quasisim.batch

    def tasks(jobs: list[Job], **settings: Any) -> list[tuple[str, str, dict[str, Any], int]]:
        fake = _FakeRay()
        monkeypatch.setattr(quasisim.batch, "_ray_init", lambda s: fake)
        s = Settings(**{"workers": 2, "threads": 1, "overrides": FAST, **settings})
        res = run_batch(jobs, tmp_path / f"out{len(list(tmp_path.iterdir()))}", s)
        assert list(res.failures) == (["broken"] if len(jobs) == 3 else []) and len(res.rows) == len(fake.tasks)
        assert res.lead == ({"clip": fake.tasks[0][1], "pid": 1} if fake.tasks[0][0] == "run_lead_job" else None)
        return fake.tasks

    jobs = _jobs(clips_dir)
    assert [j.clip for j in jobs] == ["broken", "cube_lift", "cylinder_lift_turn"]
    assert tasks(jobs) == [
        ("run_lead_job", "cube_lift", {"num_cpus": 2, "max_retries": 2, "max_calls": 1}, 2),
        ("run_job", "cylinder_lift_turn", {"num_cpus": 1, "max_retries": 2}, 1),
    ]
    plain = [("run_job", c, {"num_cpus": 1, "max_retries": 2}, 1) for c in ("cube_lift", "cylinder_lift_turn")]
    assert tasks(jobs, ray_address="127.0.0.1:6379") == plain
    assert tasks(jobs, pin_cores=False) == plain
    assert tasks(jobs, lead_clip=False) == plain
    assert tasks(jobs, workers=1) == plain
    assert tasks(jobs[1:2]) == plain[:1]
    fake, out = _FakeRay(), tmp_path / "resumed"
    monkeypatch.setattr(quasisim.batch, "_ray_init", lambda s: fake)
    s = Settings(workers=2, threads=1, overrides=FAST)
    run_batch(jobs[1:2], out, s)
    res = run_batch(jobs, out, s)  # resumed with cube_lift finished: the clips left run as ordinary tasks
    assert fake.tasks == [plain[0], plain[1]] and res.lead is None and len(res.rows) == 2


def test_batch_refuses_results_of_other_settings(clips_dir: Path, tmp_path: Path) -> None:
    from quasisim.batch import _persist

    job = _jobs(clips_dir)[0]
    _persist(tmp_path, job, Settings(overrides=FAST), {"files": {"controls.npz": b"x"}, "rows": [{"clip": job.clip}]})
    with pytest.raises(QuasisimError, match="other settings"):
        run_batch([job], tmp_path, Settings(overrides={"sampling.samples": 8}))


def test_a_batch_never_replaces_a_clip_folder_it_did_not_write(
    clips_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """OUT/<clip> without clip.json (a `quasisim transfer` folder, a folder or file of the user's) would be
    replaced by the clip's results: refused before any clip runs, naming it and --out, and left as it was (Ray a
    stand-in)."""
    import quasisim.batch
    from quasisim.errors import InputError

    fake = _FakeRay()
    monkeypatch.setattr(quasisim.batch, "_ray_init", lambda s: fake)
    out, s = tmp_path / "out", Settings(workers=1, threads=1, pin_cores=False, overrides=FAST)
    (out / "cube_lift").mkdir(parents=True)
    (out / "cube_lift" / "notes.txt").write_text("mine")
    jobs = [j for j in _jobs(clips_dir) if j.clip == "cube_lift"]
    with pytest.raises(InputError, match="--out") as e:
        run_batch(jobs, out, s)
    assert str(out / "cube_lift") in str(e.value) and "clip.json" in str(e.value) and fake.tasks == []
    assert [p.name for p in (out / "cube_lift").iterdir()] == ["notes.txt"]
    (out / "cube_lift" / "notes.txt").unlink()
    (out / "cube_lift").rmdir()
    (out / "cube_lift").write_text("mine")
    with pytest.raises(InputError, match="--out"):
        run_batch(jobs, out, s)
    assert (out / "cube_lift").read_text() == "mine" and fake.tasks == []


def test_bench_batch_never_removes_a_layout_folder_it_did_not_write(
    clips_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """bench batch starts each layout from scratch, removing OUT/<layout> (w1t1, ...) of an earlier bench batch;
    a folder of that name holding anything a batch does not write is refused before any layout runs (naming it
    and --out) and left as it was (the layouts' batches a stand-in here)."""
    import shutil

    import quasisim.bench.batch as bb
    from quasisim.errors import InputError

    ran: list[Path] = []

    def layout(jobs: list[Job], d: Path, lay: Any, overrides: dict[str, Any]) -> Any:
        ran.append(d)
        raise RuntimeError("stop here")

    monkeypatch.setattr(bb, "_run_layout", layout)
    out = tmp_path / "out"
    earlier = out / "w1t1"  # an earlier bench batch's first layout: its scratch, cache and a stored clip
    (earlier / ".work").mkdir(parents=True)
    (earlier / ".cache").mkdir()
    (earlier / "cube_lift").mkdir()
    (earlier / "cube_lift" / "clip.json").write_text("{}")
    (out / "w2t1").mkdir()
    (out / "w2t1" / "notes.txt").write_text("mine")
    lays = (bb.Layout(1, 1), bb.Layout(2, 1))
    with pytest.raises(InputError, match="--out") as e:
        bb.run_batch_bench(clips_dir, ("cube_lift",), "*.npz", SPEC, lays, out, {})
    assert str(out / "w2t1") in str(e.value) and "notes.txt" in str(e.value) and ran == []
    assert (out / "w2t1" / "notes.txt").read_text() == "mine" and (earlier / "cube_lift" / "clip.json").is_file()
    shutil.rmtree(out / "w2t1")
    with pytest.raises(RuntimeError, match="stop here"):
        bb.run_batch_bench(clips_dir, ("cube_lift",), "*.npz", SPEC, lays, out, {})
    assert ran == [earlier] and not (earlier / "cube_lift").exists()  # an earlier bench batch's: started afresh


def test_runs_in_the_simulator_name_its_revision(
    clips_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A run with a stage in the quasi-physical simulator records the simulator's revision: a batch with a
    changed simulator refuses its finished clips, reading them back (--report-only) does not; sample-target
    and the kinematic replay do not depend on it."""
    import quasisim.sim.build
    from quasisim.batch import _persist, finished_runs, identity
    from quasisim.method.spec import TransferSpec

    ours = Run("default", TransferSpec(stages=("1", "2", "sample", "select")))
    st = Run("sample-target", TransferSpec(method="sample-target", stages=("sample",)))
    s = Settings(overrides=FAST)
    assert identity(ours, s)["simulator_revision"] == quasisim.sim.build.SIMULATOR_REVISION
    assert "simulator_revision" not in identity(st, s)
    before, rev = identity(ours, s), quasisim.sim.build.SIMULATOR_REVISION
    monkeypatch.setattr(quasisim.sim.build, "SIMULATOR_REVISION", rev + 1)
    assert identity(ours, s) != before and identity(st, s) == identity(st, s)
    job = Job(sorted(clips_dir.glob("*.npz"))[0], (ours,))
    monkeypatch.setattr(quasisim.sim.build, "SIMULATOR_REVISION", rev - 1)
    _persist(tmp_path, job, s, {"files": {}, "rows": [{"clip": job.clip, "method": "x"}]})  # an older revision's
    monkeypatch.undo()
    with pytest.raises(QuasisimError, match="other settings"):
        finished_runs(tmp_path, job, s)
    assert finished_runs(tmp_path, job, s, any_revision=True) == {"default": {"clip": job.clip, "method": "x"}}
    with pytest.raises(QuasisimError, match="other settings"):  # and other settings are still refused
        finished_runs(tmp_path, job, Settings(overrides={"sampling.samples": 8}), any_revision=True)


def test_cli_batch_bad_option_is_one_line(tmp_path: Path) -> None:
    from click.testing import CliRunner

    from quasisim.cli import main

    r = CliRunner().invoke(main, ["batch", str(tmp_path), "--out", str(tmp_path / "o"), "--stages", "9"])
    assert r.exit_code == 2 and "valid stages" in r.output


def test_bench_batch_layouts_parse_and_refuse_bad_ones(tmp_path: Path) -> None:
    from click.testing import CliRunner

    from quasisim.bench.batch import Layout
    from quasisim.cli import main
    from quasisim.cli.bench import _layout

    assert _layout("2x1") == Layout(2, 1, True) and _layout("2x1-unpinned") == Layout(2, 1, False)
    # a cluster of 2 nodes of 1 CPU, and one node of 2 CPUs: two workers of one thread either way
    assert _layout("cluster:2x1") == Layout(2, 1, True, nodes=2) and _layout("cluster:1x2") == Layout(2, 1, True, 1)
    assert [_layout(x).folder for x in ("2x1", "2x1-unpinned", "cluster:2x1")] == ["w2t1", "w2t1u", "n2c1"]
    for bad in ("2x1-pinned", "2", "0x1", "axb", "cluster:2x1-unpinned", "nodes:2x1", "cluster:0x1"):
        r = CliRunner().invoke(main, ["bench", "batch", str(tmp_path), "--layouts", bad, "--out", str(tmp_path / "o")])
        assert r.exit_code != 0 and "WORKERSxTHREADS[-unpinned] or cluster:NODESxCPUS" in r.output, (bad, r.output)


def test_clips_of_one_object_are_spread_apart(tmp_path: Path) -> None:
    """Round-robin over objects, order kept within an object; an unreadable demo is its own group."""
    from quasisim.batch import spread_objects

    names = {
        "a1": "apple.obj",
        "a2": "apple.obj",
        "a3": "apple.obj",
        "b1": "ball.obj",
        "b2": "ball.obj",
        "c1": "cup.obj",
    }
    for clip, mesh in names.items():
        np.savez(tmp_path / f"{clip}.npz", object_mesh=np.array(mesh))
    (tmp_path / "zz.npz").write_bytes(b"broken")
    jobs = [Job(tmp_path / f"{c}.npz", ()) for c in [*names, "zz"]]
    assert [j.clip for j in spread_objects(jobs)] == ["a1", "b1", "c1", "zz", "a2", "b2", "a3"]


def test_bench_batch_cluster_layouts_start_run_on_and_stop_their_cluster_stand_in(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """No Ray and no cluster here: LocalCluster and run_batch are stand-ins that record their calls.
    cluster:NODESxCPUS asks for that cluster (LocalCluster.start), runs the batch on its address (--ray's path)
    and stops and removes it, even when the batch fails; a local layout asks for none. The table names both."""
    import quasisim.bench.batch as bb

    calls: list[Any] = []

    class FakeCluster:
        address = "127.0.0.1:6379"

        @classmethod
        def start(cls, cpus: tuple[int, ...]) -> FakeCluster:
            calls.append(("start", cpus))
            return cls()

        def stop(self) -> list[int]:
            calls.append("stop")
            return []

        def remove(self) -> None:
            calls.append("remove")

    def fake_run(jobs: list[Job], d: Path, s: Settings) -> str:
        calls.append(("run", s.ray_address, s.workers, s.threads))
        return "result"

    monkeypatch.setattr(bb, "LocalCluster", FakeCluster)
    monkeypatch.setattr(bb, "run_batch", fake_run)
    assert bb._run_layout([], tmp_path, bb.Layout(2, 1, True, nodes=2), {}) == "result"
    assert bb._run_layout([], tmp_path, bb.Layout(2, 1, True, nodes=1), {}) == "result"
    assert bb._run_layout([], tmp_path, bb.Layout(2, 1), {}) == "result"
    assert calls == [
        ("start", (1, 1)), ("run", "127.0.0.1:6379", 2, 1), "stop", "remove",
        ("start", (2,)), ("run", "127.0.0.1:6379", 2, 1), "stop", "remove",
        ("run", None, 2, 1),
    ]  # fmt: skip
    calls.clear()
    monkeypatch.setattr(bb, "run_batch", lambda jobs, d, s: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        bb._run_layout([], tmp_path, bb.Layout(2, 1, True, nodes=2), {})
    assert calls == [("start", (1, 1)), "stop", "remove"]
    row = {"workers": 2, "threads": 1, "pinned": True, "failures": {}, "clips_run": 4, "wall_s": 60.0,
           "clips_per_hour": 240.0, "peak_rss_mb_per_worker": {"1": 900.0}, "same_controls": True}  # fmt: skip
    rows = [{**row, "layout": bb.Layout(2, 1, True, 1).label, "nodes_used": 1},
            {**row, "layout": bb.Layout(2, 1, True, 2).label, "nodes_used": 2, "clips_per_hour": 120.0}]  # fmt: skip
    text = "\n".join(bb._markdown(rows, SPEC.checked(), 4))
    assert "| cluster: 1 node(s) x 2 CPU | 2 | 1 | yes | 1 | 4 | 0 | 60 | 240.0 | 1.00x |" in text
    assert "| cluster: 2 node(s) x 1 CPU | 2 | 1 | yes | 2 | 4 | 0 | 60 | 120.0 | 0.50x |" in text
