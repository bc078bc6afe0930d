"""``quasisim batch`` beside and on Ray clusters started here with ``ray start`` (token authentication as Ray
defaults it): a local batch never attaches to another Ray (a live cluster, its address file left behind,
``RAY_ADDRESS``), Ctrl-C ends a batch with status 130 and nothing of its Ray left and the same command resumes,
and a batch on a cluster of two nodes loses one of them in the middle of a clip, with the result of another
clip of it not yet stored, and still does every clip exactly once, with the results of a local batch. Every Ray process here is ours, stopped through the process
groups of our `ray start`s (or with the batch that started it); processes that merely name a cluster's folder
are left alone."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from batch_hooks import DRIVER, ScriptedHooks, pythonpath
from helpers import ctrl_c_restored
from quasisim.errors import QuasisimError
from quasisim.raycluster import LocalCluster, resolve, token_available

pytest.importorskip("ray", reason="Ray is installed with the 'cluster' extra (make setup installs it)")

N_CLIPS = 5
MARK = "QUASISIM_TEST_BATCH"  # in the environment of a batch's driver, so of its local Ray's processes: finds them


@pytest.fixture(scope="module")
def clips_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Five short clips (copies of the two synthetic examples under other names)."""
    import shutil

    from quasisim.data.synthetic import EXAMPLES, write_example

    d = tmp_path_factory.mktemp("cluster_clips")
    src = [write_example(name, d, n_frames=12) for name in EXAMPLES]
    for k in range(N_CLIPS):
        shutil.copy(src[k % len(src)], d / f"{src[k % len(src)].stem}_{k}.npz")
    for p in src:
        p.unlink()
    return d


@pytest.fixture(scope="module")
def token_env(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """A token where Ray looks for one (on a machine where a local Ray ever ran, ~/.ray/auth_token is there:
    then nothing changes), so that ``ray start --head`` turns token authentication on by default; the mode
    itself is left to Ray (no RAY_AUTH_MODE)."""
    mp = pytest.MonkeyPatch()
    mp.delenv("RAY_AUTH_MODE", raising=False)
    mp.delenv("RAY_ADDRESS", raising=False)
    if not token_available():
        path = tmp_path_factory.mktemp("ray_token") / "auth_token"
        path.write_text(os.urandom(32).hex())
        mp.setenv("RAY_AUTH_TOKEN_PATH", str(path))
    yield
    mp.undo()


def _batch(
    clips_dir: Path, out: Path, *extra: str, env: dict[str, str], hooks: ScriptedHooks | None = None
) -> subprocess.Popen[str]:
    """``quasisim batch`` (the cheapest method, the kinematic retarget judged in MuJoCo) in a subprocess, its
    workers with ``hooks`` where given (:mod:`batch_hooks`)."""
    cli = [sys.executable, str(DRIVER), hooks.to_json()] if hooks else [sys.executable, "-m", "quasisim.cli"]
    cmd = [*cli, "batch", str(clips_dir), "--out", str(out), "--method", "kinematic",
           "--workers", "2", "--threads", "1", *extra]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": pythonpath(), **env}
    return subprocess.Popen(ctrl_c_restored(cmd), env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait(cond: Callable[[], bool], timeout: float, what: str, proc: subprocess.Popen[str] | None = None) -> None:
    """Until ``cond()``; fails after ``timeout`` s or when ``proc`` ends first."""
    t0 = time.monotonic()
    while not cond():
        if proc is not None and proc.poll() is not None:
            raise AssertionError(f"the batch ended before {what}: {proc.communicate()[1][-2000:]}")
        assert time.monotonic() - t0 < timeout, f"no {what} after {timeout} s"
        time.sleep(0.2)


def _proc() -> Iterator[tuple[int, Path]]:
    """(pid, /proc folder) of every process but this one."""
    for d in Path("/proc").glob("[0-9]*"):
        if int(d.name) != os.getpid():
            yield int(d.name), d


def processes_with(text: str) -> list[int]:
    """Ids of the processes (this one aside) with ``text`` in their command line or environment."""
    found = []
    for pid, d in _proc():
        try:
            if text.encode() in (d / "cmdline").read_bytes() or text.encode() in (d / "environ").read_bytes():
                found.append(pid)
        except OSError:
            continue
    return found


def processes_in_sessions(sessions: set[int]) -> list[int]:
    """Ids of the processes in the sessions ``sessions`` (a LocalCluster node's: its `ray start`'s id)."""
    found = []
    for pid, d in _proc():
        try:
            if int((d / "stat").read_text().rsplit(")", 1)[1].split()[3]) in sessions:
                found.append(pid)
        except (OSError, IndexError, ValueError):
            continue
    return found


def _gone(find: Callable[[], list[int]], timeout: float = 20.0) -> list[int]:
    """The processes ``find()`` still finds after up to ``timeout`` s (workers exit after their raylet)."""
    t0 = time.monotonic()
    while (left := find()) and time.monotonic() - t0 < timeout:
        time.sleep(0.2)
    return left


def _bystanders(cluster: LocalCluster) -> list[subprocess.Popen[bytes]]:
    """Processes that name the cluster's temp folder without being its own: a `tail -f` of its head's log,
    and a process started with RAY_TMPDIR there (a driver of its own Ray, say)."""
    env = {**os.environ, "RAY_TMPDIR": str(cluster.temp)}
    return [
        subprocess.Popen(["tail", "-f", str(cluster.log(0))], stdout=subprocess.DEVNULL),
        subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"], env=env),
    ]


@dataclass(frozen=True)
class LocalRun:
    """What :func:`local_run` saw: the batch folder, each command's outcome, the processes of the interrupted
    batch left after it, the clip finished before the interrupt and its controls' time stamp."""

    out: Path
    interrupted: subprocess.CompletedProcess[str]
    left_after_interrupt: list[int]
    resumed: subprocess.CompletedProcess[str]
    first_clip: str
    first_stamp: int
    auto_stale: subprocess.CompletedProcess[str]
    address: str


def _completed(p: subprocess.Popen[str], timeout: float = 300) -> subprocess.CompletedProcess[str]:
    out, err = p.communicate(timeout=timeout)
    return subprocess.CompletedProcess(p.args, p.returncode, out, err)


@pytest.fixture(scope="module")
def local_run(clips_dir: Path, token_env: None, tmp_path_factory: pytest.TempPathFactory) -> Iterator[LocalRun]:
    """A local batch beside a live `ray start` cluster (its address file in Ray's temp folder, and
    RAY_ADDRESS naming it) interrupted with SIGINT after its first clip (the others held); the cluster then
    stopped (its address file stays, as after a crash) and the same command run again; `--ray auto` then."""
    base = tmp_path_factory.mktemp("local_run")
    out, hold = base / "out", base / "hold"
    hold.mkdir()
    cluster = LocalCluster.start((1,))
    try:
        env = {"RAY_TMPDIR": str(cluster.temp)}
        p = _batch(clips_dir, out, env={**env, "RAY_ADDRESS": cluster.address, MARK: str(hold)},
                   hooks=ScriptedHooks(hold=str(hold)))  # fmt: skip
        _wait(lambda: any(out.glob("*/clip.json")), 240, "finished clip", p)
        _wait(lambda: len(list(hold.glob("*.started"))) >= 2, 60, "held clip", p)  # the others are running
        p.send_signal(signal.SIGINT)
        interrupted = _completed(p, 180)  # a hang guard: Ray's shutdown took over 60 s once on 2 loaded cores
        left = _gone(lambda: processes_with(f"{MARK}={hold}"))  # only the batch's own processes carry it
        first = next(out.glob("*/clip.json")).parent
        stamp = (first / "controls.npz").stat().st_mtime_ns
        assert not cluster.stop()  # SIGTERM ended every process of it
        assert (cluster.temp / "ray" / "ray_current_cluster").is_file()  # left behind, as by a crashed cluster
        resumed = _completed(_batch(clips_dir, out, env=env))
        auto = _completed(_batch(clips_dir, base / "auto", "--ray", "auto", env=env))
        yield LocalRun(out, interrupted, left, resumed, first.name, stamp, auto, cluster.address)
    finally:
        cluster.stop()
        cluster.remove()


@pytest.mark.slow  # a one-node cluster beside a local batch run twice (~70 s on 2 busy cores)
def test_local_batch_ignores_other_rays_stops_on_ctrl_c_and_resumes(local_run: LocalRun) -> None:
    r = local_run
    # beside a live cluster that RAY_ADDRESS names: one line says so, the batch starts its own Ray
    assert f"note: RAY_ADDRESS is set ({r.address})" in r.interrupted.stderr
    assert "starts a Ray of its own" in r.interrupted.stderr
    # Ctrl-C: status 130, one line, no traceback, none of its Ray processes (raylet, GCS, workers) left
    assert r.interrupted.returncode == 130, r.interrupted.stderr[-2000:]
    assert "interrupted; rerun the same command to resume" in r.interrupted.stderr
    assert "Traceback" not in r.interrupted.stderr
    assert r.left_after_interrupt == []
    # the same command with the cluster gone and its address file left: resumes, finished clip untouched
    assert r.resumed.returncode == 0, r.resumed.stderr[-2000:]
    assert "where no Ray answers" in r.resumed.stderr and "starts a Ray of its own" in r.resumed.stderr
    res = json.loads((r.out / "batch.json").read_text())
    assert res["clips_run"] == N_CLIPS - 1 and not res["failures"] and len(res["rows"]) == N_CLIPS
    assert (r.out / r.first_clip / "controls.npz").stat().st_mtime_ns == r.first_stamp
    # --ray auto with only that stale file: one line naming the address and what to do, status 2
    assert r.auto_stale.returncode == 2, r.auto_stale.stderr[-2000:]
    last = r.auto_stale.stderr.strip().splitlines()[-1]
    assert last.startswith(f"error: no Ray cluster answers at {r.address}") and "ray start --head" in last
    assert "Traceback" not in r.auto_stale.stderr


@pytest.mark.slow  # two `ray start` nodes, a batch of 5 clips, one node killed; a local batch beside (~80 s)
def test_batch_on_two_nodes_survives_losing_one(clips_dir: Path, token_env: None, tmp_path: Path) -> None:
    """Clips run on both nodes; the second node's raylet is killed while it holds a clip and after it finished
    another one whose result the driver has not stored (nor fetched: the driver takes no result until then).
    Ray retries the held clip on the head and computes the finished one again there (its result was lost with
    the node): every clip done once, with the results of a local batch. The finished clip's checkpoints are
    still on the lost node (kept until the driver stored the clip: a clip that runs there again resumes from
    them); the head's scratch folder is empty (removed once the driver stored each clip); no process of the
    cluster is left."""
    hold, out = tmp_path / "hold", tmp_path / "out"
    hold.mkdir()
    # results above 1000 bytes stay in the object store of the worker's node (Ray's default: above 100 kB;
    # a real clip's are megabytes): a finished clip's result not yet fetched is lost with its node
    env = {"PYTHONPATH": pythonpath(), "RAY_max_direct_call_object_size": "1000"}  # its workers import batch_hooks
    cluster = LocalCluster.start((1, 1), env=env)
    try:
        assert b"Token authentication is enabled" in cluster.log(0).read_bytes()  # Ray's default, a token here
        raylet, node1 = cluster.raylet(1)
        # node 1 holds its second clip; the head's first clip waits for that, so that node 1 gets two clips;
        # each node keeps its scratch folders apart (OUT/.work@NODE), as nodes of their own machines would; the
        # driver takes no result until the test says `go`
        hooks = ScriptedHooks(
            hold=str(hold), hold_node=node1, gate=str(hold), node_scratch=True, results_gate=str(hold)
        )
        # the explicit address: Ray sends no token unless told (RAY_AUTH_MODE), quasisim tells it
        p = _batch(clips_dir, out, "--ray", cluster.address, env={}, hooks=hooks)
        _wait(lambda: len(list(hold.glob("*.started"))) >= 2, 240, "held clip on the second node", p)
        first, held = (f.stem for f in sorted(hold.glob("*.started"), key=lambda f: f.stat().st_mtime_ns))
        # node 1 runs one clip at a time: its first clip's worker returned before the held one started, and
        # kept its checkpoints; the driver has stored nothing, the result is only in node 1's object store
        assert (out / f".work@{node1}" / first / "runs" / "_" / "checkpoints").is_dir()
        assert not list(out.glob("*/clip.json"))
        os.kill(raylet, signal.SIGKILL)
        (hold / "go").touch()
        r = _completed(p)
        assert r.returncode == 0, r.stderr[-3000:]
        res = json.loads((out / "batch.json").read_text())
        nodes = res["node_per_clip"]
        assert not res["failures"] and res["clips_run"] == N_CLIPS
        assert (
            sorted(row["clip"] for row in res["rows"])
            == sorted(nodes)
            == sorted(p.stem for p in clips_dir.glob("*.npz"))
        )  # every clip once
        head = nodes[held]
        assert head != node1 and set(nodes.values()) == {head}  # both clips of node 1 ran again on the head
        assert not list(out.glob(".*.incoming"))  # no clip folder half written
        # the lost node's scratch folder keeps the finished clip's checkpoints (the held clip waited before
        # writing any); the head's is empty: each clip's was removed there once the driver stored it
        assert sorted(d.name for d in out.glob(".work*")) == sorted([f".work@{node1}", f".work@{head}"])
        assert [d.name for d in (out / f".work@{node1}").iterdir()] == [first]
        assert (out / f".work@{node1}" / first / "runs" / "_" / "checkpoints").is_dir()
        assert not [str(c) for c in (out / f".work@{head}").iterdir()]
        assert cluster.procs[1].poll() is not None  # the second node's `ray start` ended with its raylet
        # a local batch beside the live cluster (its address file where Ray looks) runs to its end, on its own Ray
        local = _completed(_batch(clips_dir, tmp_path / "local", env={"RAY_TMPDIR": str(cluster.temp)}))
        assert local.returncode == 0, local.stderr[-2000:]
        assert f"note: a Ray cluster runs at {cluster.address}" in local.stderr
        for c in nodes:
            assert json.loads((out / c / "metrics.json").read_text()) == json.loads(
                (tmp_path / "local" / c / "metrics.json").read_text()
            ), c
            with np.load(out / c / "controls.npz") as a, np.load(tmp_path / "local" / c / "controls.npz") as b:
                np.testing.assert_array_equal(a["q_targets"], b["q_targets"], err_msg=c)
    finally:
        others = _bystanders(cluster)
        try:
            left = cluster.stop()
            others_alive = [o.poll() is None for o in others]
        finally:
            for o in others:
                o.kill()
                o.wait()
            cluster.remove()
    # SIGTERM ended every process of the cluster, those of its sessions included (workers), and no other
    assert not left and not _gone(lambda: processes_in_sessions({p.pid for p in cluster.procs}))
    assert others_alive == [True, True]


FAKE_RAY_START = """
import os, signal, subprocess, sys, time
from pathlib import Path

ray = Path(os.environ["RAY_TMPDIR"]) / "ray"
ray.mkdir(exist_ok=True)
(ray / "ray_current_cluster").write_text("127.0.0.1:1")
child = ray / "child.pid"
subprocess.Popen([sys.executable, "-c", "import os, signal, sys, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); "
                  "open(sys.argv[1], 'w').write(str(os.getpid())); time.sleep(600)", str(child)])
while not child.is_file() or not child.read_text():
    time.sleep(0.05)
signal.signal(signal.SIGTERM, lambda *a: os._exit(0))  # leaves its child behind
print("Ray runtime started", flush=True)
time.sleep(600)
"""


def test_stopping_a_local_cluster_ends_its_processes_and_no_others(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """LocalCluster.stop() ends what its `ray start`s started and nothing else. No Ray here: `ray start` is a
    stand-in whose child ignores SIGTERM (a Ray process stuck past its node's clean-up; the two-node test
    stops a real cluster). That child is killed with its node's process group; processes that name the
    cluster's temp folder without being its own (a `tail -f` of its log, a process with RAY_TMPDIR there)
    live on."""
    import quasisim.raycluster as rc

    fake = tmp_path / "ray_start.py"
    fake.write_text(FAKE_RAY_START)
    monkeypatch.setattr(rc, "_ray_cli", lambda *args: [sys.executable, str(fake), *args])
    cluster = LocalCluster.start((1,))
    others: list[subprocess.Popen[bytes]] = []
    try:
        node, child = cluster.procs[0], int((cluster.temp / "ray" / "child.pid").read_text())
        others = _bystanders(cluster)
        assert cluster.stop(grace=1.0) == [node.pid]  # its child outlived SIGTERM: its group was killed
        assert node.poll() is not None and not _gone(lambda: [child] if Path(f"/proc/{child}").exists() else [], 10)
        assert [o.poll() for o in others] == [None, None]  # alive
    finally:
        for o in others:
            o.kill()
            o.wait()
        cluster.stop(grace=0.0)
        cluster.remove()


SLOW_ADDRESS_RAY_START = """
import os, sys, time
from pathlib import Path

print("Ray runtime started", flush=True)  # as Ray: the address file is written after this line
time.sleep(1.5)
ray = Path(os.environ["RAY_TMPDIR"]) / "ray"
ray.mkdir(exist_ok=True)
(ray / "ray_current_cluster").write_text("127.0.0.1:7")
time.sleep(600)
"""


def test_the_head_address_is_awaited_after_ray_printed_it_started(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`ray start --head` prints "Ray runtime started" before it writes its address file; on a loaded machine
    (CI, tests in parallel) the file came later and the cluster's start failed with FileNotFoundError."""
    import quasisim.raycluster as rc

    fake = tmp_path / "ray_start.py"
    fake.write_text(SLOW_ADDRESS_RAY_START)
    monkeypatch.setattr(rc, "_ray_cli", lambda *args: [sys.executable, str(fake), *args])
    cluster = LocalCluster.start((1,))
    try:
        assert cluster.address == "127.0.0.1:7"
    finally:
        cluster.stop(grace=0.0)
        cluster.remove()


def test_ray_auto_finds_the_cluster_of_ray_start(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """--ray auto: RAY_ADDRESS, else the address file of `ray start` in Ray's temp folder; checked to answer."""
    import socket

    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    monkeypatch.setenv("RAY_TMPDIR", str(tmp_path))
    with pytest.raises(QuasisimError, match="no Ray cluster started with `ray start`"):
        resolve("auto")
    with socket.socket() as srv:
        srv.bind(("127.0.0.1", 0))
        srv.listen()
        addr = f"127.0.0.1:{srv.getsockname()[1]}"
        (tmp_path / "ray").mkdir()
        (tmp_path / "ray" / "ray_current_cluster").write_text(addr + "\n")
        assert resolve("auto") == addr and resolve(addr) == addr
        monkeypatch.setenv("RAY_ADDRESS", "127.0.0.1:1")
        with pytest.raises(QuasisimError, match=r"no Ray cluster answers at 127.0.0.1:1 \(from RAY_ADDRESS"):
            resolve("auto")
    with pytest.raises(QuasisimError, match="expected HOST:PORT"):
        resolve("nowhere")


def test_an_older_ray_is_one_line_naming_the_version_needed(
    clips_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With a Ray older than 2.59 (its version monkeypatched; no Ray starts here) `quasisim batch` and a
    LocalCluster fail where they first use Ray, with one line naming the version needed, the version
    pyproject.toml asks for; 2.59 passes the version check.

    What it does not show: that quasisim works on Ray 2.59 itself. It only compares the version strings
    (RAY_MIN, a monkeypatched ``ray.__version__``, pyproject.toml's ``cluster`` extra); the Ray tests (the
    two-node test, the local batches) run on the Ray installed here (``make setup``: the newest), never on
    2.59, so a Ray API that quasisim uses and that came after 2.59 would pass here. RAY_MIN rests on reading
    Ray's sources (raycluster.RAY_MIN's comment)."""
    import re
    import tomllib

    import ray
    from click.testing import CliRunner

    from quasisim.cli import main
    from quasisim.raycluster import _import_ray

    need = "quasisim needs Ray 2.59 or later, this is Ray 2.58.1: pip install 'ray[default]>=2.59'"
    monkeypatch.setattr(ray, "__version__", "2.58.1")
    with pytest.raises(QuasisimError, match=re.escape(need)):
        _import_ray()
    with pytest.raises(QuasisimError, match=re.escape(need)):
        LocalCluster.start((1,))  # before any `ray start`
    r = CliRunner().invoke(main, ["batch", str(clips_dir), "--out", str(tmp_path / "o"), "--method", "kinematic"])
    assert r.exit_code == 2 and r.output.strip().splitlines()[-1].startswith(f"error: {need}"), r.output
    assert "Traceback" not in r.output
    monkeypatch.setattr(ray, "__version__", "2.59.0")
    assert _import_ray() is ray
    project = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())["project"]
    assert project["optional-dependencies"]["cluster"] == ["ray[default]>=2.59"]


def test_sigterm_inside_sigterm_interrupts_is_an_interrupt_that_exits_143(capsys: pytest.CaptureFixture[str]) -> None:
    """No Ray here: the part of a batch that waits on Ray (ray.wait, ray.get) runs inside sigterm_interrupts,
    because Ray turns a SystemExit raised by a signal handler while it waits into exit status 1. Inside it,
    SIGTERM raises KeyboardInterrupt (the handler from before is put back after it), and a resumable command
    (_interruptible) then exits 143, Ctrl-C 130, with one line on stderr. The slow local-batch test stops a
    real batch on Ray (with SIGINT)."""
    import quasisim.raycluster as rc
    from quasisim.cli._common import _interruptible

    def interrupted() -> None:
        raise KeyboardInterrupt

    line = "interrupted; rerun the same command to resume\n"
    try:
        with pytest.raises(SystemExit) as e:
            _interruptible(interrupted)()
        assert e.value.code == 130 and capsys.readouterr().err == line
        before = signal.getsignal(signal.SIGTERM)
        with pytest.raises(KeyboardInterrupt), rc.sigterm_interrupts():
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)
        assert rc.terminated() and signal.getsignal(signal.SIGTERM) == before
        with pytest.raises(SystemExit) as e:
            _interruptible(interrupted)()
        assert e.value.code == 143 and capsys.readouterr().err == line
    finally:
        rc._TERMINATED.clear()
