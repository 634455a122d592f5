"""``elastoid selftest``: check that this installation works, one line per check.

Meant for the frozen application (``elastoid --selftest`` in the PyInstaller
bundle), where a module or a native library left out of the bundle only shows
when it is used. Every check *uses* what it checks:

``imports``    every module of the app and the libraries it loads lazily
``solver``     a sparse SPD factorization (MKL PARDISO on x86-64, where it must load)
``resources``  the bundled demo experiment reads, with its images; the guides (Help) are there
``mesh``       fTetWild meshes a small box with a spherical inclusion in a spawned child process
``forward``    the P2 model on that mesh: finite positive probe force, stiffer inclusion = more force
``render``     pyvista draws the clipped mesh off screen (no display); the image is not blank
``rig``        the simulated GRBL stage and load cell served on ports (TCP; also pseudo-terminals
               where there are any), opened by the real drivers: status, a 1 mm move, force readings
``window``     the main window is built on Qt's offscreen platform, opens the demo, closes
``window-3d``  (only with ``--with-3d``, needs a display) the window with its pyvistaqt 3-D view

Prints ``PASS name (seconds) detail`` or ``FAIL name (seconds) reason`` per
check and a summary; the exit code is 0 only when every check passed. No Qt at
import time; the window checks import it when they run.
"""

from __future__ import annotations

import os
import platform
import sys
import tempfile
import time
import traceback
from dataclasses import dataclass
from typing import Callable

# modules the app imports lazily (inside functions) or that load plugins at run time; a
# bundle missing one of them breaks only when the feature is used
THIRD_PARTY = (
    "numpy", "scipy.sparse.linalg", "scipy.optimize", "scipy.ndimage", "scipy.signal", "scipy.spatial",
    "scipy.interpolate", "skimage.feature", "pytetwild", "pyvista", "vtkmodules.vtkRenderingOpenGL2",
    "pyvistaqt", "PySide6.QtWidgets", "PySide6.QtOpenGLWidgets", "pyqtgraph", "matplotlib.colors",
    "serial", "serial.tools.list_ports", "serial.urlhandler.protocol_socket", "serial.urlhandler.protocol_loop",
    "pydicom", "tifffile", "imageio.v3", "meshio", "tomli_w", "threadpoolctl",
)

# the app's own modules that must be importable (a walk of the packages finds the rest)
KEY_MODULES = ("app.cli", "app.core.mesh", "app.core.forward", "app.core.identify", "app.devices.sim.serve",
               "app.devices.cli", "app.gui.mainwindow", "app.gui.view3d")


def _needs_pardiso() -> bool:
    """pypardiso is a dependency on x86-64 (see pyproject.toml): there it must load."""
    return platform.machine().lower() in ("x86_64", "amd64")


@dataclass
class CheckResult:
    name: str
    passed: bool
    detail: str
    seconds: float

    def line(self) -> str:
        return f"{'PASS' if self.passed else 'FAIL'} {self.name:<10} ({self.seconds:5.1f} s) {self.detail}"


class _Context:
    """State shared by the checks (the small specimen's mesh, for the forward model and the render)."""

    def __init__(self):
        self.mesh = None
        self.regions = None


# the small specimen: 30 x 30 x 24 mm box, a 6 mm sphere, a 12 x 6 mm probe face; with these
# sizes and a coarse envelope fTetWild takes a few seconds
SIZE_MM = (30.0, 30.0, 24.0)
PROBE_RECT_MM = (9.0, 21.0, 12.0, 18.0)
SPHERE = ((15.0, 15.0, 12.0), 6.0)


# ---------------------------------------------------------------------------
# the checks: each returns a detail line or raises
# ---------------------------------------------------------------------------


def check_imports(ctx: _Context) -> str:
    import importlib
    import pkgutil

    import app

    names = set(KEY_MODULES)
    for info in pkgutil.walk_packages(app.__path__, "app."):
        names.add(info.name)
    failed = []
    for name in sorted(names) + list(THIRD_PARTY):
        if name == "app.__main__":  # running it starts the command line
            continue
        try:
            importlib.import_module(name)
        except Exception as exc:
            failed.append(f"{name} ({type(exc).__name__}: {exc})")
    if failed:
        raise RuntimeError("cannot import " + "; ".join(failed))
    n_app = sum(1 for n in sys.modules if n == "app" or n.startswith("app."))
    if n_app < 40:  # the packages hold ~80 modules; a bundle that lost most of them fails here
        raise RuntimeError(f"only {n_app} app modules were found")
    import PySide6
    import pyvista
    import vtkmodules

    return (f"{n_app} app modules, {len(THIRD_PARTY)} libraries (PySide6 {PySide6.__version__}, "
            f"pyvista {pyvista.__version__}, vtk {vtkmodules.__version__})")


def check_solver(ctx: _Context) -> str:
    import numpy as np
    import scipy.sparse as sp

    from app.core import solver

    if _needs_pardiso() and not solver.HAVE_PARDISO:
        raise RuntimeError("pypardiso (MKL) did not load on x86-64: solves would fall back to SuperLU, ~40x slower")
    n = 2000  # 1-D Laplacian + 0.01 I: SPD, exact solution known
    A = sp.diags([np.full(n - 1, -1.0), np.full(n, 2.01), np.full(n - 1, -1.0)], [-1, 0, 1], format="csr")
    x = np.sin(np.linspace(0, 7, n))
    f = solver.Factorized(A)
    try:
        got = f.solve(A @ x)
    finally:
        f.free()
    err = float(np.max(np.abs(got - x)))
    if not err < 1e-8:
        raise RuntimeError(f"{solver.backend_name()} solved a 2000x2000 SPD system with error {err:.2e}")
    return f"{solver.backend_name()}, 2000x2000 SPD solve error {err:.1e}"


def check_resources(ctx: _Context) -> str:
    from app.core.experiment import read_experiment
    from app.resources import resource_path

    demo = resource_path("demo")
    if not (demo / "experiment.toml").is_file():
        raise RuntimeError(f"the demo experiment is missing ({demo})")
    exp = read_experiment(demo)
    img = exp.image(0)
    if img.ndim != 2 or img.size == 0 or float(img.std()) == 0.0:
        raise RuntimeError(f"demo frame 0 is blank or malformed: shape {img.shape}")
    if len(exp.force_log) < 10:
        raise RuntimeError(f"demo force log has {len(exp.force_log)} samples")
    from app.core.mesh import shipped_mesh_path

    if shipped_mesh_path(exp) is None:
        raise RuntimeError("the demo's mesh is not shipped (resources/meshes): the demo would be meshed again")
    import re

    from app.resources import docs_path

    guide = docs_path("user-guide.md")
    if not guide.is_file():
        raise RuntimeError(f"the user guide is missing ({guide}): Help > User guide would show nothing")
    shots = re.findall(r"!\[[^\]]*\]\((images/[^)\s]+)\)", guide.read_text(encoding="utf-8"))
    missing = [s for s in shots if not docs_path(s).is_file()]
    if not shots or missing:
        raise RuntimeError(f"the user guide's screenshots are missing: {', '.join(missing) or 'none referenced'}")
    n_guides = len(list(docs_path().glob("*.md")))
    return (f"demo: {len(exp.frames)} frames {img.shape[1]}x{img.shape[0]} px, {len(exp.force_log)} force samples, "
            f"its mesh shipped; {n_guides} guides, the user guide's {len(shots)} screenshots")


def check_mesh(ctx: _Context) -> str:
    from app.core.geometry import Region
    from app.core.mesh import MeshSettings, build_mesh, quality

    regions = (Region("B", "background"), Region("A", "sphere", center_mm=SPHERE[0], radius_mm=SPHERE[1]))
    settings = MeshSettings(edge_mm=10.0, probe_edge_mm=5.0, epsilon=2e-3)
    # use_cache=False: the point is to run fTetWild in its spawned child (a frozen app re-runs
    # its own executable for it, which works only with multiprocessing.freeze_support())
    # fTetWild is not deterministic: its meshes of this box had smallest dihedral angles of
    # 3.8-23 deg in 25 runs here, but one CI run (2026-11-29) got a sliver of 0.47 deg. A
    # sliver in one run says nothing of the installation, so a second mesh is made; two in a
    # row fail the check
    retried = ""
    for attempt in range(2):
        mesh = build_mesh(SIZE_MM, PROBE_RECT_MM, regions, settings, use_cache=False, timeout_s=300.0)
        q = quality(mesh, regions)
        if q.min_dihedral_deg > 0.5:
            break
        if attempt:
            raise RuntimeError(f"degenerate tetrahedra in two meshes (min dihedral angles {retried} and "
                               f"{q.min_dihedral_deg:.2f} deg)")
        retried = f"{q.min_dihedral_deg:.2f}"
    if mesh.n_tets < 500 or q.n_probe_nodes < 4:
        raise RuntimeError(f"suspicious mesh: {mesh.n_tets} tets, {q.n_probe_nodes} probe-face vertices")
    for name in ("A", "B"):
        m, g = q.region_volume_mm3[name], q.region_geometric_volume_mm3[name]
        if abs(m - g) > 0.05 * g:
            raise RuntimeError(f"region {name}: meshed volume {m:.0f} mm3 vs geometric {g:.0f} mm3")
    box = SIZE_MM[0] * SIZE_MM[1] * SIZE_MM[2]
    vol = float(mesh.tet_volumes_mm3().sum())
    if abs(vol - box) > 0.005 * box:  # fTetWild's envelope allows a little
        raise RuntimeError(f"the tets fill {vol:.0f} mm3 of the {box:.0f} mm3 box")
    ctx.mesh, ctx.regions = mesh, regions
    again = f"; meshed twice, the first had a sliver of {retried} deg" if retried else ""
    return (f"{mesh.n_nodes} nodes, {mesh.n_tets} tets, inclusion volume {q.region_volume_mm3['A']:.0f} mm3 "
            f"(sphere {q.region_geometric_volume_mm3['A']:.0f}){again}")


def check_forward(ctx: _Context) -> str:
    import numpy as np

    from app.core.forward import build_model

    if ctx.mesh is None:
        raise RuntimeError("no mesh (the mesh check failed)")
    model = build_model(ctx.mesh)
    u_stiff, f_stiff = model.solve([18.0, 63.0])  # B = 18 kPa, inclusion A = 63 kPa (the paper's)
    u_soft, f_soft = model.solve([18.0, 18.0])
    _, f_double = model.solve([36.0, 126.0])
    if not (np.isfinite(f_stiff) and f_stiff > 0 and np.all(np.isfinite(u_stiff))):
        raise RuntimeError(f"probe force {f_stiff!r} N per mm is not finite and positive")
    if not f_stiff > f_soft > 0:
        raise RuntimeError(f"a stiffer inclusion must need more force: {f_stiff:.4f} vs {f_soft:.4f} N/mm")
    if abs(f_double - 2 * f_stiff) > 1e-6 * f_stiff:  # linear elasticity: force scales with the moduli
        raise RuntimeError(f"doubling the moduli gave {f_double:.6f} N/mm, expected {2 * f_stiff:.6f}")
    # the solution is for 1 mm of probe travel: the probe face is 1 mm lower, the bottom is fixed
    u = u_stiff.reshape(-1, 3)
    pts = model.space.points_mm
    probe, bottom = ctx.mesh.probe_nodes(pts), pts[:, 2] < 1e-6
    if not (np.allclose(u[probe, 2], -1.0) and np.allclose(u[bottom], 0.0)):
        raise RuntimeError("the boundary conditions do not hold in the solution")
    if not 0.0 < -u[~probe & ~bottom, 2].mean() < 1.0:
        raise RuntimeError("the interior does not move between the probe and the fixed bottom")
    return (f"{model.space.n_dofs} dofs, probe force {f_stiff:.4f} N/mm (A = 63 kPa) > {f_soft:.4f} N/mm "
            f"(A = 18 kPa)")


def check_render(ctx: _Context) -> str:
    import numpy as np
    import pyvista as pv
    from matplotlib.colors import ListedColormap

    if ctx.mesh is None:
        raise RuntimeError("no mesh (the mesh check failed)")
    mesh = ctx.mesh
    cells = np.hstack([np.full((mesh.n_tets, 1), 4), mesh.tets]).ravel()
    grid = pv.UnstructuredGrid(cells, np.full(mesh.n_tets, pv.CellType.TETRA, np.uint8), mesh.points_mm)
    grid.cell_data["region"] = mesh.labels
    part = grid.clip(normal=(0.0, 1.0, 0.0), origin=(0.0, SIZE_MM[1] / 2, 0.0), invert=True)
    plotter = pv.Plotter(off_screen=True, window_size=(320, 240))
    try:
        plotter.set_background("white")
        plotter.add_mesh(part, scalars="region", cmap=ListedColormap(["#4c78a8", "#e45756"]), clim=(-0.5, 1.5),
                         show_edges=True, show_scalar_bar=False, categories=True)
        plotter.view_isometric()
        img = plotter.screenshot(return_img=True)
        backend = type(plotter.ren_win).__name__
    finally:
        plotter.close()
    if img is None or img.ndim != 3 or img.shape[:2] != (240, 320):
        raise RuntimeError(f"no image (got {None if img is None else img.shape})")
    rgb = img[..., :3].astype(int)
    drawn = float(np.mean(np.any(np.abs(rgb - 255) > 30, axis=-1)))  # not the white background
    red = float(np.mean(rgb[..., 0] - np.maximum(rgb[..., 1], rgb[..., 2]) > 40))  # the inclusion on the cut
    if drawn < 0.05:
        raise RuntimeError(f"the image is blank ({100 * drawn:.1f}% of pixels drawn)")
    if red < 0.002:
        raise RuntimeError("the inclusion does not show on the cut (colour map not applied?)")
    return f"{backend}, 320x240, {100 * drawn:.0f}% of pixels drawn, inclusion {100 * red:.1f}%"


def _rig_round_trip(transport: str) -> str:
    from app.devices.grbl import GrblStage
    from app.devices.loadcell import AsciiLoadCell
    from app.devices.sim import NonlinearSpring, SimRig

    k, contact = 1.0, 0.5  # N/mm after 0.5 mm of travel: at 1.0 mm the force is 0.5 N
    sim = SimRig(NonlinearSpring(k, 0.0, contact), noise_N=0.001, latency_ms=2.0)
    server = sim.serve(transport)
    stage = sensor = None
    try:
        stage = GrblStage.open(server.urls["stage"])
        sensor = AsciiLoadCell.open(server.urls["force"])
        st0 = stage.query_status()
        if st0.state != "Idle" or abs(st0.travel_mm) > 1e-6:
            raise RuntimeError(f"stage status at start: {st0.state} at {st0.travel_mm} mm")
        sensor.tare()
        sensor.start(200)
        stage.start_move(1.0, 5.0)
        samples = []
        deadline = time.monotonic() + 5.0
        st = st0
        while time.monotonic() < deadline:
            samples += sensor.read_samples(0.02)
            st = stage.query_status()
            if st.state == "Idle" and abs(st.travel_mm - 1.0) < 1e-6:
                break
        settle = time.monotonic() + 0.2
        while time.monotonic() < settle:
            samples += sensor.read_samples(0.02)
        sensor.stop()
        if st.state != "Idle" or abs(st.travel_mm - 1.0) > 1e-6:
            raise RuntimeError(f"the 1 mm move ended {st.state} at {st.travel_mm} mm")
        if len(samples) < 20:
            raise RuntimeError(f"only {len(samples)} force samples in {time.monotonic() - deadline + 5:.1f} s")
        f_end = samples[-1].force_N
        if abs(f_end - k * (1.0 - contact)) > 0.02:
            raise RuntimeError(f"force at 1.0 mm: {f_end:.4f} N, the specimen gives {k * (1.0 - contact):.3f} N")
        if [s.seq for s in samples] != list(range(len(samples))):
            raise RuntimeError("force samples were lost or reordered")
        return f"{transport}: GRBL {stage.version} Idle->1.000 mm, {len(samples)} samples, {f_end:.3f} N"
    finally:
        for dev in (stage, sensor):
            if dev is not None:
                dev.close()
        sim.stop()


def check_rig(ctx: _Context) -> str:
    from app.devices.sim import ptys_available

    # TCP is what Windows uses (and exercises pyserial's socket:// handler); ptys are Linux/macOS's default
    out = [_rig_round_trip("socket")]
    if ptys_available():
        out.append(_rig_round_trip("pty"))
    return "; ".join(out)


class _QtSession:
    """The QApplication for the window checks, with settings that never touch the user's."""

    def __init__(self, platform_name: str | None):
        from PySide6.QtCore import QSettings
        from PySide6.QtWidgets import QApplication

        self.app = QApplication.instance()
        self.owned = self.app is None
        self._names = None
        if self.owned:
            if platform_name:
                os.environ["QT_QPA_PLATFORM"] = platform_name
            self._settings_dir = tempfile.mkdtemp(prefix="elastoid-selftest-settings-")
            QSettings.setDefaultFormat(QSettings.IniFormat)
            QSettings.setPath(QSettings.IniFormat, QSettings.UserScope, self._settings_dir)
            self.app = QApplication([sys.argv[0] if sys.argv else "elastoid"])
            from app.gui.style import apply_style

            apply_style(self.app)
        else:  # someone else's application (a test session): borrow it under other names
            self._names = (self.app.organizationName(), self.app.applicationName())
        self.app.setOrganizationName("ElastoID-selftest")
        self.app.setApplicationName("ElastoID-selftest")

    def restore(self) -> None:
        if self.owned:
            import shutil

            shutil.rmtree(self._settings_dir, ignore_errors=True)
        if self._names is not None:
            self.app.setOrganizationName(self._names[0])
            self.app.setApplicationName(self._names[1])


def _process_events(app, seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        app.processEvents()
        time.sleep(0.01)


def _window(ctx: _Context, *, with_3d: bool) -> str:
    qt = ctx.qt
    from PySide6.QtCore import QSettings

    QSettings().clear()
    from app.gui.mainwindow import MainWindow, demo_path

    win = MainWindow(enable_3d=with_3d, restore_layout=False)
    try:
        win.resize(1200, 800)
        win.show()
        _process_events(qt.app, 0.3)
        if not win.act_demo.isEnabled():
            raise RuntimeError(f"the window does not find the demo ({demo_path()})")
        if not win.open_experiment(demo_path()):
            raise RuntimeError("the window could not open the demo experiment")
        _process_events(qt.app, 0.5)
        if not win.session.has_experiment:
            raise RuntimeError("the demo did not load into the session")
        if win.error_boxes:
            raise RuntimeError(f"the window showed {len(win.error_boxes)} error message(s)")
        img = win.grab().toImage()
        if img.isNull() or img.width() < 100:
            raise RuntimeError("the window did not render")
        detail = f"{qt.app.platformName()}: {len(win.docks)} docks, demo opened, {img.width()}x{img.height()}"
        if with_3d:
            import numpy as np

            plotter = win.mesh_panel.plotter
            if plotter is None:
                raise RuntimeError("the mesh panel has no 3-D view")
            win.raise_panel("mesh")
            _process_events(qt.app, 0.5)
            plotter.render()
            shot = plotter.screenshot(return_img=True)
            rgb = np.asarray(shot)[..., :3].astype(int)
            drawn = float(np.mean(np.any(np.abs(rgb - rgb[0, 0]) > 30, axis=-1)))
            if drawn < 0.01:
                raise RuntimeError(f"the 3-D view is blank ({100 * drawn:.2f}% drawn)")
            detail += f", 3-D view {rgb.shape[1]}x{rgb.shape[0]} ({type(plotter.ren_win).__name__}) " \
                      f"{100 * drawn:.0f}% drawn"
        return detail
    finally:
        win.close()
        win.deleteLater()
        _process_events(qt.app, 0.2)


def check_window(ctx: _Context) -> str:
    return _window(ctx, with_3d=False)


def check_window_3d(ctx: _Context) -> str:
    return _window(ctx, with_3d=True)


CHECKS: dict[str, Callable[[_Context], str]] = {
    "imports": check_imports,
    "solver": check_solver,
    "resources": check_resources,
    "mesh": check_mesh,
    "forward": check_forward,
    "render": check_render,
    "rig": check_rig,
    "window": check_window,
    "window-3d": check_window_3d,
}
DEFAULT_CHECKS = tuple(n for n in CHECKS if n != "window-3d")


def run(names=DEFAULT_CHECKS, *, out=print) -> list[CheckResult]:
    """Run the checks in order; ``out`` receives one line per check as it finishes."""
    unknown = [n for n in names if n not in CHECKS]
    if unknown:
        raise ValueError(f"unknown check(s): {', '.join(unknown)}; the checks are {', '.join(CHECKS)}")
    ctx = _Context()
    ctx.qt = None
    results = []
    try:
        for name in names:
            t0 = time.perf_counter()
            try:
                if name.startswith("window") and ctx.qt is None:
                    # offscreen needs no display; the 3-D view needs the real platform (xcb, windows, cocoa)
                    ctx.qt = _QtSession(None if "window-3d" in names else "offscreen")
                detail, ok = CHECKS[name](ctx), True
            except Exception as exc:
                detail, ok = f"{type(exc).__name__}: {exc}", False
                if os.environ.get("ELASTOID_SELFTEST_TRACEBACK"):
                    traceback.print_exc()
            res = CheckResult(name, ok, " ".join(str(detail).split()), time.perf_counter() - t0)
            results.append(res)
            out(res.line())
    finally:
        if ctx.qt is not None:
            ctx.qt.restore()
    return results


def main(argv: list[str] | None = None) -> int:
    import argparse

    p = argparse.ArgumentParser(prog="elastoid selftest", description="Check this installation: one line per "
                                "check, exit code 0 when all pass.")
    p.add_argument("--with-3d", action="store_true", help="also build the window with its 3-D view (needs a display)")
    p.add_argument("--only", help=f"comma-separated checks to run (of {', '.join(CHECKS)})")
    args = p.parse_args(argv)
    return run_cli(args)


def run_cli(args) -> int:
    names = list(DEFAULT_CHECKS)
    if getattr(args, "only", None):
        names = [n for n in args.only.split(",") if n]
        if "forward" in names or "render" in names:
            names = (["mesh"] if "mesh" not in names else []) + names
    if getattr(args, "with_3d", False) and "window-3d" not in names:
        names.append("window-3d")
    try:
        results = run(names, out=lambda line: print(line, flush=True))
    except ValueError as exc:
        print(f"elastoid selftest: {exc}", file=sys.stderr)
        return 2
    n_ok = sum(r.passed for r in results)
    frozen = "frozen" if getattr(sys, "frozen", False) else "from source"
    print(f"selftest: {n_ok}/{len(results)} passed ({frozen}, Python {platform.python_version()}, "
          f"{platform.system()} {platform.machine()})", flush=True)
    return 0 if n_ok == len(results) else 1


if __name__ == "__main__":
    raise SystemExit(main())
