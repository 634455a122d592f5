"""Shared fixtures for the instrument tests: simulated rigs in virtual time."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:  # run from any folder, with or without an installed package
    sys.path.insert(0, str(ROOT))


@pytest.fixture
def sim_rig():
    """A simulated rig (spring 1 N/mm + 0.05 N/mm^3, contact at 2 mm) with connected drivers."""
    from app.devices.acquisition import Rig
    from app.devices.sim import NonlinearSpring, SimRig

    sim = SimRig(NonlinearSpring(1.0, 0.05, 2.0))
    stage, sensor, clk = sim.connect_virtual()
    rig = Rig(stage, sensor, clock=clk)
    yield sim, rig
    rig.close()
