"""The rig on the simulated twins in virtual time: contact, jogs, a recorded protocol."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from app.core.errors import ExperimentError
from app.core.experiment import read_experiment
from app.devices.acquisition import Progress, RampHoldUnload, Rig, SafetyLimits, default_template
from app.devices.errors import DeviceError, RigBusy
from app.devices.sim import NonlinearSpring, SimRig, SimulatedImageSource, ViscoelasticSpring, speckle_render


def with_images(rig):
    rig.images = SimulatedImageSource(speckle_render((64, 64)), lambda: rig.displacement_mm() or 0.0)
    return rig


def test_find_contact_zeroes_at_the_true_surface(sim_rig):
    sim, rig = sim_rig
    c = rig.find_contact(speed_mm_s=0.5, threshold_N=0.02)
    # crossing 0.02 N on a 1 N/mm spring is 0.02 mm past the surface; noise (2 mN) and one sample
    # of travel (5 um) blur it by about 10 um
    assert c == pytest.approx(2.02, abs=0.012)
    assert rig.displacement_mm() == pytest.approx(0.0, abs=1e-3)
    assert sim.true_travel_mm() == pytest.approx(c, abs=1e-3)


def test_find_contact_refuses_when_already_pressing(sim_rig):
    sim, rig = sim_rig
    rig.jog(3.0, 2.0)  # 1 mm into the specimen
    with pytest.raises(DeviceError, match="already in contact"):
        rig.find_contact(tare=False)


def test_ramp_hold_unload_records_a_readable_experiment(sim_rig, tmp_path):
    sim, rig = sim_rig
    with_images(rig)
    rig.find_contact(speed_mm_s=1.0)
    reports: list[Progress] = []
    res = rig.run(RampHoldUnload(depth_mm=3.0, speed_mm_s=1.0, hold_s=1.0, frames_at_mm=(0, 1.5, 3)),
                  tmp_path / "run", default_template("phantom"), progress=reports.append)
    assert res.outcome == "completed" and res.stage_stopped and res.message == "the protocol completed"
    exp = read_experiment(tmp_path / "run")
    assert exp.name.startswith("phantom (recorded")
    assert [round(f.displacement_mm, 3) for f in exp.frames] == [0.0, 1.5, 3.0]
    log = exp.force_log
    assert len(log) == res.samples and np.all(np.diff(log.time_s) > 0)
    dt = np.diff(log.time_s)
    assert dt.max() < 0.0101 and dt.min() > 0.0099  # 100 Hz, nothing missing
    # force vs displacement follows the spring (noise 2 mN), loading and unloading alike
    d0 = rig.contact_mm - 2.0
    expected = np.maximum(log.displacement_mm + d0, 0) + 0.05 * np.maximum(log.displacement_mm + d0, 0) ** 3
    assert np.abs(log.force_N - expected).max() < 0.02
    assert log.displacement_mm.max() == pytest.approx(3.0, abs=1e-3)
    assert log.displacement_mm[-1] == pytest.approx(-1.0, abs=2e-3)  # unloaded, then retracted 1 mm
    states = [p.state for p in reports]
    for s in ("ramp", "hold", "unload", "retract", "done"):
        assert s in states
    assert exp.frame_force_N(2) == pytest.approx((3.0 + d0) + 0.05 * (3.0 + d0) ** 3, abs=0.02)


def test_viscoelastic_specimen_relaxes_during_the_hold(tmp_path):
    sim = SimRig(ViscoelasticSpring(NonlinearSpring(2.0, 0.0, 1.0), g1=0.5, tau1_s=1.0), noise_N=0.0)
    stage, sensor, clock = sim.connect_virtual()
    rig = Rig(stage, sensor, clock=clock)
    rig.find_contact(speed_mm_s=1.0, threshold_N=0.01)
    res = rig.run(RampHoldUnload(depth_mm=2.0, speed_mm_s=2.0, hold_s=6.0, unload=False, frames_at_mm=()),
                  tmp_path / "r", default_template())
    assert res.outcome == "completed"
    text = (tmp_path / "r" / "force.csv").read_text().splitlines()[1:]
    f = np.array([float(x.split(",")[2]) for x in text])
    peak, end = f.max(), f[-1]
    # relaxed to g_inf = 0.5 of the elastic force 2 N/mm x 2 mm (6 tau later), from a peak well above it
    assert end == pytest.approx(2.0, abs=0.05) and peak > 1.3 * end
    with pytest.raises(ExperimentError, match="frames"):
        read_experiment(tmp_path / "r")  # no image source: a force log only, which says so on reading


def test_recording_needs_a_new_folder_and_contact(sim_rig, tmp_path):
    sim, rig = sim_rig
    with pytest.raises(DeviceError, match="contact is not known"):
        rig.run(RampHoldUnload(1.0, 1.0), tmp_path / "x", default_template())
    rig.find_contact(speed_mm_s=2.0)
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "something").write_text("x")
    with pytest.raises(DeviceError, match="not empty"):
        rig.run(RampHoldUnload(1.0, 1.0), tmp_path / "full", default_template())
    with pytest.raises(ValueError, match="beyond the travel limit"):
        rig.run(RampHoldUnload(25.0, 1.0), tmp_path / "y", default_template())


def test_stop_event_stops_and_retracts(sim_rig, tmp_path):
    sim, rig = sim_rig
    rig.find_contact(speed_mm_s=2.0)
    stop = threading.Event()

    def progress(p):
        if p.state == "ramp" and p.displacement_mm is not None and p.displacement_mm > 1.0:
            stop.set()

    res = rig.run(RampHoldUnload(3.0, 1.0, hold_s=1.0, frames_at_mm=()), tmp_path / "r", default_template(),
                  progress=progress, stop=stop)
    assert res.outcome == "stopped" and res.stage_stopped
    assert "Stopped by the user" in res.message and "retracted" in res.message
    assert sim.true_travel_mm() == pytest.approx(rig.contact_mm - 1.0, abs=1e-3)


def test_emergency_stop_halts_without_retracting(sim_rig, tmp_path):
    sim, rig = sim_rig
    rig.find_contact(speed_mm_s=2.0)

    def progress(p):
        if p.state == "ramp" and p.displacement_mm is not None and p.displacement_mm > 1.0:
            rig.emergency_stop()

    res = rig.run(RampHoldUnload(3.0, 1.0, frames_at_mm=()), tmp_path / "r", default_template(), progress=progress)
    assert res.outcome == "stopped" and res.message.startswith("Emergency stop")
    d = sim.true_travel_mm() - rig.contact_mm
    # stopped where it was (the stop came just past 1.0 mm), not retracted
    assert d == pytest.approx(1.1, abs=0.1), d
    assert sim.grbl.state == "Idle"
    assert any(e == "feed_hold" for _, e in sim.grbl.log)
    # from idle, an emergency stop is a plain, immediate stop sequence
    assert rig.emergency_stop().state == "Idle"


def test_jog_steps_continuous_and_limits(sim_rig):
    sim, rig = sim_rig
    st = rig.jog(1.0, 2.0)
    assert st.travel_mm == pytest.approx(1.0) and sim.true_travel_mm() == pytest.approx(1.0)
    rig.jog(-0.5, 2.0)
    assert sim.true_travel_mm() == pytest.approx(0.5)
    stop = threading.Event()
    seen = []

    def progress(p):
        seen.append(p.travel_mm)
        if p.travel_mm > 1.5:
            stop.set()

    rig.jog_continuous(+1, 1.0, stop, progress=progress)
    assert sim.true_travel_mm() == pytest.approx(1.6, abs=0.1)  # stopped just past 1.5 mm
    assert sim.grbl.state == "Idle"
    rig.jog(-10.0, 5.0)  # clamped to the stage's travel
    assert sim.true_travel_mm() == pytest.approx(0.0)


def test_jog_into_the_specimen_stops_at_the_force_limit(tmp_path):
    sim = SimRig(NonlinearSpring(4.0, 0.0, 1.0))
    stage, sensor, clock = sim.connect_virtual()
    rig = Rig(stage, sensor, clock=clock, limits=SafetyLimits(force_limit_N=4.0))
    with pytest.raises(DeviceError, match="limit 4 N") as info:
        rig.jog(5.0, 1.0)
    assert info.value.stage_stopped and "retract" in info.value.stop_note
    assert sim.world.truth()[2].max() < 4.0 * 1.1
    assert sim.true_travel_mm() == pytest.approx(0.0)  # backed off to where the jog started


def test_monitor_and_busy(sim_rig):
    sim, rig = sim_rig
    stop = threading.Event()
    got = []

    def progress(p):
        got.append(p)
        with pytest.raises(RigBusy):
            rig.jog(1.0, 1.0)
        if len(got) > 3:
            stop.set()

    rig.monitor(stop, progress=progress)
    assert len(got) > 3 and all(abs(p.force_N) < 0.02 for p in got)


def test_recorder_flushes_whole_lines_within_0_2_s(tmp_path):
    import time as _time

    from app.devices.acquisition import Recorder

    rec = Recorder(tmp_path / "r", default_template())
    rec.add_rows([(0.0, 0.0, 0.0), (0.01, 0.01, 0.02)])
    _time.sleep(0.21)
    rec.add_rows([(0.02, 0.02, 0.04), (0.02, 9.0, 9.0)])  # a repeated time is dropped: time must increase
    text = (tmp_path / "r" / "force.csv").read_text()
    assert text.endswith("\n") and text.count("\n") == 4  # header + 3 rows, on disk before close
    rec.add_frame(np.zeros((4, 4), np.uint8), 0.015, 0.015)
    assert read_experiment(tmp_path / "r").frames[0].displacement_mm == 0.015
    rec.close()
    assert rec.rows == 3
