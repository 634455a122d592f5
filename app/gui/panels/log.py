"""Log panel: what ElastoID did, from the ``elastoid`` loggers, with time stamps."""

from __future__ import annotations

import logging

from PySide6.QtCore import QObject, Qt, Signal
from PySide6.QtGui import QTextCursor
from PySide6.QtWidgets import QPlainTextEdit, QVBoxLayout

from ..style import mono_font
from .base import Panel

MAX_LINES = 5000


class _Bridge(QObject):
    line = Signal(str, int)


class QtLogHandler(logging.Handler):
    """A logging handler that hands records to the GUI thread through a queued signal."""

    def __init__(self):
        super().__init__(logging.INFO)
        self.bridge = _Bridge()
        self.setFormatter(logging.Formatter("%(asctime)s  %(levelname)-7s %(message)s", "%H:%M:%S"))

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self.bridge.line.emit(self.format(record), record.levelno)
        except RuntimeError:  # the bridge is gone (window closed)
            pass


class LogPanel(Panel):
    title = "Log"

    def __init__(self, parent=None, logger_name: str = "elastoid"):
        super().__init__(parent)
        lay = QVBoxLayout(self)
        lay.setContentsMargins(4, 4, 4, 4)
        self.text = QPlainTextEdit()
        self.text.setReadOnly(True)
        self.text.setFont(mono_font())
        self.text.setMaximumBlockCount(MAX_LINES)
        self.text.setPlaceholderText("Messages from meshing, identification and the rig appear here.")
        lay.addWidget(self.text)
        self.text.setContextMenuPolicy(Qt.CustomContextMenu)
        self.text.customContextMenuRequested.connect(self._menu)
        self.handler = QtLogHandler()
        self.handler.bridge.line.connect(self.append)
        self.logger = logging.getLogger(logger_name)
        self.logger.addHandler(self.handler)
        if self.logger.level == logging.NOTSET or self.logger.level > logging.INFO:
            self.logger.setLevel(logging.INFO)

    def append(self, text: str, level: int = logging.INFO) -> None:
        color = "#c62828" if level >= logging.ERROR else "#b26a00" if level >= logging.WARNING else None
        if color:
            self.text.appendHtml(f"<span style='color:{color}'>{_escape(text)}</span>")
        else:
            self.text.appendPlainText(text)
        self.text.moveCursor(QTextCursor.End)

    def _menu(self, pos) -> None:
        menu = self.text.createStandardContextMenu()
        menu.addSeparator()
        menu.addAction("Clear the log", self.text.clear)
        menu.exec(self.text.mapToGlobal(pos))

    def shutdown(self) -> None:
        self.logger.removeHandler(self.handler)


def _escape(s: str) -> str:
    return s.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
