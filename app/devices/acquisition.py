"""Acquisition: a rig (stage + force sensor + optional image source) that jogs,
finds contact and runs a ramp-hold-unload protocol while it records an
experiment folder.

Qt-free: the GUI runs these blocking calls in a worker thread, the command
line in its main thread. Each call reports through a ``progress`` callback and
stops cooperatively when its ``stop`` event is set; library code never prints.

Safety, enforced by the loop for every sample as it arrives: when the force
reaches the force limit (or is predicted to reach it before the stage could
stop), or the sensor saturates or flags a fault, or the probe reaches the
travel limit, a feed hold goes out at once (before the sample is even
recorded), the loop waits until the stage stands still, then retracts it.
Any device error ends the operation the same way, as far as the devices still
answer.

Recording: ``force.csv`` is appended and flushed at least every 0.2 s;
``experiment.toml`` is replaced atomically whenever a frame is added, so a
process killed mid-run leaves a folder that ``read_experiment`` can read.
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections import deque
from contextlib import contextmanager
from dataclasses import dataclass, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable

import numpy as np

from app.core.errors import Cancelled
from app.core.experiment import (
    TOML,
    Experiment,
    ForceLog,
    Frame,
    Imaging,
    Probe,
    Region,
    Specimen,
    experiment_to_toml,
    new_folder_problem,
    write_toml_atomic,
)
from app.devices.clock import Clock, MonotonicClock
from app.devices.errors import (
    DeviceError,
    DeviceTimeout,
    EmergencyStop,
    ForceLimitExceeded,
    GrblAlarm,
    RigBusy,
    SafetyStop,
    SensorFault,
    SensorSaturated,
    TravelLimitExceeded,
)
from app.devices.imaging import ImageSource
from app.devices.interfaces import ForceSample, ForceSensor, Stage, StageStatus

FLUSH_PERIOD_S = 0.2


# ---------------------------------------------------------------------------
# settings and reports
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class SafetyLimits:
    """Limits the acquisition loop enforces.

    ``travel_limit_mm`` is the deepest displacement from contact. With
    ``predictive`` the loop also stops when the force, rising at its present
    rate, would pass the limit within the time the stage needs to stop (one
    sample period + speed / (2 acceleration) + ``lookahead_s``, e.g. a known
    sensor latency).
    """

    force_limit_N: float = 10.0
    travel_limit_mm: float = 20.0
    retract_mm: float = 1.0
    retract_speed_mm_s: float = 2.0
    lookahead_s: float = 0.0
    predictive: bool = True  # also stop when the force would pass the limit before the stage could stop

    def __post_init__(self):
        if not self.force_limit_N > 0:
            raise ValueError(f"force_limit_N must be positive, got {self.force_limit_N!r}")
        if not self.travel_limit_mm > 0:
            raise ValueError(f"travel_limit_mm must be positive, got {self.travel_limit_mm!r}")


@dataclass(frozen=True)
class RampHoldUnload:
    """Press to ``depth_mm`` at ``speed_mm_s``, hold ``hold_s``, unload to contact, retract.

    Frames are captured during the ramp as the displacement passes each of
    ``frames_at_mm`` (mm from contact).
    """

    depth_mm: float
    speed_mm_s: float
    hold_s: float = 0.0
    unload: bool = True
    unload_speed_mm_s: float | None = None
    frames_at_mm: tuple[float, ...] = (0.0,)
    retract_after: bool = True

    def check(self, limits: SafetyLimits) -> None:
        if not self.depth_mm > 0:
            raise ValueError(f"depth_mm must be positive, got {self.depth_mm!r}")
        if not self.speed_mm_s > 0:
            raise ValueError(f"speed_mm_s must be positive, got {self.speed_mm_s!r}")
        if self.hold_s < 0:
            raise ValueError(f"hold_s must not be negative, got {self.hold_s!r}")
        if self.depth_mm > limits.travel_limit_mm:
            raise ValueError(f"depth {self.depth_mm:g} mm is beyond the travel limit {limits.travel_limit_mm:g} mm")
        bad = [f for f in self.frames_at_mm if not 0 <= f <= self.depth_mm]
        if bad:
            raise ValueError(f"frames at {', '.join(f'{f:g}' for f in bad)} mm of travel lie outside 0..{self.depth_mm:g} "
                             "mm (from contact to the depth)")


@dataclass(frozen=True)
class Progress:
    state: str  # idle, contact, jog, ramp, hold, unload, retract, stopping, done
    samples: int  # rows recorded (or samples seen, when not recording)
    time_s: float
    displacement_mm: float | None  # from contact (None before contact is known)
    travel_mm: float
    force_N: float
    frames: int
    message: str = ""


@dataclass(frozen=True)
class RunResult:
    folder: Path | None
    outcome: str  # completed | safety | stopped | fault
    message: str
    samples: int
    frames: int
    max_force_N: float
    stage_stopped: bool
    bad_lines: int = 0
    lost_samples: int = 0
    trip_time_s: float | None = None
    error: BaseException | None = None

    @property
    def ok(self) -> bool:
        return self.outcome == "completed"


# ---------------------------------------------------------------------------
# recording
# ---------------------------------------------------------------------------


class Recorder:
    """Grows a new experiment folder: force.csv appended, experiment.toml replaced atomically."""

    def __init__(self, folder: str | Path, template: Experiment, *, name: str | None = None, notes: str = ""):
        self.folder = Path(folder)
        problem = new_folder_problem(self.folder)
        if problem:
            raise DeviceError(f"{self.folder} {problem}", device="recorder")
        (self.folder / "images").mkdir(parents=True, exist_ok=True)
        stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
        self.exp = replace(template, name=name or f"{template.name} (recorded {stamp})",
                           notes=notes, frames=(), force_log_file="force.csv", path=self.folder,
                           force_log=ForceLog(np.zeros(0), np.zeros(0), np.zeros(0)))
        self._fd = os.open(self.folder / "force.csv", os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        os.write(self._fd, b"time_s,displacement_mm,force_N\n")
        self._buf: list[str] = []
        self._last_flush = time.monotonic()
        self.rows = 0
        self.rows_on_disk = 0
        self._last_t = -math.inf
        self._toml_stale = False
        self.closed = False

    @property
    def frames(self) -> int:
        return len(self.exp.frames)

    def add_rows(self, rows) -> None:
        for t, d, f in rows:
            if t <= self._last_t:  # force.csv needs strictly increasing time
                continue
            self._last_t = t
            self._buf.append(f"{t:.6f},{d:.6f},{f:.6f}\n")
            self.rows += 1
        if time.monotonic() - self._last_flush >= FLUSH_PERIOD_S:
            self.flush()

    def flush(self) -> None:
        if self._buf and not self.closed:
            # One write per flush: a killed process leaves whole lines only.
            os.write(self._fd, "".join(self._buf).encode("ascii"))
            self.rows_on_disk += len(self._buf)
            self._buf.clear()
        self._last_flush = time.monotonic()
        if self._toml_stale and self.rows_on_disk >= 2:
            self._write_toml()

    def add_frame(self, pixels: np.ndarray, time_s: float, displacement_mm: float) -> Frame:
        import imageio.v3 as iio

        img = np.asarray(pixels)
        if img.dtype not in (np.uint8, np.uint16):
            img = np.clip(np.round(np.asarray(img, float) * 255.0), 0, 255).astype(np.uint8)
        rel = f"images/frame_{self.frames:03d}.png"
        tmp = self.folder / f"images/.tmp-frame_{self.frames:03d}.png"
        iio.imwrite(tmp, img, extension=".png")
        os.replace(tmp, self.folder / rel)
        fr = Frame(image=rel, time_s=round(max(0.0, time_s), 6), displacement_mm=round(displacement_mm, 6) + 0.0)
        self.exp = self.exp.with_frames(self.exp.frames + (fr,))
        self._toml_stale = True
        self.flush()
        return fr

    def set_notes(self, notes: str) -> None:
        self.exp = replace(self.exp, notes=notes)
        self._toml_stale = True

    def _write_toml(self) -> None:
        os.fsync(self._fd)
        write_toml_atomic(self.folder / TOML, experiment_to_toml(self.exp))
        self._toml_stale = False

    def close(self) -> None:
        if self.closed:
            return
        self.flush()
        self._write_toml()
        os.close(self._fd)
        self.closed = True


def default_template(name: str = "ElastoID recording") -> Experiment:
    """A placeholder description for recordings made without a template: edit it afterwards."""
    return Experiment(
        name=name,
        specimen=Specimen(size_mm=(90.0, 90.0, 50.0), regions=(Region(name="B", kind="background"),)),
        probe=Probe(face_mm=(40.0, 10.0), center_mm=(45.0, 45.0), lateral_axis=(1.0, 0.0, 0.0)),
        imaging=Imaging(pixel_spacing_mm=(0.2, 0.2), probe_face_px=(64.0, 0.0)),
        frames=(), force_log=ForceLog(np.zeros(0), np.zeros(0), np.zeros(0)),
        notes="Placeholder specimen, probe and imaging description: edit experiment.toml to match the specimen.",
    )


# ---------------------------------------------------------------------------
# the monitoring loop
# ---------------------------------------------------------------------------


class _Session:
    """One streaming session: reads samples and status, enforces the limits, records."""

    def __init__(self, rig: "Rig", *, state: str, recorder: Recorder | None, progress, stop):
        self.rig = rig
        self.clock = rig.clock
        self.state = state
        self.recorder = recorder
        self.progress = progress
        self.stop = stop
        now = self.clock.now()
        self.t0 = now
        self.sensor_alive = True
        self.stage_alive = True
        self.securing = False  # while stopping: record, but no trips or timeouts
        self.armed = True
        self.direction = 0  # +1 pressing, -1 retracting, 0 still
        self.speed_mm_s = 0.0
        self.target_mm: float | None = None  # travel the present move was commanded to
        self.trip: DeviceError | None = None
        self.trip_time_s: float | None = None
        self._offset: float | None = None
        self._st_t: deque[float] = deque(maxlen=4000)
        self._st_x: deque[float] = deque(maxlen=4000)
        self._st_v: deque[float] = deque(maxlen=4000)  # speed magnitude at each report
        self._pending: deque[tuple[float, float]] = deque()
        self._recent: deque[tuple[float, float]] = deque(maxlen=6)
        self.last_sample_t = now
        self.last_status_t = now
        self._last_req = -math.inf
        self._unanswered_since: float | None = None  # first status request not answered yet
        self._last_progress = -math.inf
        self.samples = 0
        self.force_N = 0.0
        self.max_force_N = 0.0
        self.rows = 0
        self.crossing_t: float | None = None
        self.crossing_threshold: float | None = None
        self._above = 0
        st = rig.stage.last_status
        if st is not None:
            self._st_t.append(st.time_s)
            self._st_x.append(st.travel_mm)
            self._st_v.append(st.speed_mm_s)

    # ---- positions ----------------------------------------------------------
    def travel_at(self, t: float) -> float:
        if not self._st_t:
            return 0.0
        ts, xs = self._st_t, self._st_x
        if t >= ts[-1]:
            if len(ts) >= 2 and self._st_v[-1] > 0 and xs[-1] != xs[-2]:
                v = self._st_v[-1] * (1.0 if xs[-1] > xs[-2] else -1.0)
                return xs[-1] + v * min(t - ts[-1], 2 * self.rig.status_period_s)
            return xs[-1]
        if t <= ts[0]:
            return xs[0]
        # cubic Hermite between the two reports around t, with their speeds as slopes (the
        # stage accelerates between reports; a straight line would cut the corners)
        i = len(ts) - 1
        while ts[i - 1] > t:
            i -= 1
        t0, t1, x0, x1 = ts[i - 1], ts[i], xs[i - 1], xs[i]
        h = t1 - t0
        if h <= 0:
            return x1
        sign = 1.0 if x1 > x0 else (-1.0 if x1 < x0 else 0.0)
        v0, v1 = sign * self._st_v[i - 1], sign * self._st_v[i]
        u = (t - t0) / h
        x = ((2 * u**3 - 3 * u**2 + 1) * x0 + (u**3 - 2 * u**2 + u) * h * v0
             + (-2 * u**3 + 3 * u**2) * x1 + (u**3 - u**2) * h * v1)
        return float(min(max(x, min(x0, x1)), max(x0, x1)))  # the stage moves one way between reports

    def displacement_now(self) -> float:
        return self.travel_at(self.clock.now()) - (self.rig.contact_mm or 0.0)

    # ---- safety ---------------------------------------------------------------
    def _trip(self, exc: DeviceError) -> None:
        if self.trip is not None or self.securing:
            return
        try:
            self.rig.stage.feed_hold()  # first thing: the stage decelerates while we do the rest
        except DeviceError:
            pass
        self.trip = exc
        self.trip_time_s = self.clock.now() - self.t0

    def _check_sample(self, s: ForceSample) -> None:
        lim = self.rig.limits
        if s.saturated:
            self._trip(SensorSaturated(self.rig.sensor_full_scale_N(), s.force_N))
        elif s.fault:
            self._trip(SensorFault("the sensor flagged its measurement as invalid (bridge or converter fault); "
                                   "the run was stopped", device="force sensor"))
        elif not self.armed or self.direction < 0:
            return
        elif s.force_N >= lim.force_limit_N:
            self._trip(ForceLimitExceeded(
                f"force {s.force_N:.3f} N reached the limit {lim.force_limit_N:g} N", device="safety"))
        elif lim.predictive and self.direction > 0 and len(self._recent) >= 3:
            tt = np.array([p[0] for p in self._recent])
            ff = np.array([p[1] for p in self._recent])
            slope = float(np.polyfit(tt - tt[-1], ff, 1)[0]) if tt[-1] > tt[0] else 0.0
            a = max(self.rig.stage.acceleration_mm_s2, 1e-6)
            tau = self.rig.sample_period_s + self.speed_mm_s / (2 * a) + lim.lookahead_s
            if s.force_N + max(slope, 0.0) * tau >= lim.force_limit_N:
                self._trip(ForceLimitExceeded(
                    f"force {s.force_N:.3f} N rising at {slope:.2f} N/s would pass the limit "
                    f"{lim.force_limit_N:g} N before the stage could stop",
                    device="safety"))

    def _check_travel(self, st: StageStatus) -> None:
        if not self.armed or self.direction < 0 or self.rig.contact_mm is None:
            return
        deeper = len(self._st_x) >= 2 and self._st_x[-1] > self._st_x[-2]
        if not deeper and st.travel_mm - self.rig.contact_mm < self.rig.limits.travel_limit_mm + 0.01:
            return
        lim = self.rig.limits
        a = max(self.rig.stage.acceleration_mm_s2, 1e-6)
        d = st.travel_mm - self.rig.contact_mm
        stop_mm = st.speed_mm_s**2 / (2 * a) + st.speed_mm_s * self.rig.status_period_s
        # A move the rig clamped to the limit stops there by itself; anything else is stopped early.
        clamped = self.target_mm is not None and self.target_mm - self.rig.contact_mm <= lim.travel_limit_mm + 1e-6
        if d >= lim.travel_limit_mm + 0.01 or (not clamped and d + stop_mm >= lim.travel_limit_mm + 1e-6):
            self._trip(TravelLimitExceeded(
                f"the probe reached {d:.3f} mm, at the travel limit {lim.travel_limit_mm:g} mm",
                device="safety"))

    # ---- the tick -------------------------------------------------------------
    def tick(self, timeout_s: float | None = None) -> None:
        """Read what arrived (waiting up to ``timeout_s``), enforce the limits, record, report."""
        rig = self.rig
        if timeout_s is None:
            timeout_s = min(rig.sample_period_s, rig.status_period_s) / 2
        samples: list[ForceSample] = []
        # Silence is judged up to the start of a read that then found nothing. Had it been judged at
        # the end of the tick, a stall of this process (a long GIL hold, a busy machine) between the
        # read and the check would pass for a dead sensor while its data waited in the port.
        listened_t = self.clock.now()
        if self.sensor_alive:
            try:
                samples = rig.sensor.read_samples(timeout_s)
            except DeviceError:
                self.sensor_alive = False
                if not self.securing:
                    raise
        elif self.stage_alive:
            self._poll_stage(timeout_s)
        else:
            self.clock.sleep(timeout_s)
        for s in samples:
            self._on_sample(s)
        now = self.clock.now()
        if self.stage_alive and now - self._last_req >= rig.status_period_s:
            try:
                rig.stage.request_status()
            except DeviceError:
                self.stage_alive = False
                if not self.securing:
                    raise
            self._last_req = now
            if self._unanswered_since is None:
                self._unanswered_since = now
        polled_t = self.clock.now()
        self._poll_stage(0.0)
        self._resolve(final=False)
        self._check_timeouts(listened_t, polled_t)
        self._report(now)
        if not self.securing:
            if rig._estop.is_set():
                raise EmergencyStop("emergency stop pressed: the stage was halted", device="rig")
            if self.stop is not None and self.stop.is_set():
                raise Cancelled("stopped by the user")

    def _poll_stage(self, timeout_s: float) -> None:
        if not self.stage_alive:
            return
        try:
            new = self.rig.stage.poll(timeout_s)
        except GrblAlarm:
            self.stage_alive = True
            raise
        except DeviceError:
            self.stage_alive = False
            if not self.securing:
                raise
            return
        if new:
            self._unanswered_since = None
        for st in new:
            self.last_status_t = st.time_s
            if not self._st_t or st.time_s > self._st_t[-1]:
                self._st_t.append(st.time_s)
                self._st_x.append(st.travel_mm)
                self._st_v.append(st.speed_mm_s)
            self._check_travel(st)

    def _on_sample(self, s: ForceSample) -> None:
        self._check_sample(s)  # safety first, before any bookkeeping
        if self._offset is None:
            origin = getattr(self.rig.sensor, "stream_origin_s", None)
            if origin is None:  # a sensor that cannot say when its clock started: use this arrival
                origin = s.host_time_s - s.device_time_s
            self._offset = origin - self.rig.sensor_latency_s
        t = s.device_time_s + self._offset
        self._recent.append((t, s.force_N))
        self.samples += 1
        self.force_N = s.force_N
        self.max_force_N = max(self.max_force_N, s.force_N)
        self.last_sample_t = self.clock.now()
        if self.crossing_threshold is not None and self.crossing_t is None:
            self._above = self._above + 1 if s.force_N >= self.crossing_threshold else 0
            if self._above == 1:
                self._first_above = t
            if self._above >= 2:
                self.crossing_t = self._first_above
        if t >= self.t0:
            self._pending.append((t, s.force_N))

    def _resolve(self, final: bool) -> None:
        """Give each pending sample its displacement once a status report brackets it."""
        if not self._pending:
            return
        last_st = self._st_t[-1] if self._st_t else -math.inf
        horizon = 3 * self.rig.status_period_s
        rows = []
        contact = self.rig.contact_mm or 0.0
        now = self.clock.now()
        while self._pending:
            t, f = self._pending[0]
            if not final and t > last_st and now - t < horizon:
                break
            self._pending.popleft()
            rows.append((t - self.t0, self.travel_at(t) - contact, f))
        if rows and self.recorder is not None:
            self.recorder.add_rows(rows)
        self.rows += len(rows)

    def _check_timeouts(self, listened_t: float, polled_t: float) -> None:
        """Fault a device silent for longer than its timeout before the read (poll) that found it silent."""
        if self.securing:
            return
        rig = self.rig
        silent = listened_t - self.last_sample_t
        if self.sensor_alive and silent > rig.sensor_timeout_s:
            self.sensor_alive = False
            raise DeviceTimeout(f"no samples for {silent:.2f} s: the sensor stopped sending data",
                                device="force sensor")
        waited = 0.0 if self._unanswered_since is None else polled_t - self._unanswered_since
        if self.stage_alive and waited > rig.stage_timeout_s:
            self.stage_alive = False
            raise DeviceTimeout(f"no status report for {waited:.2f} s: the stage controller stopped answering",
                                device="stage")

    def _report(self, now: float, force: bool = False) -> None:
        if self.progress is None or (not force and now - self._last_progress < 0.1):
            return
        self._last_progress = now
        travel = self.travel_at(now)
        contact = self.rig.contact_mm
        self.progress(Progress(
            state=self.state, samples=self.recorder.rows if self.recorder else self.samples,
            time_s=now - self.t0, displacement_mm=None if contact is None else travel - contact,
            travel_mm=travel, force_N=self.force_N, frames=self.recorder.frames if self.recorder else 0))

    def set_state(self, state: str) -> None:
        self.state = state
        self._report(self.clock.now(), force=True)

    def finish(self) -> None:
        self._resolve(final=True)
        if self.recorder is not None:
            self.recorder.flush()


# ---------------------------------------------------------------------------
# the rig
# ---------------------------------------------------------------------------


def _sentence(text: str) -> str:
    text = text.strip()
    return (text[:1].upper() + text[1:] + ("" if text.endswith(".") else ".")) if text else ""


class Rig:
    """Stage + force sensor (+ image source): jog, find contact, run a protocol, record.

    ``contact_mm`` is the stage travel at first contact; displacement = travel - contact_mm.
    All operations block until done; call them from a worker thread in a GUI.
    :meth:`emergency_stop` may be called from any thread.
    """

    def __init__(self, stage: Stage, sensor: ForceSensor, images: ImageSource | None = None, *,
                 limits: SafetyLimits = SafetyLimits(), clock: Clock | None = None, sample_rate_hz: float = 100.0,
                 status_period_s: float = 0.05, sensor_timeout_s: float = 0.2, stage_timeout_s: float = 0.5,
                 sensor_latency_s: float = 0.0):
        self.stage = stage
        self.sensor = sensor
        self.images = images
        self.limits = limits
        self.clock = clock or MonotonicClock()
        self.sample_rate_hz = sample_rate_hz
        self.status_period_s = status_period_s
        self.sensor_timeout_s = sensor_timeout_s
        self.stage_timeout_s = stage_timeout_s
        self.sensor_latency_s = sensor_latency_s
        self.contact_mm: float | None = None
        self._busy = threading.Lock()
        self._estop = threading.Event()
        self._full_scale: float | None = None
        self.session: _Session | None = None

    @property
    def sample_period_s(self) -> float:
        return 1.0 / self.sample_rate_hz

    def sensor_full_scale_N(self) -> float:
        if self._full_scale is None:
            try:
                self._full_scale = self.sensor.full_scale_N
            except DeviceError:
                return float("nan")
        return self._full_scale

    def displacement_mm(self) -> float | None:
        """Latest displacement from contact (None before contact is known)."""
        if self.contact_mm is None:
            return None
        if self.session is not None:
            return self.session.displacement_now()
        st = self.stage.last_status
        return None if st is None else st.travel_mm - self.contact_mm

    def zero_here(self) -> float:
        """Declare the present position the contact point (displacement 0)."""
        self.contact_mm = self.stage.query_status().travel_mm
        return self.contact_mm

    def allowed_range_mm(self) -> tuple[float, float]:
        lo, hi = self.stage.travel_range_mm
        if self.contact_mm is not None:
            hi = min(hi, self.contact_mm + self.limits.travel_limit_mm)
        return lo, hi

    # ---- plumbing ---------------------------------------------------------------
    @contextmanager
    def _operation(self, state: str, *, recorder=None, progress=None, stop=None, tare: bool = False):
        if not self._busy.acquire(blocking=False):
            raise RigBusy("the rig is busy with another operation", device="rig")
        self._estop.clear()
        session = None
        try:
            if self.sensor.streaming:
                self.sensor.stop()
                self.sensor.read_samples()
            if tare:
                self.sensor.tare()
            self.stage.query_status()
            self.sensor.start(self.sample_rate_hz)
            session = _Session(self, state=state, recorder=recorder, progress=progress, stop=stop)
            self.session = session
            yield session
        finally:
            if session is not None and session.sensor_alive:
                try:
                    self.sensor.stop()
                    for s in self.sensor.read_samples():
                        session._on_sample(s)
                except DeviceError:
                    session.sensor_alive = False
            if session is not None:
                session.finish()
                session.set_state("idle")
            self.session = None
            self._busy.release()

    def _move(self, s: _Session, target_mm: float, speed_mm_s: float, *, direction: int,
              until: Callable[[_Session], bool] | None = None, on_tick: Callable[[_Session], None] | None = None) -> str:
        """Move to ``target_mm`` (stage travel) while monitoring; 'arrived' or 'until'."""
        lo, hi = self.stage.travel_range_mm
        target_mm = min(max(target_mm, lo), hi)
        s.direction, s.speed_mm_s, s.target_mm = direction, speed_mm_s, target_mm
        self.stage.start_move(target_mm, speed_mm_s)
        t_cmd = self.clock.now()
        st0 = self.stage.last_status
        dist = abs(target_mm - (st0.travel_mm if st0 else target_mm))
        a = max(self.stage.acceleration_mm_s2, 1e-6)
        t_max = dist / speed_mm_s + 2 * speed_mm_s / a + 2.0 + 4 * self.stage_timeout_s
        try:
            while True:
                s.tick()
                if s.trip is not None:
                    raise s.trip
                if on_tick is not None:
                    on_tick(s)
                if until is not None and until(s):
                    return "until"
                st = self.stage.last_status
                now = self.clock.now()
                if st is not None and st.time_s > t_cmd + 1e-9 and not st.moving:
                    if st.alarm:
                        raise DeviceError("the stage is in its alarm state and stopped", device="stage")
                    if abs(st.travel_mm - target_mm) < 0.005:
                        return "arrived"
                    if st.time_s > t_cmd + 3 * self.status_period_s + 0.05:
                        raise DeviceError(f"the stage stopped at {st.travel_mm:.3f} mm before reaching "
                                          f"{target_mm:.3f} mm ({st.state})", device="stage")
                if now - t_cmd > t_max:
                    raise DeviceTimeout(f"the stage did not reach {target_mm:.3f} mm within {t_max:.1f} s",
                                        device="stage")
        finally:
            s.direction, s.target_mm = 0, None

    def _wait(self, s: _Session, seconds: float, on_tick=None) -> None:
        t_end = self.clock.now() + seconds
        s.direction = 0
        while self.clock.now() < t_end:
            s.tick(min(s.rig.sample_period_s, max(1e-4, t_end - self.clock.now())))
            if s.trip is not None:
                raise s.trip
            if on_tick is not None:
                on_tick(s)

    def _halt(self, s: _Session, timeout_s: float = 5.0) -> StageStatus:
        """Feed hold (if not already sent), wait still while recording, then clear the hold."""
        self.stage.feed_hold()
        deadline = self.clock.now() + timeout_s
        t_hold = self.clock.now()
        while True:
            s.tick()
            st = self.stage.last_status
            if st is not None and st.time_s > t_hold and not st.moving:
                break
            if not s.stage_alive:
                raise DeviceTimeout("the stage controller stopped answering while stopping", device="stage")
            if self.clock.now() > deadline:
                raise DeviceTimeout(f"the stage was still moving {timeout_s:g} s after the feed hold",
                                    device="stage")
        return self.stage.finish_hold(timeout_s)

    def _secure(self, s: _Session, *, retract: bool, retract_to: float | None) -> tuple[bool, str]:
        """Bring the stage to rest (and back off); return (stopped for sure, what happened)."""
        s.securing = True
        s.set_state("stopping")
        if not s.stage_alive:
            try:
                self.stage.feed_hold()  # in case only the answers are lost
            except DeviceError:
                pass
            return False, ("the stage controller does not answer any more, so the rig could not confirm that it "
                           "stopped: it may still be moving. Use the hardware emergency stop and check the machine.")
        try:
            st = self._halt(s)
        except GrblAlarm as exc:
            return True, f"the stage went into alarm while stopping ({exc.meaning})"
        except DeviceError as exc:
            try:
                self.stage.emergency_stop(timeout_s=1.0)
            except DeviceError:
                pass
            return False, (f"the rig could not confirm that the stage stopped ({exc.message}); it may still be "
                           f"moving. Use the hardware emergency stop and check the machine.")
        if st.alarm:
            return True, "the stage stopped in its alarm state (locked until unlocked with $X); not retracted"
        if not retract or retract_to is None:
            return True, "the stage stopped"
        if st.travel_mm <= retract_to + 1e-3:
            return True, "the stage stopped (already clear of the specimen)"
        try:
            s.armed = False
            s.trip = None
            s.set_state("retract")
            self._move(s, retract_to, self.limits.retract_speed_mm_s, direction=-1)
            return True, f"the stage stopped and retracted to {retract_to - (self.contact_mm or 0):+.3f} mm"
        except DeviceError as exc:
            return True, f"the stage stopped but could not retract ({exc.message})"

    def _retract_target(self, start_travel: float) -> float:
        if self.contact_mm is not None:
            return max(self.contact_mm - self.limits.retract_mm, self.stage.travel_range_mm[0])
        return start_travel

    # ---- operations ---------------------------------------------------------------
    def emergency_stop(self) -> StageStatus | None:
        """Stop from any state, from any thread: feed hold at once; the running operation (if any)
        then discards the rest of the motion and does not retract."""
        self._estop.set()
        if self._busy.locked():
            self.stage.feed_hold()
            return None
        return self.stage.emergency_stop()

    def _guarded(self, s: _Session, body: Callable[[], None], start_travel: float) -> None:
        """Run ``body``; on any trouble stop (and retract when that is safe), then re-raise."""
        try:
            body()
        except BaseException as exc:
            retract = not isinstance(exc, (EmergencyStop, GrblAlarm))
            stopped, note = self._secure(s, retract=retract, retract_to=self._retract_target(start_travel))
            try:
                exc.stage_stopped, exc.stop_note = stopped, note
            except AttributeError:  # an exception type that takes no attributes
                pass
            raise

    def jog(self, delta_mm: float, speed_mm_s: float, *, progress=None, stop=None) -> StageStatus:
        """Move by ``delta_mm`` (positive = into the specimen) and return the final status."""
        with self._operation("jog", progress=progress, stop=stop) as s:
            st = self.stage.query_status()
            lo, hi = self.allowed_range_mm()
            target = min(max(st.travel_mm + delta_mm, lo), hi)
            self._guarded(s, lambda: self._move(s, target, speed_mm_s, direction=1 if delta_mm > 0 else -1),
                          st.travel_mm)
            return self.stage.last_status

    def jog_continuous(self, direction: int, speed_mm_s: float, stop: threading.Event, *,
                       progress=None) -> StageStatus:
        """Move in ``direction`` (+1 into the specimen, -1 away) until ``stop`` is set or a limit is reached."""
        with self._operation("jog", progress=progress) as s:
            st = self.stage.query_status()
            lo, hi = self.allowed_range_mm()
            target = hi if direction > 0 else lo
            if math.isinf(target):
                target = st.travel_mm + direction * 1000.0
            d = 1 if direction > 0 else -1

            def body():
                if self._move(s, target, speed_mm_s, direction=d, until=lambda _: stop.is_set()) == "until":
                    self._halt(s)

            self._guarded(s, body, st.travel_mm)
            return self.stage.last_status

    def monitor(self, stop: threading.Event, *, progress=None) -> None:
        """Stream and report the force (no motion) until ``stop`` is set; the force limit still applies."""
        with self._operation("idle", progress=progress) as s:
            start = self.stage.last_status.travel_mm

            def body():
                while not stop.is_set():
                    s.tick(s.rig.sample_period_s)
                    if s.trip is not None:
                        raise s.trip

            self._guarded(s, body, start)

    def find_contact(self, *, speed_mm_s: float = 0.5, threshold_N: float = 0.05, max_travel_mm: float = 20.0,
                     tare: bool = True, back_to_contact: bool = True, progress=None, stop=None) -> float:
        """Approach until the force crosses ``threshold_N``; set ``contact_mm`` there; return it.

        The sensor is tared first (the probe must be clear of the specimen). The
        contact point is the travel when the force first crossed the threshold
        (two samples in a row); the stage then backs up to it.
        """
        with self._operation("contact", progress=progress, stop=stop, tare=tare) as s:
            st = self.stage.query_status()
            start = st.travel_mm
            self._wait(s, 5 * self.sample_period_s)
            if s.force_N >= threshold_N:
                raise DeviceError(f"already in contact ({s.force_N:.3f} N >= {threshold_N:g} N): retract the "
                                  f"probe first", device="rig")
            s.crossing_threshold = threshold_N
            lo, hi = self.stage.travel_range_mm
            target = min(start + max_travel_mm, hi)
            old_contact = self.contact_mm
            self.contact_mm = None

            def body():
                how = self._move(s, target, speed_mm_s, direction=1, until=lambda ss: ss.crossing_t is not None)
                if how != "until":
                    raise DeviceError(f"no contact within {target - start:.2f} mm: the force stayed below "
                                      f"{threshold_N:g} N", device="rig")
                self._halt(s)
                self.contact_mm = s.travel_at(s.crossing_t)
                if back_to_contact:
                    s.armed = True
                    self._move(s, self.contact_mm, speed_mm_s, direction=-1)

            try:
                self._guarded(s, body, start)
            except BaseException:
                if self.contact_mm is None:
                    self.contact_mm = old_contact
                raise
            return self.contact_mm

    def run(self, protocol: RampHoldUnload, folder: str | Path, template: Experiment, *, name: str | None = None,
            progress: Callable[[Progress], None] | None = None, stop: threading.Event | None = None) -> RunResult:
        """Run ``protocol`` from the contact point, recording into the new folder ``folder``.

        Never raises for device trouble: the result says what happened
        (``outcome`` completed / safety / stopped / fault), whether the stage is
        known to be stopped, and where the data are. Raises ValueError for a
        protocol the limits forbid, DeviceError before anything moves if contact
        is unknown or ``folder`` exists and is not empty.
        """
        protocol.check(self.limits)
        if self.contact_mm is None:
            raise DeviceError("contact is not known: find contact (or zero at contact) first", device="rig")
        notes = (f"Recorded by ElastoID: ramp to {protocol.depth_mm:g} mm at {protocol.speed_mm_s:g} mm/s, "
                 f"hold {protocol.hold_s:g} s, {'unload' if protocol.unload else 'no unload'}; force limit "
                 f"{self.limits.force_limit_N:g} N. {template.notes}").strip()
        recorder = Recorder(folder, template, name=name, notes=notes)
        outcome, message, error, stopped = "completed", "the protocol completed", None, True
        contact = self.contact_mm
        frames_todo = sorted(set(protocol.frames_at_mm))
        s_ref: list[_Session] = []

        def capture(s: _Session, final: bool = False) -> None:
            if self.images is None:
                frames_todo.clear()
                return
            d = s.displacement_now()
            while frames_todo and (d >= frames_todo[0] - 1e-3 or final):
                frames_todo.pop(0)
                # the frame shows the probe where it was when the frame was taken, not
                # where it is once the frame has arrived (the stage keeps moving)
                t_frame, d_frame = self.clock.now() - s.t0, s.displacement_now()
                img = self.images.frame()
                d_meta = img.metadata.get("displacement_mm")
                recorder.add_frame(img.pixels, t_frame, d_frame if d_meta is None else float(d_meta))
                if final:
                    break

        try:
            with self._operation("ramp", recorder=recorder, progress=progress, stop=stop) as s:
                s_ref.append(s)

                def body():
                    capture(s)
                    self._move(s, contact + protocol.depth_mm, protocol.speed_mm_s, direction=1, on_tick=capture)
                    while frames_todo:
                        capture(s, final=True)
                    if protocol.hold_s > 0:
                        s.set_state("hold")
                        self._wait(s, protocol.hold_s)
                    if protocol.unload:
                        s.set_state("unload")
                        self._move(s, contact, protocol.unload_speed_mm_s or protocol.speed_mm_s, direction=-1)
                        if protocol.retract_after:
                            s.set_state("retract")
                            self._move(s, self._retract_target(contact), self.limits.retract_speed_mm_s,
                                       direction=-1)
                    s.set_state("done")

                self._guarded(s, body, contact)
        except Cancelled as exc:
            outcome, error = "stopped", exc
            stopped = getattr(exc, "stage_stopped", True)
            message = f"Stopped by the user. {_sentence(getattr(exc, 'stop_note', ''))}"
        except EmergencyStop as exc:
            outcome, error = "stopped", exc
            stopped = getattr(exc, "stage_stopped", True)
            message = f"Emergency stop: {exc.message}. {_sentence(getattr(exc, 'stop_note', ''))}"
        except (SafetyStop, SensorSaturated, SensorFault) as exc:
            outcome, error = "safety", exc
            stopped = getattr(exc, "stage_stopped", True)
            who = "" if isinstance(exc, SafetyStop) else f"{exc.device}: "
            message = f"Safety stop: {who}{exc.message}. {_sentence(getattr(exc, 'stop_note', ''))}"
        except DeviceError as exc:
            outcome, error = "fault", exc
            stopped = getattr(exc, "stage_stopped", False)
            message = f"Device fault: {str(exc).rstrip('.')}. {_sentence(getattr(exc, 'stop_note', 'the stage state is unknown'))}"
        finally:
            if outcome != "completed":
                recorder.set_notes(f"{recorder.exp.notes} Run ended early ({outcome}): {message}")
            recorder.close()
        s = s_ref[0] if s_ref else None
        return RunResult(folder=recorder.folder, outcome=outcome, message=message, samples=recorder.rows,
                         frames=recorder.frames, max_force_N=s.max_force_N if s else float("nan"),
                         stage_stopped=stopped, bad_lines=getattr(self.sensor, "bad_lines", 0),
                         lost_samples=getattr(self.sensor, "lost_samples", 0),
                         trip_time_s=s.trip_time_s if s else None, error=error)

    def close(self) -> None:
        for dev in (self.stage, self.sensor, self.images):
            if dev is not None:
                try:
                    dev.close()
                except Exception:  # closing must never mask the real outcome
                    pass
