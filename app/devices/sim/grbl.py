"""A simulated GRBL 1.1h controller driving one axis.

State machine Idle / Run / Jog / Hold:1 / Hold:0 / Alarm with a trapezoidal
velocity profile (feed rate, acceleration), soft limits (jog -> error:15,
G-code -> ALARM:2), hard limits (ALARM:1), the realtime bytes ``?`` ``!`` ``~``
0x18 0x85, and the lines ``$X $$ $I $G $H $J= $N=v`` and ``G0/G1 G53 G90 G91
G21 F``. Machine space is GRBL's after homing: [-max travel, 0] on the axis.
"""

from __future__ import annotations

import math
import re
from collections import deque
from dataclasses import dataclass

from app.devices.sim.base import SimDevice

BANNER = b"\r\nGrbl 1.1h ['$' for help]\r\n"
_WORD = re.compile(r"([A-Z])([-+]?(?:\d+\.?\d*|\.\d+))")
_AXES = "XYZ"


@dataclass
class _Block:
    target: float  # machine position on the axis, mm
    feed_mm_s: float
    jog: bool


class SimGrbl(SimDevice):
    name = "stage"

    def __init__(self, *, axis: str = "Z", accel_mm_s2: float = 50.0, max_rate_mm_min: float = 1200.0,
                 max_travel_mm: float = 50.0, start_mpos: float = 0.0, soft_limits: bool = True,
                 hard_limits: bool = True, report_wpos: bool = False, wco: tuple = (0.0, 0.0, 0.0),
                 dt_s: float = 0.001, seed: int = 1):
        super().__init__(seed)
        self.i = _AXES.index(axis.upper())
        self.settings: dict[int, float] = {
            0: 10, 1: 25, 2: 0, 3: 0, 4: 0, 5: 0, 6: 0, 10: 0 if report_wpos else 1, 11: 0.010, 12: 0.002,
            13: 0, 20: int(soft_limits), 21: int(hard_limits), 22: 0, 23: 0, 24: 25.0, 25: 500.0,
            26: 250, 27: 1.0, 30: 1000, 31: 0, 32: 0, 100: 250.0, 101: 250.0, 102: 250.0,
            110: 1200.0, 111: 1200.0, 112: 1200.0, 120: 50.0, 121: 50.0, 122: 50.0,
            130: 200.0, 131: 200.0, 132: 200.0,
        }
        self.settings[110 + self.i] = max_rate_mm_min
        self.settings[120 + self.i] = accel_mm_s2
        self.settings[130 + self.i] = max_travel_mm
        self.wco = tuple(wco)
        self.dt = dt_s
        self.t = 0.0
        self.pos = float(start_mpos)
        self.vel = 0.0
        self.queue: deque[_Block] = deque()
        self.holding = False
        self.alarm: int | None = None
        self.absolute = True
        self.feed_mm_min: float | None = None
        self._rx = bytearray()
        self._overflow = False
        self.error_next: int | None = None  # fault: answer the next line with error:N
        self.n_status = 0

    # ---- derived ---------------------------------------------------------
    @property
    def accel(self) -> float:
        return self.settings[120 + self.i]

    @property
    def limits(self) -> tuple[float, float]:
        return (-self.settings[130 + self.i], 0.0)

    @property
    def state(self) -> str:
        if self.alarm is not None:
            return "Alarm"
        if self.queue:
            if self.queue[0].jog:
                return "Jog"
            if self.holding:
                return "Hold:0" if self.vel == 0 else "Hold:1"
            return "Run"
        return "Idle"

    @property
    def moving(self) -> bool:
        return self.vel != 0.0 or (bool(self.queue) and not (self.holding and self.vel == 0))

    # ---- input -----------------------------------------------------------
    def receive(self, data: bytes, t: float) -> None:
        if self.lost or self.mute:
            return
        for b in data:
            if b == 0x3F:  # ?
                self._status(t)
            elif b == 0x21:  # !
                self.log.append((t, "feed_hold"))
                if self.queue and self.alarm is None:
                    self.holding = True
            elif b == 0x7E:  # ~
                if self.holding and self.vel == 0 and self.queue and not self.queue[0].jog:
                    self.holding = False
            elif b == 0x18:
                self.log.append((t, "soft_reset"))
                self._reset(t)
            elif b == 0x85:
                self.log.append((t, "jog_cancel"))
                if self.queue and self.queue[0].jog:
                    self.holding = True
            elif b >= 0x80:
                pass  # other realtime overrides: accepted, ignored
            elif b == 0x0A:
                line = self._rx.decode("ascii", "replace")
                over, self._overflow = self._overflow, False
                self._rx.clear()
                self._line(line, t, over)
            elif b == 0x0D:
                pass
            else:
                if len(self._rx) >= 80:
                    self._overflow = True
                else:
                    self._rx.append(b)

    def _send(self, t: float, text: str) -> None:
        self.emit(t, text.encode("ascii") + b"\r\n")

    def _status(self, t: float) -> None:
        m = [0.0, 0.0, 0.0]
        m[self.i] = self.pos
        self.n_status += 1
        fmt = lambda v: ",".join(f"{x:.3f}" for x in v)  # noqa: E731
        parts = [self.state]
        if self.settings[10] == 0:
            parts.append("WPos:" + fmt([a - b for a, b in zip(m, self.wco)]))
        else:
            parts.append("MPos:" + fmt(m))
        parts.append(f"Bf:{15 - len(self.queue)},128")
        parts.append(f"FS:{abs(self.vel) * 60.0:.0f},0")
        if self.settings[10] == 0 and self.n_status % 10 == 1:
            parts.append("WCO:" + fmt(self.wco))
        if self.n_status % 10 == 2:
            parts.append("Ov:100,100,100")
        self._send(t, "<" + "|".join(parts) + ">")

    def _reset(self, t: float) -> None:
        was_moving = self.vel != 0.0 or (bool(self.queue) and not self.holding)
        self.queue.clear()
        self.holding = False
        self.vel = 0.0
        self._rx.clear()
        self.absolute = True
        self.feed_mm_min = None
        self.error_next = None
        if was_moving:
            self.alarm = 3
            self._send(t, "ALARM:3")
        self.emit(t, BANNER)
        if self.alarm is not None:
            self._send(t, "[MSG:'$H'|'$X' to unlock]")

    def raise_alarm(self, t: float, code: int) -> None:
        """Enter the alarm state at once (motion halts, queue flushed) and push ``ALARM:code``."""
        self.alarm = code
        self.queue.clear()
        self.holding = False
        self.vel = 0.0
        self.log.append((t, f"alarm:{code}"))
        self._send(t, f"ALARM:{code}")

    # ---- lines -----------------------------------------------------------
    def _line(self, line: str, t: float, overflow: bool) -> None:
        text = line.replace(" ", "").upper()
        self.log.append((t, f"line:{text}"))
        if self.error_next is not None:
            code, self.error_next = self.error_next, None
            return self._send(t, f"error:{code}")
        if overflow:
            return self._send(t, "error:11")
        if not text:
            return self._send(t, "ok")
        if text.startswith("$"):
            return self._system(text, t)
        if self.alarm is not None or (self.queue and self.queue[0].jog):
            return self._send(t, "error:9")
        self._gcode(text, t)

    def _system(self, text: str, t: float) -> None:
        if text == "$X":
            if self.alarm is not None:
                self.alarm = None
                self._send(t, "[MSG:Caution: Unlocked]")
            return self._send(t, "ok")
        if text == "$$":
            for k in sorted(self.settings):
                v = self.settings[k]
                self._send(t, f"${k}={v:.3f}" if isinstance(v, float) else f"${k}={v}")
            return self._send(t, "ok")
        if text == "$I":
            self._send(t, "[VER:1.1h.20190825:]")
            self._send(t, "[OPT:V,15,128]")
            return self._send(t, "ok")
        if text == "$G":
            self._send(t, f"[GC:G0 G54 G17 G21 {'G90' if self.absolute else 'G91'} G94 M5 M9 T0 F0 S0]")
            return self._send(t, "ok")
        if text == "$H":
            return self._send(t, "error:5")
        if text.startswith("$J="):
            return self._jog(text[3:], t)
        m = re.fullmatch(r"\$(\d+)=([-+]?\d*\.?\d+)", text)
        if m:
            if self.moving:
                return self._send(t, "error:8")
            k = int(m.group(1))
            if k not in self.settings:
                return self._send(t, "error:3")
            v = float(m.group(2))
            self.settings[k] = int(v) if isinstance(self.settings[k], int) else v
            return self._send(t, "ok")
        return self._send(t, "error:3")

    def _words(self, text: str) -> list[tuple[str, float]] | int:
        words = _WORD.findall(text)
        if "".join(a + b for a, b in words) != text:
            return 1 if not text[:1].isalpha() else 2
        return [(a, float(b)) for a, b in words]

    def _jog(self, text: str, t: float) -> None:
        if self.alarm is not None:
            return self._send(t, "error:9")
        if self.queue and not self.queue[0].jog:
            return self._send(t, "error:8")
        words = self._words(text)
        if isinstance(words, int):
            return self._send(t, "error:16")
        absolute, machine, target, feed = self.absolute, False, None, None
        for letter, val in words:
            if letter == "G":
                if val == 90:
                    absolute = True
                elif val == 91:
                    absolute = False
                elif val == 53:
                    machine = True
                elif val == 21:
                    pass
                else:
                    return self._send(t, "error:16")
            elif letter == "F":
                feed = val
            elif letter in _AXES:
                if _AXES.index(letter) == self.i:
                    target = val
            else:
                return self._send(t, "error:16")
        if feed is None or feed <= 0:
            return self._send(t, "error:22")
        if target is None:
            return self._send(t, "ok")
        end = self._end_of_queue()
        goal = (target if machine else target + self.wco[self.i]) if (absolute or machine) else end + target
        lo, hi = self.limits
        if self.settings[20] and not (lo - 1e-9 <= goal <= hi + 1e-9):
            return self._send(t, "error:15")
        self.queue.append(_Block(goal, min(feed, self.settings[110 + self.i]) / 60.0, jog=True))
        self._send(t, "ok")

    def _end_of_queue(self) -> float:
        return self.queue[-1].target if self.queue else self.pos

    def _gcode(self, text: str, t: float) -> None:
        words = self._words(text)
        if isinstance(words, int):
            return self._send(t, f"error:{words}")
        motion, machine, target = None, False, None
        absolute = self.absolute
        feed = self.feed_mm_min
        for letter, val in words:
            if letter == "G":
                if val in (0, 1):
                    motion = int(val)
                elif val == 90:
                    absolute = True
                elif val == 91:
                    absolute = False
                elif val == 53:
                    machine = True
                elif val in (21, 94, 17, 54):
                    pass
                else:
                    return self._send(t, "error:20")
            elif letter == "F":
                feed = val
            elif letter in _AXES:
                if _AXES.index(letter) == self.i:
                    target = val
            elif letter == "N":
                pass
            else:
                return self._send(t, "error:20")
        self.absolute = absolute
        self.feed_mm_min = feed
        if target is None:
            return self._send(t, "ok")
        if motion is None:
            motion = 1
        if motion == 1 and not feed:
            return self._send(t, "error:22")
        speed = self.settings[110 + self.i] / 60.0 if motion == 0 else min(feed, self.settings[110 + self.i]) / 60.0
        end = self._end_of_queue()
        goal = (target if machine else target + self.wco[self.i]) if (absolute or machine) else end + target
        lo, hi = self.limits
        if self.settings[20] and not (lo - 1e-9 <= goal <= hi + 1e-9):
            self._send(t, "ok")
            return self.raise_alarm(t, 2)
        self.queue.append(_Block(goal, speed, jog=False))
        self._send(t, "ok")

    # ---- kinematics ---------------------------------------------------------
    def advance(self, t_end: float) -> None:
        while self.t < t_end - 1e-12:
            dt = min(self.dt, t_end - self.t)
            self._step(dt)
            self.t += dt

    def _step(self, dt: float) -> None:
        if not self.queue or self.alarm is not None:
            self.vel = 0.0
            return
        a = self.accel
        blk = self.queue[0]
        d = blk.target - self.pos
        if self.holding:
            goal_v = 0.0
        else:
            goal_v = math.copysign(min(blk.feed_mm_s, math.sqrt(2.0 * a * abs(d))), d) if d else 0.0
        dv = max(-a * dt, min(a * dt, goal_v - self.vel))
        v_new = self.vel + dv
        step = 0.5 * (self.vel + v_new) * dt
        if not self.holding and (abs(d) <= max(1e-7, abs(step)) and (d == 0 or step * d >= 0)):
            self.pos = blk.target
            self.vel = 0.0
            self.queue.popleft()
        else:
            self.pos += step
            self.vel = v_new
            if self.holding and abs(self.vel) < 1e-9:
                self.vel = 0.0
                if blk.jog:  # a hold (or jog cancel) ends a jog: flush it, back to Idle
                    self.queue.clear()
                    self.holding = False
        lo, hi = self.limits
        if self.settings[21] and not (lo - 0.5 <= self.pos <= hi + 0.5):
            self.raise_alarm(self.t, 1)
