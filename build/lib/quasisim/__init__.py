"""quasisim: human hand-object demonstrations to robot-hand controls via quasi-physical simulators.

Importing the package is light: MuJoCo, PyBullet and Ray load only inside the modules that use them.
"""

import os

# MuJoCo picks its OpenGL backend when it is first imported; offscreen EGL works on headless machines.
os.environ.setdefault("MUJOCO_GL", "egl")
# XLA's CPU backend routes small dots and reductions through YNNPACK fusions, which made the simulator's
# substep ~3x slower on CPU (measured: 3.1 ms -> 1.1 ms per substep); keep them off unless the user set
# the flag. This must happen before JAX creates its CPU client.
if "xla_cpu_experimental_ynn_fusion_type" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_experimental_ynn_fusion_type=").strip()

from quasisim.errors import InputError, QuasisimError

__version__ = "0.1.0"
__all__ = ["InputError", "QuasisimError", "__version__"]
