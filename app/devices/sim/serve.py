"""Serve a simulated world's devices in real time over pseudo-terminals (or TCP).

Each device gets a pty (``os.openpty``): a driver opens the slave name
(``/dev/pts/N``) with pyserial like any serial port. Where there are no ptys,
each device listens on ``socket://127.0.0.1:PORT`` instead. One thread runs the
world: it reads what the drivers sent, advances the world to the present and
writes what the devices answered. A ``port_lost`` fault closes the device's
end, so the driver sees its port disappear.
"""

from __future__ import annotations

import errno
import os
import select
import socket
import threading
import time

from app.devices.sim.base import SimDevice
from app.devices.sim.world import SimWorld


class _PtyEnd:
    def __init__(self):
        import tty

        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        os.set_blocking(self.master, False)
        self.url = os.ttyname(self.slave)
        self.closed = False

    def fileno(self):
        return self.master

    def fds(self):
        return [] if self.closed else [self.master]

    def ready(self, fd) -> bytes:
        try:
            return os.read(self.master, 4096)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError:
            return b""

    def send(self, data: bytes) -> None:
        if self.closed:
            return
        try:
            os.write(self.master, data)
        except (BlockingIOError, InterruptedError):
            pass  # nobody reads: the bytes are lost, as with a real device's full buffer
        except OSError as exc:
            if exc.errno not in (errno.EIO, errno.EAGAIN):
                raise

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            for fd in (self.master, self.slave):
                try:
                    os.close(fd)
                except OSError:
                    pass


class _SocketEnd:
    def __init__(self):
        self.listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.listener.bind(("127.0.0.1", 0))
        self.listener.listen(1)
        self.listener.setblocking(False)
        self.url = f"socket://127.0.0.1:{self.listener.getsockname()[1]}"
        self.conn: socket.socket | None = None
        self.closed = False

    def fds(self):
        if self.closed:
            return []
        return [self.conn.fileno()] if self.conn else [self.listener.fileno()]

    def ready(self, fd) -> bytes:
        if self.conn is None:
            try:
                self.conn, _ = self.listener.accept()
                self.conn.setblocking(False)
                self.conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            except OSError:
                pass
            return b""
        try:
            data = self.conn.recv(4096)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError:
            data = b""
        if not data:  # client went away: wait for the next one
            self.conn.close()
            self.conn = None
        return data

    def send(self, data: bytes) -> None:
        if self.conn is None or self.closed:
            return
        try:
            self.conn.sendall(data)
        except OSError:
            pass

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            for s in (self.conn, self.listener):
                if s is not None:
                    try:
                        s.close()
                    except OSError:
                        pass


def ptys_available() -> bool:
    try:
        m, s = os.openpty()
    except (OSError, AttributeError):
        return False
    os.close(m)
    os.close(s)
    return True


class SimServer:
    """Runs ``world`` in real time on a thread; ``urls`` maps device name to the address to open."""

    def __init__(self, world: SimWorld, *, transport: str = "auto"):
        if transport not in ("auto", "pty", "socket"):
            raise ValueError(f"transport must be auto, pty or socket, got {transport!r}")
        if transport == "auto":
            transport = "pty" if ptys_available() else "socket"
        self.world = world
        self.transport = transport
        self._ends = {name: (_PtyEnd() if transport == "pty" else _SocketEnd()) for name in world.devices}
        self.urls = {name: end.url for name, end in self._ends.items()}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None

    def start(self) -> "SimServer":
        self._t0 = time.monotonic() - self.world.t
        self._thread = threading.Thread(target=self._run, name="elastoid-sim-rig", daemon=True)
        self._thread.start()
        return self

    def now(self) -> float:
        return time.monotonic() - self._t0

    def _run(self) -> None:
        try:
            self._loop()
        except BaseException as exc:  # surfaced through .error; the thread must not die silently
            self.error = exc
        finally:
            for end in self._ends.values():
                end.close()

    def _loop(self) -> None:
        world = self.world
        fd_owner: dict[int, tuple[str, object]] = {}
        while not self._stop.is_set():
            fd_owner.clear()
            for name, end in self._ends.items():
                for fd in end.fds():
                    fd_owner[fd] = (name, end)
            now = self.now()
            wait = max(0.0, min(0.005, world.next_event_time(after=now) - now))
            try:
                readable = select.select(list(fd_owner), [], [], wait)[0] if fd_owner else []
            except (OSError, ValueError):
                readable = []
            if not fd_owner:
                time.sleep(wait or 0.001)
            now = self.now()
            for fd in readable:
                name, end = fd_owner[fd]
                data = end.ready(fd)
                if data:
                    with world.lock:
                        world.run_until(now)
                        world.deliver(world.devices[name], data)
            world.run_until(now)
            for name, end in self._ends.items():
                dev: SimDevice = world.devices[name]
                if dev.lost:
                    end.close()
                    continue
                out = dev.take(now)
                if out:
                    end.send(out)

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)

    def __enter__(self) -> "SimServer":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
