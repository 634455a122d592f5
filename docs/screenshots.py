"""The screenshots of docs/user-guide.md and README.md, taken from the current code.

    xvfb-run -a /work/venv/bin/python docs/screenshots.py        # writes docs/images/*.png

It drives the real window (1280 x 800) the way a user does:

- the welcome page;
- "Run the demo" on the welcome page: the demo experiment (resources/demo) opened
  and identified with one click; then the Identification panel, the Images panel
  (ROI, warped overlay), the Specimen and mesh panel with its 3-D view;
- the simulated rig recording a short ramp-hold-unload;
- the Model check on a small synthetic experiment with a hidden viscoelastic
  effect (made here by the simulator): identify the baseline, compare, diagnose,
  add the verdict, check the added version's mesh;
- the log of all of it.

Options replace the demo and the model-check experiment with given folders and
shorten the runs (the GUI test passes small ones, to stay quick); the images keep
their names and sizes. The 3-D view needs an OpenGL-capable X display (Xvfb with
Mesa is fine), so run it under xvfb-run on a headless machine.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

SIZE = (1280, 800)
# every image this script writes, and what it shows
IMAGES = {
    "welcome.png": "the welcome page",
    "identification.png": "the demo identified with one click (Run the demo)",
    "images.png": "the demo's frames: ROI and the source warped by the identified model over the target",
    "mesh.png": "the specimen, its regions and the mesh deformed at the target frame (3-D view)",
    "rig.png": "the simulated rig after a ramp-hold-unload",
    "modelcheck-compare.png": "model check: the baseline model against the measurements",
    "modelcheck-diagnosis.png": "model check: the ranked candidate effects and the verdict",
    "modelcheck-history.png": "model check: the versions and the error falling",
    "log.png": "the log of the session",
}


def model_check_spec():
    """A small phantom (40 x 40 x 30 mm, a stiff inclusion) with a hidden viscoelastic
    effect, a 6 s hold and an unloading: what the model check screenshots show."""
    from app.core.geometry import Region
    from app.core.mesh import MeshSettings
    from app.core.simulate import SyntheticSpec

    return SyntheticSpec(
        name="Small phantom with a hidden viscoelastic effect (synthetic)", size_mm=(40.0, 40.0, 30.0),
        regions=(Region("B", "background"), Region("A", "sphere", center_mm=(20.0, 20.0, 18.0), radius_mm=7.0)),
        moduli_kPa={"B": 15.0, "A": 45.0}, face_mm=(24.0, 8.0), depth_mm=5.0, frames_at_mm=(0.0, 2.5, 5.0),
        image_shape=(128, 120), hold_s=6.0, unload=True, rate_Hz=50.0, effects=("viscoelastic",), g1=0.35,
        tau1_s=2.0, seed=4, truth_mesh=MeshSettings(edge_mm=4.2, probe_edge_mm=1.75, region_edge_mm=1.75))


MODEL_CHECK_MESH = (6.0, 2.5, 2.5)  # element sizes (far, under the probe, regions) for the model check


class Driver:
    """The application, the window and small helpers to wait and to shoot."""

    def __init__(self, out: Path, settings_dir: Path):
        from PySide6.QtCore import QSettings
        from PySide6.QtWidgets import QApplication

        self.out = out
        QSettings.setDefaultFormat(QSettings.IniFormat)
        QSettings.setPath(QSettings.IniFormat, QSettings.UserScope, str(settings_dir))  # never the user's
        self.app = QApplication.instance() or QApplication([sys.argv[0]])
        self.app.setOrganizationName("ElastoID-screenshots")
        self.app.setApplicationName("ElastoID-screenshots")
        from app.gui.style import apply_style

        apply_style(self.app)
        from app.gui.mainwindow import MainWindow

        self.t0 = time.monotonic()
        self.win = MainWindow(restore_layout=False)
        self.win.resize(*SIZE)
        self.win.show()
        self.settle(500)
        self.written: list[Path] = []

    def settle(self, ms: int = 300) -> None:
        from PySide6.QtCore import QEventLoop

        t_end = time.monotonic() + ms / 1000
        while time.monotonic() < t_end:
            self.app.processEvents(QEventLoop.AllEvents, 20)
            time.sleep(0.005)

    def wait(self, cond, timeout_s: float, what: str) -> None:
        t0 = time.monotonic()
        while not cond():
            self.settle(50)
            if self.win.error_boxes:
                texts = [b.informativeText() for b in self.win.error_boxes]
                raise RuntimeError(f"{what}: the window reported an error: {texts}")
            if time.monotonic() - t0 > timeout_s:
                raise RuntimeError(f"timed out after {timeout_s:.0f} s: {what}")

    def shoot(self, name: str) -> Path:
        """The whole window as it is on screen, with the 3-D view painted in (PNG, 256 colours)."""
        from PySide6.QtCore import QPoint, QRect
        from PySide6.QtGui import QImage, QPainter

        assert name in IMAGES, name
        self.settle(400)
        win = self.win
        if (win.width(), win.height()) != SIZE:
            raise RuntimeError(f"the window is {win.width()} x {win.height()}, not {SIZE[0]} x {SIZE[1]}: "
                               f"a panel's minimum size grew")
        img = win.grab().toImage().convertToFormat(QImage.Format_RGB888)
        mp = win.mesh_panel
        if mp.plotter is not None and mp.view_widget.isVisible():
            import numpy as np

            shot = np.ascontiguousarray(mp.plotter.screenshot(None, return_img=True)[..., :3])
            h, w = shot.shape[:2]
            q = QImage(shot.data, w, h, 3 * w, QImage.Format_RGB888).copy()
            p = QPainter(img)
            p.drawImage(QRect(mp.view_widget.mapTo(win, QPoint(0, 0)), mp.view_widget.size()), q)
            p.end()
        path = self.out / name
        save_png(img, path)
        self.written.append(path)
        print(f"{time.monotonic() - self.t0:6.1f} s  wrote {path} ({path.stat().st_size // 1024} KB): {IMAGES[name]}",
              flush=True)
        return path


def save_png(qimage, path: Path) -> None:
    """An RGB QImage as an optimized 256-colour PNG: the 64 most frequent colours (backgrounds,
    text, lines) exactly, the rest from a palette that covers the image; each pixel its nearest."""
    import numpy as np
    from PIL import Image

    h, w, bpl = qimage.height(), qimage.width(), qimage.bytesPerLine()
    rgb = np.frombuffer(qimage.constBits(), np.uint8, count=bpl * h).reshape(h, bpl)[:, : 3 * w].reshape(h, w, 3)
    rgb = np.ascontiguousarray(rgb)
    flat = rgb.reshape(-1, 3).astype(np.int64)
    codes = (flat[:, 0] << 16) | (flat[:, 1] << 8) | flat[:, 2]
    uniq, inv, counts = np.unique(codes, return_inverse=True, return_counts=True)
    colours = np.stack([(uniq >> 16) & 255, (uniq >> 8) & 255, uniq & 255], 1)
    if len(uniq) <= 256:
        pal = colours
    else:
        exact = 64
        top = colours[np.argsort(-counts)[:exact]]
        cover = Image.fromarray(rgb, "RGB").quantize(256 - exact, method=Image.Quantize.MAXCOVERAGE,
                                                     dither=Image.Dither.NONE)
        pal = np.vstack([top, np.array(cover.getpalette()[: 3 * (256 - exact)]).reshape(-1, 3)])
    nearest = np.empty(len(colours), np.int64)
    for s in range(0, len(colours), 8192):
        d = ((colours[s:s + 8192, None, :] - pal[None].astype(np.int64)) ** 2).sum(-1)
        nearest[s:s + 8192] = d.argmin(1)
    out = Image.fromarray(nearest[inv].reshape(h, w).astype(np.uint8), "P")
    out.putpalette(pal.astype(np.uint8).ravel().tolist())
    path.parent.mkdir(parents=True, exist_ok=True)
    out.save(path, optimize=True)


def run(args) -> list[Path]:
    """Shoot every image of IMAGES into ``args.out``; the recording, the simulated
    experiment and the settings it makes on the way are removed afterwards."""
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix="elastoid-screenshots-"))
    try:
        return _shoot_all(args, out, tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _shoot_all(args, out: Path, tmp: Path) -> list[Path]:
    from app.core.mesh import MeshSettings
    from app.gui.mainwindow import demo_path

    d = Driver(out, tmp / "settings")
    win = d.win
    s = win.session

    # 1. the welcome page
    d.shoot("welcome.png")

    # 2. the demo, identified with one click (or a given experiment, identified with shorter settings)
    ident = win.identification_panel
    if args.experiment is None:
        win.welcome.run_demo_button.click()
    else:
        win.open_experiment(args.experiment)
        if args.mesh:
            e, p = args.mesh
            s.set_mesh_settings(replace(s.effective_mesh_settings(), edge_mm=e, probe_edge_mm=p))
        s.set_identification(replace(s.identification, starts_kPa=tuple(args.starts),
                                     max_evaluations=args.max_evaluations))
        win.raise_panel("identification")
        ident.run()
    d.wait(lambda: ident.task is not None or s.outcome is not None, 30, "the identification to start")
    d.wait(lambda: ident.task is None, 900, "the identification")
    if s.outcome is None:
        raise RuntimeError(f"the identification gave no result: {ident.state.text()}")
    print("identified:", ", ".join(f"{k} = {v:.2f}" for k, v in s.outcome.parameters.items()), flush=True)
    win.raise_panel("identification")
    d.shoot("identification.png")

    win.raise_panel("images")
    win.images_panel.set_mode("overlay")
    d.shoot("images.png")

    win.raise_panel("mesh")
    d.settle(300)
    win.mesh_panel._redraw()
    d.shoot("mesh.png")

    # 3. the simulated rig: contact, then a short ramp-hold-unload
    from app.devices.sim import ptys_available

    if not ptys_available():
        raise RuntimeError("the simulated rig needs pseudo-terminals (ptys), which this system does not offer")
    rig = win.rig_panel
    win.raise_panel("rig")
    rig.use_twin.setChecked(False)  # a generic specimen: a twin of the experiment would mesh for a while
    rig.start_simulated()
    d.wait(lambda: rig.up_button.isEnabled() and "GRBL" in rig.conn_state.text(), 60, "the simulated rig")
    events = []
    rig.worker.rig_event.connect(lambda k, p: events.append((k, p)))
    rig.find_contact()
    d.wait(lambda: any(k != "started" and p[0] == "contact" for k, p in events), 60, "contact")
    rig.depth_spin.setValue(2.0)
    rig.speed.setValue(1.0)
    rig.hold.setValue(2.0)
    rig.unload.setChecked(True)
    rig.frames_at.setText("0, 1, 2")
    rig.out_folder.setText(str(tmp / "recording"))
    rig.run_protocol()
    d.wait(lambda: any(k != "started" and p[0] == "run" for k, p in events), 120, "the protocol")
    d.shoot("rig.png")
    win.rig.disconnect()

    # 4. the model check on an experiment with a hidden viscoelastic effect
    visco = args.visco
    if visco is None:
        from app.core.simulate import simulate_experiment

        print("simulating the model-check experiment...", flush=True)
        visco = simulate_experiment(tmp / "visco", model_check_spec())
    win.open_experiment(visco)
    sizes = dict(zip(("edge_mm", "probe_edge_mm", "region_edge_mm"), args.visco_mesh))
    s.set_mesh_settings(replace(s.effective_mesh_settings(), **sizes))
    win.raise_panel("modelcheck")
    mc = win.modelcheck_panel
    mc.identify_button.click()
    d.wait(lambda: mc.task is None, 900, "the model check's identification")
    if mc.model.n_versions != 1:
        raise RuntimeError(f"the model check identified nothing: {mc.state.text()}")
    mc.frame_box.setCurrentIndex(mc.frame_box.count() - 1)
    mc.tabs.setCurrentIndex(0)
    d.shoot("modelcheck-compare.png")
    for eff, cb in mc.candidate_boxes.items():
        cb.setChecked(eff in args.candidates)
    mc.diagnose_button.click()
    d.wait(lambda: mc.task is None, 1800, "the diagnosis")
    verdict = mc.model.snapshot.diagnosis.verdict
    print("verdict:", verdict, flush=True)
    if verdict == "none":
        raise RuntimeError("the diagnosis found no effect; the screenshots would not show one being added")
    mc.tabs.setCurrentIndex(1)
    d.shoot("modelcheck-diagnosis.png")
    mc.add_verdict_button.click()
    d.wait(lambda: mc.task is None, 300, "adding the verdict")
    mc.mesh_check_button.click()  # the added version identified again on a finer mesh, kept with it
    d.wait(lambda: mc.task is None, 900, "the mesh check")
    if not mc.model.history.current_version.mesh_check:
        raise RuntimeError(f"the mesh check kept nothing: {mc.state.text()}")
    mc.compare_versions()  # the error falling from the baseline, then the mesh check's figures
    mc.tabs.setCurrentIndex(2)
    d.shoot("modelcheck-history.png")

    # 5. the log, made taller
    from PySide6.QtCore import Qt

    win.resizeDocks([win.docks["log"]], [330], Qt.Vertical)
    win.docks["log"].raise_()
    d.shoot("log.png")

    win.close()
    d.settle(200)
    missing = sorted(set(IMAGES) - {p.name for p in d.written})
    if missing:
        raise RuntimeError(f"not written: {missing}")
    return d.written


def _floats(text: str) -> tuple[float, ...]:
    return tuple(float(x) for x in text.replace(",", " ").split())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(ROOT / "docs" / "images"), help="folder for the PNG files")
    ap.add_argument("--experiment", type=Path, help="an experiment folder instead of the demo (no one-click run)")
    ap.add_argument("--mesh", type=_floats, help="EDGE,PROBE element sizes in mm for --experiment")
    ap.add_argument("--starts", type=_floats, default=(10.0, 30.0, 60.0), help="starts in kPa for --experiment")
    ap.add_argument("--max-evaluations", type=int, default=60, help="evaluations per start for --experiment")
    ap.add_argument("--visco", type=Path, help="the model-check experiment (default: simulated here)")
    ap.add_argument("--visco-mesh", type=_floats, default=MODEL_CHECK_MESH,
                    help="EDGE,PROBE[,REGION] element sizes in mm for the model check (REGION: automatic)")
    ap.add_argument("--candidates", type=lambda t: tuple(x for x in t.split(",") if x),
                    default=("viscoelastic", "sliding-bottom", "probe-slip", "compressibility"),
                    help="candidate effects the diagnosis tries")
    args = ap.parse_args(argv)
    t0 = time.monotonic()
    written = run(args)
    print(f"{len(written)} screenshots in {time.monotonic() - t0:.0f} s", flush=True)
    from app.gui.workers import wait_for_all

    wait_for_all(30)
    return 0


if __name__ == "__main__":  # the mesher runs in a spawned process: it must not re-run this
    os.environ.setdefault("PYTHONDONTWRITEBYTECODE", "1")
    sys.exit(main())
