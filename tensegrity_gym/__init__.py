"""tensegrity_gym: Gymnasium environments for a six-rod tensegrity, on MuJoCo or on an identified twin.

Importing the package registers ``TensegrityIco-v0`` with Gymnasium
(``gym.make("tensegrity_gym:TensegrityIco-v0")`` imports it for you).
"""

import os as _os
import sys as _sys

# Offscreen rendering on a headless Linux machine: MuJoCo picks its GL back-end when it is first
# imported, and its default (GLFW) needs a display.  Ask for EGL unless the user chose.
if _sys.platform.startswith("linux") and not _os.environ.get("DISPLAY"):
    _os.environ.setdefault("MUJOCO_GL", "egl")

__version__ = "0.1.0"

from tensegrity_gym import envs as _envs  # noqa: F401  (registers the env ids)
