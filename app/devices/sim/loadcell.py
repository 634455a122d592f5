"""A simulated ELC-1 load cell (protocol in docs/devices.md).

It measures the true force the world hands it at each sample time, adds
Gaussian noise (``noise_N``), removes the tare offset, clips at
``full_scale_N`` with the saturation flag, and sends each line ``latency_ms``
after the measurement.
"""

from __future__ import annotations

from collections import deque
from typing import Callable

from app.devices.loadcell import FLAG_SATURATED, frame, sample_body
from app.devices.sim.base import SimDevice


class SimLoadCell(SimDevice):
    name = "force sensor"

    def __init__(self, *, full_scale_N: float = 50.0, noise_N: float = 0.002, latency_ms: float = 5.0,
                 max_rate_hz: int = 2000, serial: str = "SIM0001", seed: int = 2):
        super().__init__(seed)
        self.full_scale_N = full_scale_N
        self.noise_N = noise_N
        self.latency_s = latency_ms / 1000.0
        self.max_rate_hz = max_rate_hz
        self.serial = serial
        self.streaming = False
        self.rate_hz = 0
        self.t0 = 0.0
        self.n_claimed = 0
        self.n_measured = 0
        self.tare_offset_N = 0.0
        self.force_saturate = False  # fault: report saturation from now on
        self.current_force: Callable[[], float] = lambda: 0.0  # set by the world (for TARE)
        self._pending: deque[tuple[float, str]] = deque()
        self._rx = bytearray()

    # ---- schedule --------------------------------------------------------
    def next_measure_time(self) -> float:
        if not self.streaming:
            return float("inf")
        return self.t0 + (self.n_claimed + 1) / self.rate_hz

    def claim_measurement(self) -> float:
        """Reserve the next sample time (the world then computes its force)."""
        t = self.next_measure_time()
        self.n_claimed += 1
        return t

    def next_pending_time(self) -> float:
        return self._pending[0][0] if self._pending else float("inf")

    def next_event_time(self) -> float:
        t = self._pending[0][0] if self._pending else float("inf")
        return min(t, self.next_measure_time(), self.next_output_time())

    def measure(self, t: float, true_force_N: float) -> None:
        if not self.streaming:
            return
        reading = true_force_N - self.tare_offset_N + (self.rng.normal(0.0, self.noise_N) if self.noise_N else 0.0)
        flags = 0
        if self.force_saturate or abs(reading) >= self.full_scale_N:
            reading = self.full_scale_N if (self.force_saturate or reading > 0) else -self.full_scale_N
            flags |= FLAG_SATURATED
        body = sample_body(self.n_measured, int(round((t - self.t0) * 1e6)), reading, flags)
        self.n_measured += 1
        self._pending.append((t + self.latency_s, body))

    def advance(self, t: float) -> None:
        while self._pending and self._pending[0][0] <= t + 1e-12:
            te, body = self._pending.popleft()
            self.emit(te, frame(body))

    # ---- commands ----------------------------------------------------------
    def _reply(self, t: float, body: str) -> None:
        # Replies queue behind samples in flight so the order on the wire is the order of events.
        te = max(t, self._pending[-1][0]) if self._pending else t
        self._pending.append((te, body))

    def receive(self, data: bytes, t: float) -> None:
        if self.lost or self.mute:
            return
        for b in data:
            if b == 0x0A:
                line = self._rx.decode("ascii", "replace").strip()
                self._rx.clear()
                self._command(line, t)
            elif b == 0x0D:
                continue
            elif len(self._rx) < 64:
                self._rx.append(b)
            else:
                self._rx.clear()
                self._reply(t, "ERR,4,LINE TOO LONG")

    def _command(self, line: str, t: float) -> None:
        self.log.append((t, f"cmd:{line}"))
        if not line:
            return
        word, _, arg = line.partition(" ")
        if word == "ID?":
            self._reply(t, f"ID,ElastoID,SimCell-{self.full_scale_N:g}N,{self.serial},1.0,{self.full_scale_N:.3f}")
        elif word == "TARE":
            if self.streaming:
                return self._reply(t, "ERR,3,NOT ALLOWED WHILE STREAMING")
            self.tare_offset_N = self.current_force()
            self._reply(t + 0.1, f"OK,TARE,{self.tare_offset_N:+.4f}")
        elif word == "START":
            try:
                rate = int(arg)
            except ValueError:
                return self._reply(t, "ERR,2,RATE MUST BE A WHOLE NUMBER OF HZ")
            if not 1 <= rate <= self.max_rate_hz:
                return self._reply(t, f"ERR,2,RATE OUT OF RANGE 1..{self.max_rate_hz}")
            self._reply(t, f"OK,START,{rate}")
            self.streaming = True
            self.rate_hz = rate
            self.t0 = t
            self.n_claimed = 0
            self.n_measured = 0
        elif word == "STOP":
            n = self.n_measured
            self.streaming = False
            self._reply(t, f"OK,STOP,{n}")
        else:
            self._reply(t, "ERR,1,UNKNOWN COMMAND")
