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
    "prony_memory", "ptys_available", "specimen_force_model", "specimen_moduli_kPa", "specimen_twin",
    "speckle_render",
]


def specimen_moduli_kPa(experiment_path: str | Path) -> dict:
    """The moduli a simulated specimen has: its ``truth.toml`` (a synthetic experiment's
    ground truth, which only simulators read), else the experiment's [reference]."""
    from app.core.errors import ElastoidError
    from app.core.experiment import read_experiment

    truth = Path(experiment_path) / "truth.toml"
    if truth.is_file():
        import tomllib

        return {k: float(v) for k, v in tomllib.loads(truth.read_text(encoding="utf-8"))["moduli_kPa"].items()}
    ref = read_experiment(experiment_path, check_images=False).reference_moduli_kPa()
    if not ref:
        raise ElastoidError(f"{experiment_path}: neither truth.toml nor [reference] moduli; the simulated rig "
                            "needs the specimen's moduli to press against")
    return ref


_TWINS: dict = {}


def specimen_twin(experiment_path: str | Path, *, seed: int = 0, progress=None):
    """The finite-element twin (force and B-mode frames) of the specimen an experiment
    folder describes, built once per folder and process."""
    from app.core.experiment import read_experiment
    from app.core.twin import SpecimenTwin

    key = (str(Path(experiment_path).resolve()), seed)
    if key not in _TWINS:
        exp = read_experiment(experiment_path, check_images=False)
        shape = (256, 200)
        if exp.frames and exp.path is not None and (exp.path / exp.frames[0].image).is_file():
            shape = exp.image(0).shape
        _TWINS[key] = SpecimenTwin.build(exp, specimen_moduli_kPa(experiment_path), image_shape=shape, seed=seed,
                                         progress=progress, echogenicity={r.name: 1.8 for r in exp.specimen.regions[1:]})
    return _TWINS[key]


def specimen_force_model(experiment_path: str | Path | None, effects: Sequence[str] = (),
                         *, contact_mm: float = 2.0, progress=None) -> ForceModel:
    """The force model the simulated rig presses against for ``elastoid rig --sim --specimen``.

    With a specimen, the finite-element twin of the experiment's specimen gives the
    force per mm of indentation (linear elasticity: F = k d after contact); with
    ``"viscoelastic"`` among ``effects`` it relaxes by a one-term Prony series
    (g1 = 0.3, tau1 = 2 s). Without a specimen, a generic soft nonlinear spring.
    ``contact_mm`` is the gap the probe travels before touching.
    """
    k, k3 = 1.0, 0.05
    if experiment_path is not None:
        k, k3 = specimen_twin(experiment_path, progress=progress).force_N_per_mm, 0.0
    spring = NonlinearSpring(k_N_per_mm=k, k3_N_per_mm3=k3, contact_mm=contact_mm)
    if "viscoelastic" in set(effects):
        return ViscoelasticSpring(spring, g1=0.3, tau1_s=2.0)
    return spring
