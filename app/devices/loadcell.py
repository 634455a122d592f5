"""ELC-1: a streaming ASCII load-cell protocol, and its driver.

Byte-level description in docs/devices.md. In short: the host sends plain
commands ending in LF (``ID?``, ``TARE``, ``START <hz>``, ``STOP``); every line
the device sends is framed ``$<body>*<CC>\\r\\n`` where CC is the CRC-8
(polynomial 0x07, initial value 0, no reflection, as two upper-case hex
digits) of the body bytes. A sample body is
``S,<seq>,<t_us>,<force_N>,<flags>``.

A line whose CRC does not match, or that cannot be parsed, is dropped and
counted in ``bad_lines``; it is never read as a force. A gap in the sequence
numbers is counted in ``lost_samples``. Garbage before a ``$`` is skipped, and
a partial line waits in the buffer for its end.
"""

from __future__ import annotations

from dataclasses import dataclass

from app.devices.clock import Clock, MonotonicClock
from app.devices.errors import DeviceError, DeviceTimeout, ProtocolError
from app.devices.interfaces import ForceSample, ForceSensor, SensorInfo
from app.devices.transport import LineBuffer, Port, SerialPort

SEQ_MODULO = 1 << 16
TIME_MODULO_US = 1 << 32
FLAG_SATURATED = 0x01
FLAG_FAULT = 0x02

ERROR_TEXT = {
    1: "unknown command",
    2: "bad argument",
    3: "not allowed while streaming",
    4: "command line too long",
    5: "tare failed: the reading was not steady",
}


def _crc8_table() -> list[int]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x07) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table.append(crc)
    return table


_CRC8 = _crc8_table()


def crc8(data: bytes) -> int:
    """CRC-8, polynomial 0x07, init 0x00, no reflection, no final XOR (CRC-8/SMBUS; "123456789" -> 0xF4)."""
    crc = 0
    for b in data:
        crc = _CRC8[crc ^ b]
    return crc


def frame(body: str) -> bytes:
    """A device line: ``$`` body ``*`` CRC ``\\r\\n``."""
    raw = body.encode("ascii")
    return b"$" + raw + b"*" + f"{crc8(raw):02X}".encode("ascii") + b"\r\n"


def unframe(line: bytes) -> str | None:
    """The body of a framed line, or None if the frame or its CRC is wrong. Skips garbage before ``$``."""
    i = line.rfind(b"$")
    if i < 0:
        return None
    line = line[i + 1:]
    j = line.rfind(b"*")
    if j < 0 or len(line) - j != 3:
        return None
    body, cc = line[:j], line[j + 1:]
    try:
        want = int(cc.decode("ascii"), 16)
        text = body.decode("ascii")
    except (UnicodeDecodeError, ValueError):
        return None
    if not all(c in "0123456789ABCDEF" for c in cc.decode("ascii")) or crc8(body) != want:
        return None
    if not text.isprintable():
        return None
    return text


def sample_body(seq: int, t_us: int, force_N: float, flags: int) -> str:
    return f"S,{seq % SEQ_MODULO},{t_us % TIME_MODULO_US},{force_N:+.4f},{flags:02X}"


@dataclass
class _Reply:
    kind: str  # "OK", "ERR", "ID"
    fields: list[str]


class AsciiLoadCell(ForceSensor):
    """Driver for an ELC-1 load cell (see docs/devices.md)."""

    name = "force sensor"

    def __init__(self, port: Port, *, clock: Clock | None = None, reply_timeout_s: float = 1.0):
        self.port = port
        self.clock = clock or MonotonicClock()
        self.reply_timeout_s = reply_timeout_s
        self._lines = LineBuffer(max_len=200)
        self._samples: list[ForceSample] = []
        self._replies: list[_Reply] = []
        self._streaming = False
        self._next_seq: int | None = None
        self._seq_base = 0
        self._last_raw_seq: int | None = None
        self._t_base_us = 0
        self._last_raw_t: int | None = None
        self.info: SensorInfo | None = None
        self.rate_hz: float | None = None
        self.stream_origin_s: float | None = None
        self.bad_lines = 0
        self.lost_samples = 0
        self.samples_received = 0

    @classmethod
    def open(cls, url: str, *, baudrate: int = 115200, identify: bool = True, **kw) -> "AsciiLoadCell":
        cell = cls(SerialPort(url, baudrate=baudrate, device="force sensor"), **kw)
        if identify:
            try:
                cell.stop()  # a sensor left streaming by a previous session
                cell.identify()
            except BaseException:
                cell.close()
                raise
        return cell

    # ---- parsing ----------------------------------------------------------
    def _pump(self, timeout_s: float) -> None:
        data = self.port.read_some(timeout_s)
        if not data:
            return
        overflows = self._lines.overflows
        for line in self._lines.feed(data):
            self._handle(line)
        self.bad_lines += self._lines.overflows - overflows

    def _handle(self, line: bytes) -> None:
        if not line.strip():
            return
        body = unframe(line)
        if body is None:
            self.bad_lines += 1
            return
        fields = body.split(",")
        kind = fields[0]
        if kind == "S":
            s = self._parse_sample(fields)
            if s is None:
                self.bad_lines += 1
            elif self._streaming:
                self._samples.append(s)
        elif kind in ("OK", "ERR", "ID"):
            self._replies.append(_Reply(kind, fields[1:]))
        else:
            self.bad_lines += 1

    def _parse_sample(self, fields: list[str]) -> ForceSample | None:
        if len(fields) != 5:
            return None
        try:
            seq = int(fields[1])
            t_us = int(fields[2])
            force = float(fields[3])
            flags = int(fields[4], 16)
        except ValueError:
            return None
        if not (0 <= seq < SEQ_MODULO and 0 <= t_us < TIME_MODULO_US) or force != force:
            return None
        # unwrap sequence and device time
        if self._last_raw_seq is not None and seq < self._last_raw_seq:
            self._seq_base += SEQ_MODULO
        self._last_raw_seq = seq
        if self._last_raw_t is not None and t_us < self._last_raw_t:
            self._t_base_us += TIME_MODULO_US
        self._last_raw_t = t_us
        full_seq = self._seq_base + seq
        if self._next_seq is not None and full_seq > self._next_seq:
            self.lost_samples += full_seq - self._next_seq
        self._next_seq = full_seq + 1
        self.samples_received += 1
        return ForceSample(seq=full_seq, device_time_s=(self._t_base_us + t_us) * 1e-6, force_N=force,
                           saturated=bool(flags & FLAG_SATURATED), fault=bool(flags & FLAG_FAULT),
                           host_time_s=self.clock.now())

    def _request(self, command: str, expect: str, timeout_s: float | None = None) -> list[str]:
        timeout_s = self.reply_timeout_s if timeout_s is None else timeout_s
        self._replies.clear()
        self.port.write(command.encode("ascii") + b"\n")
        deadline = self.clock.now() + timeout_s
        word = command.split()[0]
        while True:
            while self._replies:
                r = self._replies.pop(0)
                if r.kind == "ERR":
                    code = int(r.fields[0]) if r.fields and r.fields[0].isdigit() else 0
                    text = ",".join(r.fields[1:]) or ERROR_TEXT.get(code, "error")
                    raise DeviceError(f"the sensor refused {command!r}: {text} (ERR {code})",
                                      device="force sensor")
                if r.kind == expect and (expect != "OK" or (r.fields and r.fields[0] == word)):
                    return r.fields
            remaining = deadline - self.clock.now()
            if remaining <= 0:
                raise DeviceTimeout(f"no reply to {command!r} within {timeout_s:g} s: the sensor "
                                    f"stopped answering", device="force sensor")
            self._pump(min(remaining, 0.05))

    # ---- commands -----------------------------------------------------------
    def identify(self) -> SensorInfo:
        f = self._request("ID?", "ID")
        if len(f) != 5:
            raise ProtocolError(f"unexpected identity reply {f!r}", device="force sensor")
        try:
            fs = float(f[4])
        except ValueError:
            raise ProtocolError(f"unexpected full scale {f[4]!r} in identity reply", device="force sensor") from None
        self.info = SensorInfo(vendor=f[0], model=f[1], serial=f[2], firmware=f[3], full_scale_N=fs)
        return self.info

    @property
    def full_scale_N(self) -> float:
        if self.info is None:
            self.identify()
        return self.info.full_scale_N

    @property
    def streaming(self) -> bool:
        return self._streaming

    def tare(self) -> float:
        f = self._request("TARE", "OK", timeout_s=max(self.reply_timeout_s, 2.0))
        try:
            return float(f[1])
        except (IndexError, ValueError):
            raise ProtocolError(f"unexpected tare reply {f!r}", device="force sensor") from None

    def start(self, rate_hz: float) -> None:
        rate = int(round(rate_hz))
        self._next_seq = None
        self._seq_base = 0
        self._last_raw_seq = None
        self._t_base_us = 0
        self._last_raw_t = None
        self._samples.clear()
        self._streaming = True
        t_sent = self.clock.now()
        try:
            f = self._request(f"START {rate}", "OK")
        except BaseException:
            self._streaming = False
            raise
        self.rate_hz = float(f[1]) if len(f) > 1 else float(rate)
        # Device time 0 is when START arrived: between sending it and the reply, so take the middle.
        self.stream_origin_s = 0.5 * (t_sent + self.clock.now())

    def stop(self) -> None:
        self._request("STOP", "OK")
        self._streaming = False

    def read_samples(self, timeout_s: float = 0.0) -> list[ForceSample]:
        if not self._samples:
            self._pump(timeout_s)
        else:
            self._pump(0.0)
        out, self._samples = self._samples, []
        return out

    def close(self) -> None:
        self.port.close()
