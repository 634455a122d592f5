"""Synthetic experiments for identification tests: truth on a finer mesh, frames
from the scatterer simulator, noisy force (never the identifier's own forward model)."""

from __future__ import annotations

from pathlib import Path

from app.core.geometry import Region
from app.core.mesh import MeshSettings
from app.core.simulate import SyntheticSpec, read_truth, simulate_experiment

GEOMETRIES = {
    # a stiff sphere (the paper's case, scaled down so tests stay fast)
    "sphere": dict(size_mm=(40.0, 40.0, 30.0),
                   regions=(Region("B", "background"), Region("A", "sphere", center_mm=(20.0, 20.0, 18.0), radius_mm=7.0)),
                   moduli_kPa={"B": 15.0, "A": 45.0}),
    # a soft, flat, off-centre ellipsoid
    "ellipsoid": dict(size_mm=(44.0, 40.0, 32.0),
                      regions=(Region("B", "background"),
                               Region("A", "ellipsoid", center_mm=(24.0, 20.0, 19.0), radii_mm=(9.0, 7.0, 5.0))),
                      moduli_kPa={"B": 24.0, "A": 9.0}),
}
COMMON = dict(face_mm=(24.0, 8.0), depth_mm=5.0, frames_at_mm=(0.0, 2.5, 5.0), image_shape=(128, 120))

# Mid-size specimens for the identification tests: the small ones above carry too
# little image information (about 10k ROI pixels) to fix a ratio within 5%; the
# paper-size demo has 31k. These have about 25k and stay fast enough for CI.
_MEDIUM = dict(face_mm=(32.0, 10.0), depth_mm=8.0, frames_at_mm=(0.0, 4.0, 8.0), image_shape=(200, 160))
GEOMETRIES["medium-sphere"] = dict(
    size_mm=(60.0, 60.0, 50.0), moduli_kPa={"B": 15.0, "A": 45.0},
    regions=(Region("B", "background"), Region("A", "sphere", center_mm=(30.0, 30.0, 32.0), radius_mm=10.0)),
    **_MEDIUM)
GEOMETRIES["medium-ellipsoid"] = dict(
    size_mm=(64.0, 60.0, 50.0), moduli_kPa={"B": 24.0, "A": 9.0},
    regions=(Region("B", "background"),
             Region("A", "ellipsoid", center_mm=(34.0, 30.0, 32.0), radii_mm=(12.0, 10.0, 8.0))),
    **_MEDIUM)


def make(folder: Path, geometry: str, seed: int, **overrides) -> tuple[Path, SyntheticSpec]:
    spec = SyntheticSpec(seed=seed, **{**COMMON, **GEOMETRIES[geometry], **overrides})
    return simulate_experiment(folder, spec, overwrite=True), spec


COMMITTED = Path(__file__).resolve().parents[1] / "data" / "experiments"
COMMITTED_CASES = (("medium-sphere", 1), ("medium-sphere", 2), ("medium-ellipsoid", 3))


def committed(geometry: str, seed: int) -> Path:
    """The committed experiment made by :func:`make` (tests/data/experiments)."""
    folder = COMMITTED / f"{geometry}-seed{seed}"
    if not (folder / "experiment.toml").is_file():
        raise FileNotFoundError(f"{folder}: not committed; write it with `python -m tests.core.synthetic`")
    return folder


# The hidden-effect experiments of tests/core/test_diagnose.py: a 40 x 40 x 30 mm
# phantom with a stiff sphere, truth on a mesh 0.7 of the identification mesh's
# size. Simulating one takes about 12 s, the neo-Hookean truth about 80 s: the
# suite reads them from tests/data/experiments/diagnose instead (written by
# ``python -m tests.core.synthetic``, the same simulator).
DIAGNOSE_ID_MESH = MeshSettings(edge_mm=6.0, probe_edge_mm=2.5, region_edge_mm=2.5)
DIAGNOSE_BASE = dict(size_mm=(40.0, 40.0, 30.0),
                     regions=(Region("B", "background"),
                              Region("A", "sphere", center_mm=(20.0, 20.0, 18.0), radius_mm=7.0)),
                     moduli_kPa={"B": 15.0, "A": 45.0}, face_mm=(24.0, 8.0), depth_mm=5.0,
                     frames_at_mm=(0.0, 2.5, 5.0), image_shape=(192, 180),
                     truth_mesh=DIAGNOSE_ID_MESH.with_scale(0.7))
# name -> (seed, what differs from DIAGNOSE_BASE)
DIAGNOSE_CASES = {
    "visco": (4, dict(effects=("viscoelastic",), g1=0.35, tau1_s=2.0, hold_s=6.0)),
    "none-5": (5, {}),
    "none-6": (6, {}),
    "hyper": (1, dict(effects=("hyperelastic",), depth_mm=7.5, frames_at_mm=(0.0, 3.75, 7.5))),
    "two": (3, dict(effects=("viscoelastic", "sliding-bottom"))),
    "sliding-bottom": (13, dict(effects=("sliding-bottom",))),
    "probe-slip": (14, dict(effects=("probe-slip",))),
    "probe-slip-15": (15, dict(effects=("probe-slip",))),
    "two-16": (16, dict(effects=("viscoelastic",), nu=0.3)),
    "none-17": (17, {}),
    "compressibility-45": (18, dict(nu=0.45)),
    "compressibility": (14, dict(nu=0.3)),
    "inclusion": (13, dict(hidden_regions=(Region("C", "sphere", center_mm=(26.0, 20.0, 14.0), radius_mm=4.0),),
                           moduli_kPa={"B": 15.0, "A": 45.0, "C": 60.0})),
    # the probe slips over a stiffer sphere near its right end, 5 mm deep: each hides the other
    "slip-inclusion": (30, dict(effects=("probe-slip",),
                                hidden_regions=(Region("C", "sphere", center_mm=(28.0, 20.0, 25.0), radius_mm=4.0),),
                                moduli_kPa={"B": 15.0, "A": 45.0, "C": 60.0})),
}
# A second geometry: a soft, flat, off-centre ellipsoid (9 kPa in 24 kPa tissue) in a
# 44 x 40 x 32 mm block, with its own seeds (the "e-" cases)
DIAGNOSE_ELLIPSOID = dict(size_mm=(44.0, 40.0, 32.0),
                          regions=(Region("B", "background"),
                                   Region("A", "ellipsoid", center_mm=(24.0, 20.0, 19.0), radii_mm=(9.0, 7.0, 5.0))),
                          moduli_kPa={"B": 24.0, "A": 9.0})
DIAGNOSE_CASES.update({
    "e-visco": (21, dict(DIAGNOSE_ELLIPSOID, effects=("viscoelastic",), g1=0.35, tau1_s=2.0, hold_s=6.0)),
    "e-sliding-bottom": (22, dict(DIAGNOSE_ELLIPSOID, effects=("sliding-bottom",))),
    # measured by bench/probe_slip_signal.py, not tested (see tests/core/test_diagnose.py)
    "e-probe-slip": (23, dict(DIAGNOSE_ELLIPSOID, effects=("probe-slip",))),
    "e-compressibility": (24, dict(DIAGNOSE_ELLIPSOID, nu=0.3)),
    "e-inclusion": (25, dict(DIAGNOSE_ELLIPSOID,
                             hidden_regions=(Region("C", "sphere", center_mm=(32.0, 20.0, 25.0), radius_mm=4.0),),
                             moduli_kPa={"B": 24.0, "A": 9.0, "C": 72.0})),
    "e-hyper": (26, dict(DIAGNOSE_ELLIPSOID, effects=("hyperelastic",), depth_mm=7.5, frames_at_mm=(0.0, 3.75, 7.5))),
    "e-none-27": (27, dict(DIAGNOSE_ELLIPSOID)),
    "e-none-29": (29, dict(DIAGNOSE_ELLIPSOID)),
    "e-two": (28, dict(DIAGNOSE_ELLIPSOID, effects=("viscoelastic", "sliding-bottom"))),
})
DIAGNOSE_DIR = COMMITTED / "diagnose"


def diagnose_spec(name: str) -> SyntheticSpec:
    seed, kw = DIAGNOSE_CASES[name]
    return SyntheticSpec(seed=seed, **{**DIAGNOSE_BASE, **kw})


def diagnose_case(name: str) -> Path:
    """The committed hidden-effect experiment ``name`` of DIAGNOSE_CASES, checked
    against its spec (seed, effects, moduli, Poisson's ratio in truth.toml)."""
    folder = DIAGNOSE_DIR / name
    if not (folder / "experiment.toml").is_file():
        raise FileNotFoundError(f"{folder}: not committed; write it with `python -m tests.core.synthetic`")
    spec, truth = diagnose_spec(name), read_truth(folder)
    recorded = (truth["seed"], tuple(truth["effects"]), truth["moduli_kPa"], truth["nu"])
    wanted = (spec.seed, tuple(spec.effects), dict(spec.moduli_kPa), spec.nu)
    if recorded != wanted:
        raise AssertionError(f"{folder / 'truth.toml'}: written for {recorded}, the case is {wanted}; "
                             f"write it again with `python -m tests.core.synthetic`")
    return folder


# the candidates that refit quickly (no new mesh, no neo-Hookean solves)
DIAGNOSE_FAST = ("viscoelastic", "sliding-bottom", "probe-slip")


def diagnose_experiment(tmp_path_factory, name: str):
    """A copy of the committed hidden-effect experiment ``name``, read, after
    checking that its identification mesh (DIAGNOSE_ID_MESH) is one of the
    committed meshes (tests/data/meshes)."""
    import shutil

    from app.core.experiment import read_experiment

    folder = tmp_path_factory.mktemp(name) / "exp"
    shutil.copytree(diagnose_case(name), folder)
    exp = read_experiment(folder)
    assert_mesh_committed(exp)
    return exp


def assert_mesh_committed(exp, inclusion: dict | None = None) -> None:
    """That the mesh of ``exp`` (with the located sphere ``inclusion`` added, if
    given) at DIAGNOSE_ID_MESH is one of the committed meshes (tests/data/meshes):
    fTetWild is not deterministic, so a test whose outcome depends on the mesh,
    meshed afresh, passes or fails by chance (a located sphere that moved left the
    hidden-inclusion test on a fresh mesh of it for a day, 2026-11-29)."""
    from dataclasses import replace

    from app.core.effects.inclusion import inclusion_region
    from app.core.mesh import _mesh_key

    if inclusion is not None:
        exp = replace(exp, specimen=exp.specimen.with_region(inclusion_region(inclusion)))
    key = _mesh_key(exp.specimen.size_mm, exp.probe.face_rect_mm(), exp.specimen.regions, DIAGNOSE_ID_MESH)
    meshes = Path(__file__).resolve().parents[1] / "data" / "meshes"
    assert (meshes / f"{key}.npz").is_file(), (
        f"tests/data/meshes has no mesh {key}.npz (regions {[r.name for r in exp.specimen.regions]}): meshing "
        "(MESH_VERSION) or what the diagnosis locates changed; commit the mesh from the test's cache "
        "(ELASTOID_CACHE_DIR/meshes)")


def moduli_errors(params: dict, truth: dict) -> dict:
    """Relative error of each region's modulus in ``params`` against ``truth`` (kPa by region)."""
    return {k: params[f"E_{k}_kPa"] / v - 1 for k, v in truth.items()}


if __name__ == "__main__":  # python -m tests.core.synthetic: write the committed experiments again
    import sys

    only = set(sys.argv[1:])
    for g, s in COMMITTED_CASES:
        if not only or f"{g}-seed{s}" in only:
            print(make(COMMITTED / f"{g}-seed{s}", g, s)[0], flush=True)
    for name in DIAGNOSE_CASES:
        if not only or name in only:
            print(simulate_experiment(DIAGNOSE_DIR / name, diagnose_spec(name), overwrite=True), flush=True)
