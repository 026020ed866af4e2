"""cell: a networked industrial robot cell on one machine (README.md)."""

import os as _os

# MuJoCo picks its OpenGL backend once, when it is first imported, from MUJOCO_GL; without a display
# the default (GLFW) cannot render, so off-screen EGL is chosen here, before anything imports mujoco.
if "MUJOCO_GL" not in _os.environ and not (_os.environ.get("DISPLAY") or _os.environ.get("WAYLAND_DISPLAY")):
    _os.environ["MUJOCO_GL"] = "egl"

__version__ = "0.1.0"
