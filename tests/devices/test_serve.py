"""The twins served in real time over pseudo-terminals and TCP, opened by the real drivers."""

from __future__ import annotations

import time

import pytest

from app.devices.errors import PortLost
from app.devices.grbl import GrblStage
from app.devices.loadcell import AsciiLoadCell
from app.devices.sim import NonlinearSpring, SimRig, ptys_available


@pytest.mark.parametrize("transport", ["pty", "socket"])
def test_drivers_open_the_served_twins(transport):
    if transport == "pty":
        assert ptys_available()  # this machine has them; the socket case covers machines that do not
    sim = SimRig(NonlinearSpring(1.0, 0.0, 0.5))
    server = sim.serve(transport)
    try:
        url = server.urls["stage"]
        assert url.startswith("/dev/") if transport == "pty" else url.startswith("socket://127.0.0.1:")
        stage = GrblStage.open(server.urls["stage"])
        sensor = AsciiLoadCell.open(server.urls["force"])
        assert stage.version == "1.1h" and sensor.info.full_scale_N == 50.0
        sensor.start(200)
        stage.start_move(1.0, 5.0)
        got = []
        t_end = time.monotonic() + 0.6
        while time.monotonic() < t_end:
            got += sensor.read_samples(0.02)
        sensor.stop()
        st = stage.query_status()
        assert st.state == "Idle" and st.travel_mm == pytest.approx(1.0)
        assert len(got) > 60 and got[-1].force_N == pytest.approx(0.5, abs=0.01)
        assert [s.seq for s in got] == list(range(len(got)))  # nothing lost on the way
        stage.close()
        sensor.close()
    finally:
        sim.stop()


def test_port_disappearing_raises_port_lost():
    sim = SimRig()
    server = sim.serve("pty")
    try:
        sensor = AsciiLoadCell.open(server.urls["force"])
        sensor.start(100)
        sim.faults.add("port_lost", "force", at_s=sim.world.t + 0.1)
        with pytest.raises(PortLost, match="disappeared"):
            t_end = time.monotonic() + 2.0
            while time.monotonic() < t_end:
                sensor.read_samples(0.02)
        sensor.close()
    finally:
        sim.stop()


def test_opening_a_missing_port_says_so():
    with pytest.raises(PortLost, match="cannot open port /dev/does-not-exist"):
        GrblStage.open("/dev/does-not-exist")
