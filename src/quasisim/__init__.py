"""quasisim: human hand-object demonstrations to robot-hand controls via quasi-physical simulators.

Importing the package is light: MuJoCo, PyBullet and Ray load only inside the modules that use them.
"""

import os

# MuJoCo picks its OpenGL backend when it is first imported; offscreen EGL works on headless machines.
os.environ.setdefault("MUJOCO_GL", "egl")

from quasisim.errors import InputError, QuasisimError

__version__ = "0.1.0"
__all__ = ["InputError", "QuasisimError", "__version__"]
