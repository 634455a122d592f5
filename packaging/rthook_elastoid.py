"""PyInstaller runtime hook: runs inside the frozen app before any of its code.

- pyvistaqt imports Qt through qtpy: pin it to PySide6, the only binding in the bundle.
- pypardiso looks for MKL's runtime library by name; point it at the copy in the
  bundle (packaging/elastoid.spec collects MKL next to it), unless the user chose one.
"""

import glob
import os
import sys

os.environ.setdefault("QT_API", "pyside6")

_base = getattr(sys, "_MEIPASS", os.path.dirname(sys.executable))
if "PYPARDISO_MKL_RT" not in os.environ:
    for _pattern in ("lib/libmkl_rt.so*", "lib/libmkl_rt*.dylib", "Library/bin/mkl_rt*.dll"):
        _found = sorted(glob.glob(os.path.join(_base, _pattern)), key=len)
        if _found:
            os.environ["PYPARDISO_MKL_RT"] = _found[0]
            break

# Windows: MKL's DLLs load each other (and libiomp5md.dll) by name; let the loader find them
if sys.platform == "win32" and hasattr(os, "add_dll_directory"):
    _mkl_dir = os.path.join(_base, "Library", "bin")
    if os.path.isdir(_mkl_dir):
        os.add_dll_directory(_mkl_dir)
