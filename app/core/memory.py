"""How much memory is left, for the choices that trade memory for time.

A diagnosis keeps factorizations alive to save time (a tangent per requested
travel for warm starts, the inclusion's model built beside the other
candidates). On the demo that peaks at about 4 GB, but on a finer mesh (the
boxed phantom: 28,161 tetrahedra) at 8.3 GB, more than a lab PC with 8 GB has.
Those choices ask :func:`can_hold` first, and take the slower way when the
answer is no.

``ELASTOID_MEMORY_GB`` caps the memory ElastoID assumes it may use (its own
resident memory included): for a batch of diagnoses sharing a server, and to
try the lean path on a large machine.
"""

from __future__ import annotations

import os
import sys

GB = 1e9
# kept free for the rest of the machine (and for what one estimate leaves out)
RESERVE_BYTES = 1.0 * GB


def _meminfo() -> dict:
    out = {}
    with open("/proc/meminfo") as fh:
        for line in fh:
            key, _, rest = line.partition(":")
            parts = rest.split()
            if parts:
                out[key] = int(parts[0]) * 1024
    return out


def _windows_available() -> int | None:
    import ctypes

    class MemoryStatusEx(ctypes.Structure):
        _fields_ = [("dwLength", ctypes.c_ulong), ("dwMemoryLoad", ctypes.c_ulong),
                    ("ullTotalPhys", ctypes.c_ulonglong), ("ullAvailPhys", ctypes.c_ulonglong),
                    ("ullTotalPageFile", ctypes.c_ulonglong), ("ullAvailPageFile", ctypes.c_ulonglong),
                    ("ullTotalVirtual", ctypes.c_ulonglong), ("ullAvailVirtual", ctypes.c_ulonglong),
                    ("ullAvailExtendedVirtual", ctypes.c_ulonglong)]

    status = MemoryStatusEx()
    status.dwLength = ctypes.sizeof(MemoryStatusEx)
    if not ctypes.windll.kernel32.GlobalMemoryStatusEx(ctypes.byref(status)):
        return None
    return int(status.ullAvailPhys)


def resident_bytes() -> int | None:
    """This process' resident memory, or None where it cannot be read."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    if sys.platform == "win32":  # tested with a stand-in for ctypes.windll (tests/core/test_memory.py)
        try:
            import ctypes
            from ctypes import wintypes

            class Counters(ctypes.Structure):
                _fields_ = [("cb", wintypes.DWORD), ("PageFaultCount", wintypes.DWORD),
                            ("PeakWorkingSetSize", ctypes.c_size_t), ("WorkingSetSize", ctypes.c_size_t),
                            ("QuotaPeakPagedPoolUsage", ctypes.c_size_t), ("QuotaPagedPoolUsage", ctypes.c_size_t),
                            ("QuotaPeakNonPagedPoolUsage", ctypes.c_size_t),
                            ("QuotaNonPagedPoolUsage", ctypes.c_size_t), ("PagefileUsage", ctypes.c_size_t),
                            ("PeakPagefileUsage", ctypes.c_size_t)]

            c = Counters()
            c.cb = ctypes.sizeof(Counters)
            current = ctypes.windll.kernel32.GetCurrentProcess
            current.restype = wintypes.HANDLE  # a pseudo-handle (-1): as a C int it would be truncated
            info = ctypes.windll.psapi.GetProcessMemoryInfo
            info.argtypes = [wintypes.HANDLE, ctypes.POINTER(Counters), wintypes.DWORD]
            if info(current(), ctypes.byref(c), c.cb):
                return int(c.WorkingSetSize)
        except Exception:
            return None
    return None


def limit_bytes() -> float | None:
    """The cap set by ``ELASTOID_MEMORY_GB``, or None. A value that is not a
    positive number is an error that names the variable."""
    raw = os.environ.get("ELASTOID_MEMORY_GB", "").strip()
    if not raw:
        return None
    try:
        value = float(raw)
    except ValueError:
        value = float("nan")
    if not value > 0:
        from app.core.errors import ElastoidError

        raise ElastoidError(f"ELASTOID_MEMORY_GB must be a positive number of gigabytes, not {raw!r}")
    return value * GB


def available_bytes() -> float | None:
    """Memory this process may still take: the machine's available memory
    (MemAvailable on Linux, the available physical memory on Windows), capped by
    ``ELASTOID_MEMORY_GB`` minus what the process holds. None when unknown (then
    nothing is held back)."""
    avail = None
    try:
        info = _meminfo()
        avail = info.get("MemAvailable", info.get("MemFree"))
    except OSError:
        if sys.platform == "win32":  # tested with a stand-in for ctypes.windll (tests/core/test_memory.py)
            avail = _windows_available()
    cap = limit_bytes()
    if cap is not None:
        held = resident_bytes()
        if held is not None:
            left = max(cap - held, 0.0)
            avail = left if avail is None else min(avail, left)
    return None if avail is None else float(avail)


def can_hold(n_bytes: float, reserve: float = RESERVE_BYTES) -> bool:
    """Whether ``n_bytes`` more can be taken and still leave ``reserve`` free (True
    when the available memory is unknown)."""
    avail = available_bytes()
    return avail is None or avail - n_bytes >= reserve


def describe(n_bytes: float | None) -> str:
    return "unknown" if n_bytes is None else f"{n_bytes / GB:.1f} GB"
