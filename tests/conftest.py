import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


@pytest.fixture(scope="session", autouse=True)
def _mesh_cache(tmp_path_factory):
    """Meshes are cached on disk; tests share one cache per session (or the one given)."""
    if "ELASTOID_CACHE_DIR" not in os.environ:
        os.environ["ELASTOID_CACHE_DIR"] = str(tmp_path_factory.mktemp("elastoid-cache"))
    yield
