import os
import sys
from pathlib import Path

import pytest

# Two pytest-xdist workers share this machine's two cores. MKL's OpenMP threads
# (PARDISO's factorizations and solves) would be two per worker, four on two
# cores, spinning while they wait for one another: one per worker. Measured
# 2026-11-27, two no-effect diagnoses side by side: 139 s wall and 267
# CPU-seconds with MKL's default threads, 107 s and 205 with one. Set before
# anything loads MKL; a value given in the environment wins.
if os.environ.get("PYTEST_XDIST_WORKER"):
    for _var in ("MKL_NUM_THREADS", "OMP_NUM_THREADS"):
        os.environ.setdefault(_var, "1")

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


FIXED_MESHES = ROOT / "tests" / "data" / "meshes"


@pytest.fixture(scope="session", autouse=True)
def _mesh_cache(tmp_path_factory):
    """Meshes are cached on disk; tests share one cache per session (or the one given).

    The cache starts with the committed meshes of tests/data/meshes (named by
    their cache key): fTetWild is not deterministic, so the tests whose outcome
    depends on the exact mesh (identification accuracy, diagnosis) use fixed
    ones and a run is reproducible. The spread over fresh meshes is measured in
    bench/ (identify_spread.py, diagnose_effects.py)."""
    import shutil

    if "ELASTOID_CACHE_DIR" not in os.environ:
        os.environ["ELASTOID_CACHE_DIR"] = str(tmp_path_factory.mktemp("elastoid-cache"))
    from app.core.mesh import cache_dir

    dst = cache_dir()
    dst.mkdir(parents=True, exist_ok=True)
    for f in FIXED_MESHES.glob("*.npz"):
        shutil.copy(f, dst / f.name)
    yield
