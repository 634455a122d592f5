"""Clocks: real (monotonic) time, or virtual time that a simulated rig advances.

Drivers and the acquisition loop take a ``clock`` so that the same code runs
against hardware in real time and against the simulated twins in virtual time,
where a ten-second ramp takes a fraction of a second to compute.
"""

from __future__ import annotations

import threading
import time
from typing import Callable, Protocol


class Clock(Protocol):
    def now(self) -> float:
        """Seconds, monotonic, arbitrary origin."""

    def sleep(self, seconds: float) -> None:
        """Let ``seconds`` pass."""


class MonotonicClock:
    """Real time: :func:`time.monotonic` and :func:`time.sleep`."""

    def now(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds)


class VirtualClock:
    """Virtual seconds that pass only when someone waits.

    ``advance_to(t)`` runs ``on_advance(t)`` (the simulated world) and moves
    the clock. ``pace`` > 0 slows it to ``pace`` times real time (for a demo or
    a kill test); ``None`` runs as fast as the computer can.
    """

    def __init__(self, start_s: float = 0.0, pace: float | None = None):
        self._t = float(start_s)
        self.pace = pace
        self.on_advance: Callable[[float], None] | None = None
        self.lock = threading.RLock()

    def now(self) -> float:
        return self._t

    def advance_to(self, t: float) -> None:
        with self.lock:
            if t <= self._t:
                return
            if self.pace:
                time.sleep((t - self._t) / self.pace)
            if self.on_advance is not None:
                self.on_advance(t)
            self._t = t

    def sleep(self, seconds: float) -> None:
        self.advance_to(self._t + max(0.0, seconds))
