"""app.devices stays Qt-free and below the GUI: it imports only numpy/scipy/pyserial-level
libraries and, from app.core, only the experiment format, the errors and (for the
simulated rig) the specimen twin built on the forward model."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
DEVICES = ROOT / "app" / "devices"
FORBIDDEN = ("PySide6", "PyQt5", "PyQt6", "qtpy", "pyqtgraph", "pyvistaqt", "app.gui", "app.cli")
ALLOWED_CORE = ("app.core.experiment", "app.core.errors", "app.core.twin")


def _imports(path: Path):
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            yield node.module


def test_devices_import_no_qt_and_only_allowed_core_modules():
    files = sorted(DEVICES.rglob("*.py"))
    assert len(files) > 10
    for f in files:
        for mod in _imports(f):
            assert not mod.startswith(FORBIDDEN), f"{f.relative_to(ROOT)} imports {mod}"
            if mod.startswith("app.core"):
                assert mod in ALLOWED_CORE, f"{f.relative_to(ROOT)} imports {mod}"


def test_importing_the_whole_package_loads_no_qt():
    code = ("import sys, app.devices, app.devices.acquisition, app.devices.cli, app.devices.sim;"
            "bad = [m for m in sys.modules if m.split('.')[0] in ('PySide6', 'PyQt5', 'PyQt6', 'pyqtgraph')"
            " or m.startswith('app.gui')]; print(bad); sys.exit(1 if bad else 0)")
    run = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stdout + run.stderr
