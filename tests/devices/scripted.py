"""A scripted fake transport for byte-exact driver tests."""

from __future__ import annotations

from app.devices.clock import VirtualClock


class ScriptedPort:
    """A fake transport that checks each request's exact bytes and answers the scripted reply.

    ``script`` is a list of (expected request bytes, reply bytes). Bytes written
    must match the next expected request exactly (as a whole, or as a prefix
    while a request is being written in pieces). Reading with nothing to read
    lets virtual time pass, so timeouts are exercised without waiting.
    """

    def __init__(self, script=(), *, pushed: bytes = b"", clock: VirtualClock | None = None):
        self.script = list(script)
        self.rx = bytearray(pushed)
        self.sent = bytearray()
        self._partial = bytearray()
        self.clock = clock or VirtualClock()
        self.name = "scripted://"

    def push(self, data: bytes) -> None:
        self.rx += data

    def write(self, data: bytes) -> None:
        self.sent += data
        self._partial += data
        while self._partial:
            assert self.script, f"unexpected request {bytes(self._partial)!r}: the script is finished"
            want, reply = self.script[0]
            if bytes(self._partial[: len(want)]) == want:
                del self._partial[: len(want)]
                self.script.pop(0)
                self.rx += reply
            else:
                assert want.startswith(bytes(self._partial)), \
                    f"request {bytes(self._partial)!r} does not match the expected {want!r}"
                break

    def read_some(self, timeout_s: float) -> bytes:
        if not self.rx:
            self.clock.sleep(timeout_s)
            return b""
        out = bytes(self.rx)
        self.rx.clear()
        return out

    def close(self) -> None:
        pass

    def done(self) -> bool:
        return not self.script and not self._partial
