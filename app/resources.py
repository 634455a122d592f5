"""Where the bundled resources (the demo experiment) are, from a source checkout or
from the frozen application (PyInstaller). No Qt here.

In the source tree the resources sit next to the ``app`` package
(``<repo>/resources``). In a PyInstaller bundle they are copied under the
bundle's data directory, ``sys._MEIPASS`` (``<bundle>/_internal/resources`` for
a onedir build); see packaging/elastoid.spec.
"""

from __future__ import annotations

import sys
from pathlib import Path


def is_frozen() -> bool:
    """True inside a PyInstaller bundle."""
    return bool(getattr(sys, "frozen", False))


def resource_root() -> Path:
    """The ``resources`` directory."""
    if is_frozen():
        base = getattr(sys, "_MEIPASS", None)
        return Path(base if base is not None else Path(sys.executable).resolve().parent) / "resources"
    return Path(__file__).resolve().parent.parent / "resources"


def resource_path(*parts: str) -> Path:
    """A path under the ``resources`` directory, e.g. ``resource_path("demo")``."""
    return resource_root().joinpath(*parts)


__all__ = ["is_frozen", "resource_path", "resource_root"]
