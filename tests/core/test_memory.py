"""The memory budget: what is left, capped by ELASTOID_MEMORY_GB."""

import pytest

from app.core import memory
from app.core.errors import ElastoidError


def test_the_cap_counts_what_the_process_holds(monkeypatch):
    monkeypatch.delenv("ELASTOID_MEMORY_GB", raising=False)
    free = memory.available_bytes()
    held = memory.resident_bytes()
    assert free is not None and free > 0 and held is not None and held > 0  # Linux: /proc is read
    cap_gb = (held + 0.5 * memory.GB) / memory.GB
    monkeypatch.setenv("ELASTOID_MEMORY_GB", f"{cap_gb:.6f}")
    capped = memory.available_bytes()
    assert capped <= min(free, 0.5 * memory.GB) + 0.05 * memory.GB  # the process may grow a little meanwhile
    assert memory.can_hold(0.0, reserve=0.0) and not memory.can_hold(0.6 * memory.GB, reserve=0.0)
    monkeypatch.setenv("ELASTOID_MEMORY_GB", "0.001")  # below what the process holds: nothing left
    assert memory.available_bytes() == 0.0 and not memory.can_hold(1.0)


@pytest.mark.parametrize("raw", ["eight", "-2", "0", "nan"])
def test_a_cap_that_is_not_a_positive_number_is_named(monkeypatch, raw):
    monkeypatch.setenv("ELASTOID_MEMORY_GB", raw)
    with pytest.raises(ElastoidError, match=r"ELASTOID_MEMORY_GB must be a positive number of gigabytes, not "):
        memory.available_bytes()


def test_the_windows_branches_read_what_windows_reports(monkeypatch):
    """Lab PCs run Windows, where /proc is missing: the available physical memory
    comes from GlobalMemoryStatusEx and the process' own from
    GetProcessMemoryInfo. Run here against a stand-in for ctypes.windll that
    fills the structures the way Windows does (by field name)."""
    import builtins
    import ctypes
    import types

    calls = []

    def no_proc(path, *a, **kw):
        if str(path).startswith("/proc"):
            raise FileNotFoundError(path)
        return builtins.open(path, *a, **kw)

    def global_memory_status_ex(ref):
        status = ref._obj
        assert status.dwLength == ctypes.sizeof(status)  # Windows refuses a structure without its size
        status.ullTotalPhys, status.ullAvailPhys = 16 * 10**9, 3 * 10**9
        calls.append("GlobalMemoryStatusEx")
        return 1

    def get_process_memory_info(handle, ref, cb):
        counters = ref._obj
        assert handle == -1 and cb == ctypes.sizeof(counters) == counters.cb
        counters.WorkingSetSize, counters.PeakWorkingSetSize = 2 * 10**9, 2 * 10**9
        calls.append("GetProcessMemoryInfo")
        return 1

    def get_current_process():
        return -1  # Windows' pseudo-handle of the calling process

    # plain functions: the code sets restype and argtypes on them, as on ctypes' own
    kernel32 = types.SimpleNamespace(GlobalMemoryStatusEx=global_memory_status_ex,
                                     GetCurrentProcess=get_current_process)
    psapi = types.SimpleNamespace(GetProcessMemoryInfo=get_process_memory_info)
    monkeypatch.setattr(ctypes, "windll", types.SimpleNamespace(kernel32=kernel32, psapi=psapi), raising=False)
    monkeypatch.setattr(memory, "open", no_proc, raising=False)
    monkeypatch.setattr(memory.sys, "platform", "win32")
    monkeypatch.delenv("ELASTOID_MEMORY_GB", raising=False)

    assert memory.resident_bytes() == 2 * 10**9
    assert memory.available_bytes() == 3 * 10**9
    assert memory.can_hold(1.5 * memory.GB) and not memory.can_hold(2.5 * memory.GB)
    monkeypatch.setenv("ELASTOID_MEMORY_GB", "4")  # 4 GB, 2 of them held: 2 left, below Windows' 3
    assert memory.available_bytes() == pytest.approx(2 * 10**9)
    assert calls.count("GlobalMemoryStatusEx") == 4 and calls.count("GetProcessMemoryInfo") == 2
