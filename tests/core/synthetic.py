"""Synthetic experiments for identification tests: truth on a finer mesh, frames
from the scatterer simulator, noisy force (never the identifier's own forward model)."""

from __future__ import annotations

from pathlib import Path

from app.core.geometry import Region
from app.core.simulate import SyntheticSpec, simulate_experiment

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


if __name__ == "__main__":  # python -m tests.core.synthetic: write the committed experiments again
    for g, s in COMMITTED_CASES:
        print(make(COMMITTED / f"{g}-seed{s}", g, s)[0])
