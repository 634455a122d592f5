"""The fault table: each fault injected mid-ramp on the simulated rig.

Each must end with the stage stopped (or a clear message that it could not
be), the data so far on disk and readable, a message a user understands, no
hang, and no sample lost before the fault.
"""

from __future__ import annotations

import numpy as np
import pytest

from app.core.experiment import read_experiment
from app.devices.acquisition import RampHoldUnload, Rig, default_template
from app.devices.sim import NonlinearSpring, SimRig, SimulatedImageSource, speckle_render

# fault, device, params -> outcome, stage known stopped, words the message must contain
TABLE = [
    ("port_lost", "stage", {}, "fault", False, ["disappeared", "could not confirm", "emergency stop"]),
    ("port_lost", "force", {}, "fault", True, ["force sensor", "disappeared", "retracted"]),
    ("garbage", "force", {}, "completed", True, ["completed"]),
    ("garbage", "stage", {}, "completed", True, ["completed"]),
    ("partial_lines", "force", {}, "completed", True, ["completed"]),
    ("partial_lines", "stage", {}, "completed", True, ["completed"]),
    ("mute", "stage", {}, "fault", False, ["stopped answering", "could not confirm"]),
    ("mute", "force", {}, "fault", True, ["stopped sending", "retracted"]),
    ("grbl_error", "stage", {"code": 20}, "fault", True, ["error:20", "Unsupported", "retracted"]),
    ("grbl_alarm", "stage", {"code": 1}, "fault", True, ["alarm 1", "Hard limit", "unlock"]),
    ("saturate", "force", {}, "safety", True, ["full scale", "retracted"]),
]


@pytest.mark.parametrize("kind, device, params, outcome, stopped, words", TABLE,
                         ids=[f"{k}-{d}" for k, d, *_ in TABLE])
def test_fault_mid_ramp(tmp_path, kind, device, params, outcome, stopped, words):
    sim = SimRig(NonlinearSpring(1.0, 0.05, 2.0))
    stage, sensor, clock = sim.connect_virtual()
    rig = Rig(stage, sensor, clock=clock)
    rig.images = SimulatedImageSource(speckle_render((32, 32)), lambda: rig.displacement_mm() or 0.0)
    contact = rig.find_contact(speed_mm_s=1.0)
    fault = sim.faults.add(kind, device, at_travel_mm=contact + 1.5, **params)
    t_start = clock.now()
    res = rig.run(RampHoldUnload(3.0, 1.0, hold_s=0.5, frames_at_mm=(0.0, 1.0, 2.0, 3.0)), tmp_path / "run",
                  default_template())
    assert clock.now() - t_start < 30.0  # no hang (virtual seconds)
    assert fault.fired_at_s is not None
    assert res.outcome == outcome, res.message
    assert res.stage_stopped is stopped
    for w in words:
        assert w.lower() in res.message.lower(), res.message
    if not stopped:
        assert "may still be moving" in res.message
    else:
        assert not sim.grbl.moving
    # the data so far are on disk and readable
    exp = read_experiment(tmp_path / "run")
    assert len(exp.frames) >= 2 and len(exp.force_log) == res.samples
    # no sample lost before the fault: rows every 10 ms, without a gap, up to the fault
    t = exp.force_log.time_s
    t_fault = fault.fired_at_s - t_start  # recording began just after t_start
    before = t[t < t_fault - 0.1]
    assert len(before) > 50 and np.all(np.diff(before) < 0.0101)
    if outcome == "completed":
        assert np.all(np.diff(t) < 0.0101) and res.lost_samples == 0
    if kind == "garbage" and device == "force":
        assert res.bad_lines == 1
