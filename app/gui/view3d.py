"""The 3-D view: pyvistaqt when an OpenGL window can exist, a notice otherwise."""

from __future__ import annotations

import os
import sys

from PySide6.QtGui import QGuiApplication

NO_OPENGL_PLATFORMS = ("offscreen", "minimal", "linuxfb", "vnc")


def can_use_3d() -> bool:
    """False where pyvistaqt's QOpenGLWidget cannot work: Qt platforms without OpenGL
    (offscreen, minimal, ...), headless Linux, or ELASTOID_NO_3D set."""
    if os.environ.get("ELASTOID_NO_3D"):
        return False
    app = QGuiApplication.instance()
    platform = app.platformName() if app is not None else ""
    if platform in NO_OPENGL_PLATFORMS or not platform:
        return False
    if sys.platform.startswith("linux") and not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
        return False
    return True
