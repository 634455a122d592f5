"""What every panel tells the main window: status text, busy state, errors."""

from __future__ import annotations

from PySide6.QtCore import Signal
from PySide6.QtWidgets import QWidget


class Panel(QWidget):
    status = Signal(str)  # a line for the status bar
    busy = Signal(str, int, int)  # (what, done, total); total 0 = indeterminate; what "" = idle
    error = Signal(object, str)  # (exception, details)

    title = "Panel"

    def shutdown(self) -> None:
        """Stop whatever the panel runs (the window is closing)."""
