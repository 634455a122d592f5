"""The main window: composes the panels as docks, the menus, the toolbar with the
STOP button, and the status bar. It holds no business logic: actions call the
models' and panels' own methods."""

from __future__ import annotations

import logging
from pathlib import Path

from PySide6.QtCore import QByteArray, QSettings, QSize, Qt, QTimer
from PySide6.QtGui import QAction, QKeySequence
from PySide6.QtWidgets import (QDockWidget, QFileDialog, QLabel, QMainWindow, QMessageBox, QSizePolicy,
                               QTabWidget, QToolBar, QToolButton, QWidget)

from app import __version__

from .errors import show_error
from .models.rig import RigController
from .models.session import SessionModel
from .panels.common import BusyBar
from .panels.identification import IdentificationPanel
from .panels.images import ImagesPanel
from .panels.log import LogPanel
from .panels.mesh import MeshPanel
from .panels.modelcheck import ModelCheckPanel
from .panels.rig import RigPanel
from .panels.welcome import WelcomePage
from .workers import Task

log = logging.getLogger("elastoid.gui")

MAX_RECENT = 8
LAYOUT_VERSION = 2  # 2: the Model check dock


def demo_path() -> Path:
    from app.resources import resource_path  # the source tree's resources/ or the frozen bundle's

    return resource_path("demo")


class MainWindow(QMainWindow):
    def __init__(self, *, session: SessionModel | None = None, rig: RigController | None = None,
                 identify_backend=None, enable_3d: bool | None = None, restore_layout: bool = True):
        super().__init__()
        self.setObjectName("ElastoIDMainWindow")
        self.setWindowTitle("ElastoID")
        self.session = session or SessionModel()
        self.rig = rig or RigController()
        self.error_boxes: list = []
        self._busy: dict[str, tuple[str, int, int]] = {}
        self._closing = False
        self.guide_window = None  # Help > User guide, made on first use

        self.log_panel = LogPanel()
        self.images_panel = ImagesPanel(self.session)
        self.mesh_panel = MeshPanel(self.session, enable_3d=enable_3d)
        self.identification_panel = IdentificationPanel(self.session, backend=identify_backend)
        self.modelcheck_panel = ModelCheckPanel(self.session)
        self.rig_panel = RigPanel(self.rig, self.session)
        self.panels = {"images": self.images_panel, "mesh": self.mesh_panel,
                       "identification": self.identification_panel, "modelcheck": self.modelcheck_panel,
                       "rig": self.rig_panel, "log": self.log_panel}
        titles = {"images": "Images", "mesh": "Specimen and mesh", "identification": "Identification",
                  "modelcheck": "Model check", "rig": "Rig", "log": "Log"}

        self.docks: dict[str, QDockWidget] = {}
        for key, panel in self.panels.items():
            dock = QDockWidget(titles[key], self)
            dock.setObjectName(f"dock_{key}")
            dock.setWidget(panel)
            dock.setFeatures(QDockWidget.DockWidgetMovable | QDockWidget.DockWidgetFloatable
                             | QDockWidget.DockWidgetClosable)
            self.docks[key] = dock
            if hasattr(panel, "status"):
                panel.status.connect(self._status)
            if key != "log":
                panel.busy.connect(lambda what, done, total, key=key: self._set_busy(key, what, done, total))
                panel.error.connect(self._error)
        self.setDockNestingEnabled(True)
        self.setTabPosition(Qt.AllDockWidgetAreas, QTabWidget.North)
        self._default_layout()

        self.welcome = WelcomePage(demo_path().joinpath("experiment.toml").is_file())
        self.welcome.open_demo.connect(self.open_demo)
        self.welcome.run_demo.connect(self.run_demo)
        self.welcome.start_rig.connect(self.start_simulated_rig)
        self.welcome.open_folder.connect(self.open_experiment_dialog)
        self.welcome.open_recent.connect(self._open_recent)
        self.setCentralWidget(self.welcome)

        self._build_actions()
        self._build_menus()
        self._build_toolbar()
        self._build_statusbar()
        self.session.experiment_changed.connect(self._on_experiment)
        self.resize(1480, 940)
        self._welcome_shown = False
        self._hidden_docks: list[str] = []
        if restore_layout:
            self._restore_layout()
        self._restore_preferences()
        self.show_welcome(True)
        log.info("ElastoID %s ready", __version__)

    # ---- layout -------------------------------------------------------------------------------
    def _default_layout(self) -> None:
        main = ("images", "mesh", "identification", "modelcheck", "rig")
        for key in main:
            self.addDockWidget(Qt.LeftDockWidgetArea, self.docks[key])
            self.docks[key].show()
        for key in main[1:]:
            self.tabifyDockWidget(self.docks["images"], self.docks[key])
        self.addDockWidget(Qt.BottomDockWidgetArea, self.docks["log"])
        self.docks["log"].show()
        self.resizeDocks([self.docks["log"]], [120], Qt.Vertical)
        self.docks["images"].raise_()

    def reset_layout(self) -> None:
        for d in self.docks.values():
            d.setFloating(False)
        self._default_layout()

    def _restore_layout(self) -> None:
        st = QSettings()
        geo = st.value("window/geometry")
        if isinstance(geo, QByteArray):
            self.restoreGeometry(geo)
        state = st.value("window/state")
        if isinstance(state, QByteArray) and int(st.value("window/layout_version", 0)) == LAYOUT_VERSION:
            self.restoreState(state, LAYOUT_VERSION)

    def _restore_preferences(self) -> None:
        """The last mesh settings and identification choices, as defaults for the next experiment."""
        import json
        from dataclasses import replace

        from app.core.mesh import MeshSettings

        from .models.session import IdentificationSettings

        st = QSettings()
        try:
            mesh = st.value("defaults/mesh_settings", "", str)
            if mesh and mesh != "auto":
                self.session.set_mesh_settings(MeshSettings(**json.loads(mesh)))
            ident = st.value("defaults/identification", "", str)
            if ident:
                d = IdentificationSettings.from_json(json.loads(ident))
                self.session.set_identification(replace(d, parameters=()))
        except (TypeError, ValueError):  # preferences from another version: keep the defaults
            pass

    def save_preferences(self) -> None:
        import json
        from dataclasses import asdict, replace

        st = QSettings()
        ms = self.session.mesh_settings
        st.setValue("defaults/mesh_settings", "auto" if ms is None else json.dumps(asdict(ms)))
        st.setValue("defaults/identification", json.dumps(replace(self.session.identification, parameters=()).to_json()))

    def save_layout(self) -> None:
        if self._welcome_shown:
            self._restore_docks()
        st = QSettings()
        st.setValue("window/geometry", self.saveGeometry())
        st.setValue("window/state", self.saveState(LAYOUT_VERSION))
        st.setValue("window/layout_version", LAYOUT_VERSION)

    def show_welcome(self, on: bool) -> None:
        """The welcome page fills the window; the panels come back as they were when it goes."""
        if on == self._welcome_shown:
            return
        self._welcome_shown = on
        if on:
            self.welcome.set_recent(self.recent_items())
            self._hidden_docks = [k for k, d in self.docks.items() if d.isVisible() or not d.isHidden()]
            for d in self.docks.values():
                d.hide()
            self.welcome.show()
        else:
            self.welcome.hide()
            self._restore_docks()

    def _restore_docks(self) -> None:
        keys = self._hidden_docks or list(self.docks)
        for k in keys:
            self.docks[k].show()
        self._hidden_docks = []

    def raise_panel(self, key: str) -> None:
        self.show_welcome(False)
        dock = self.docks[key]
        dock.show()
        dock.raise_()

    # ---- actions and menus --------------------------------------------------------------------------
    def _action(self, text: str, slot, shortcut=None, tip: str = "") -> QAction:
        a = QAction(text, self)
        if shortcut:
            a.setShortcut(QKeySequence(shortcut))
        if tip:
            a.setStatusTip(tip)
            a.setToolTip(tip)
        a.triggered.connect(slot)
        return a

    def _build_actions(self) -> None:
        self.act_open = self._action("&Open experiment folder...", self.open_experiment_dialog, QKeySequence.Open,
                                     "Open an experiment folder (experiment.toml, force.csv, images/)")
        self.act_demo = self._action("Open the &demo experiment", self.open_demo)
        self.act_demo.setEnabled(demo_path().joinpath("experiment.toml").is_file())
        self.act_run_demo = self._action("R&un the demo (open and identify)", self.run_demo, None,
                                         "Open the demo experiment and identify its moduli in one go")
        self.act_run_demo.setEnabled(self.act_demo.isEnabled())
        self.act_open_session = self._action("Open &session...", self.open_session_dialog, "Ctrl+Shift+O")
        self.act_save = self._action("&Save session", self.save_session, QKeySequence.Save,
                                     "Save the ROI, mesh settings and results as a session file")
        self.act_save_as = self._action("Save session &as...", self.save_session_as, "Ctrl+Shift+S")
        self.act_export_report = self._action("Export &report (HTML)...", lambda: self.export("report"), "Ctrl+E",
                                              "The parameters with their uncertainties, the force, the overlays")
        self.act_export_vtu = self._action("Export calibrated model (&VTU)...", lambda: self.export("vtu"), None,
                                           "The mesh with region labels and moduli, for simulators")
        self.act_export_feb = self._action("Export &FEBio input (.feb)...", lambda: self.export("feb"), None,
                                           "The calibrated model as an FEBio 4 input file")
        self.act_quit = self._action("&Quit", self.close, QKeySequence.Quit)
        self.act_stop = self._action("STOP", self.emergency_stop, None,
                                     "Emergency stop: halt the stage at once (Esc)")
        self.act_stop.setShortcuts([QKeySequence(Qt.Key_Escape), QKeySequence("Ctrl+Space")])
        self.act_stop.setShortcutContext(Qt.ApplicationShortcut)
        self.addAction(self.act_stop)
        self.act_sim = self._action("Start the &simulated rig", self.start_simulated_rig)
        self.act_connect = self._action("&Connect to the rig ports", self.rig_panel.connect_ports)
        self.act_disconnect = self._action("&Disconnect", self.rig.disconnect)
        self.act_contact = self._action("Find &contact", self.rig_panel.find_contact)
        self.act_reset_layout = self._action("&Reset layout", self.reset_layout)
        self.act_welcome = self._action("&Welcome page", lambda: self.show_welcome(True))
        self.act_guide = self._action("&User guide", lambda: self.show_guide(), QKeySequence.HelpContents,
                                      "The user guide and the other guides, in a window of their own (F1)")
        self.act_about = self._action("&About ElastoID", self.about)

    def _build_menus(self) -> None:
        mb = self.menuBar()
        f = mb.addMenu("&File")
        for a in (self.act_open, self.act_demo, self.act_run_demo):
            f.addAction(a)
        self.recent_menu = f.addMenu("Open &recent")
        self.recent_menu.aboutToShow.connect(self._fill_recent)
        f.addSeparator()
        for a in (self.act_open_session, self.act_save, self.act_save_as):
            f.addAction(a)
        f.addSeparator()
        for a in (self.act_export_report, self.act_export_vtu, self.act_export_feb):
            f.addAction(a)
        f.addSeparator()
        f.addAction(self.act_quit)
        r = mb.addMenu("&Rig")
        for a in (self.act_sim, self.act_connect, self.act_disconnect, self.act_contact):
            r.addAction(a)
        r.addSeparator()
        r.addAction(self.act_stop)
        v = mb.addMenu("&View")
        for d in self.docks.values():
            v.addAction(d.toggleViewAction())
        v.addSeparator()
        v.addAction(self.act_reset_layout)
        v.addAction(self.act_welcome)
        h = mb.addMenu("&Help")
        h.addAction(self.act_guide)
        h.addSeparator()
        h.addAction(self.act_about)

    def _build_toolbar(self) -> None:
        tb = QToolBar("Main")
        tb.setObjectName("toolbar_main")
        tb.setMovable(False)
        tb.setIconSize(QSize(18, 18))
        tb.setToolButtonStyle(Qt.ToolButtonTextOnly)
        tb.addAction(self.act_open)
        tb.addAction(self.act_open_session)
        tb.addAction(self.act_save)
        tb.addSeparator()
        for key, text in (("images", "Images"), ("mesh", "Mesh"), ("identification", "Identify"),
                          ("modelcheck", "Model check"), ("rig", "Rig")):
            tb.addAction(self._action(text, lambda _=False, key=key: self.raise_panel(key)))
        spacer = QWidget()
        spacer.setSizePolicy(QSizePolicy.Expanding, QSizePolicy.Preferred)
        tb.addWidget(spacer)
        self.rig_state = QLabel("Rig: not connected")
        self.rig_state.setObjectName("hint")
        tb.addWidget(self.rig_state)
        self.stop_button = QToolButton()
        self.stop_button.setObjectName("estop")
        self.stop_button.setDefaultAction(self.act_stop)
        self.stop_button.setText("\u25a0  STOP")
        self.stop_button.setToolTip("Emergency stop: halt the stage at once, from any state (Esc)")
        self.stop_button.setMinimumSize(QSize(130, 40))
        self.stop_button.setFocusPolicy(Qt.NoFocus)
        tb.addWidget(self.stop_button)
        self.addToolBar(Qt.TopToolBarArea, tb)
        self.toolbar = tb

    def _build_statusbar(self) -> None:
        sb = self.statusBar()
        self.progress = BusyBar()
        self.progress.setMaximumWidth(260)
        self.progress.setTextVisible(False)
        self.progress.hide()
        self.busy_label = QLabel("")
        sb.addPermanentWidget(self.busy_label)
        sb.addPermanentWidget(self.progress)
        self._rig_timer = QTimer(self)
        self._rig_timer.setInterval(250)
        self._rig_timer.timeout.connect(self._show_rig_state)
        self._rig_timer.start()

    # ---- status, busy, errors ---------------------------------------------------------------------
    def _status(self, text: str) -> None:
        self.statusBar().showMessage(text[:1].upper() + text[1:], 8000)

    def _set_busy(self, key: str, what: str, done: int, total: int) -> None:
        if what:
            self._busy[key] = (what, done, total)
        else:
            self._busy.pop(key, None)
        if not self._busy:
            self.progress.hide()
            self.busy_label.setText("")
            return
        what, done, total = list(self._busy.values())[-1]
        self.busy_label.setText(what)
        self.progress.setRange(0, total)
        self.progress.setValue(done)
        self.progress.show()

    def _error(self, exc, details: str = "") -> None:
        if self._closing:
            return
        self.error_boxes = [b for b in self.error_boxes if b.isVisible()][-4:]
        self.error_boxes.append(show_error(self, exc, details))

    def _show_rig_state(self) -> None:
        st = self.rig.status
        if not st.connected:
            self.rig_state.setText("Rig: not connected  ")
        else:
            f = f"{st.force_N:.3f} N" if st.force_N == st.force_N else "-- N"
            d = f", {st.displacement_mm:.3f} mm" if st.displacement_mm is not None else ""
            self.rig_state.setText(f"Rig{' (simulated)' if st.simulated else ''}: {st.operation}, {f}{d}  ")

    # ---- file actions ----------------------------------------------------------------------------------
    def open_experiment(self, folder) -> bool:
        try:
            exp = self.session.open_experiment(folder)
        except Exception as exc:
            self._error(exc)
            return False
        self._add_recent("experiment", Path(folder))
        log.info("opened experiment %s: %s (%d frames, %d force samples)", folder, exp.name, len(exp.frames),
                 len(exp.force_log))
        return True

    def open_experiment_dialog(self) -> None:
        start = QSettings().value("paths/last_experiment_dir", str(Path.home()), str)
        folder = QFileDialog.getExistingDirectory(self, "Open an experiment folder", start)
        if folder:
            QSettings().setValue("paths/last_experiment_dir", str(Path(folder).parent))
            self.open_experiment(folder)

    def open_demo(self) -> None:
        self.open_experiment(demo_path())

    def run_demo(self) -> None:
        """One click to a result: open the demo and run the identification with the current
        settings (by default the paper's: six starts, NMI and force)."""
        if self.identification_panel.running:
            self.raise_panel("identification")
            return
        if not self.open_experiment(demo_path()):
            return
        self.raise_panel("identification")
        self.identification_panel.run()

    def open_session(self, path) -> bool:
        try:
            checked = self.session.load_session(path)
        except Exception as exc:
            self._error(exc)
            return False
        self._add_recent("session", Path(path))
        self._update_title()
        log.info("opened session %s", path)
        if checked:
            self.modelcheck_panel.restore(checked)
        return True

    def open_session_dialog(self) -> None:
        start = QSettings().value("paths/last_session_dir", str(Path.home()), str)
        path, _ = QFileDialog.getOpenFileName(self, "Open a session", start, "ElastoID sessions (*.json)")
        if path:
            QSettings().setValue("paths/last_session_dir", str(Path(path).parent))
            self.open_session(path)

    def save_session(self) -> bool:
        if self.session.session_path is None:
            return self.save_session_as()
        return self._save_to(self.session.session_path)

    _EXPORTS = {"report": ("Export the report", "report.html", "HTML (*.html)"),
                "vtu": ("Export the calibrated model", "model.vtu", "VTK unstructured grid (*.vtu)"),
                "feb": ("Export an FEBio input", "model.feb", "FEBio input (*.feb)")}

    def export(self, kind: str, path: Path | None = None) -> Path | None:
        """Write the report or the calibrated model; asks for a file unless ``path`` is given."""
        from app.core import export as ex

        from .models.modelcheck import report_data

        s = self.session
        checked = report_data(self.modelcheck_panel.model.snapshot) if kind == "report" else None
        if (s.outcome is None or s.mesh is None) and checked is None:
            self._status("run an identification first: the exports hold its result"
                         + (" (or, for the report, a model check)" if kind == "report" else ""))
            return None
        if path is None:
            title, name, filt = self._EXPORTS[kind]
            start = QSettings().value("paths/last_export_dir", str(Path.home()), str)
            chosen, _ = QFileDialog.getSaveFileName(self, title, str(Path(start) / name), filt)
            if not chosen:
                return None
            path = Path(chosen)
            QSettings().setValue("paths/last_export_dir", str(path.parent))
        nu = s.identification.nu
        try:
            if kind == "report":
                overlays = []
                if s.overlay is not None:
                    warped, target = s.overlay[0], s.overlay[1]
                    overlays.append((f"frame {s.target_frame}", warped, target))
                o = s.outcome
                ex.write_report_html(path, experiment=s.experiment, parameters=o.parameters if o else None,
                                     cost=o.cost if o else None, standard_error_rel=o.standard_error_rel if o else None,
                                     identifiability_lines=o.identifiability if o else (),
                                     model_force_N=s.model_force_N if o else self.modelcheck_panel.model_force_N(),
                                     overlays=overlays,
                                     mesh_lines=s.mesh_quality, nu=nu, model_check=checked,
                                     mesh_check_lines=o.mesh_check if o else ())
            elif kind == "vtu":
                ex.write_vtu(path, s.mesh, s.outcome.parameters, nu)
            else:
                d = max(f.displacement_mm for f in s.experiment.frames)
                ex.write_feb(path, s.mesh, s.outcome.parameters, nu, probe_travel_mm=d)
        except Exception as exc:
            self._error(exc)
            return None
        self._status(f"wrote {path}")
        return path

    def save_session_as(self) -> bool:
        if not self.session.has_experiment:
            self._status("open an experiment first: a session refers to one")
            return False
        start = QSettings().value("paths/last_session_dir", str(Path.home()), str)
        name = f"{Path(self.session.experiment.path).name}-session.json"
        path, _ = QFileDialog.getSaveFileName(self, "Save the session", str(Path(start) / name),
                                              "ElastoID sessions (*.json)")
        if not path:
            return False
        if not path.endswith(".json"):
            path += ".json"
        QSettings().setValue("paths/last_session_dir", str(Path(path).parent))
        return self._save_to(Path(path))

    def _save_to(self, path: Path) -> bool:
        try:
            self.session.save_session(path, self.modelcheck_panel.model.state(self.session))
        except Exception as exc:
            self._error(exc)
            return False
        self._add_recent("session", path)
        self._update_title()
        self._status(f"session saved to {path}")
        log.info("session saved to %s", path)
        return True

    def _add_recent(self, kind: str, path: Path) -> None:
        st = QSettings()
        entry = f"{kind}:{Path(path).resolve()}"
        items = [x for x in (st.value("recent/items", [], list) or []) if x != entry]
        st.setValue("recent/items", [entry] + items[: MAX_RECENT - 1])

    def recent_items(self) -> list[tuple[str, Path]]:
        out = []
        for x in QSettings().value("recent/items", [], list) or []:
            kind, _, p = str(x).partition(":")
            out.append((kind, Path(p)))
        return out

    def _open_recent(self, kind: str, path: str) -> None:
        (self.open_session if kind == "session" else self.open_experiment)(Path(path))

    def _fill_recent(self) -> None:
        m = self.recent_menu
        m.clear()
        items = self.recent_items()
        if not items:
            a = m.addAction("(nothing yet)")
            a.setEnabled(False)
            return
        for kind, p in items:
            label = f"{p.name}  -  {p.parent}" + ("  (session)" if kind == "session" else "")
            a = m.addAction(label)
            a.setEnabled(p.exists())
            if kind == "session":
                a.triggered.connect(lambda _=False, p=p: self.open_session(p))
            else:
                a.triggered.connect(lambda _=False, p=p: self.open_experiment(p))
        m.addSeparator()
        m.addAction("Clear the list", lambda: QSettings().setValue("recent/items", []))

    def _on_experiment(self) -> None:
        self._update_title()
        if self.session.has_experiment:
            self.raise_panel("images")

    def _update_title(self) -> None:
        exp = self.session.experiment
        parts = ["ElastoID"]
        if exp is not None:
            parts.append(exp.name)
        if self.session.session_path is not None:
            parts.append(self.session.session_path.name)
        self.setWindowTitle(" - ".join(parts))

    # ---- rig -----------------------------------------------------------------------------------------------
    def start_simulated_rig(self) -> None:
        self.raise_panel("rig")
        self.rig_panel.start_simulated()

    def emergency_stop(self) -> None:
        self.rig_panel.emergency_stop()

    def show_guide(self, name: str = "user-guide.md", anchor: str = ""):
        """The guides' window (one per main window), showing ``name`` at ``anchor``."""
        from .guide import GuideWindow

        if self.guide_window is None:
            self.guide_window = GuideWindow(self)
        w = self.guide_window
        w.show_guide(name, anchor)
        w.show()
        w.raise_()
        w.activateWindow()
        return w

    def about(self) -> None:
        QMessageBox.about(self, "About ElastoID",
                          f"<b>ElastoID {__version__}</b><br>Identifies the Young's modulus of each tissue region "
                          f"of a specimen from a robotic ultrasound indentation: a finite-element model predicts "
                          f"the deformation, the pre-deformation frame is warped by it and compared with the "
                          f"measured frame by normalized mutual information, and Nelder-Mead finds the moduli.")

    # ---- closing -------------------------------------------------------------------------------------------
    def closeEvent(self, event) -> None:
        self._closing = True
        try:
            self.save_layout()
            self.save_preferences()
        except Exception:
            log.exception("saving the settings")
        for panel in self.panels.values():
            try:
                panel.shutdown()
            except Exception:
                log.exception("shutting down %s", type(panel).__name__)
        Task.shutdown_all(timeout_s=15.0)
        super().closeEvent(event)
