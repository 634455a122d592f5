"""A tiny Qt-free observer: models announce changes, panels listen.

Models are changed on the GUI thread only (workers hand their results back
through Qt signals first), so listeners run on the GUI thread too.
"""

from __future__ import annotations

from typing import Callable


class Signal:
    """``connect(fn)``, ``disconnect(fn)``, ``emit(*args)``; listeners run in connection order."""

    def __init__(self) -> None:
        self._slots: list[Callable] = []

    def connect(self, fn: Callable) -> Callable:
        if fn not in self._slots:
            self._slots.append(fn)
        return fn

    def disconnect(self, fn: Callable | None = None) -> None:
        if fn is None:
            self._slots.clear()
        elif fn in self._slots:
            self._slots.remove(fn)

    def emit(self, *args) -> None:
        for fn in list(self._slots):
            fn(*args)
