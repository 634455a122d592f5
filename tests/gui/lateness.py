"""How late a 10 ms Qt timer fires while the window works: the event loop's
responsiveness as a user feels it. Shared by the GUI tests and bench/live_plot.py."""

from __future__ import annotations

import numpy as np
from PySide6.QtCore import QElapsedTimer, QTimer


class TimerLateness:
    """``start()``, let the event loop run, ``stop()``: the lateness (ms) of every tick after the first."""

    def __init__(self, interval_ms: int = 10):
        self.interval_ms = interval_ms
        self.lateness_ms: list[float] = []
        self._clock = QElapsedTimer()
        self._timer = QTimer()
        self._timer.setInterval(interval_ms)
        self._timer.timeout.connect(self._tick)
        self._last: float | None = None

    def _tick(self) -> None:
        now = self._clock.nsecsElapsed() / 1e6
        if self._last is not None:
            self.lateness_ms.append(max(0.0, now - self._last - self.interval_ms))
        self._last = now

    def start(self) -> None:
        self._clock.start()
        self._timer.start()

    def stop(self) -> np.ndarray:
        self._timer.stop()
        return np.asarray(self.lateness_ms)
