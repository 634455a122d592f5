"""Where the bundled resources (the demo experiment) and the guides are, from a
source checkout or from the frozen application (PyInstaller). No Qt here.

In the source tree the resources and the guides sit next to the ``app``
package (``<repo>/resources``, ``<repo>/docs``). In a PyInstaller bundle they
are copied under the bundle's data directory, ``sys._MEIPASS``
(``<bundle>/_internal/resources`` and ``_internal/docs`` for a onedir build);
see packaging/elastoid.spec.
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


def docs_path(*parts: str) -> Path:
    """A path under the guides' directory (``docs/`` beside ``resources/``, in the
    source tree and in the bundle alike), e.g. ``docs_path("user-guide.md")``."""
    return resource_root().parent.joinpath("docs", *parts)


__all__ = ["docs_path", "is_frozen", "resource_path", "resource_root"]
