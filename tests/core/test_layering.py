"""The layers: core imports no Qt and no serial; devices no Qt; arrows point down."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _imports(path: Path):
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            yield from (a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            yield node.module


def test_core_imports_no_gui_serial_devices_or_cli():
    bad = ("PySide6", "PyQt5", "PyQt6", "qtpy", "pyqtgraph", "pyvistaqt", "superqt", "serial",
           "app.gui", "app.devices", "app.cli")
    files = sorted((ROOT / "app" / "core").rglob("*.py"))
    assert len(files) > 10
    for f in files:
        for mod in _imports(f):
            assert not (mod == "serial" or mod.startswith(tuple(b for b in bad if b != "serial"))
                        or mod.startswith("serial.")), f"{f.relative_to(ROOT)} imports {mod}"


def test_import_linter_contracts_hold():
    from importlinter.cli import lint_imports

    import os

    cwd = os.getcwd()
    os.chdir(ROOT)
    try:
        assert lint_imports() == 0
    finally:
        os.chdir(cwd)
