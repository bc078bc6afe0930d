"""Compile time of the simulator's value and gradient under the XLA flags of the environment: the synthetic
16-frame cube_lift, the Shadow hand, 5 substeps per frame and 32 contact candidates (the tests' tiny budget),
persistent cache off. Prints trace + lower, backend compile and one call's seconds, and the loss (to see
whether the flags change the arithmetic). One process per setting:

    XLA_FLAGS="--xla_backend_optimization_level=0" python scripts/compile_flags.py
    XLA_FLAGS="--xla_backend_optimization_level=0 --xla_cpu_use_fusion_emitters=false" python scripts/compile_flags.py
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp

from quasisim.runtime import configure


def main() -> None:
    configure()
    jax.config.update("jax_enable_compilation_cache", False)
    from quasisim.bench.sim import kinematic_replay
    from quasisim.data.synthetic import write_example
    from quasisim.sim.step import object_pose, rollout

    r = kinematic_replay(write_example("cube_lift", Path(tempfile.mkdtemp()), n_frames=16), "shadow", 5, 32)
    model = r.prob.model
    target = jnp.asarray(r.prob.demo.object_pos[1:], jnp.float32)

    def loss(c, p, s):  # noqa: ANN001, ANN202
        return jnp.mean(jnp.sum((object_pose(model, rollout(model, p, s, c))[0] - target) ** 2, -1))

    t0 = time.perf_counter()
    lowered = jax.jit(jax.value_and_grad(loss)).lower(r.ctrl, r.params, r.s0)
    t1 = time.perf_counter()
    compiled = lowered.compile()
    t2 = time.perf_counter()
    value = jax.block_until_ready(compiled(r.ctrl, r.params, r.s0))
    t3 = time.perf_counter()
    print(
        f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}: trace + lower {t1 - t0:.1f} s, compile {t2 - t1:.1f} s, "
        f"one call {t3 - t2:.2f} s, loss {float(value[0]):.8g}"
    )


if __name__ == "__main__":
    main()
