"""A specimen's digital twin: the truth a simulator presses against.

Given an experiment's specimen, probe and imaging description and the true
moduli, it solves the model once on a fine mesh (linear elasticity: the field is
proportional to the probe travel) and then gives, for any probe travel, the
force on the probe and a B-mode frame from the scatterer simulator. Used by
``elastoid simulate`` and by the simulated rig.

The truth may include physical effects the baseline model lacks (ids of
:mod:`app.core.effects`): ``hyperelastic`` (neo-Hookean solve along load
steps: force curve and fields at each step), ``viscoelastic`` (Prony series on
the force history, :meth:`SpecimenTwin.force_history_N`), ``sliding-bottom`` /
``probe-slip`` (relaxed boundary conditions), ``compressibility`` (the given
``nu``) and ``inclusion`` (regions in ``hidden_regions``, present in the truth
but not in the experiment it images).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from app.core.fem import interpolation_matrix
from app.core.forward import build_model
from app.core.mesh import TRUTH, MeshSettings, auto_settings, specimen_mesh
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
    effects: tuple = ()
    g1: float = 0.0
    tau1_s: float = 1.0
    # hyperelastic truth: fields at the load steps (travel mm, (k, n_scatterers, 3) mm) and forces
    step_depths_mm: np.ndarray | None = None
    step_fields_mm: np.ndarray | None = None
    step_forces_N: np.ndarray | None = None

    @classmethod
    def build(cls, exp, moduli_kPa: dict, *, nu: float = 0.49, mesh_settings: MeshSettings | None = None,
              mesh_scale: float = 0.7, image_shape=(256, 200), max_travel_mm: float = 20.0, seed: int = 0,
              echogenicity: dict | None = None, density_per_mm3: float = 25.0,
              progress: Callable[[str], None] | None = None, cancel=None, effects: tuple = (),
              hidden_regions: tuple = (), g1: float = 0.0, tau1_s: float = 1.0,
              load_steps_mm=None) -> "SpecimenTwin":
        """``effects``, ``hidden_regions``, ``g1``, ``tau1_s``: the truth's effects (see
        the module docstring); ``load_steps_mm``: the hyperelastic load steps
        (default: 8 equal steps to ``max_travel_mm``)."""
        say = progress or (lambda s: None)
        rng = np.random.default_rng(seed)
        truth_exp = exp
        for r in hidden_regions:
            truth_exp = replace(truth_exp, specimen=truth_exp.specimen.with_region(r))
        # the truth is meshed finer than identification meshes are (no inverse crime):
        # the automatic sizes times mesh_scale, the probe face's outline included
        settings = mesh_settings or auto_settings(truth_exp.specimen.size_mm, truth_exp.probe.face_rect_mm(),
                                                  truth_exp.specimen.regions).with_scale(mesh_scale)
        say("meshing the truth")
        mesh = specimen_mesh(truth_exp, settings, progress=say, cancel=cancel, kind=TRUTH)
        say("solving the truth")
        from app.core.forward import Boundary

        boundary = Boundary(bottom="sliding" if "sliding-bottom" in effects else "bonded",
                            probe="slip" if "probe-slip" in effects else "bonded")
        fe = build_model(mesh, boundary)
        E = [moduli_kPa[r.name] for r in truth_exp.specimen.regions]
        u, g = fe.solve(E, nu)
        say("placing scatterers")
        scat = make_scatterers(truth_exp, rng, max_travel_mm, density_per_mm3, echogenicity or {})
        P = interpolation_matrix(fe.space, scat.points_mm)
        field = (P @ u).reshape(-1, 3)
        twin = cls(exp, dict(moduli_kPa), nu, float(g), scat.points_mm, scat.amplitude, field, mesh.n_nodes,
                   mesh.n_tets, tuple(image_shape), Transducer(), rng, effects=tuple(effects), g1=g1, tau1_s=tau1_s)
        if "hyperelastic" in effects:
            from app.core.hyperelastic import HyperelasticModel

            steps = np.asarray(load_steps_mm if load_steps_mm is not None
                               else np.linspace(max_travel_mm / 8, max_travel_mm, 8), float)
            say(f"solving the neo-Hookean truth in {len(steps)} load steps")
            hm = HyperelasticModel(fe, warm_starts=False)  # one solve: no equilibria kept per travel
            try:
                sol = hm.solve(E, nu, steps, cancel=cancel)
            finally:
                hm.free()
            twin.step_depths_mm = sol.depths_mm
            twin.step_forces_N = sol.force_N
            twin.step_fields_mm = np.stack([(P @ f).reshape(-1, 3) for f in sol.fields])
        return twin

    def field_mm(self, displacement_mm: float) -> np.ndarray:
        """Displacement (n_scatterers, 3) mm of the scatterers at a probe travel."""
        d = max(float(displacement_mm), 0.0)
        if self.step_depths_mm is None:
            return d * self.scatterer_field
        dd = np.concatenate([[0.0], self.step_depths_mm])
        k = int(np.clip(np.searchsorted(dd, d), 1, len(dd) - 1))
        w = (d - dd[k - 1]) / (dd[k] - dd[k - 1])
        lo = self.step_fields_mm[k - 2] if k >= 2 else np.zeros_like(self.scatterer_field)
        return (1 - w) * lo + w * self.step_fields_mm[k - 1]

    def force_history_N(self, time_s, displacement_mm) -> np.ndarray:
        """Force (N) over a travel history: the elastic force, through the Prony
        series when the truth is viscoelastic."""
        F = self.force_N(displacement_mm)
        if "viscoelastic" in self.effects and self.g1 > 0:
            from app.core.effects.viscoelastic import prony_force

            F = prony_force(np.asarray(time_s, float), F, self.g1, self.tau1_s)
        return F

    def force_N(self, displacement_mm):
        """Elastic force (N) at probe travel(s) from first contact; no force before contact."""
        d = np.clip(np.asarray(displacement_mm, float), 0.0, None)
        if self.step_depths_mm is not None:
            from scipy.interpolate import PchipInterpolator

            dd = np.concatenate([[0.0], self.step_depths_mm])
            FF = np.concatenate([[0.0], self.step_forces_N])
            return PchipInterpolator(dd, FF, extrapolate=True)(d)
        return self.force_N_per_mm * d

    def frame(self, displacement_mm: float) -> np.ndarray:
        """B-mode frame (uint8) with the probe at this travel from first contact."""
        d = max(float(displacement_mm), 0.0)
        img, ref = render(self.scatterer_points_mm + self.field_mm(d), self.scatterer_amplitude, self.exp, d,
                          self.image_shape, self.transducer, reference=self._reference, rng=self.rng)
        if self._reference is None:
            self._reference = ref
        return img
