"""GUI test fixtures: a headless Qt (offscreen), isolated settings, small experiments.

Qt runs on the ``offscreen`` platform, where the 3-D view is disabled. The 3-D
view (pyvistaqt's QOpenGLWidget) needs a Qt platform with OpenGL: each test
marked ``view3d`` runs in a child pytest process on the ``xcb`` platform, on
the X display pytest-xvfb started (skipped when there is none).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

VIEW3D_CHILD = bool(os.environ.get("ELASTOID_VIEW3D_CHILD"))
os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

SCREENSHOTS = Path(__file__).resolve().parent / "screenshots"
TEST_MESH = dict(edge_mm=10.0, probe_edge_mm=3.0)  # one mesh for every test: meshed once, then cached


def pytest_configure(config):
    config.addinivalue_line("markers", "view3d: needs the VTK 3-D view (runs under Xvfb via pytest-xvfb)")
    config.addinivalue_line("markers", "gui: drives the Qt window")


@pytest.hookimpl(tryfirst=True)
def pytest_pyfunc_call(pyfuncitem):
    """Run a ``view3d`` test in a child process on Qt's xcb platform (this one is offscreen)."""
    if VIEW3D_CHILD or not pyfuncitem.get_closest_marker("view3d"):
        return None
    env = dict(os.environ, ELASTOID_VIEW3D_CHILD="1", QT_QPA_PLATFORM="xcb")
    env.pop("ELASTOID_NO_3D", None)
    tiny = pyfuncitem.funcargs.get("tiny_experiment")
    if tiny is not None:
        env["ELASTOID_TEST_TINY_EXPERIMENT"] = str(tiny)
    cmd = [sys.executable, "-m", "pytest", pyfuncitem.nodeid, "-q", "-p", "no:cacheprovider", "--rootdir", str(ROOT)]
    if pyfuncitem.config.pluginmanager.hasplugin("xvfb"):
        cmd.append("--no-xvfb")  # the child uses this process's display
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    tail = "\n".join((proc.stdout + proc.stderr).splitlines()[-60:])
    if proc.returncode != 0:
        pytest.fail(f"the 3-D test failed in its xcb child process (exit {proc.returncode}):\n{tail}",
                    pytrace=False)
    if " passed" not in proc.stdout:
        pytest.fail(f"the 3-D child process ran no test:\n{tail}", pytrace=False)
    return True


def pytest_collection_modifyitems(config, items):
    here = Path(__file__).resolve().parent
    for item in items:
        if Path(str(item.fspath)).resolve().parent == here:
            item.add_marker(pytest.mark.gui)


@pytest.fixture(scope="session")
def _qt_env(qapp, tmp_path_factory):
    from PySide6.QtCore import QSettings

    from app.gui.style import apply_style

    settings_dir = tmp_path_factory.mktemp("qsettings")
    QSettings.setDefaultFormat(QSettings.IniFormat)
    QSettings.setPath(QSettings.IniFormat, QSettings.UserScope, str(settings_dir))
    qapp.setOrganizationName("ElastoID-tests")
    qapp.setApplicationName("ElastoID-tests")
    apply_style(qapp)
    if "ELASTOID_CACHE_DIR" not in os.environ:
        os.environ["ELASTOID_CACHE_DIR"] = str(tmp_path_factory.mktemp("elastoid-cache"))
    return settings_dir


@pytest.fixture(autouse=True)
def _gui_env(request, _qt_env, monkeypatch):
    """3-D only for ``view3d`` tests, and only where an X display exists."""
    if request.node.get_closest_marker("view3d"):
        if not VIEW3D_CHILD:
            try:
                xvfb = request.getfixturevalue("xvfb")  # pytest-xvfb's display, when it runs
            except pytest.FixtureLookupError:
                xvfb = None
            # fail, not skip: .ci/run installs Xvfb, so a missing display is a broken setup
            assert xvfb is not None or os.environ.get("DISPLAY"), \
                "the 3-D view needs an X display (install the Debian package xvfb for pytest-xvfb)"
        monkeypatch.delenv("ELASTOID_NO_3D", raising=False)
    else:
        monkeypatch.setenv("ELASTOID_NO_3D", "1")
    from PySide6.QtCore import QSettings

    QSettings().clear()
    yield


# ---------------------------------------------------------------------------
# experiments
# ---------------------------------------------------------------------------


def tiny_spec():
    from app.core.geometry import Region
    from app.core.mesh import MeshSettings
    from app.core.simulate import SyntheticSpec

    return SyntheticSpec(
        name="Tiny phantom (test)", size_mm=(40.0, 40.0, 30.0),
        regions=(Region("B", "background"), Region("A", "sphere", center_mm=(20.0, 20.0, 18.0), radius_mm=6.0)),
        moduli_kPa={"B": 18.0, "A": 63.0}, face_mm=(20.0, 8.0), depth_mm=3.0, frames_at_mm=(0.0, 1.5, 3.0),
        image_shape=(100, 100), pixel_spacing_mm=(0.2, 0.2),
        truth_mesh=MeshSettings(edge_mm=8.0, probe_edge_mm=2.5), scatterer_density_per_mm3=10.0, rate_Hz=20.0)


@pytest.fixture(scope="session")
def tiny_experiment(tmp_path_factory, _qt_env) -> Path:
    """A small synthetic experiment (scatterer frames, FE force), with reference moduli added."""
    from dataclasses import replace

    from app.core.experiment import read_experiment, write_experiment
    from app.core.simulate import simulate_experiment

    given = os.environ.get("ELASTOID_TEST_TINY_EXPERIMENT")
    if given and (Path(given) / "experiment.toml").is_file():  # a view3d child reuses its parent's
        return Path(given)
    raw = simulate_experiment(tmp_path_factory.mktemp("sim") / "tiny", tiny_spec())
    exp = read_experiment(raw)
    exp = replace(exp, reference={"youngs_modulus_kPa": {"A": 63.0, "B": 18.0},
                                  "method": "simulation truth (test)"})
    out = tmp_path_factory.mktemp("exp") / "tiny"
    write_experiment(out, exp)
    return out


def visco_spec():
    """The tiny phantom with a hidden viscoelastic effect, a hold and an unloading (the model check's data).
    Same geometry and truth mesh as :func:`tiny_spec`, so both share the cached meshes."""
    return tiny_spec().with_(name="Tiny phantom, viscoelastic (test)", effects=("viscoelastic",), g1=0.35,
                             tau1_s=2.0, hold_s=4.0, unload=True)


@pytest.fixture(scope="session")
def visco_experiment(tmp_path_factory, _qt_env) -> Path:
    from app.core.simulate import simulate_experiment

    return simulate_experiment(tmp_path_factory.mktemp("visco") / "visco", visco_spec())


@pytest.fixture(scope="session")
def noise_experiment(tmp_path_factory, _qt_env) -> Path:
    """A quick experiment with random-noise frames (no physics): for views and sessions."""
    from app.core.experiment import Experiment, ForceLog, Frame, Imaging, Probe, Specimen, write_experiment
    from app.core.geometry import Region

    rng = np.random.default_rng(1)
    t = np.linspace(0, 4, 41)
    d = t.copy()
    exp = Experiment(
        name="Noise frames (test)",
        specimen=Specimen((40.0, 40.0, 30.0), (Region("B", "background"),
                                               Region("A", "sphere", center_mm=(20.0, 20.0, 18.0), radius_mm=6.0))),
        probe=Probe((20.0, 8.0), (20.0, 20.0), (1.0, 0.0, 0.0)),
        imaging=Imaging((0.2, 0.2), (59.5, 0.0), roi_px=(10, 8, 110, 90)),
        frames=tuple(Frame(f"images/frame_{i:03d}.png", float(i), float(i)) for i in range(3)),
        force_log=ForceLog(t, d, 0.4 * d + 0.01 * rng.standard_normal(len(t))),
        reference={"youngs_modulus_kPa": {"A": 60.0, "B": 20.0}, "method": "test"})
    images = {f.image: rng.integers(0, 255, size=(100, 120), dtype=np.uint8) for f in exp.frames}
    out = tmp_path_factory.mktemp("noise") / "noise"
    write_experiment(out, exp, images)
    return out


def folder_digest(folder: Path) -> dict:
    """Name -> (size, mtime_ns, sha1) of every file: to prove a folder was not touched."""
    import hashlib

    out = {}
    for p in sorted(Path(folder).rglob("*")):
        if p.is_file():
            st = p.stat()
            out[str(p.relative_to(folder))] = (st.st_size, st.st_mtime_ns, hashlib.sha1(p.read_bytes()).hexdigest())
    return out


# ---------------------------------------------------------------------------
# windows
# ---------------------------------------------------------------------------


@pytest.fixture
def make_window(qtbot):
    """Builds main windows that are closed (and their threads stopped) after the test."""
    from app.gui.mainwindow import MainWindow

    made = []

    def make(**kw):
        kw.setdefault("restore_layout", False)
        win = MainWindow(**kw)
        win.resize(1400, 900)
        win.show()
        qtbot.waitExposed(win)
        made.append(win)
        return win

    yield make
    for win in made:
        if win.isVisible():
            win.close()
        for b in win.error_boxes:
            b.close()


@pytest.fixture
def window(make_window):
    return make_window()


def wait_task_done(qtbot, panel, timeout_s: float = 120.0):
    qtbot.waitUntil(lambda: panel.task is None, timeout=int(timeout_s * 1000))
