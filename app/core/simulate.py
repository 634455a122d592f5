"""Synthetic experiments: the truth on a finer mesh, B-mode frames from the
scatterer simulator, a noisy force log, and ``truth.toml`` beside the folder's
experiment.toml (never read by identification or diagnosis)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np

from app.core.errors import ElastoidError, ExperimentError
from app.core.experiment import (Experiment, ForceLog, Frame, Imaging, Probe, Specimen, probe_off_top,
                                 new_folder_problem, region_outside, write_experiment)
from app.core.fem import poisson_problem
from app.core.geometry import Region
from app.core.mesh import MeshSettings
from app.core.twin import SpecimenTwin


def paper_regions() -> tuple[Region, ...]:
    return (Region("B", "background"), Region("A", "sphere", center_mm=(45.0, 45.0, 66.0), radius_mm=15.0))


@dataclass(frozen=True)
class SyntheticSpec:
    """What to simulate. Lengths mm, moduli kPa, times s, forces N."""

    name: str | None = None  # experiment.toml name (default: the specimen in words, see _default_name)
    size_mm: tuple = (90.0, 90.0, 96.0)
    regions: tuple = field(default_factory=paper_regions)
    moduli_kPa: dict = field(default_factory=lambda: {"B": 18.0, "A": 63.0})
    nu: float = 0.49
    face_mm: tuple = (40.0, 10.0)
    probe_center_mm: tuple | None = None  # default: centre of the top face
    lateral_axis: tuple = (1.0, 0.0, 0.0)  # the image columns' direction: one of PROBE_TURNS' axes
    depth_mm: float = 14.8
    speed_mm_s: float = 1.0
    hold_s: float = 0.0
    unload: bool = False
    rate_Hz: float = 100.0
    frames_at_mm: tuple = (0.0, 7.4, 14.8)
    image_shape: tuple = (256, 200)  # rows (depth), columns (lateral)
    pixel_spacing_mm: tuple = (0.2, 0.2)
    force_noise_N: float = 0.02
    truth_mesh: MeshSettings | None = None  # default: the automatic sizes times truth_mesh_scale
    truth_mesh_scale: float = 0.7
    echogenicity: dict = field(default_factory=lambda: {"A": 1.8})
    scatterer_density_per_mm3: float = 25.0
    seed: int = 0
    # write the true moduli as the experiment's [reference] (as a rheometer would give them)
    reference_method: str | None = None
    # physical effects in the truth (ids of app.core.effects) and their parameters
    effects: tuple = ()
    g1: float = 0.3  # viscoelastic: relaxing fraction of the instantaneous moduli
    tau1_s: float = 2.0  # viscoelastic: relaxation time
    hidden_regions: tuple = ()  # inclusion: regions in the truth but not in experiment.toml (moduli in moduli_kPa)
    load_steps: int = 8  # hyperelastic: load steps of the truth's neo-Hookean solve
    notes: str | None = None  # experiment.toml notes (default: "simulated by ElastoID (seed N)")

    def with_(self, **kw) -> "SyntheticSpec":
        return replace(self, **kw)


#: The bundled demo (resources/demo): ``elastoid simulate --demo resources/demo --overwrite``
#: writes it again (the truth mesh is fTetWild's, so the frames differ slightly run to run).
DEMO_SPEC = SyntheticSpec(
    name="Demo: gelatin phantom with a stiff inclusion (synthetic, after the paper)",
    notes=("Synthetic twin of the paper phantom: 90 x 90 x 96 mm, inclusion A (63 kPa) in tissue B (18 kPa), "
           "probe pressed 14.8 mm. Frames from the scatterer simulator, truth on a finer mesh (truth.toml)."),
    reference_method="simulation truth, in place of the paper rheometer values",
    seed=7,
)


def _default_name(spec: SyntheticSpec) -> str:
    """The specimen in words, e.g. "Synthetic phantom, 90 x 90 x 96 mm, region A
    (sphere) in B". Only what experiment.toml describes: never a hidden effect."""
    size = " x ".join(f"{v:g}" for v in spec.size_mm)
    background, *inside = spec.regions
    if not inside:
        return f"Synthetic phantom, {size} mm, one region ({background.name})"
    listed = ", ".join(f"{r.name} ({r.kind})" for r in inside)
    return f"Synthetic phantom, {size} mm, region{'s' if len(inside) > 1 else ''} {listed} in {background.name}"


def _template(spec: SyntheticSpec) -> Experiment:
    rows, cols = spec.image_shape
    center = spec.probe_center_mm or (spec.size_mm[0] / 2, spec.size_mm[1] / 2)
    m = max(2, cols // 20)
    roi = (m, m, cols - m, min(rows - m, int(rows * 0.72)))
    imaging = Imaging(pixel_spacing_mm=tuple(spec.pixel_spacing_mm), probe_face_px=((cols - 1) / 2.0, 0.0),
                      elevation_thickness_mm=1.0, roi_px=roi)
    return Experiment(name=spec.name or _default_name(spec), specimen=Specimen(tuple(spec.size_mm), tuple(spec.regions)),
                      probe=Probe(tuple(spec.face_mm), tuple(center), tuple(spec.lateral_axis)),
                      imaging=imaging,
                      frames=(), force_log=ForceLog(np.zeros(2), np.zeros(2), np.zeros(2)),
                      notes=spec.notes or f"simulated by ElastoID (seed {spec.seed})")


# the probe turned about the vertical, degrees from x to the image columns -> their direction
# (the simulator writes quarter turns: the model meshes the face along x or y)
PROBE_TURNS = {"0": (1.0, 0.0, 0.0), "90": (0.0, 1.0, 0.0), "180": (-1.0, 0.0, 0.0), "270": (0.0, -1.0, 0.0)}


class SpecError(ElastoidError):
    """A simulation setting that cannot be simulated; ``field`` names the
    SyntheticSpec field (the command line maps it to its option)."""

    def __init__(self, field_name: str, message: str):
        super().__init__(f"{field_name}: {message}")
        self.field, self.reason = field_name, message


def check_spec(spec: SyntheticSpec) -> None:
    """Refuse, before any meshing, a setting that cannot be simulated: each
    message names the field (SpecError). The checks an experiment folder gets
    when it is read (positive sizes, regions inside the specimen, the probe face
    on the top face) and those of the loading protocol."""
    def fail(name, msg):
        raise SpecError(name, msg)

    def positive(name, values, n=None):
        vals = [values] if np.isscalar(values) else list(values)
        if n is not None and len(vals) != n:
            fail(name, f"expected {n} numbers, got {len(vals)}")
        if not all(np.isfinite(v) and v > 0 for v in vals):
            fail(name, f"must be positive, got {', '.join(f'{v:g}' for v in vals)}")

    positive("size_mm", spec.size_mm, 3)
    size = tuple(float(v) for v in spec.size_mm)
    if poisson_problem(spec.nu):
        fail("nu", poisson_problem(spec.nu))
    positive("face_mm", spec.face_mm, 2)
    if tuple(float(v) for v in spec.lateral_axis) not in PROBE_TURNS.values():
        fail("lateral_axis", f"must be x, -x, y or -y, got {list(spec.lateral_axis)}")
    if spec.probe_center_mm is not None and (len(spec.probe_center_mm) != 2
                                             or not all(np.isfinite(v) for v in spec.probe_center_mm)):
        fail("probe_center_mm", f"expected 2 numbers, got {list(spec.probe_center_mm)}")
    center = spec.probe_center_mm or (size[0] / 2, size[1] / 2)
    off = probe_off_top(Probe(tuple(spec.face_mm), tuple(center), tuple(spec.lateral_axis)), size)
    if off:
        fail("face_mm" if spec.probe_center_mm is None else "probe_center_mm", off)
    sz = size[2]
    positive("depth_mm", spec.depth_mm)
    if spec.depth_mm >= sz:
        fail("depth_mm", f"the probe cannot travel {spec.depth_mm:g} mm into a specimen {sz:g} mm high")
    for name in ("speed_mm_s", "rate_Hz", "truth_mesh_scale", "scatterer_density_per_mm3"):
        positive(name, getattr(spec, name))
    positive("pixel_spacing_mm", spec.pixel_spacing_mm, 2)
    for name in ("hold_s", "force_noise_N"):
        v = getattr(spec, name)
        if not (np.isfinite(v) and v >= 0):
            fail(name, f"must be zero or positive, got {v:g}")
    at = [float(x) for x in spec.frames_at_mm]
    if len(at) < 2:
        fail("frames_at_mm", f"a source frame and at least one deformed frame are needed, got {len(at)}")
    if any(x < 0 or x > spec.depth_mm + 1e-9 for x in at):
        fail("frames_at_mm", f"frames are taken during the loading, between 0 and the depth ({spec.depth_mm:g} mm), "
                             f"got {', '.join(f'{x:g}' for x in at)}")
    if any(b <= a for a, b in zip(at, at[1:])):
        fail("frames_at_mm", f"the probe travels must increase, got {', '.join(f'{x:g}' for x in at)}")
    rows, cols = spec.image_shape
    if min(rows, cols) < 32:
        fail("image_shape", f"frames need at least 32 x 32 pixels, got {rows} rows x {cols} columns")
    names = [r.name for r in (*spec.regions, *spec.hidden_regions)]
    for which, regions in (("regions", spec.regions), ("hidden_regions", spec.hidden_regions)):
        for r in regions:
            outside = region_outside(r, size)
            if outside:
                fail(which, outside)
    for n in names:
        E = spec.moduli_kPa.get(n)
        if E is None:
            fail("moduli_kPa", f"no modulus for region {n!r}")
        if not (np.isfinite(E) and E > 0):
            fail("moduli_kPa", f"the modulus of region {n!r} must be positive, got {E:g} kPa")
    if "viscoelastic" in spec.effects:
        if not 0 <= spec.g1 < 1:
            fail("g1", f"the relaxing fraction must lie in [0, 1), got {spec.g1:g}")
        positive("tau1_s", spec.tau1_s)


def protocol(spec: SyntheticSpec) -> tuple[np.ndarray, np.ndarray]:
    """(time_s, displacement_mm) of a ramp, optional hold and optional unload."""
    t_ramp = spec.depth_mm / spec.speed_mm_s
    t_end = t_ramp + spec.hold_s + (t_ramp if spec.unload else 0.0)
    t = np.arange(0.0, t_end + 0.5 / spec.rate_Hz, 1.0 / spec.rate_Hz)
    d = np.clip(t * spec.speed_mm_s, 0, spec.depth_mm)
    if spec.unload:
        t_un = t_ramp + spec.hold_s
        d = np.where(t > t_un, np.clip(spec.depth_mm - (t - t_un) * spec.speed_mm_s, 0, None), d)
    return t, d


def simulate_experiment(out: str | Path, spec: SyntheticSpec = SyntheticSpec(), *,
                        progress: Callable[[str], None] | None = None, cancel=None, overwrite: bool = False) -> Path:
    """Write a synthetic experiment folder (format 1) with ``truth.toml`` beside it."""
    say = progress or (lambda s: None)
    check_spec(spec)
    problem = new_folder_problem(out, overwrite)
    if problem:  # now, not after the minutes of meshing and solving the truth
        raise ExperimentError(out, "", problem)
    exp = _template(spec)
    from app.core.effects import check

    effects = check(spec.effects)
    steps = None
    if "hyperelastic" in effects:
        marks = sorted({float(x) for x in spec.frames_at_mm if x > 0} | {float(spec.depth_mm)})
        steps = sorted(set(np.round(np.concatenate(
            [np.linspace(0, spec.depth_mm, spec.load_steps + 1)[1:], marks]), 9)))
    twin = SpecimenTwin.build(exp, spec.moduli_kPa, nu=spec.nu, mesh_settings=spec.truth_mesh,
                              mesh_scale=spec.truth_mesh_scale,
                              image_shape=spec.image_shape, max_travel_mm=spec.depth_mm, seed=spec.seed,
                              echogenicity=spec.echogenicity, density_per_mm3=spec.scatterer_density_per_mm3,
                              progress=say, cancel=cancel, effects=effects, hidden_regions=tuple(spec.hidden_regions),
                              g1=spec.g1, tau1_s=spec.tau1_s, load_steps_mm=steps)
    t, d = protocol(spec)
    images, frames = {}, []
    for k, dk in enumerate(spec.frames_at_mm):
        say(f"rendering frame {k} at {dk:g} mm")
        name = f"images/frame_{k:03d}.png"
        images[name] = twin.frame(dk)
        frames.append(Frame(name, round(float(dk / spec.speed_mm_s), 6), float(dk)))
    F = twin.force_history_N(t, d) + spec.force_noise_N * twin.rng.standard_normal(len(t))
    exp = replace(exp, frames=tuple(frames), force_log=ForceLog(t, d, F))
    if spec.reference_method:
        exp = replace(exp, reference={"youngs_modulus_kPa": dict(spec.moduli_kPa), "method": spec.reference_method})
    out = Path(out)
    write_experiment(out, exp, images, overwrite=overwrite)
    extra = {}
    if "viscoelastic" in effects:
        extra["viscoelastic"] = {"g1": spec.g1, "tau1_s": spec.tau1_s}
    if spec.hidden_regions:
        extra["hidden_regions"] = [{"name": r.name, "kind": r.kind, "center_mm": list(r.center_mm),
                                    **({"radius_mm": r.radius_mm} if r.radius_mm else {})} for r in spec.hidden_regions]
    write_truth(out, spec, twin.mesh_nodes, twin.mesh_tets, twin.force_N_per_mm, effects, extra)
    say(f"wrote {out}")
    return out


def write_truth(out: Path, spec: SyntheticSpec, n_nodes: int, n_tets: int, force_per_mm: float,
                effects: tuple = (), extra: dict | None = None) -> None:
    import tomli_w

    doc = {"moduli_kPa": dict(spec.moduli_kPa), "nu": spec.nu, "effects": list(effects),
           "seed": spec.seed, "force_noise_N": spec.force_noise_N,
           "truth_mesh": {"nodes": n_nodes, "tetrahedra": n_tets},
           "force_N_per_mm": force_per_mm}
    if extra:
        doc.update(extra)
    (Path(out) / "truth.toml").write_text(tomli_w.dumps(doc), encoding="utf-8")


def read_truth(folder: str | Path) -> dict:
    import tomllib

    return tomllib.loads((Path(folder) / "truth.toml").read_text(encoding="utf-8"))
