"""The simulated twins: GRBL state machine and kinematics, the load cell, the force models."""

from __future__ import annotations

import numpy as np
import pytest

from app.devices.loadcell import unframe
from app.devices.sim import NonlinearSpring, SimGrbl, SimLoadCell, SimRig, ViscoelasticSpring, prony_memory
from app.devices.sim.models import ForceModel


def lines(dev, t=1e9):
    return dev.take(t).decode().split("\r\n")


def run(dev: SimGrbl, seconds: float):
    dev.advance(dev.t + seconds)


def test_grbl_trapezoid_matches_closed_form():
    g = SimGrbl(accel_mm_s2=50.0, max_rate_mm_min=1200.0)
    g.receive(b"$J=G91 G21 Z-10 F600\n", 0.0)
    assert lines(g)[0] == "ok"
    # 10 mm at 10 mm/s with 50 mm/s^2: ramps of 0.2 s (1 mm each), 0.8 s cruise -> 1.2 s in all
    run(g, 0.6)
    assert g.state == "Jog" and g.vel == pytest.approx(-10.0, abs=1e-6)
    assert g.pos == pytest.approx(-(1.0 + 10 * 0.4), abs=0.02)
    run(g, 0.7)
    assert g.state == "Idle" and g.pos == -10.0 and g.vel == 0.0


def test_grbl_status_report_format():
    g = SimGrbl()
    g.receive(b"?", 0.0)
    assert lines(g)[0] == "<Idle|MPos:0.000,0.000,0.000|Bf:15,128|FS:0,0>"
    g.receive(b"G1 Z-1 F60\n?", 0.0)
    run(g, 0.5)
    g.receive(b"?", 0.5)
    out = lines(g)
    assert out[0] == "ok" and out[2].startswith("<Run|MPos:0.000,0.000,-0.4") and "|FS:60,0" in out[2]
    w = SimGrbl(report_wpos=True, wco=(0.0, 0.0, -0.5))
    w.receive(b"?", 0.0)
    assert lines(w)[0] == "<Idle|WPos:0.000,0.000,0.500|Bf:15,128|FS:0,0|WCO:0.000,0.000,-0.500>"


def test_grbl_feed_hold_resume_and_reset_in_hold_keeps_position():
    g = SimGrbl()
    g.receive(b"G1 Z-5 F120\n", 0.0)
    run(g, 0.5)
    g.receive(b"!", g.t)
    run(g, 0.01)
    assert g.state == "Hold:1"
    run(g, 0.2)
    assert g.state == "Hold:0"
    held = g.pos
    g.receive(b"~", g.t)
    run(g, 0.1)
    assert g.state == "Run" and g.pos < held
    g.receive(b"!", g.t)
    run(g, 0.3)
    pos = g.pos
    g.take(1e9)
    g.receive(b"\x18", g.t)
    out = lines(g)
    assert "ALARM:3" not in out and "Grbl 1.1h ['$' for help]" in out
    assert g.state == "Idle" and g.pos == pos


def test_grbl_reset_in_motion_raises_alarm_3_and_locks():
    g = SimGrbl()
    g.receive(b"$J=G91 Z-5 F300\n", 0.0)
    run(g, 0.2)
    g.take(1e9)
    g.receive(b"\x18", g.t)
    out = lines(g)
    assert out[0] == "ALARM:3" and "[MSG:'$H'|'$X' to unlock]" in out
    g.receive(b"G1 Z-1 F60\n", g.t)
    assert lines(g)[0] == "error:9"
    g.receive(b"$X\n", g.t)
    assert lines(g)[:2] == ["[MSG:Caution: Unlocked]", "ok"]
    assert g.state == "Idle"


def test_grbl_jog_cancel_and_feed_hold_end_a_jog_in_idle():
    for byte in (b"\x85", b"!"):
        g = SimGrbl()
        g.receive(b"$J=G91 Z-5 F300\n", 0.0)
        run(g, 0.3)
        g.receive(byte, g.t)
        run(g, 0.3)
        assert g.state == "Idle" and -5.0 < g.pos < 0 and not g.queue


def test_grbl_limits_errors_and_alarms():
    g = SimGrbl(max_travel_mm=10.0)
    g.receive(b"$J=G53 Z-11 F60\n", 0.0)
    assert lines(g)[0] == "error:15"
    g.receive(b"G1 Z-1\n", 0.0)
    assert lines(g)[0] == "error:22"
    g.receive(b"G2 Z-1 F10\n", 0.0)
    assert lines(g)[0] == "error:20"
    g.receive(b"$Q\n", 0.0)
    assert lines(g)[0] == "error:3"
    g.receive(b"G1 Z-12 F60\n", 0.0)
    assert lines(g)[:2] == ["ok", "ALARM:2"] and g.state == "Alarm"
    h = SimGrbl(max_travel_mm=10.0, soft_limits=False)
    h.receive(b"G1 Z-12 F600\n", 0.0)
    run(h, 3.0)
    assert h.alarm == 1 and h.pos == pytest.approx(-10.5, abs=0.02)  # hard limit switch just past travel


def test_load_cell_noise_latency_saturation():
    c = SimLoadCell(noise_N=0.01, latency_ms=20.0, full_scale_N=5.0, seed=3)
    c.receive(b"START 100\n", 0.0)
    c.advance(0.0)
    assert unframe(c.take(0.0).rstrip(b"\r\n")) == "OK,START,100"
    readings = []
    for i in range(200):
        t = c.claim_measurement()
        c.measure(t, 1.0 if i < 199 else 7.0)
        c.advance(t + 0.0199)
        assert c.take(t + 0.0199) == b""  # not before its latency
        c.advance(t + 0.02)
        readings.append(unframe(c.take(t + 0.02).rstrip(b"\r\n")).split(","))
    f = np.array([float(r[3]) for r in readings[:-1]])
    assert abs(f.mean() - 1.0) < 0.003 and 0.007 < f.std() < 0.013
    assert readings[-1][3] == "+5.0000" and readings[-1][4] == "01"
    assert [int(r[1]) for r in readings] == list(range(200))
    assert int(readings[1][2]) == 20000  # device microseconds since START


def test_models_satisfy_the_protocol_and_closed_forms():
    spring = NonlinearSpring(2.0, 0.1, contact_mm=1.5)
    visco = ViscoelasticSpring(spring, g1=0.4, tau1_s=1.5)
    assert isinstance(spring, ForceModel) and isinstance(visco, ForceModel)
    d = np.array([0.0, 1.5, 2.5, 3.5])
    np.testing.assert_allclose(spring.force_N(np.arange(4.0), d), [0, 0, 2.1, 4.8])
    assert spring.depth_for_force_mm(4.8) == pytest.approx(2.0)
    # step to 1 mm indentation, then hold: F(t) = F_e (g_inf + g1 exp(-t / tau))
    t = np.linspace(0, 10, 2001)
    dd = np.where(t > 0, 2.5, 0.0)
    f = visco.force_N(t, dd)
    np.testing.assert_allclose(f[1:], 2.1 * (0.6 + 0.4 * np.exp(-(t[1:] - t[1]) / 1.5)), rtol=1e-9)


def test_prony_memory_matches_a_direct_sum_over_long_histories():
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.01, 0.5, size=3000))  # ~750 s, far beyond exp overflow for tau = 1
    inc = rng.normal(size=t.size)
    h = prony_memory(t, inc, 1.0)
    for i in (0, 10, 1500, 2999):
        direct = np.sum(np.exp(-(t[i] - t[: i + 1]) / 1.0) * inc[: i + 1])
        assert h[i] == pytest.approx(direct, abs=1e-9)


def test_world_truth_follows_the_model():
    sim = SimRig(NonlinearSpring(1.0, 0.0, 2.0), noise_N=0.0, latency_ms=0.0)
    stage, sensor, clock = sim.connect_virtual()
    sensor.start(200)
    stage.start_move(4.0, 2.0)
    got = []
    while clock.now() < 3.0:
        got += sensor.read_samples(0.05)
    t, d, f = sim.world.truth()
    np.testing.assert_allclose(f, np.maximum(d - 2.0, 0.0), atol=1e-12)
    assert f.max() == pytest.approx(2.0)
    assert [s.force_N for s in got] == pytest.approx(list(np.round(f[: len(got)], 4)), abs=1e-4)
