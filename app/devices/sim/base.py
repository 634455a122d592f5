"""What every simulated device shares: an output queue with timestamps and fault switches."""

from __future__ import annotations

from collections import deque

import numpy as np


class SimDevice:
    """Bytes a simulated device has sent, each chunk available from its time on.

    Fault switches: ``mute`` (stops answering: input ignored, nothing sent),
    ``lost`` (the port disappeared), ``fragment`` (lines arrive in pieces).
    """

    name = "device"

    def __init__(self, seed: int = 0):
        self.rng = np.random.default_rng(seed)
        self._out: deque[tuple[float, bytes]] = deque()
        self.mute = False
        self.lost = False
        self.fragment = False
        self.log: list[tuple[float, str]] = []  # (time, event) for tests and the bench

    def emit(self, t: float, data: bytes) -> None:
        if self.mute or self.lost or not data:
            return
        if self.fragment and len(data) > 3:
            k = int(min(3, len(data) - 1))
            cuts = sorted(int(c) for c in self.rng.choice(np.arange(1, len(data)), size=k, replace=False))
            pieces = [data[a:b] for a, b in zip([0] + cuts, cuts + [len(data)])]
            for i, p in enumerate(pieces):
                self._out.append((t + 0.002 * i, p))
        else:
            self._out.append((t, data))

    def garbage(self, t: float, n: int = 24) -> None:
        """A burst of line noise (random bytes, never a '$' or LF), ended by CR LF."""
        raw = self.rng.integers(0, 256, size=n).astype(np.uint8).tobytes()
        raw = raw.replace(b"\n", b"#").replace(b"$", b"#")
        self._out.append((t, raw + b"\r\n"))

    def take(self, t: float) -> bytes:
        """All bytes available at time ``t``, in order."""
        out = bytearray()
        while self._out and self._out[0][0] <= t + 1e-12:
            out += self._out.popleft()[1]
        return bytes(out)

    def next_output_time(self) -> float:
        return self._out[0][0] if self._out else float("inf")

    def next_output_after(self, t: float) -> float:
        """The first time after ``t`` at which more bytes become available."""
        for ta, _ in self._out:
            if ta > t + 1e-12:
                return ta
        return float("inf")

    def receive(self, data: bytes, t: float) -> None:
        raise NotImplementedError

    def advance(self, t: float) -> None:
        raise NotImplementedError
