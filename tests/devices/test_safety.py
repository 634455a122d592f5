"""Safety on the simulated rig: the feed hold timing, the overshoot, the travel limit."""

from __future__ import annotations

import numpy as np
import pytest

from app.devices.acquisition import RampHoldUnload, Rig, SafetyLimits, default_template
from app.devices.sim import NonlinearSpring, SimRig


def _press(tmp_path, *, k, speed, latency_ms, limits=SafetyLimits(), noise=0.002, depth=19.0):
    sim = SimRig(NonlinearSpring(k, 0.1 * k, 2.0), latency_ms=latency_ms, noise_N=noise)
    stage, sensor, clock = sim.connect_virtual()
    rig = Rig(stage, sensor, clock=clock, limits=limits)
    rig.find_contact(speed_mm_s=1.0)
    res = rig.run(RampHoldUnload(depth, speed, frames_at_mm=()), tmp_path / f"r{k}-{speed}-{latency_ms}",
                  default_template())
    return sim, rig, res


def test_feed_hold_goes_out_within_one_sample_period_of_the_crossing(tmp_path):
    limits = SafetyLimits(force_limit_N=5.0, predictive=False)
    sim, rig, res = _press(tmp_path, k=2.0, speed=1.0, latency_ms=7.0, limits=limits, noise=0.0)
    assert res.outcome == "safety" and "limit 5 N" in res.message
    t, d, f = sim.world.truth()
    i = int(np.argmax(f >= 5.0))
    arrival = t[i] + 0.007  # the first sample at the limit reaches the host after the sensor latency
    holds = [te for te, e in sim.grbl.log if e == "feed_hold" and te >= arrival - 1e-9]
    assert holds and holds[0] - arrival <= 1.0 / rig.sample_rate_hz
    assert holds[0] - arrival < 1e-6  # in virtual time the hold goes out as the sample is read


@pytest.mark.parametrize("k, speed, latency_ms", [(1.0, 2.0, 30.0), (5.0, 2.0, 20.0), (10.0, 1.0, 10.0),
                                                  (3.0, 0.5, 0.0)])
def test_force_overshoot_stays_within_10_percent(tmp_path, k, speed, latency_ms):
    sim, rig, res = _press(tmp_path, k=k, speed=speed, latency_ms=latency_ms)
    assert res.outcome == "safety" and res.stage_stopped
    true_peak = sim.world.truth()[2].max()
    assert true_peak <= 1.10 * rig.limits.force_limit_N
    assert true_peak >= 0.9 * rig.limits.force_limit_N  # and it did press to near the limit
    assert "retracted" in res.message
    assert sim.true_travel_mm() == pytest.approx(rig.contact_mm - rig.limits.retract_mm, abs=1e-3)


def test_travel_limit_stops_a_soft_specimen(tmp_path):
    limits = SafetyLimits(force_limit_N=10.0, travel_limit_mm=2.0)
    sim = SimRig(NonlinearSpring(0.1, 0.0, 2.0))
    stage, sensor, clock = sim.connect_virtual()
    rig = Rig(stage, sensor, clock=clock, limits=limits)
    rig.find_contact(speed_mm_s=1.0, threshold_N=0.01)
    # a jog towards the deep end is clamped by the rig to the travel limit
    rig.jog(10.0, 2.0)
    assert sim.true_travel_mm() - rig.contact_mm == pytest.approx(2.0, abs=1e-3)
    rig.jog(-2.0, 2.0)
    # the loop's own check trips when the stage runs on past the limit (a move the rig did not clamp)
    s_stage = rig.stage
    s_stage.start_move(rig.contact_mm + 5.0, 2.0)
    with pytest.raises(Exception, match="travel limit 2 mm") as info:
        rig.monitor(__import__("threading").Event())
    assert info.value.stage_stopped
    assert sim.true_travel_mm() - rig.contact_mm <= 2.0 + 1e-6
