"""Errors shown to the user: a plain message first, the details (file, field, traceback) on demand."""

from __future__ import annotations

import logging

from PySide6.QtWidgets import QMessageBox, QWidget

from app.core.errors import ElastoidError, ExperimentError

log = logging.getLogger("elastoid.gui")


def describe(exc: BaseException) -> tuple[str, str]:
    """(headline, explanation) for a user: ElastoidErrors speak for themselves."""
    if isinstance(exc, ExperimentError):
        where = f"File: {exc.file}" + (f"\nField: {exc.field}" if exc.field else "")
        return "The experiment cannot be used", f"{where}\n\n{exc.message}"
    file = getattr(exc, "file", None)
    field = getattr(exc, "field", None)
    if isinstance(exc, ElastoidError):
        msg = getattr(exc, "message", None) or str(exc)
        where = ""
        if file:
            where = f"File: {file}" + (f"\nField: {field}" if field else "") + "\n\n"
        device = getattr(exc, "device", "")
        head = f"{device[:1].upper() + device[1:]} problem" if device else "ElastoID could not do that"
        note = getattr(exc, "stop_note", "")
        return head, where + msg + (f"\n\n{note[:1].upper() + note[1:]}." if note else "")
    if isinstance(exc, (ValueError, OSError)):
        return "ElastoID could not do that", str(exc)
    return "Unexpected error", f"{type(exc).__name__}: {exc}"


def show_error(parent: QWidget | None, exc: BaseException, details: str = "", *, title: str = "ElastoID") -> QMessageBox:
    """A modal-less error dialog; logs the error too. Returns the box (tests close it)."""
    head, text = describe(exc)
    log.error("%s: %s", head, text.replace("\n", " "))
    box = QMessageBox(parent)
    box.setIcon(QMessageBox.Warning if isinstance(exc, ElastoidError) else QMessageBox.Critical)
    box.setWindowTitle(title)
    box.setText(f"<b>{head}</b>")
    box.setInformativeText(text)
    if details:
        box.setDetailedText(details)
    box.setStandardButtons(QMessageBox.Ok)
    box.setModal(False)
    box.show()
    return box
