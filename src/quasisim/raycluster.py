"""Which Ray a batch runs on, how the driver gets there, and small Ray clusters of our own on this machine.

- A local batch (no ``--ray``) starts a Ray of its own (``ray.init(address="local")``, ``RAY_ADDRESS`` set
  aside), whatever else runs here: a cluster made by ``ray start``, the address file a crashed one left
  behind, another batch. It says so in one line when it finds one (:func:`other_ray`).
- ``--ray auto`` (:func:`resolve`): ``RAY_ADDRESS`` where set, else the cluster ``ray start`` made on this
  machine (its address file, ``ray_current_cluster`` in Ray's temp folder). ``--ray HOST:PORT`` (or
  ``ray://HOST:PORT``, Ray Client): that cluster. The address must answer before Ray is asked to connect.
- Token authentication: Ray >= 2.59 turns it on for local clusters and for ``ray start --head`` where a token
  exists (``~/.ray/auth_token``, which any local ``ray.init`` writes). A driver connecting to an explicit
  address does not send a token unless ``RAY_AUTH_MODE=token``; :func:`connect` sets it where a token is
  found by Ray's rules (``RAY_AUTH_TOKEN``, ``RAY_AUTH_TOKEN_PATH``, ``~/.ray/auth_token``) and the user has
  not set the mode (a cluster without authentication ignores the token).
- Every failure to start or reach Ray is a :class:`~quasisim.errors.QuasisimError` (one line: the address
  and what to do).
- :class:`LocalCluster`: ``ray start --block`` processes of our own (a head and more nodes, all on this
  machine) for the two-node test and ``quasisim bench batch``'s cluster layouts; each started in a session
  of its own and stopped through its process group (never ``ray stop``, which ends every Ray on the
  machine, nor a search for processes that mention the cluster).

Linux only where it reads ``/proc`` (finding running Ray processes), as Ray's own discovery does.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from quasisim.errors import QuasisimError

ADDRESS_FILE = "ray_current_cluster"  # written by `ray start --head` into Ray's temp folder
# The oldest Ray with what this module and quasisim.batch count on: ray.shutdown(wait_for_processes=) (since
# 2.57), and token authentication turned on by `ray start --head` where a token exists and by a local
# ray.init (since 2.59; LocalCluster tells its other nodes RAY_AUTH_MODE=token where a token exists, which
# a head of an older Ray leaves without authentication). Read in the sources of Ray 2.55.0 to 2.60.0.
RAY_MIN = "2.59"
TOKEN_HELP = (
    "a cluster with token authentication needs its token here (~/.ray/auth_token, RAY_AUTH_TOKEN or "
    "RAY_AUTH_TOKEN_PATH; `ray get-auth-token` on its head node prints it)"
)


# ---- where Ray is ---------------------------------------------------------------------------------------


def ray_temp_dir() -> Path:
    """Ray's default temp folder, as Ray finds it: ``$RAY_TMPDIR/ray``, else ``$TMPDIR/ray`` (Linux), else
    ``/tmp/ray``."""
    base = os.environ.get("RAY_TMPDIR") or (os.environ.get("TMPDIR") if sys.platform.startswith("linux") else None)
    return Path(base or "/tmp") / "ray"


def address_file() -> Path:
    """The file in which ``ray start --head`` leaves its cluster's address (kept after a crash)."""
    return ray_temp_dir() / ADDRESS_FILE


def _host_port(address: str) -> tuple[str, int] | None:
    host, _, port = address.split("://")[-1].rpartition(":")
    return (host or "127.0.0.1", int(port)) if port.isdigit() else None


def reachable(address: str, timeout: float = 2.0) -> bool:
    """Whether something listens at ``address`` (HOST:PORT or ray://HOST:PORT)."""
    hp = _host_port(address)
    if hp is None:
        return False
    try:
        with socket.create_connection(hp, timeout=timeout):
            return True
    except OSError:
        return False


def _processes() -> Iterator[tuple[int, list[str]]]:
    """(pid, command line) of every process this user can read (``/proc``)."""
    for d in Path("/proc").glob("[0-9]*"):
        try:
            args = (d / "cmdline").read_bytes().decode(errors="replace").split("\0")
        except OSError:
            continue
        yield int(d.name), [a for a in args if a]


def running_gcs() -> set[str]:
    """Addresses of the Ray clusters with a raylet on this machine (from the raylets' command lines)."""
    found = set()
    for _, args in _processes():
        if args and Path(args[0]).name == "raylet":
            for a in " ".join(args).split():
                if a.startswith(("--gcs-address=", "--gcs_address=")):
                    found.add(a.split("=", 1)[1])
    return found


def other_ray() -> str | None:
    """What a plain ``ray.init()`` here would attach to instead of starting its own Ray, in words (None:
    nothing): ``RAY_ADDRESS``, a cluster's address file (live or left behind) or a running Ray."""
    env = os.environ.get("RAY_ADDRESS")
    if env:
        return f"RAY_ADDRESS is set ({env})"
    f = address_file()
    addr = f.read_text().strip() if f.is_file() else ""
    if addr:
        if reachable(addr):
            return f"a Ray cluster runs at {addr} ({f})"
        return f"{f} names {addr}, where no Ray answers (a cluster that stopped or crashed)"
    gcs = running_gcs()
    return f"another Ray runs on this machine ({', '.join(sorted(gcs))})" if gcs else None


def resolve(address: str) -> str:
    """``--ray``'s value as the address to connect to (``auto``: ``RAY_ADDRESS``, else the address file of
    ``ray start``); an error naming the address when nothing answers there."""
    if address != "auto":
        where = "--ray"
        addr = address
    elif os.environ.get("RAY_ADDRESS"):
        where, addr = "RAY_ADDRESS", os.environ["RAY_ADDRESS"]
    else:
        f = address_file()
        where, addr = str(f), f.read_text().strip() if f.is_file() else ""
        if not addr:
            gcs = running_gcs()
            hint = f" (Ray runs here at {', '.join(sorted(gcs))}: give --ray HOST:PORT)" if gcs else ""
            raise QuasisimError(
                f"--ray auto: no Ray cluster started with `ray start` on this machine (no RAY_ADDRESS, no {f}){hint}; "
                "start one (`ray start --head`), give its address (--ray HOST:PORT) or leave out --ray for a local batch"
            )
    if _host_port(addr) is None:
        raise QuasisimError(f"--ray: expected HOST:PORT (or auto), got {addr!r} (from {where})")
    if not reachable(addr):
        raise QuasisimError(
            f"no Ray cluster answers at {addr} (from {where}; a cluster that stopped leaves its address behind): start "
            "it (`ray start --head` on its head node), give the address of a running one, or leave out --ray for a "
            "local batch"
        )
    return addr


# ---- the driver -----------------------------------------------------------------------------------------


def token_available() -> bool:
    """Whether Ray would find an authentication token here (its own order: ``RAY_AUTH_TOKEN``,
    ``RAY_AUTH_TOKEN_PATH``, ``~/.ray/auth_token``)."""
    path = os.environ.get("RAY_AUTH_TOKEN_PATH")
    return bool(os.environ.get("RAY_AUTH_TOKEN")) or Path(path or Path.home() / ".ray" / "auth_token").is_file()


def _send_token() -> None:
    """``RAY_AUTH_MODE=token`` where the user left the mode unset and a token exists (before Ray reads it)."""
    if "RAY_AUTH_MODE" in os.environ or not token_available():
        return
    os.environ["RAY_AUTH_MODE"] = "token"
    if "ray" in sys.modules:  # Ray's settings are read once: read them again, as Ray does when it turns auth on
        from ray._raylet import Config

        Config.initialize("")


def _import_ray() -> Any:
    """The ``ray`` module, or an error saying how to install it (Ray not installed, or older than
    :data:`RAY_MIN`). Called where a batch or a cluster first uses Ray, not when quasisim is imported."""
    try:
        import ray
    except ImportError:
        raise QuasisimError(
            "batches run on Ray, which is not installed here: pip install 'quasisim[cluster]' (make setup installs it)"
        ) from None
    if _older(ray.__version__, RAY_MIN):
        raise QuasisimError(
            f"quasisim needs Ray {RAY_MIN} or later, this is Ray {ray.__version__}: pip install 'ray[default]>={RAY_MIN}' "
            "(on every node of a cluster)"
        )
    return ray


def _older(version: str, than: str) -> bool:
    """Whether the Ray version ``version`` is older than ``than`` (a version that cannot be read is not)."""
    from packaging.version import InvalidVersion, Version  # Ray's own dependency

    try:
        return Version(version) < Version(than)
    except InvalidVersion:
        return False


def _one_line(e: BaseException) -> str:
    lines = [x.strip() for x in str(e).splitlines() if x.strip()]
    return f"{type(e).__name__}: {lines[0] if lines else ''}"[:300]


_TERMINATED = threading.Event()


def terminated() -> bool:
    """Whether a KeyboardInterrupt came from SIGTERM (:func:`sigterm_interrupts`) rather than Ctrl-C."""
    return _TERMINATED.is_set()


def _raise_interrupt(signum: int, frame: Any) -> None:
    _TERMINATED.set()
    raise KeyboardInterrupt


@contextmanager
def sigterm_interrupts() -> Iterator[None]:
    """SIGTERM raises KeyboardInterrupt inside (the clean-up of Ctrl-C; :func:`terminated` tells them apart):
    Ray turns a SystemExit raised by a signal handler while it waits (``ray.wait``, ``ray.get``) into exit
    status 1, a KeyboardInterrupt it passes on."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    before = signal.getsignal(signal.SIGTERM)
    signal.signal(signal.SIGTERM, _raise_interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL if before is None else before)


@contextmanager
def _sigterm_kept() -> Iterator[None]:
    """``ray.init`` makes SIGTERM exit with status 15: the handler from before is put back."""
    main = threading.current_thread() is threading.main_thread()
    before = signal.getsignal(signal.SIGTERM) if main else None
    try:
        yield
    finally:
        if main:
            signal.signal(signal.SIGTERM, signal.SIG_DFL if before is None else before)


def connect(address: str, env: dict[str, str], min_cpus: int) -> Any:
    """``ray`` connected to the cluster of ``--ray address`` (workers get ``env``); an error when no node
    of it has ``min_cpus`` CPUs (a clip's task could never start)."""
    addr = resolve(address)
    _send_token()
    ray = _import_ray()

    try:
        with _sigterm_kept():
            ray.init(address=addr, runtime_env={"env_vars": env}, log_to_driver=False, logging_level="ERROR")
    except Exception as e:
        mode = os.environ.get("RAY_AUTH_MODE", "")
        hint = f"; RAY_AUTH_MODE is {mode!r} here: unset it or set it to 'token'" if mode != "token" and mode else ""
        raise QuasisimError(
            f"could not connect to the Ray cluster at {addr} ({_one_line(e)}); {TOKEN_HELP}{hint}"
        ) from None
    alive = [n["Resources"].get("CPU", 0) for n in ray.nodes() if n["Alive"]]
    cpus = max(alive, default=0)
    print(f"on the Ray cluster at {addr}: {len(alive)} node(s), {sum(alive):g} CPUs", file=sys.stderr)
    if cpus < min_cpus:
        ray.shutdown()
        raise QuasisimError(
            f"the Ray cluster at {addr}: each clip asks for {min_cpus} CPUs (--threads) but its largest node has "
            f"{cpus:g}: give --threads {max(1, int(cpus))} or fewer"
        )
    return ray


def start_local(num_cpus: int, env: dict[str, str]) -> Any:
    """``ray`` started on this machine for this batch alone (never attached to another Ray; one line on
    stderr when one is found)."""
    ray = _import_ray()
    other = other_ray()
    if other:
        print(f"note: {other}; this batch starts a Ray of its own (--ray auto runs it on the cluster of `ray start`)",
              file=sys.stderr)  # fmt: skip

    before = os.environ.pop("RAY_ADDRESS", None)
    try:
        with _sigterm_kept():
            ray.init(
                address="local", num_cpus=num_cpus, include_dashboard=False, log_to_driver=False,
                runtime_env={"env_vars": env}, logging_level="ERROR",
            )  # fmt: skip
    except Exception as e:
        raise QuasisimError(
            f"could not start a Ray of this batch's own on this machine ({_one_line(e)}); Ray's logs are in "
            f"{ray_temp_dir()}/session_latest/logs (a full /tmp or /dev/shm is the usual cause; RAY_TMPDIR moves "
            "Ray's files elsewhere)"
        ) from None
    finally:
        if before is not None:
            os.environ["RAY_ADDRESS"] = before
    return ray


# ---- clusters of our own (tests, bench batch) -----------------------------------------------------------


def _ray_cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "ray.scripts.scripts", *args]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("", 0))
        return int(s.getsockname()[1])


@dataclass
class LocalCluster:
    """Ray nodes on this machine, each a ``ray start --block`` process of ours with the Ray temp folder
    ``temp`` (``$RAY_TMPDIR``: its sessions, sockets and address file stay there, away from other Rays).

    Token authentication as Ray defaults it: the head turns it on where a token exists (the other nodes are
    told so with ``RAY_AUTH_MODE=token``, as Ray asks of every node)."""

    temp: Path
    address: str = ""
    procs: list[subprocess.Popen[bytes]] = field(default_factory=list)

    @classmethod
    def start(cls, cpus: tuple[int, ...], env: dict[str, str] | None = None,
              node_env: dict[int, dict[str, str]] | None = None) -> LocalCluster:  # fmt: skip
        """A head of ``cpus[0]`` CPUs and a node per later entry; ``node_env[i]``: more environment of node i."""
        _import_ray()  # the `ray start`s are this Ray's: an error now where it is missing or too old
        c = cls(Path(tempfile.mkdtemp(prefix="qsray", dir="/tmp")))  # short: Unix socket paths
        try:
            c._start_node(0, cpus[0], {**(env or {}), **(node_env or {}).get(0, {})})
            for i, n in enumerate(cpus[1:], 1):
                c._start_node(i, n, {**(env or {}), **(node_env or {}).get(i, {})})
        except BaseException:
            c.stop()
            raise
        return c

    def _env(self, extra: dict[str, str], head: bool) -> dict[str, str]:
        e = {**os.environ, **extra, "RAY_TMPDIR": str(self.temp)}
        e.pop("RAY_ADDRESS", None)
        if not head and "RAY_AUTH_MODE" not in e and token_available():
            e["RAY_AUTH_MODE"] = "token"
        return e

    def _start_node(self, i: int, cpus: int, extra: dict[str, str]) -> None:
        # ports of its own where Ray has fixed defaults (another Ray on this machine may hold them)
        common = ["--num-cpus", str(cpus), "--dashboard-agent-listen-port", str(_free_port()), "--disable-usage-stats",
                  "--block"]  # fmt: skip
        if i == 0:
            args = _ray_cli("start", "--head", "--port", "0", "--include-dashboard=false",
                            "--ray-client-server-port", str(_free_port()), *common)  # fmt: skip
        else:
            args = _ray_cli("start", "--address", self.address, *common)
        log = self.log(i)
        with open(log, "wb") as f:  # a session of its own: the process group of its processes is ours alone
            self.procs.append(subprocess.Popen(args, env=self._env(extra, i == 0), stdout=f, stderr=subprocess.STDOUT,
                                               start_new_session=True))  # fmt: skip
        self._wait_started(i)
        if i == 0:
            self.address = self._read_address()

    def log(self, i: int) -> Path:
        """The output of node ``i``'s ``ray start``."""
        return self.temp / f"node{i}.log"

    def _wait_started(self, i: int, timeout: float = 120.0) -> None:
        self._wait(i, lambda: b"Ray runtime started" in self.log(i).read_bytes(), timeout)

    def _read_address(self, timeout: float = 60.0) -> str:
        """The head's address: `ray start --head` writes its address file only after it printed that the
        runtime started (a loaded machine shows the gap), so it is awaited like the start."""
        file = self.temp / "ray" / ADDRESS_FILE
        self._wait(0, lambda: file.is_file() and bool(file.read_text().strip()), timeout)
        return file.read_text().strip()

    def _wait(self, i: int, done: Callable[[], bool], timeout: float) -> None:
        t0 = time.monotonic()
        while not done():
            if self.procs[i].poll() is not None or time.monotonic() - t0 > timeout:
                tail = self.log(i).read_text(errors="replace").strip().splitlines()[-3:]
                raise QuasisimError(f"ray start of node {i} failed ({self.log(i)}): {' | '.join(tail)}")
            time.sleep(0.2)

    def raylet(self, i: int) -> tuple[int, str]:
        """(pid, node id) of node ``i``'s raylet (a child of its ``ray start``)."""
        parent = str(self.procs[i].pid)
        for pid, args in _processes():
            if args and Path(args[0]).name == "raylet" and _ppid(pid) == parent:
                node = next(a.split("=", 1)[1] for a in args if a.startswith("--node_id="))
                return pid, node
        raise QuasisimError(f"node {i} of the cluster at {self.address} has no raylet")

    def stop(self, timeout: float = 30.0, grace: float = 10.0) -> list[int]:
        """End the nodes, the last first: SIGTERM to each ``ray start`` (which ends the processes it started),
        then SIGKILL to its process group where anything is left in it ``grace`` s after it exited; returns
        the groups that had to be killed so. Only the nodes' own processes are signalled: each ``ray start``
        leads a session of its own, and its process group holds it, its GCS, raylet and agents; Ray puts each
        worker in a group of its own, which its raylet ends (a worker whose raylet died exits by itself)."""
        killed = []
        for p in reversed(self.procs):
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
                try:
                    p.wait(timeout)
                except subprocess.TimeoutExpired:
                    pass
            if not _group_ends(p.pid, grace if p.poll() is not None else 0.0):
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGKILL)
                killed.append(p.pid)
            p.wait()
        return killed

    def remove(self) -> None:
        """Delete ``temp`` (sessions, logs, the address file) once the cluster is stopped."""
        shutil.rmtree(self.temp, ignore_errors=True)


def _ppid(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1]
    except (OSError, IndexError):
        return ""


def _group_ends(pgid: int, timeout: float) -> bool:
    """Whether the process group ``pgid`` is empty within ``timeout`` s."""
    t0 = time.monotonic()
    while True:
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return True
        if time.monotonic() - t0 >= timeout:
            return False
        time.sleep(0.1)
