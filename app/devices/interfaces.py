"""What the acquisition loop needs from a stage and a force sensor.

Another vendor is one new subclass: implement the abstract methods with that
device's commands; :mod:`app.devices.acquisition` never sees the bytes.

Positions are *probe travel into the specimen*, in mm, in the stage's own
frame (0 where the stage's machine zero is); the rig subtracts the contact
point to get the displacement written to force.csv.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass


@dataclass(frozen=True)
class StageStatus:
    """One status report. ``state`` is the controller's word (Idle, Run, Jog, Hold, Alarm, ...)."""

    state: str
    travel_mm: float  # probe travel into the specimen (positive = pressing)
    speed_mm_s: float  # current speed magnitude
    time_s: float  # host clock when the report arrived
    substate: int | None = None
    raw: str = ""

    @property
    def moving(self) -> bool:
        if self.speed_mm_s > 1e-9:
            return True
        if self.state in ("Run", "Jog", "Home"):
            return True
        return self.state == "Hold" and self.substate == 1

    @property
    def alarm(self) -> bool:
        return self.state == "Alarm"


class Stage(ABC):
    """A one-axis motion stage that presses the probe into the specimen."""

    name: str = "stage"

    @property
    @abstractmethod
    def last_status(self) -> StageStatus | None:
        """The latest status report received (None before the first)."""

    @property
    @abstractmethod
    def acceleration_mm_s2(self) -> float:
        """Acceleration the controller uses to start and stop (for stop-distance estimates)."""

    @property
    @abstractmethod
    def travel_range_mm(self) -> tuple[float, float]:
        """(lowest, highest) travel the controller will move to."""

    @abstractmethod
    def query_status(self, timeout_s: float = 1.0) -> StageStatus:
        """Ask for a status report and wait for it."""

    @abstractmethod
    def request_status(self) -> None:
        """Ask for a status report without waiting (the answer comes through :meth:`poll`)."""

    @abstractmethod
    def poll(self, timeout_s: float = 0.0) -> list[StageStatus]:
        """Process whatever the controller sent; return the new status reports (oldest first).

        Raises the device's typed error if it reported one (e.g. an alarm)."""

    @abstractmethod
    def start_move(self, travel_mm: float, speed_mm_s: float) -> None:
        """Start an interruptible move to ``travel_mm``; returns once the controller accepted it."""

    @abstractmethod
    def feed_hold(self) -> None:
        """Start decelerating to a stop now. Non-blocking, safe to call from another thread."""

    @abstractmethod
    def finish_hold(self, timeout_s: float = 5.0) -> StageStatus:
        """After :meth:`feed_hold`: wait until stopped, discard the rest of the motion, return the status
        once the stage is idle (or in alarm). Raises DeviceTimeout if it does not stop."""

    @abstractmethod
    def emergency_stop(self, timeout_s: float = 3.0) -> StageStatus:
        """Stop from any state as fast as the controller allows and discard all queued motion."""

    @abstractmethod
    def unlock(self) -> None:
        """Leave an alarm state after the user checked the machine."""

    @abstractmethod
    def close(self) -> None:
        """Release the port; never raises."""


@dataclass(frozen=True)
class ForceSample:
    seq: int  # device sequence number (unwrapped)
    device_time_s: float  # device's own timestamp, seconds since streaming started (unwrapped)
    force_N: float  # positive = compression on the probe
    saturated: bool = False
    fault: bool = False
    host_time_s: float = 0.0  # host clock when the line was parsed


@dataclass(frozen=True)
class SensorInfo:
    vendor: str
    model: str
    serial: str
    firmware: str
    full_scale_N: float


class ForceSensor(ABC):
    """A force sensor that streams samples at a set rate."""

    name: str = "force sensor"
    bad_lines: int = 0  # corrupted or unreadable lines dropped
    lost_samples: int = 0  # gaps in the sequence numbers
    stream_origin_s: float | None = None  # host clock time of device time 0 (set by start), if known

    @abstractmethod
    def identify(self) -> SensorInfo: ...

    @property
    @abstractmethod
    def full_scale_N(self) -> float: ...

    @property
    @abstractmethod
    def streaming(self) -> bool: ...

    @abstractmethod
    def tare(self) -> float:
        """Zero the reading at the present load; return the offset removed (N)."""

    @abstractmethod
    def start(self, rate_hz: float) -> None:
        """Start streaming samples at ``rate_hz``; sequence and device time restart at 0."""

    @abstractmethod
    def stop(self) -> None:
        """Stop streaming; samples still in flight are kept for :meth:`read_samples`."""

    @abstractmethod
    def read_samples(self, timeout_s: float = 0.0) -> list[ForceSample]:
        """Samples received so far (waiting up to ``timeout_s`` for at least one)."""

    @abstractmethod
    def close(self) -> None: ...
