"""Hooks of the batch tests (:class:`quasisim.batch.BatchHooks`): a worker killed in the middle of a clip, clips
held until the test lets them go, a driver that takes no result until the test lets it. The hooks travel to the workers with each task, so the workers must import
this module: tests put this folder on the ``PYTHONPATH`` of the batch's driver (a local Ray's workers inherit
it) and of the ``ray start`` nodes (:func:`pythonpath`)."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from quasisim.batch import BatchHooks

HERE = Path(__file__).resolve().parent
DRIVER = HERE / "batch_driver.py"  # `quasisim batch` with hooks: python DRIVER HOOKS_JSON batch ...


def pythonpath() -> str:
    """``PYTHONPATH`` with this folder first (for the driver and the nodes whose workers run hooked clips)."""
    return os.pathsep.join([str(HERE), *filter(None, [os.environ.get("PYTHONPATH")])])


def _node() -> str:
    import ray

    return str(ray.get_runtime_context().get_node_id()) if ray.is_initialized() else ""


def _sleep_until(done: Callable[[], bool], limit_s: float) -> None:
    t0 = time.monotonic()
    while not done() and time.monotonic() - t0 < limit_s:
        time.sleep(0.2)


@dataclass(frozen=True)
class ScriptedHooks(BatchHooks):
    """- ``fault`` (a clip): that clip's first attempt kills its own worker in the middle of the clip, as its
      second checkpointed piece starts (the first one is saved).
    - ``hold`` (a folder): every clip but the first one started writes ``<clip>.started`` there and waits
      (until its worker is killed, or ``limit_s``); only on the Ray node ``hold_node`` where one is named.
    - ``gate`` (a folder): on the nodes that do not hold, a clip waits until that folder shows a held clip
      (two ``.started`` files), so that another node gets clips meanwhile.
    - ``node_scratch``: each Ray node keeps its clips' scratch folders in a folder of its own,
      ``OUT/.work@<node id>/<clip>`` (nodes on this one machine share its disk; on a cluster each has its own).
    - ``results_gate`` (a folder): the driver waits for no clip's result (so stores none, and fetches none from
      the node that holds it) until that folder holds ``go``."""

    fault: str = ""
    hold: str = ""
    hold_node: str = ""
    gate: str = ""
    node_scratch: bool = False
    results_gate: str = ""
    limit_s: float = 120.0

    def to_json(self) -> str:
        return json.dumps(asdict(self))

    def scratch(self, scratch: Path) -> Path:
        return (
            scratch.parent.with_name(f"{scratch.parent.name}@{_node()}") / scratch.name
            if self.node_scratch
            else scratch
        )

    def starting(self, clip: str) -> None:
        if self.hold and self.hold_node in ("", _node()):
            hold = Path(self.hold)
            waits = any(hold.glob("*.started"))  # not the first clip
            (hold / f"{clip}.started").write_text(str(os.getpid()))
            if waits:
                _sleep_until(lambda: False, self.limit_s)
        elif self.gate:
            _sleep_until(lambda: len(list(Path(self.gate).glob("*.started"))) >= 2, self.limit_s)

    def waiting(self) -> None:
        if self.results_gate:
            _sleep_until(lambda: (Path(self.results_gate) / "go").exists(), self.limit_s)

    def piece_hook(self, clip: str, scratch: Path) -> Callable[[str, Callable[[], Any]], Any] | None:
        if clip != self.fault or (scratch / "fault-injected").exists():
            return None
        pieces: list[str] = []

        def hook(name: str, compute: Callable[[], Any]) -> Any:
            pieces.append(name)
            if len(pieces) == 2:
                scratch.mkdir(parents=True, exist_ok=True)
                (scratch / "fault-injected").touch()
                os.kill(os.getpid(), 9)
            return compute()

        return hook
