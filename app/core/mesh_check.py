"""The mesh check: an identified model identified again on a finer mesh.

A finite element mesh has an error of its own, and the fit puts it into the
parameters. How much of each identified value is the mesh's is measured the way
an FE analyst does it: the same model (the same effects, the same inclusion
sphere, the same frames and options) on a mesh MESH_CHECK_SCALE times the size,
the refinement the simulator's truth meshes use, identified from the first
mesh's optimum. A parameter that moves by more than its standard error from
the data is limited by the mesh, not by the measurements.

Measured (docs/model-check.md, "Why soft spheres: the mesh"): the described
regions moved by 0-2% between the automatic mesh and the finer one at paper
size (the demo: +1.2% and +1.3%), 1-3% on a small test phantom; an undescribed
sphere's modulus fitted at its true place moved by tens of percent (a 70 kPa
sphere: 54.5 -> 75.3 kPa; a 6 kPa one: 0.6 -> 5.6 kPa).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

from app.core.identify import parameter_text, percent_text

# the finer mesh's lengths relative to the identification's (as the simulator's truth meshes)
MESH_CHECK_SCALE = 0.7


@dataclass
class MeshCheck:
    """The identified parameters (``before``) against the same model identified on
    a finer mesh (``parameters``)."""

    scale: float
    nodes: tuple[int | None, int]  # vertices of the identification's mesh (None: not known) and of the finer one
    before: dict
    parameters: dict
    cost: dict
    seconds: float

    @property
    def change(self) -> dict:
        """Each parameter's relative change on the finer mesh (finer / identified - 1)."""
        return {k: v / self.before[k] - 1.0 for k, v in self.parameters.items()
                if isinstance(v, float) and self.before.get(k)}

    def lines(self, standard_errors: dict | None = None) -> list[str]:
        """The check in words; ``standard_errors``: each parameter's relative standard
        error from the data (Identifiability.standard_error_rel_data), to say which
        modulus the mesh limits."""
        n0, n1 = self.nodes
        change = self.change
        moved = ", ".join(parameter_text(k, self.parameters[k]) + f" ({c:+.1%})" for k, c in change.items())
        against = "" if n0 is None else f" against {n0:,}"
        out = [f"mesh check: on a mesh {self.scale:g} times the size ({n1:,} vertices{against}; "
               f"{self.seconds:.0f} s): {moved}"]
        se = {k: v for k, v in (standard_errors or {}).items() if v is not None and math.isfinite(v)}
        moduli = [k for k in change if k.endswith("_kPa") and k in se]
        beyond = [k for k in moduli if abs(change[k]) > se[k]]
        if beyond:
            one = len(beyond) == 1
            out.append(f"{', '.join(k[:-4] for k in beyond)} moved by more than {'its' if one else 'their'} "
                       f"standard error from the data ({', '.join(percent_text(se[k]) for k in beyond)}): the "
                       f"mesh, not the measurements, limits {'it' if one else 'them'}")
        elif moduli:
            out.append("each modulus moved by less than its standard error from the data: the mesh is fine "
                       "enough for these measurements")
        return out

    def to_dict(self) -> dict:
        return {"scale": self.scale, "nodes": list(self.nodes), "parameters": dict(self.parameters),
                "change": self.change, "cost": dict(self.cost), "seconds": round(self.seconds, 2)}


def identification_settings(exp, mesh_settings=None, inclusion: dict | None = None):
    """The mesh settings a model of ``exp`` (with ``inclusion``'s sphere, if any) was
    meshed with: ``mesh_settings``, or the automatic ones it stood for (None)."""
    from app.core.diagnose import _with_inclusion
    from app.core.mesh import auto_settings

    if mesh_settings is not None:
        return mesh_settings
    if inclusion is not None:
        return _with_inclusion(exp, inclusion, None)[1]
    return auto_settings(exp.specimen.size_mm, exp.probe.face_rect_mm(), exp.specimen.regions)


def mesh_check(exp, effects, parameters: dict, nodes: int | None, *, mesh_settings=None,
               inclusion: dict | None = None, scale: float | None = None, fixed=(), progress=None, cancel=None,
               **options) -> MeshCheck:
    """The model of ``effects`` (with ``inclusion``'s sphere, if any) identified at
    ``parameters`` on a mesh of ``nodes`` vertices made with ``mesh_settings``
    (None: the automatic ones), identified again on a mesh ``scale`` times the
    size (None: MESH_CHECK_SCALE), from ``parameters`` (as a diagnosis identifies the model it calls for:
    :func:`app.core.diagnose.identify_from`). ``options``: the problem's ROI,
    frames, cost, Poisson's ratio and similarity, as the first identification's.
    ``fixed``: names of parameters the identification held fixed; they stay at
    ``parameters``' values. With the image-only cost (NMI) and nothing fixed the
    moduli's level is not identifiable, so the first modulus stays at its value
    and the others' ratios to it are searched, as the identification does
    (:func:`app.core.identify.identify`)."""
    from app.core.diagnose import current_model, identify_from

    t0 = time.perf_counter()
    scale = MESH_CHECK_SCALE if scale is None else float(scale)
    settings = identification_settings(exp, mesh_settings, inclusion)
    say = progress or (lambda s: None)
    say(f"mesh check: meshing with elements {scale:g} times the size")
    names = tuple(exp.specimen.region_names) + ((inclusion["name"],) if inclusion is not None else ())
    near = [parameters.get(f"E_{n}_kPa") for n in names]  # its reduced model trained about the result
    problem = current_model(exp, tuple(effects), mesh_settings=settings.with_scale(scale), inclusion=inclusion,
                            near_kPa=None if None in near else near, progress=progress, cancel=cancel, **options)
    try:
        say("mesh check: identifying on the finer mesh")
        free = [n for n in problem.parameter_names if n not in set(fixed)]
        if problem.cost_kind == "nmi" and len(free) > 1 and not fixed:
            free = free[1:]  # the level: not identifiable from the images alone
        res = identify_from(problem, {k: v for k, v in parameters.items() if isinstance(v, float)}, cancel=cancel,
                            free=tuple(free))
        return MeshCheck(scale, (None if nodes is None else int(nodes), int(problem.mesh.n_nodes)),
                         dict(parameters), dict(res.parameters), dict(res.cost), time.perf_counter() - t0)
    finally:
        problem.release()
