"""Per clip, in one process: wall time and JAX's compile events (trace, lowering, backend compile or cache load).

Runs `transfer` with the given stages on several clips one after the other in one process, as a batch worker
does, and prints each clip's wall time and the seconds of each compile phase (JAX's monitoring events). A
program the process already holds costs nothing; one it traces again costs its trace and lowering even when
the persistent cache has it.

    python scripts/compile_per_clip.py --stages 1 --out /tmp/cpc grab_s1_apple_lift grab_s1_mug_drink_1
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
from collections import defaultdict
from pathlib import Path

from quasisim.runtime import configure


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("clips", nargs="+", help="clip names in $QUASISIM_DATA (without .npz)")
    ap.add_argument("--stages", default="1,2", help="stages of each transfer (default: 1,2)")
    ap.add_argument("--out", type=Path, required=True, help="folder for the runs (one subfolder per clip)")
    a = ap.parse_args()
    configure()
    import jax

    from quasisim import pipeline
    from quasisim.bench.profile import COMPILE_EVENTS
    from quasisim.method.spec import TransferSpec

    phases: dict[str, float] = defaultdict(float)

    def on_event(event: str, duration: float, **_: object) -> None:
        if event in COMPILE_EVENTS:  # the events `quasisim bench profile` counts
            phases[event.rsplit("/", 1)[-1].removesuffix("_duration")] += duration

    jax.monitoring.register_event_duration_secs_listener(on_event)
    spec = dataclasses.replace(TransferSpec(), stages=tuple(a.stages.split(",")))
    data = Path(os.environ.get("QUASISIM_DATA", "../shared/data"))
    print("| clip | wall s | trace s | lowering s | backend compile / cache load s |")
    print("|---|---|---|---|---|")
    for clip in a.clips:
        phases.clear()
        t0 = time.perf_counter()
        pipeline.run_transfer(data / f"{clip}.npz", a.out / clip, spec, overwrite=True)
        p = {k: f"{v:.1f}" for k, v in phases.items()}
        print(
            f"| {clip} | {time.perf_counter() - t0:.1f} | {p.get('jaxpr_trace', '0')} | "
            f"{p.get('jaxpr_to_mlir_module', '0')} | {p.get('backend_compile', '0')} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
