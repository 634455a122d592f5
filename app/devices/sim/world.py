"""The simulated world: one stage, one sensor, one specimen (a force model), one clock.

:class:`SimWorld` advances the controller's kinematics, records the probe's
travel history, asks the force model for the force at each sensor sample time
and fires scheduled faults. :class:`VirtualPort` connects a driver to a device
in virtual time (the world advances only while a driver waits);
:mod:`app.devices.sim.serve` serves the same devices over pseudo-terminals in
real time.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np

from app.devices.clock import VirtualClock
from app.devices.errors import PortLost
from app.devices.sim.base import SimDevice
from app.devices.sim.grbl import SimGrbl
from app.devices.sim.loadcell import SimLoadCell
from app.devices.sim.models import ForceModel

FAULT_KINDS = ("port_lost", "garbage", "partial_lines", "mute", "grbl_error", "grbl_alarm", "saturate")


@dataclass
class Fault:
    """One scheduled fault. Fires once, at ``at_s`` (world time) or when the probe's travel reaches
    ``at_travel_mm``, whichever is set (immediately if neither)."""

    kind: str
    device: str  # "stage" or "force"
    at_s: float | None = None
    at_travel_mm: float | None = None
    code: int = 1  # grbl_error / grbl_alarm
    n_bytes: int = 24  # garbage
    fired_at_s: float | None = None


@dataclass
class FaultInjector:
    """The faults waiting to fire on a simulated rig."""

    faults: list[Fault] = field(default_factory=list)

    def add(self, kind: str, device: str = "stage", *, at_s: float | None = None,
            at_travel_mm: float | None = None, **params) -> Fault:
        if kind not in FAULT_KINDS:
            raise ValueError(f"unknown fault {kind!r}; known: {', '.join(FAULT_KINDS)}")
        if device not in ("stage", "force"):
            raise ValueError(f"device must be 'stage' or 'force', got {device!r}")
        f = Fault(kind, device, at_s=at_s, at_travel_mm=at_travel_mm, **params)
        self.faults.append(f)
        return f

    def due(self, t: float, travel_mm: float) -> list[Fault]:
        out = []
        for f in self.faults:
            if f.fired_at_s is not None:
                continue
            if (f.at_s is not None and t >= f.at_s) or (f.at_travel_mm is not None and travel_mm >= f.at_travel_mm) \
                    or (f.at_s is None and f.at_travel_mm is None):
                f.fired_at_s = t
                out.append(f)
        return out


class _Growing:
    """A float array that grows by appending (amortised O(1))."""

    def __init__(self):
        self.a = np.empty(1024)
        self.n = 0

    def append(self, x: float) -> None:
        if self.n == self.a.size:
            self.a = np.concatenate([self.a, np.empty(self.a.size)])
        self.a[self.n] = x
        self.n += 1

    def view(self) -> np.ndarray:
        return self.a[: self.n]


class SimWorld:
    """Couples the simulated controller and sensor through a force model.

    ``into_specimen`` and ``axis`` say how machine position maps to probe
    travel (travel = into_specimen * machine position), as in the driver.
    Truth for tests and the bench: ``truth()`` gives (time, travel, true force)
    at every sensor sample.
    """

    def __init__(self, model: ForceModel, grbl: SimGrbl, sensor: SimLoadCell, *, into_specimen: int = -1,
                 faults: FaultInjector | None = None):
        self.model = model
        self.grbl = grbl
        self.sensor = sensor
        self.into = into_specimen
        self.faults = faults or FaultInjector()
        self.t = 0.0
        self.lock = threading.RLock()
        self._ht, self._hd = _Growing(), _Growing()  # travel history the model sees
        self._truth_idx: list[int] = []
        self._truth_force: list[float] = []
        self._last_hist_t = -1.0
        sensor.current_force = self.force_now
        self.devices: dict[str, SimDevice] = {"stage": grbl, "force": sensor}

    # ---- state -------------------------------------------------------------
    def travel_mm(self) -> float:
        return self.into * self.grbl.pos

    def force_now(self) -> float:
        with self.lock:
            self._record(self.t)
            return float(self.model.force_N(self._ht.view(), self._hd.view())[-1])

    def truth(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        idx = np.asarray(self._truth_idx, int)
        return self._ht.view()[idx].copy(), self._hd.view()[idx].copy(), np.asarray(self._truth_force)

    def _record(self, t: float) -> int:
        if t > self._last_hist_t:
            self._ht.append(t)
            self._hd.append(self.travel_mm())
            self._last_hist_t = t
        return self._ht.n - 1

    # ---- time ----------------------------------------------------------------
    def deliver(self, device: SimDevice, data: bytes) -> None:
        with self.lock:
            device.receive(data, self.t)

    def next_event_time(self, after: float | None = None) -> float:
        """The next time something happens (strictly after ``after``, if given)."""
        if after is None:
            return min(self.sensor.next_event_time(), self.grbl.next_output_time())
        times = [self.sensor.next_measure_time(), self.sensor.next_pending_time(),
                 self.grbl.next_output_after(after), self.sensor.next_output_after(after)]
        return min([t for t in times if t > after + 1e-12], default=float("inf"))

    def run_until(self, t_end: float) -> None:
        with self.lock:
            claimed: list[tuple[float, int]] = []
            while self.t < t_end - 1e-12:
                t_meas = self.sensor.next_measure_time()
                t_next = min(t_end, self.t + 0.001, t_meas)
                self.grbl.advance(t_next)
                self.t = t_next
                if t_meas <= t_next + 1e-12:
                    self.sensor.claim_measurement()
                    claimed.append((t_meas, self._record(t_next)))
                elif self.grbl.moving and t_next - self._last_hist_t >= 0.01 - 1e-12:
                    self._record(t_next)
                elif t_next - self._last_hist_t >= 1.0:
                    self._record(t_next)
                for f in self.faults.due(self.t, self.travel_mm()):
                    self._apply(f)
            if claimed:
                forces = self.model.force_N(self._ht.view(), self._hd.view())
                for t_m, i in claimed:
                    self._truth_idx.append(i)
                    self._truth_force.append(float(forces[i]))
                    self.sensor.measure(t_m, float(forces[i]))
            self.sensor.advance(t_end)
            self.t = max(self.t, t_end)

    def _apply(self, f: Fault) -> None:
        dev = self.devices[f.device]
        dev.log.append((self.t, f"fault:{f.kind}"))
        if f.kind == "port_lost":
            dev.lost = True
        elif f.kind == "garbage":
            dev.garbage(self.t, f.n_bytes)
        elif f.kind == "partial_lines":
            dev.fragment = True
        elif f.kind == "mute":
            dev.mute = True
        elif f.kind == "grbl_error":
            self.grbl.error_next = f.code
        elif f.kind == "grbl_alarm":
            self.grbl.raise_alarm(self.t, f.code)
        elif f.kind == "saturate":
            self.sensor.force_saturate = True


class VirtualPort:
    """A driver's port onto a simulated device, in the world's virtual time."""

    def __init__(self, world: SimWorld, device: SimDevice, clock: VirtualClock, name: str):
        self.world = world
        self.device = device
        self.clock = clock
        self.name = name

    def _check(self) -> None:
        if self.device.lost:
            raise PortLost(f"port {self.name} disappeared (the device was unplugged or powered off)",
                           device=self.device.name)

    def write(self, data: bytes) -> None:
        with self.world.lock:
            self._check()
            self.world.deliver(self.device, data)

    def read_some(self, timeout_s: float) -> bytes:
        with self.world.lock:
            deadline = self.clock.now() + max(0.0, timeout_s)
            while True:
                self._check()
                self.world.run_until(self.clock.now())  # lets replies due now go out
                data = self.device.take(self.clock.now())
                if data:
                    return data
                now = self.clock.now()
                if now >= deadline - 1e-12:
                    return b""
                nxt = min(deadline, self.world.next_event_time(after=now))
                self.clock.advance_to(max(nxt, now + 1e-6))

    def close(self) -> None:
        pass
