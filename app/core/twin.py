"""A specimen's digital twin: the truth a simulator presses against.

Given an experiment's specimen, probe and imaging description and the true
moduli, it solves the model once on a fine mesh (linear elasticity: the field is
proportional to the probe travel) and then gives, for any probe travel, the
force on the probe and a B-mode frame from the scatterer simulator. Used by
``elastoid simulate`` and by the simulated rig.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from app.core.fem import interpolation_matrix
from app.core.forward import build_model
from app.core.mesh import MeshSettings, auto_settings, specimen_mesh
from app.core.ultrasound import Transducer, make_scatterers, render


@dataclass
class SpecimenTwin:
    exp: object
    moduli_kPa: dict
    nu: float
    force_N_per_mm: float
    scatterer_points_mm: np.ndarray
    scatterer_amplitude: np.ndarray
    scatterer_field: np.ndarray  # displacement per mm of travel at each scatterer
    mesh_nodes: int
    mesh_tets: int
    image_shape: tuple
    transducer: Transducer
    rng: np.random.Generator
    _reference: float | None = None

    @classmethod
    def build(cls, exp, moduli_kPa: dict, *, nu: float = 0.49, mesh_settings: MeshSettings | None = None,
              mesh_scale: float = 0.7, image_shape=(256, 200), max_travel_mm: float = 20.0, seed: int = 0,
              echogenicity: dict | None = None, density_per_mm3: float = 25.0,
              progress: Callable[[str], None] | None = None, cancel=None) -> "SpecimenTwin":
        say = progress or (lambda s: None)
        rng = np.random.default_rng(seed)
        # the truth is meshed finer than identification meshes are (no inverse crime)
        settings = mesh_settings or auto_settings(exp.specimen.size_mm, exp.probe.face_rect_mm(),
                                                  exp.specimen.regions).with_scale(mesh_scale)
        say("meshing the truth")
        mesh = specimen_mesh(exp, settings, progress=say, cancel=cancel)
        say("solving the truth")
        fe = build_model(mesh)
        E = [moduli_kPa[r.name] for r in exp.specimen.regions]
        u, g = fe.solve(E, nu)
        say("placing scatterers")
        scat = make_scatterers(exp, rng, max_travel_mm, density_per_mm3, echogenicity or {})
        field = (interpolation_matrix(fe.space, scat.points_mm) @ u).reshape(-1, 3)
        return cls(exp, dict(moduli_kPa), nu, float(g), scat.points_mm, scat.amplitude, field, mesh.n_nodes,
                   mesh.n_tets, tuple(image_shape), Transducer(), rng)

    def force_N(self, displacement_mm):
        """Force (N) at probe travel(s) from first contact; no force before contact."""
        return self.force_N_per_mm * np.clip(np.asarray(displacement_mm, float), 0.0, None)

    def frame(self, displacement_mm: float) -> np.ndarray:
        """B-mode frame (uint8) with the probe at this travel from first contact."""
        d = max(float(displacement_mm), 0.0)
        img, ref = render(self.scatterer_points_mm + d * self.scatterer_field, self.scatterer_amplitude, self.exp, d,
                          self.image_shape, self.transducer, reference=self._reference, rng=self.rng)
        if self._reference is None:
            self._reference = ref
        return img
