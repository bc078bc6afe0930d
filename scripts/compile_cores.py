"""Backend compile time of the simulator's two large programs, one after the other or both at once.

Lowers the tracking objective's value and gradient for one clip twice (the stiffest simulator's substeps and
the soft simulators' half of them), then times XLA's backend compile (the persistent cache off) either one
after the other or the two at once in two threads. Run it pinned to one core (``taskset -c 0``) and unpinned
to see how many cores one compilation uses (BENCHMARKS.md, "Compiling the next stages' programs in the
background").

    python scripts/compile_cores.py ../shared/data/grab_s1_cup_lift.npz --mode serial
    taskset -c 0 python scripts/compile_cores.py ../shared/data/grab_s1_cup_lift.npz --mode serial
"""

from __future__ import annotations

import argparse
import threading
import time
from pathlib import Path

from quasisim.runtime import configure


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("demo", type=Path)
    ap.add_argument("--mode", choices=("serial", "threads"), default="serial")
    ap.add_argument("--substeps", type=int, default=20)
    args = ap.parse_args()
    configure()
    import jax

    jax.config.update("jax_enable_compilation_cache", False)
    from quasisim.bench.sim import kinematic_replay
    from quasisim.method.config import TransferConfig
    from quasisim.optim.objective import padded_value_and_grad
    from quasisim.optim.sysid import SysID

    r = kinematic_replay(args.demo, "shadow", args.substeps)
    obj = r.prob.objective(r.prob.reference())
    rest = (r.prob.trajectory(r.q_kin), SysID.init(), r.params, TransferConfig.from_yaml().weights.arrays())
    t0 = time.perf_counter()
    lowered = [jax.jit(padded_value_and_grad.fn).lower(o, *rest) for o in (obj, obj.with_substeps(args.substeps // 2))]
    print(f"trace and lower both: {time.perf_counter() - t0:.1f} s")
    t0 = time.perf_counter()
    if args.mode == "serial":
        for name, low in zip(("stiffest", "soft"), lowered, strict=True):
            t = time.perf_counter()
            low.compile()
            print(f"backend compile, {name}: {time.perf_counter() - t:.1f} s")
    else:
        th = threading.Thread(target=lowered[1].compile)
        th.start()
        lowered[0].compile()
        th.join()
    print(f"backend compile, {args.mode}: {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
