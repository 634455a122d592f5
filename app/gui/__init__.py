"""The desktop application (PySide6, pyqtgraph, pyvistaqt). Only this package imports Qt.

``main(argv)`` opens the main window; an optional argument opens an experiment
folder or a session file at start.
"""

from __future__ import annotations

import sys
from pathlib import Path


def main(argv=None) -> int:
    """Create the QApplication, show the main window, run the event loop; return its exit code."""
    import argparse
    import multiprocessing

    multiprocessing.freeze_support()  # the mesher runs in a spawned child process
    parser = argparse.ArgumentParser(prog="elastoid", description="ElastoID desktop application")
    parser.add_argument("path", nargs="?", type=Path, help="an experiment folder or a session file (.json) to open")
    args, qt_args = parser.parse_known_args(list(sys.argv[1:] if argv is None else argv))

    from PySide6.QtWidgets import QApplication

    from .style import apply_style

    app = QApplication.instance() or QApplication([sys.argv[0] if sys.argv else "elastoid", *qt_args])
    app.setOrganizationName("ElastoID")
    app.setApplicationName("ElastoID")
    apply_style(app)

    from .mainwindow import MainWindow

    win = MainWindow()
    win.show()
    if args.path is not None:
        if args.path.suffix.lower() == ".json":
            win.open_session(args.path)
        else:
            win.open_experiment(args.path)
    code = app.exec()
    from .workers import wait_for_all

    wait_for_all()  # threads still finishing an uncancellable step must end before Python does
    return code


__all__ = ["main"]
