"""Worker threads. Workers never touch widgets: they hand results back through signals."""

from __future__ import annotations

import threading
import traceback
from typing import Any, Callable

from PySide6.QtCore import QThread, Signal

from app.core.errors import Cancelled


class Task(QThread):
    """Runs ``fn(progress, cancel)`` on its own thread.

    ``progress(text)`` becomes the :attr:`progress` signal; ``cancel`` is a
    threading.Event the function polls. Exactly one of :attr:`succeeded`,
    :attr:`failed` (exception, traceback text) or :attr:`cancelled` follows.
    Running tasks are kept referenced until they end, so closing the panel
    that started one never destroys a running thread.
    """

    progress = Signal(str)
    succeeded = Signal(object)
    failed = Signal(object, str)
    cancelled = Signal()

    _alive: set["Task"] = set()

    def __init__(self, fn: Callable[[Callable[[str], None], threading.Event], Any], name: str = "task"):
        super().__init__()
        self.fn = fn
        self.name = name
        self.setObjectName(name)
        self.cancel_event = threading.Event()
        self.finished.connect(self._release)

    def start(self) -> None:  # noqa: D401 - QThread API
        Task._alive.add(self)
        super().start()

    def run(self) -> None:
        try:
            result = self.fn(self.progress.emit, self.cancel_event)
        except Cancelled:
            self.cancelled.emit()
        except BaseException as exc:  # reported to the GUI; a worker must never die silently
            if self.cancel_event.is_set():
                self.cancelled.emit()
            else:
                self.failed.emit(exc, traceback.format_exc())
        else:
            self.succeeded.emit(result)

    def cancel(self) -> None:
        self.cancel_event.set()

    def _release(self) -> None:
        Task._alive.discard(self)
        self.deleteLater()

    @classmethod
    def running(cls) -> list["Task"]:
        return [t for t in cls._alive if t.isRunning()]

    @classmethod
    def shutdown_all(cls, timeout_s: float = 10.0) -> bool:
        """Cancel every running task and wait for them; True when all ended."""
        tasks = list(cls._alive)
        for t in tasks:
            t.cancel()
        ok = True
        for t in tasks:
            ok = t.wait(int(timeout_s * 1000)) and ok
        return ok


class RigWorker(QThread):
    """The thread that talks to the instruments: runs ``RigController.serve`` until shutdown."""

    rig_event = Signal(str, object)  # (kind, payload); not "event", which would shadow QObject.event()

    def __init__(self, controller):
        super().__init__()
        self.setObjectName("rig-io")
        self.controller = controller
        controller.on_event = self.rig_event.emit

    def run(self) -> None:
        self.controller.serve()

    def shutdown(self, timeout_s: float = 8.0) -> bool:
        """Ask the rig thread to end; if an uncancellable step (a twin being built) keeps it
        busy, keep this object alive until it ends, so the thread is never destroyed running."""
        self.controller.shutdown()
        if self.wait(int(timeout_s * 1000)):
            return True
        _LINGERING.add(self)
        self.finished.connect(lambda: _LINGERING.discard(self))
        return False


_LINGERING: set = set()


def wait_for_all(timeout_s: float = 60.0) -> bool:
    """Before the process exits: wait for tasks and rig threads still finishing."""
    ok = Task.shutdown_all(timeout_s)
    for w in list(_LINGERING):
        ok = w.wait(int(timeout_s * 1000)) and ok
    return ok
