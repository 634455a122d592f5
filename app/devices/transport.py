"""Byte transports: what a driver reads from and writes to.

A driver talks to a :class:`Port`: ``write(bytes)``, ``read_some(timeout_s)``
and ``close()``. :class:`SerialPort` opens anything pyserial's
``serial_for_url`` understands (``/dev/ttyUSB0``, ``COM3``,
``socket://host:port``, ``loop://``); tests use scripted fakes and the
simulated rig a virtual port, all through this same small surface.
"""

from __future__ import annotations

import threading
from typing import Protocol

import serial

from app.devices.errors import DeviceTimeout, PortLost


class Port(Protocol):
    name: str

    def write(self, data: bytes) -> None:
        """Send bytes; raise PortLost if the port is gone."""

    def read_some(self, timeout_s: float) -> bytes:
        """Whatever bytes arrive within ``timeout_s`` (b"" if none); PortLost if the port is gone."""

    def close(self) -> None:
        """Release the port; never raises."""


class SerialPort:
    """A pyserial port opened with ``serial.serial_for_url``.

    Note: pyserial's open flushes the input buffer, so whatever the device
    said before the port was opened (a power-on banner) is gone.
    """

    _TICK_S = 0.005  # read granularity; the port's own timeout is fixed to avoid reconfiguring it

    def __init__(self, url: str, *, baudrate: int = 115200, device: str = ""):
        self.name = url
        self.device = device
        self._write_lock = threading.Lock()
        try:
            self._ser = serial.serial_for_url(url, baudrate=baudrate, timeout=self._TICK_S, write_timeout=2.0)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise PortLost(f"cannot open port {url}: {exc}", device=device) from None

    def write(self, data: bytes) -> None:
        with self._write_lock:
            try:
                self._ser.write(data)
            except serial.SerialTimeoutException:
                raise DeviceTimeout(f"writing to {self.name} timed out: the device does not take data",
                                    device=self.device) from None
            except (serial.SerialException, OSError, AttributeError, TypeError) as exc:
                raise PortLost(f"port {self.name} disappeared while writing ({exc})", device=self.device) from None

    def read_some(self, timeout_s: float) -> bytes:
        import time

        deadline = time.monotonic() + max(0.0, timeout_s)
        try:
            while True:
                n = self._ser.in_waiting
                if n:
                    return self._ser.read(n)
                if timeout_s <= 0:
                    return b""
                data = self._ser.read(1)
                if data:
                    n = self._ser.in_waiting
                    return data + (self._ser.read(n) if n else b"")
                if time.monotonic() >= deadline:
                    return b""
        except (serial.SerialException, OSError, AttributeError, TypeError) as exc:
            raise PortLost(f"port {self.name} disappeared while reading ({exc})", device=self.device) from None

    def close(self) -> None:
        try:
            self._ser.close()
        except Exception:  # closing a vanished port may fail in many ways; it is closed either way
            pass


class LineBuffer:
    """Bytes in, complete lines out; a partial line waits for its end.

    Lines end with LF; a CR before it is dropped. A partial line longer than
    ``max_len`` is discarded (counted in ``overflows``) so garbage without a
    newline cannot grow the buffer forever.
    """

    def __init__(self, max_len: int = 256):
        self._buf = bytearray()
        self.max_len = max_len
        self.overflows = 0

    def feed(self, data: bytes) -> list[bytes]:
        self._buf += data
        lines = []
        while True:
            i = self._buf.find(b"\n")
            if i < 0:
                break
            line = bytes(self._buf[:i]).rstrip(b"\r")
            del self._buf[: i + 1]
            lines.append(line)
        if len(self._buf) > self.max_len:
            self._buf.clear()
            self.overflows += 1
        return lines

    def clear(self) -> None:
        self._buf.clear()

    @property
    def pending(self) -> bytes:
        return bytes(self._buf)
