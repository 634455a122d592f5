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
