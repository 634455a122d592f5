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
# the tests that mesh on purpose: meshing itself, the self-test a user runs on a lab PC, and
# the Mesh panel's cancel (a fast machine can finish fTetWild's part before the click)
MESHING_TESTS = ("tests/core/test_mesh.py::", "tests/test_selftest.py::",
                 "tests/gui/test_gui_mesh.py::test_cancel_meshing")


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
    from app.core import mesh

    fresh: list[str] = []
    tetwild = mesh._tetwild

    def counted(*args, **kwargs):
        out = tetwild(*args, **kwargs)  # a meshing cancelled on purpose raises here and counts for nothing
        fresh.append(os.environ.get("PYTEST_CURRENT_TEST", "?").rsplit(" ", 1)[0])
        return out

    mesh._tetwild = counted
    yield
    mesh._tetwild = tetwild
    # a test that meshes afresh is not reproducible (the mesh moves from run to run;
    # a fresh truth mesh of the tiny phantom failed CI once): commit its mesh (see
    # the developer guide, "Mesh cache"). Only the tests of meshing itself mesh on purpose.
    stray = sorted({t for t in fresh if not t.startswith(MESHING_TESTS)})
    assert not stray, ("these tests made meshes that tests/data/meshes does not hold (run them with "
                       f"ELASTOID_CACHE_DIR set to a copy of it and commit the new files): {stray}")
