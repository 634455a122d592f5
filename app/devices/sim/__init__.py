"""Simulated twins of the rig: GRBL stage, ELC-1 load cell, specimen force models, images, faults."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from app.devices.sim.grbl import SimGrbl
from app.devices.sim.imaging import SimulatedImageSource, speckle_render
from app.devices.sim.loadcell import SimLoadCell
from app.devices.sim.models import ForceModel, NonlinearSpring, ViscoelasticSpring, prony_memory
from app.devices.sim.rig import SimRig
from app.devices.sim.serve import SimServer, ptys_available
from app.devices.sim.world import FAULT_KINDS, Fault, FaultInjector, SimWorld, VirtualPort

__all__ = [
    "FAULT_KINDS", "Fault", "FaultInjector", "ForceModel", "NonlinearSpring", "SimGrbl", "SimLoadCell",
    "SimRig", "SimServer", "SimWorld", "SimulatedImageSource", "ViscoelasticSpring", "VirtualPort",
    "prony_memory", "ptys_available", "specimen_force_model", "speckle_render",
]


def specimen_force_model(experiment_path: str | Path | None, effects: Sequence[str] = (),
                         *, contact_mm: float = 2.0) -> ForceModel:
    """The force model the simulated rig presses against for ``elastoid rig --sim --specimen``.

    This is where the lead engineer wires the finite-element model of the
    specimen described by ``experiment_path`` (with the physical ``effects``,
    ids as in the command-line contract). Until then it returns one of the
    simple models: a nonlinear spring whose stiffness is fitted (least squares,
    F = k d + k3 d^3 on the loading rows) to the experiment's force log when
    there is one, with Prony relaxation (g1 = 0.3, tau1 = 2 s) when
    ``"viscoelastic"`` is among ``effects``. ``contact_mm`` is the gap the
    probe travels before touching.
    """
    k, k3 = 1.0, 0.05
    if experiment_path is not None:
        from app.core.experiment import read_experiment

        exp = read_experiment(experiment_path, check_images=False)
        d = exp.force_log.displacement_mm
        f = exp.force_log.force_N
        load = (d > 0) & (np.concatenate([[True], np.diff(d) >= 0]))
        if load.sum() >= 3:
            a = np.column_stack([d[load], d[load] ** 3])
            coef, *_ = np.linalg.lstsq(a, f[load], rcond=None)
            k, k3 = max(float(coef[0]), 1e-3), max(float(coef[1]), 0.0)
    spring = NonlinearSpring(k_N_per_mm=k, k3_N_per_mm3=k3, contact_mm=contact_mm)
    if "viscoelastic" in set(effects):
        return ViscoelasticSpring(spring, g1=0.3, tau1_s=2.0)
    return spring
