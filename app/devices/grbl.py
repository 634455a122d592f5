"""GRBL 1.1 motion controller driving one axis of a linear stage.

The protocol (GRBL 1.1 "interface" and "commands" documents):

* a command is one ASCII line ending in LF; GRBL answers ``ok`` or ``error:N``
  once it has parsed (not executed) the line;
* realtime bytes act at once and get no ``ok``: ``?`` status report, ``!`` feed
  hold, ``~`` cycle resume, 0x18 soft reset, 0x85 jog cancel;
* pushed lines may come at any time: ``<...>`` status reports,
  ``ALARM:N``, ``[MSG:...]`` feedback, and the banner
  ``Grbl 1.1h ['$' for help]`` after a reset.

pyserial flushes input on open, so a power-on banner is lost: :meth:`connect`
sends a soft reset (0x18) and waits for the banner it provokes.
"""

from __future__ import annotations

import re
import threading
from dataclasses import dataclass

from app.devices.clock import Clock, MonotonicClock
from app.devices.errors import DeviceTimeout, GrblAlarm, GrblError, ProtocolError
from app.devices.interfaces import Stage, StageStatus
from app.devices.transport import LineBuffer, Port, SerialPort

SOFT_RESET = b"\x18"
STATUS_QUERY = b"?"
FEED_HOLD = b"!"
CYCLE_RESUME = b"~"
JOG_CANCEL = b"\x85"

# GRBL 1.1 error codes: short name, then what GRBL means (after its error_codes_en_US.csv).
GRBL_ERRORS: dict[int, str] = {
    1: "Expected command letter: G-code words consist of a letter and a value; the letter was not found.",
    2: "Bad number format: a value is missing or its number format is not valid.",
    3: "Invalid statement: the '$' system command was not recognized or is not supported.",
    4: "Value < 0: a negative value was received for an expected positive value.",
    5: "Setting disabled: homing is not enabled in the settings ($22).",
    6: "Value < 3 usec: the minimum step pulse time must be greater than 3 microseconds.",
    7: "EEPROM read fail: settings could not be read and were restored to defaults.",
    8: "Not idle: this '$' command can only be used when GRBL is idle.",
    9: "G-code lock: G-code commands are locked out during the alarm or jog state.",
    10: "Homing not enabled: soft limits cannot be enabled without homing.",
    11: "Line overflow: too many characters in the line; it was not executed.",
    12: "Step rate > 30kHz: the setting would exceed the maximum step rate.",
    13: "Check door: the safety door was detected open.",
    14: "Line length exceeded: build info or startup line too long for EEPROM; not stored.",
    15: "Jog travel exceeds max travel: the jog target exceeds the machine travel (soft limits); "
        "the jog was ignored.",
    16: "Invalid jog command: the jog has no '=' or contains prohibited G-code.",
    17: "Setting disabled: laser mode requires PWM output.",
    20: "Unsupported command: unsupported or invalid G-code command found in the line.",
    21: "Modal group violation: more than one G-code command from the same modal group in the line.",
    22: "Undefined feed rate: the feed rate has not been set or is undefined.",
    23: "Invalid G-code ID:23: the command requires an integer value.",
    24: "Invalid G-code ID:24: more than one command that requires axis words in the line.",
    25: "Invalid G-code ID:25: a G-code word was repeated in the line.",
    26: "Invalid G-code ID:26: no axis words found for a command that needs them.",
    27: "Invalid G-code ID:27: line number value is invalid.",
    28: "Invalid G-code ID:28: the command is missing a required value word.",
    29: "Invalid G-code ID:29: G59.x work coordinate systems are not supported.",
    30: "Invalid G-code ID:30: G53 is only allowed with G0 and G1 motion modes.",
    31: "Invalid G-code ID:31: axis words found when no command or modal state uses them.",
    32: "Invalid G-code ID:32: G2/G3 arcs need at least one in-plane axis word.",
    33: "Invalid G-code ID:33: the motion target is invalid.",
    34: "Invalid G-code ID:34: the arc radius value is invalid.",
    35: "Invalid G-code ID:35: G2/G3 arcs need at least one in-plane offset word.",
    36: "Invalid G-code ID:36: unused value words found in the line.",
    37: "Invalid G-code ID:37: G43.1 tool length offset is not assigned to the tool length axis.",
    38: "Invalid G-code ID:38: tool number greater than the maximum supported.",
}

GRBL_ALARMS: dict[int, str] = {
    1: "Hard limit triggered: a limit switch was hit; machine position is likely lost due to the sudden "
       "halt, re-homing is recommended.",
    2: "Soft limit: the G-code motion target exceeds the machine travel; machine position retained, the "
       "alarm may be safely unlocked.",
    3: "Abort during cycle: reset while in motion; machine position is likely lost, re-homing is "
       "recommended.",
    4: "Probe fail: the probe is not in the expected initial state before the probe cycle.",
    5: "Probe fail: the probe did not contact the workpiece within the programmed travel.",
    6: "Homing fail: the active homing cycle was reset.",
    7: "Homing fail: the safety door was opened during homing.",
    8: "Homing fail: pull-off travel failed to clear the limit switch.",
    9: "Homing fail: could not find the limit switch within the search distance.",
}


def grbl_error_text(code: int) -> str:
    return GRBL_ERRORS.get(code, f"unknown GRBL error code {code}.")


def grbl_alarm_text(code: int) -> str:
    return GRBL_ALARMS.get(code, f"unknown GRBL alarm code {code}.")


@dataclass(frozen=True)
class GrblReport:
    """A parsed ``<...>`` status report, GRBL's own units (mm, mm/min)."""

    state: str
    substate: int | None
    mpos: tuple[float, ...] | None
    wpos: tuple[float, ...] | None
    wco: tuple[float, ...] | None
    feed_mm_min: float | None
    spindle_rpm: float | None
    buffer: tuple[int, int] | None  # planner blocks free, rx bytes free
    overrides: tuple[int, ...] | None  # feed, rapid, spindle (%)
    pins: str = ""
    line_number: int | None = None
    raw: str = ""


_STATUS_RE = re.compile(r"<([A-Za-z]+(?::\d)?(?:\|[^<>]*)?)>")
_BANNER_RE = re.compile(r"Grbl (\S+) \['\$' for help\]")
_OK_RE = re.compile(r"(?:^|[^A-Za-z])ok$")
_ERROR_RE = re.compile(r"error:(\d+)$")
_ALARM_RE = re.compile(r"ALARM:(\d+)$")
_BRACKET_RE = re.compile(r"\[([^\[\]]*)\]$")
_SETTING_RE = re.compile(r"^\$(\d+)=([-+0-9.]+)")


def _floats(s: str) -> tuple[float, ...]:
    return tuple(float(x) for x in s.split(","))


def parse_status(text: str) -> GrblReport:
    """Parse ``<State[:n]|MPos:x,y,z|FS:f,s|...>`` (or WPos/WCO/F/Bf/Ov/Pn/Ln variants)."""
    m = _STATUS_RE.search(text)
    if not m:
        raise ProtocolError(f"not a GRBL status report: {text!r}", device="stage")
    parts = m.group(1).split("|")
    state, _, sub = parts[0].partition(":")
    fields: dict[str, str] = {}
    for p in parts[1:]:
        name, _, val = p.partition(":")
        fields[name] = val
    try:
        mpos = _floats(fields["MPos"]) if "MPos" in fields else None
        wpos = _floats(fields["WPos"]) if "WPos" in fields else None
        wco = _floats(fields["WCO"]) if "WCO" in fields else None
        feed = spindle = None
        if "FS" in fields:
            fs = _floats(fields["FS"])
            feed, spindle = fs[0], (fs[1] if len(fs) > 1 else None)
        elif "F" in fields:
            feed = float(fields["F"])
        buf = tuple(int(x) for x in fields["Bf"].split(",")) if "Bf" in fields else None
        ov = tuple(int(x) for x in fields["Ov"].split(",")) if "Ov" in fields else None
        ln = int(fields["Ln"]) if "Ln" in fields else None
    except (ValueError, IndexError):
        raise ProtocolError(f"malformed GRBL status report: {text!r}", device="stage") from None
    if mpos is None and wpos is None:
        raise ProtocolError(f"GRBL status report without a position: {text!r}", device="stage")
    return GrblReport(state=state, substate=int(sub) if sub else None, mpos=mpos, wpos=wpos, wco=wco,
                      feed_mm_min=feed, spindle_rpm=spindle, buffer=buf, overrides=ov,
                      pins=fields.get("Pn", ""), line_number=ln, raw=m.group(0))


_AXES = "XYZ"


class GrblStage(Stage):
    """One axis of a GRBL 1.1 controller as a :class:`Stage`.

    ``axis`` ("X", "Y" or "Z") is the axis that carries the probe and
    ``into_specimen`` (+1 or -1) the sign of machine motion that presses the
    probe into the specimen: travel_mm = into_specimen * machine position.
    Positions are machine coordinates (MPos, or WPos + WCO), so work offsets
    set by other software do not move the rig's zero.
    """

    name = "stage"

    def __init__(self, port: Port, *, axis: str = "Z", into_specimen: int = -1, clock: Clock | None = None,
                 reply_timeout_s: float = 2.0, banner_timeout_s: float = 3.0):
        axis = axis.upper()
        if axis not in _AXES:
            raise ValueError(f"axis must be X, Y or Z, got {axis!r}")
        if into_specimen not in (1, -1):
            raise ValueError(f"into_specimen must be +1 or -1, got {into_specimen!r}")
        self.port = port
        self.axis = axis
        self.into_specimen = into_specimen
        self.clock = clock or MonotonicClock()
        self.reply_timeout_s = reply_timeout_s
        self.banner_timeout_s = banner_timeout_s
        self._i = _AXES.index(axis)
        self._lines = LineBuffer()
        self._wco: tuple[float, ...] = (0.0, 0.0, 0.0)
        self._last: StageStatus | None = None
        self._last_report: GrblReport | None = None
        self._new: list[StageStatus] = []
        self._lock = threading.RLock()  # one reader at a time; realtime bytes bypass it
        self.version: str | None = None
        self.settings: dict[int, float] = {}
        self.messages: list[str] = []  # [MSG:...] and other bracketed feedback
        self.ignored_lines = 0  # lines that were none of GRBL's (noise, garbage)
        self.resets_seen = 0

    # ---- opening --------------------------------------------------------
    @classmethod
    def open(cls, url: str, *, baudrate: int = 115200, connect: bool = True, **kw) -> "GrblStage":
        """Open ``url`` with pyserial's ``serial_for_url`` and (by default) :meth:`connect`."""
        stage = cls(SerialPort(url, baudrate=baudrate, device="stage"), **kw)
        if connect:
            try:
                stage.connect()
            except BaseException:
                stage.close()
                raise
        return stage

    def connect(self) -> StageStatus:
        """Soft-reset (the power-on banner was flushed by open), read ``$$``, query the status."""
        self.soft_reset()
        self.settings = self.read_settings()
        return self.query_status()

    # ---- low level ------------------------------------------------------
    def _write(self, data: bytes) -> None:
        self.port.write(data)

    def _read_lines(self, timeout_s: float) -> list[str]:
        data = self.port.read_some(timeout_s)
        out = []
        for raw in self._lines.feed(data):
            text = "".join(ch for ch in raw.decode("ascii", "replace") if ch.isprintable()).strip()
            if text:
                out.append(text)
        return out

    def _classify(self, line: str) -> tuple[str, object]:
        """Sort one line; store status reports and messages as a side effect."""
        if "<" in line and _STATUS_RE.search(line):
            try:
                rep = parse_status(line)
            except ProtocolError:
                self.ignored_lines += 1
                return "noise", None
            self._store(rep)
            return "status", rep
        m = _ERROR_RE.search(line)
        if m:
            return "error", int(m.group(1))
        m = _ALARM_RE.search(line)
        if m:
            return "alarm", int(m.group(1))
        m = _BANNER_RE.search(line)
        if m:
            self.version = m.group(1)
            self.resets_seen += 1
            return "banner", m.group(1)
        if _OK_RE.search(line):
            return "ok", None
        m = _BRACKET_RE.search(line)
        if m:
            self.messages.append(m.group(1))
            return "info", line
        if _SETTING_RE.match(line):
            return "info", line
        self.ignored_lines += 1
        return "noise", None

    def _store(self, rep: GrblReport) -> None:
        if rep.wco is not None:
            self._wco = rep.wco
        if rep.mpos is not None:
            m = rep.mpos
        else:
            m = tuple(w + o for w, o in zip(rep.wpos, self._wco))
        speed = (rep.feed_mm_min or 0.0) / 60.0
        st = StageStatus(state=rep.state, substate=rep.substate, travel_mm=self.into_specimen * m[self._i] + 0.0,
                         speed_mm_s=speed, time_s=self.clock.now(), raw=rep.raw)
        self._last, self._last_report = st, rep
        self._new.append(st)

    def _fmt_target(self, travel_mm: float) -> str:
        return f"{self.axis}{self.into_specimen * travel_mm:.3f}"

    @staticmethod
    def _feed(speed_mm_s: float) -> str:
        if not speed_mm_s > 0:
            raise ValueError(f"speed must be positive, got {speed_mm_s!r} mm/s")
        return f"F{speed_mm_s * 60.0:.1f}"

    # ---- commands -------------------------------------------------------
    def command(self, line: str, timeout_s: float | None = None) -> list[str]:
        """Send one line, wait for ``ok``; return the informational lines that came before it.

        Raises GrblError on ``error:N``, GrblAlarm on ``ALARM:N``, DeviceTimeout without a reply."""
        timeout_s = self.reply_timeout_s if timeout_s is None else timeout_s
        with self._lock:
            self._write(line.encode("ascii") + b"\n")
            deadline = self.clock.now() + timeout_s
            info: list[str] = []
            while True:
                remaining = deadline - self.clock.now()
                if remaining <= 0:
                    raise DeviceTimeout(f"no reply to {line!r} within {timeout_s:g} s: the controller "
                                        f"stopped answering", device="stage")
                result = None
                alarm = None
                for text in self._read_lines(min(remaining, 0.05)):
                    kind, val = self._classify(text)
                    if kind == "info":
                        info.append(text)
                    elif kind == "alarm" and alarm is None:
                        alarm = val
                    elif kind in ("ok", "error") and result is None:
                        result = (kind, val)
                if alarm is not None:
                    raise GrblAlarm(alarm)
                if result is not None:
                    if result[0] == "error":
                        raise GrblError(result[1], line)
                    return info

    def soft_reset(self) -> str:
        """Send 0x18 and wait for the banner; return GRBL's version (e.g. "1.1h")."""
        with self._lock:
            self._write(SOFT_RESET)
            deadline = self.clock.now() + self.banner_timeout_s
            while self.clock.now() < deadline:
                version = None
                for text in self._read_lines(min(0.05, max(0.0, deadline - self.clock.now()))):
                    kind, val = self._classify(text)
                    if kind == "banner":
                        version = val
                if version is not None:
                    return version
            raise DeviceTimeout(
                f"no GRBL banner within {self.banner_timeout_s:g} s after a soft reset (0x18) on "
                f"{self.port.name}: is this a GRBL 1.1 controller, at the right baud rate?", device="stage")

    def read_settings(self) -> dict[int, float]:
        out = {}
        for text in self.command("$$"):
            m = _SETTING_RE.match(text)
            if m:
                out[int(m.group(1))] = float(m.group(2))
        return out

    def build_info(self) -> list[str]:
        return self.command("$I")

    def unlock(self) -> None:
        self.command("$X")

    # ---- realtime ---------------------------------------------------------
    def request_status(self) -> None:
        self._write(STATUS_QUERY)

    def feed_hold(self) -> None:
        self._write(FEED_HOLD)

    def cycle_resume(self) -> None:
        self._write(CYCLE_RESUME)

    def jog_cancel(self) -> None:
        self._write(JOG_CANCEL)

    # ---- status -----------------------------------------------------------
    @property
    def last_status(self) -> StageStatus | None:
        return self._last

    @property
    def last_report(self) -> GrblReport | None:
        return self._last_report

    def poll(self, timeout_s: float = 0.0) -> list[StageStatus]:
        with self._lock:
            alarm = None
            for text in self._read_lines(timeout_s):
                kind, val = self._classify(text)
                if kind == "alarm" and alarm is None:
                    alarm = val
            new, self._new = self._new, []
            if alarm is not None:
                raise GrblAlarm(alarm)
            return new

    def query_status(self, timeout_s: float = 1.0) -> StageStatus:
        with self._lock:
            self._new = []
            self.request_status()
            deadline = self.clock.now() + timeout_s
            while True:
                new = self.poll(min(0.05, max(0.0, deadline - self.clock.now())))
                if new:
                    return new[-1]
                if self.clock.now() >= deadline:
                    raise DeviceTimeout(f"no status report within {timeout_s:g} s: the controller "
                                        f"stopped answering", device="stage")

    # ---- motion -----------------------------------------------------------
    def jog_by(self, delta_mm: float, speed_mm_s: float) -> None:
        """Relative jog ``$J=G91 G21 <axis>.. F..`` (cancellable with 0x85)."""
        self.command(f"$J=G91 G21 {self.axis}{self.into_specimen * delta_mm:.3f} {self._feed(speed_mm_s)}")

    def jog_to(self, travel_mm: float, speed_mm_s: float) -> None:
        """Jog to a machine position ``$J=G53 G21 <axis>.. F..`` (cancellable with 0x85)."""
        self.command(f"$J=G53 G21 {self._fmt_target(travel_mm)} {self._feed(speed_mm_s)}")

    def linear_move(self, travel_mm: float, speed_mm_s: float, *, relative: bool = False) -> None:
        """G-code feed move: ``G90 G1`` (absolute, work coordinates) or ``G91 G1`` (relative)."""
        if relative:
            self.command(f"G91 G1 {self.axis}{self.into_specimen * travel_mm:.3f} {self._feed(speed_mm_s)}")
        else:
            self.command(f"G90 G1 {self._fmt_target(travel_mm)} {self._feed(speed_mm_s)}")

    def start_move(self, travel_mm: float, speed_mm_s: float) -> None:
        # A jog, not G1: a feed hold ends it cleanly (decelerate, flush, Idle) with no reset needed.
        self.jog_to(travel_mm, speed_mm_s)

    def _wait_stopped(self, timeout_s: float) -> StageStatus:
        deadline = self.clock.now() + timeout_s
        while True:
            st = self.query_status(max(0.05, min(1.0, deadline - self.clock.now())))
            if not st.moving:
                return st
            if self.clock.now() >= deadline:
                raise DeviceTimeout(f"the stage was still moving ({st.state}, {st.speed_mm_s:.2f} mm/s) "
                                    f"{timeout_s:g} s after the stop", device="stage")
            self.clock.sleep(0.01)

    def finish_hold(self, timeout_s: float = 5.0) -> StageStatus:
        with self._lock:
            st = self._wait_stopped(timeout_s)
            if st.state == "Hold":
                # A completed hold (Hold:0) keeps position across a soft reset; the reset drops the
                # rest of the G-code motion so the controller is Idle and ready for new commands.
                self.soft_reset()
                st = self.query_status()
            elif st.state == "Jog":
                self.jog_cancel()
                st = self._wait_stopped(timeout_s)
            return st

    def emergency_stop(self, timeout_s: float = 3.0) -> StageStatus:
        self._write(FEED_HOLD + JOG_CANCEL)
        try:
            return self.finish_hold(timeout_s)
        except DeviceTimeout:
            self._write(SOFT_RESET)  # last resort: GRBL halts at once (and raises ALARM:3)
            raise

    # ---- settings-derived ---------------------------------------------------
    @property
    def acceleration_mm_s2(self) -> float:
        return float(self.settings.get(120 + self._i, 10.0))

    @property
    def max_speed_mm_s(self) -> float:
        return float(self.settings.get(110 + self._i, 500.0)) / 60.0

    @property
    def travel_range_mm(self) -> tuple[float, float]:
        if not self.settings.get(20, 0):
            return (float("-inf"), float("inf"))
        span = float(self.settings.get(130 + self._i, 0.0))
        # GRBL's machine space after homing is [-max_travel, 0] on each axis.
        a, b = sorted((0.0, -span * self.into_specimen))
        return (a, b)

    def close(self) -> None:
        self.port.close()
