"""quasisim: human hand-object demonstrations to robot-hand controls via quasi-physical simulators.

Importing the package is light and changes nothing: call :func:`quasisim.runtime.configure` before
simulating (the command line does). MuJoCo, PyBullet and Ray load only inside the modules that use them.
"""

from quasisim.errors import InputError, QuasisimError

__version__ = "0.1.0"
__all__ = ["InputError", "QuasisimError", "__version__"]
