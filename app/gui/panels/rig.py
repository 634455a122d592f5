"""Rig panel: connect (or start the simulated rig), limits, jog, find contact and zero,
the ramp-hold-unload protocol, and live force plots.

All instrument I/O runs on the rig's own thread (:class:`~app.gui.workers.RigWorker`);
samples land in the controller's ring buffer and a 25 Hz timer draws them, so a
100 Hz stream never queues up in the event loop.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import QSettings, Qt, QTimer
from PySide6.QtGui import QKeySequence, QShortcut
from PySide6.QtWidgets import (QCheckBox, QComboBox, QFileDialog, QFormLayout, QGridLayout, QGroupBox, QHBoxLayout,
                               QLabel, QLineEdit, QPushButton, QScrollArea, QSplitter, QToolButton, QVBoxLayout,
                               QWidget)

from app.core.experiment import new_folder_problem

from ..models.rig import DISP, FORCE, T, TRAVEL, Protocol, RigController, RigSettings
from ..models.session import SessionModel
from ..style import STOP_RED, style_plot
from ..workers import RigWorker
from .base import Panel
from .common import hint, spin

log = logging.getLogger("elastoid.gui")

DRAW_HZ = 25
WINDOW_S = 30.0
JOG_STEPS_MM = (0.01, 0.05, 0.1, 0.5, 1.0, 5.0)
OPERATION_TEXT = {"disconnected": "not connected", "connect": "connecting...", "idle": "ready (streaming)",
                  "jog": "jogging", "contact": "finding contact", "zero": "zeroing", "run": "running the protocol",
                  "unlock": "unlocking", "paused": "streaming paused", "disconnect": "disconnecting"}


def steady_range(current: tuple[float, float] | None, lo: float, hi: float,
                 min_span: float) -> tuple[float, float] | None:
    """A plot range for data spanning [lo, hi] that moves only when it must: None (keep
    ``current``) while the data fit inside it and fill at least a third of it; else a
    new range with 10% margins. A range that followed the data exactly would change
    with every noisy sample, and pyqtgraph lays its axis out again on every change."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return None
    span = max(hi - lo, min_span)
    if current is not None:
        c0, c1 = current
        if c0 <= lo and hi <= c1 and (c1 - c0) <= 3 * span:
            return None
    mid = 0.5 * (lo + hi)
    return mid - 0.6 * span, mid + 0.6 * span


def list_serial_ports() -> list[str]:
    try:
        from serial.tools import list_ports

        return [p.device for p in sorted(list_ports.comports(), key=lambda p: p.device)]
    except Exception:
        return []


def default_recording_folder() -> Path:
    return Path.home() / "ElastoID" / "recordings" / time.strftime("%Y-%m-%d_%H%M%S")


class RigPanel(Panel):
    title = "Rig"

    def __init__(self, controller: RigController, session: SessionModel, parent=None):
        super().__init__(parent)
        self.controller = controller
        self.session = session
        self.worker = RigWorker(controller)
        self.worker.rig_event.connect(self._on_event)
        self._gen = -1
        self._last_recording: Path | None = None
        self._build()
        self._load_settings()
        self.timer = QTimer(self)
        self.timer.setInterval(int(1000 / DRAW_HZ))
        self.timer.timeout.connect(self.redraw)
        self.worker.start()
        self.timer.start()
        self._refresh_enabled()

    # ---- layout -------------------------------------------------------------------------------
    def _build(self) -> None:
        outer = QVBoxLayout(self)
        outer.setContentsMargins(4, 4, 4, 4)
        split = QSplitter(Qt.Vertical)
        outer.addWidget(split)

        side = QWidget()
        cols = QHBoxLayout(side)
        cols.setContentsMargins(0, 0, 0, 0)
        col1, col2, col3 = QVBoxLayout(), QVBoxLayout(), QVBoxLayout()
        for c in (col1, col2, col3):
            cols.addLayout(c, 1)

        readout = QGroupBox("Now")
        r = QGridLayout(readout)
        self.force_label = _big()
        self.disp_label = _big()
        self.travel_label = _big()
        r.addWidget(QLabel("Force"), 0, 0)
        r.addWidget(self.force_label, 0, 1)
        r.addWidget(_unit("N"), 0, 2)
        r.addWidget(QLabel("Displacement"), 1, 0)
        r.addWidget(self.disp_label, 1, 1)
        r.addWidget(_unit("mm from contact"), 1, 2)
        r.addWidget(QLabel("Stage travel"), 2, 0)
        r.addWidget(self.travel_label, 2, 1)
        r.addWidget(_unit("mm"), 2, 2)
        self.op_label = QLabel("")
        self.op_label.setWordWrap(True)
        r.addWidget(self.op_label, 3, 0, 1, 3)
        col1.addWidget(readout)

        limits = QGroupBox("Safety limits")
        f = QFormLayout(limits)
        self.force_limit = spin(0.01, 1000, 10.0, decimals=2, step=0.5, suffix="N",
                                tip="The stage stops (and backs off) before the force reaches this")
        self.travel_limit = spin(0.1, 200, 20.0, decimals=2, step=0.5, suffix="mm",
                                 tip="Deepest displacement from contact the stage may reach")
        f.addRow("Force limit", self.force_limit)
        f.addRow("Travel limit", self.travel_limit)
        self.force_limit.valueChanged.connect(self._limits_edited)
        self.travel_limit.valueChanged.connect(self._limits_edited)
        col2_limits = limits  # goes under the connection



        conn = QGroupBox("Connection")
        c = QGridLayout(conn)
        self.stage_port = QComboBox()
        self.stage_port.setEditable(True)
        self.force_port = QComboBox()
        self.force_port.setEditable(True)
        for box, tip in ((self.stage_port, "GRBL motion controller, e.g. /dev/ttyUSB0, COM3 or socket://host:port"),
                         (self.force_port, "Force sensor (ELC-1 protocol), e.g. /dev/ttyACM0 or COM4")):
            box.setToolTip(tip)
            box.setMinimumContentsLength(14)
        self.refresh_ports = QToolButton()
        self.refresh_ports.setText("Scan")
        self.refresh_ports.setToolTip("List the serial ports of this computer")
        self.refresh_ports.clicked.connect(self._scan_ports)
        c.addWidget(QLabel("Stage port"), 0, 0)
        c.addWidget(self.stage_port, 0, 1)
        c.addWidget(self.refresh_ports, 0, 2)
        c.addWidget(QLabel("Force port"), 1, 0)
        c.addWidget(self.force_port, 1, 1, 1, 2)
        self.image_folder = QLineEdit()
        self.image_folder.setPlaceholderText("scanner export folder (optional)")
        self.image_folder.setToolTip("The folder the ultrasound scanner exports frames into (DICOM, PNG, TIFF): "
                                     "the protocol takes the newest complete frame at each capture displacement")
        ibrowse = QToolButton()
        ibrowse.setText("...")
        ibrowse.clicked.connect(self._browse_images)
        c.addWidget(QLabel("Frames from"), 2, 0)
        c.addWidget(self.image_folder, 2, 1)
        c.addWidget(ibrowse, 2, 2)
        b = QHBoxLayout()
        self.connect_button = QPushButton("Connect")
        self.sim_button = QPushButton("Start simulated rig")
        self.sim_button.setObjectName("primary")
        self.sim_button.setToolTip("A simulated stage and force sensor on virtual serial ports: everything works "
                                   "as with the hardware")
        self.disconnect_button = QPushButton("Disconnect")
        for w in (self.sim_button, self.connect_button, self.disconnect_button):
            b.addWidget(w)
        c.addLayout(b, 3, 0, 1, 3)
        self.use_twin = QCheckBox("Simulated rig presses on the open experiment's specimen")
        self.use_twin.setToolTip("Force and ultrasound frames from a finite-element twin of the specimen (built once, "
                                 "about half a minute); otherwise a generic soft specimen and speckle frames")
        self.use_twin.setChecked(True)
        c.addWidget(self.use_twin, 4, 0, 1, 3)
        self.conn_state = hint("Not connected.")
        self.conn_state.setTextInteractionFlags(Qt.TextSelectableByMouse)
        c.addWidget(self.conn_state, 5, 0, 1, 3)
        self.connect_button.clicked.connect(self.connect_ports)
        self.sim_button.clicked.connect(self.start_simulated)
        self.disconnect_button.clicked.connect(self.controller.disconnect)
        col2.addWidget(conn)
        col2.addWidget(col2_limits)
        col2.addStretch(1)


        jog = QGroupBox("Jog and contact")
        j = QGridLayout(jog)
        self.step_box = QComboBox()
        for s in JOG_STEPS_MM:
            self.step_box.addItem(f"{s:g} mm", s)
        self.step_box.setCurrentIndex(3)
        self.jog_speed = spin(0.01, 20, 2.0, decimals=2, step=0.5, suffix="mm/s")
        j.addWidget(QLabel("Step"), 0, 0)
        j.addWidget(self.step_box, 0, 1)
        j.addWidget(QLabel("Speed"), 0, 2)
        j.addWidget(self.jog_speed, 0, 3)
        self.up_button = QPushButton("\u25b2 Up (away)")
        self.up_button.setToolTip("Retract the probe by one step  [Ctrl+Up]")
        self.down_button = QPushButton("\u25bc Down (press)")
        self.down_button.setToolTip("Press the probe in by one step  [Ctrl+Down]")
        j.addWidget(self.up_button, 1, 0, 1, 2)
        j.addWidget(self.down_button, 1, 2, 1, 2)
        self.contact_button = QPushButton("Find contact")
        self.contact_button.setToolTip("Tare the sensor, approach slowly until the force crosses the threshold, "
                                       "and set displacement 0 there  [Ctrl+K]")
        self.zero_button = QPushButton("Zero here")
        self.zero_button.setToolTip("Declare the present position the contact point (displacement 0)")
        self.unlock_button = QPushButton("Unlock")
        self.unlock_button.setToolTip("Leave the stage's alarm state after checking the machine ($X)")
        j.addWidget(self.contact_button, 2, 0, 1, 2)
        j.addWidget(self.zero_button, 2, 2)
        j.addWidget(self.unlock_button, 2, 3)
        self.threshold = spin(0.001, 10, 0.05, decimals=3, step=0.01, suffix="N")
        self.approach = spin(0.01, 5, 0.5, decimals=2, step=0.1, suffix="mm/s")
        j.addWidget(QLabel("Contact at"), 3, 0)
        j.addWidget(self.threshold, 3, 1)
        j.addWidget(QLabel("Approach"), 3, 2)
        j.addWidget(self.approach, 3, 3)
        self.up_button.clicked.connect(lambda: self.jog(-1))
        self.down_button.clicked.connect(lambda: self.jog(+1))
        self.contact_button.clicked.connect(self.find_contact)
        self.zero_button.clicked.connect(self.controller.zero_here)
        self.unlock_button.clicked.connect(self.controller.unlock)
        for key, fn in (("Ctrl+Up", lambda: self.jog(-1)), ("Ctrl+Down", lambda: self.jog(+1)),
                        ("Ctrl+K", self.find_contact)):
            sc = QShortcut(QKeySequence(key), self)
            sc.setContext(Qt.WidgetWithChildrenShortcut)
            sc.activated.connect(fn)
        col1.addWidget(jog)  # under the readouts: jogging is done while watching them
        col1.addStretch(1)


        proto = QGroupBox("Ramp - hold - unload")
        p = QFormLayout(proto)
        self.depth_spin = spin(0.01, 100, 5.0, decimals=2, step=0.5, suffix="mm")
        self.speed = spin(0.01, 20, 0.5, decimals=2, step=0.1, suffix="mm/s")
        self.hold = spin(0, 3600, 10.0, decimals=1, step=1.0, suffix="s")
        self.unload = QCheckBox("Unload to contact, then back off")
        self.unload.setChecked(True)
        self.frames_at = QLineEdit("0, 1, 2, 3, 4, 5")
        self.frames_at.setToolTip("Displacements (mm from contact) at which an ultrasound frame is captured")
        self.out_folder = QLineEdit(str(default_recording_folder()))
        browse = QToolButton()
        browse.setText("...")
        browse.clicked.connect(self._browse_folder)
        orow = QHBoxLayout()
        orow.addWidget(self.out_folder, 1)
        orow.addWidget(browse)
        p.addRow("Depth", self.depth_spin)
        p.addRow("Speed", self.speed)
        p.addRow("Hold", self.hold)
        p.addRow("", self.unload)
        p.addRow("Frames at (mm)", self.frames_at)
        p.addRow("Record into", orow)
        rb = QHBoxLayout()
        self.run_button = QPushButton("Run protocol")
        self.run_button.setObjectName("primary")
        self.stop_button = QPushButton("Stop")
        self.stop_button.setToolTip("End the running operation normally: halt, then back off when safe.\n"
                                    "For an immediate halt use the red STOP (Esc).")
        self.open_button = QPushButton("Open the recording")
        self.open_button.setEnabled(False)
        rb.addWidget(self.run_button)
        rb.addWidget(self.stop_button)
        rb.addWidget(self.open_button)
        p.addRow(rb)
        self.run_state = hint("")
        p.addRow(self.run_state)
        self.run_button.clicked.connect(self.run_protocol)
        self.stop_button.clicked.connect(self.controller.stop)
        self.open_button.clicked.connect(self._open_recording)
        col3.addWidget(proto)
        col3.addStretch(1)

        plots = pg.GraphicsLayoutWidget()
        self.pt = plots.addPlot(row=0, col=0, title=f"Force vs time (last {WINDOW_S:g} s)")
        self.pt.setLabel("bottom", "time", units="s")
        self.pt.setLabel("left", "force", units="N")
        self.pd = plots.addPlot(row=0, col=1, title="Force vs displacement")
        self.pd.setLabel("bottom", "displacement from contact", units="mm")
        self._pd_label = "displacement from contact"
        self.pd.setLabel("left", "force", units="N")
        for plot in (self.pt, self.pd):
            style_plot(plot)
            plot.setClipToView(True)
        # the ranges follow the data by steps (steady_range); the time axis scrolls
        self.pt.enableAutoRange(x=True, y=False)
        self.pd.enableAutoRange(x=False, y=False)
        self._ranges = {}
        # 1 px pens: a live curve is redrawn 25 times a second
        self.curve_t = self.pt.plot([], [], pen=pg.mkPen("#1f5fa8", width=1), skipFiniteCheck=True)
        self.curve_d = self.pd.plot([], [], pen=pg.mkPen("#d55e00", width=1), skipFiniteCheck=True)
        self.limit_lines = []
        for plot in (self.pt, self.pd):
            line = pg.InfiniteLine(self.force_limit.value(), angle=0,
                                   pen=pg.mkPen(STOP_RED, width=1, style=Qt.DashLine),
                                   label="force limit", labelOpts={"position": 0.1, "color": STOP_RED})
            plot.addItem(line, ignoreBounds=True)  # visible when the force comes near it
            self.limit_lines.append(line)
        plots.setMinimumHeight(220)
        split.addWidget(plots)
        scroll = QScrollArea()
        scroll.setWidget(side)
        scroll.setWidgetResizable(True)
        scroll.setHorizontalScrollBarPolicy(Qt.ScrollBarAlwaysOff)
        scroll.setFrameShape(QScrollArea.NoFrame)
        split.addWidget(scroll)
        split.setStretchFactor(0, 4)
        split.setStretchFactor(1, 5)
        split.setSizes([330, 420])

    # ---- settings ------------------------------------------------------------------------------------
    def _load_settings(self) -> None:
        st = QSettings()
        self._scan_ports()
        self.stage_port.setCurrentText(st.value("rig/stage_port", "", str))
        self.force_port.setCurrentText(st.value("rig/force_port", "", str))
        self.image_folder.setText(st.value("rig/image_folder", "", str))
        self.force_limit.setValue(float(st.value("rig/force_limit_N", 10.0)))
        self.travel_limit.setValue(float(st.value("rig/travel_limit_mm", 20.0)))
        self.depth_spin.setValue(float(st.value("rig/depth_mm", 5.0)))
        self.speed.setValue(float(st.value("rig/speed_mm_s", 0.5)))
        self.hold.setValue(float(st.value("rig/hold_s", 10.0)))

    def _save_settings(self) -> None:
        st = QSettings()
        if not self.controller.status.simulated:
            st.setValue("rig/stage_port", self.stage_port.currentText())
            st.setValue("rig/force_port", self.force_port.currentText())
            st.setValue("rig/image_folder", self.image_folder.text())
        st.setValue("rig/force_limit_N", self.force_limit.value())
        st.setValue("rig/travel_limit_mm", self.travel_limit.value())
        st.setValue("rig/depth_mm", self.depth_spin.value())
        st.setValue("rig/speed_mm_s", self.speed.value())
        st.setValue("rig/hold_s", self.hold.value())

    def _scan_ports(self) -> None:
        ports = list_serial_ports()
        for box in (self.stage_port, self.force_port):
            cur = box.currentText()
            box.clear()
            box.addItems(ports)
            box.setCurrentText(cur)

    def settings(self) -> RigSettings:
        return replace(self.controller.settings, stage_port=self.stage_port.currentText().strip(),
                       force_port=self.force_port.currentText().strip(), force_limit_N=self.force_limit.value(),
                       image_folder=self.image_folder.text().strip(),
                       travel_limit_mm=self.travel_limit.value(), approach_speed_mm_s=self.approach.value(),
                       contact_threshold_N=self.threshold.value(), jog_speed_mm_s=self.jog_speed.value())

    # ---- actions (all go through the controller) ----------------------------------------------------
    def connect_ports(self) -> None:
        self._save_settings()
        self.controller.connect_ports(self.settings())

    def start_simulated(self) -> None:
        exp = self.session.experiment if self.use_twin.isChecked() else None
        self.controller.start_simulated(self.settings(), exp.path if exp is not None else None)
        self.conn_state.setText("Starting the simulated rig" + (f" pressing on {exp.name}" if exp is not None else "")
                                + "...")
        self.status.emit("starting the simulated rig")

    def jog(self, direction: int) -> None:
        if not self.controller.status.connected:
            return
        step = float(self.step_box.currentData())
        self.controller.jog(direction * step, self.jog_speed.value())

    def find_contact(self) -> None:
        if not self.controller.status.connected:
            return
        self.controller.settings = self.settings()
        self.controller.find_contact()

    def _limits_edited(self) -> None:
        self.controller.set_limits(self.force_limit.value(), self.travel_limit.value())
        for line in self.limit_lines:
            line.setValue(self.force_limit.value())

    def _browse_images(self) -> None:
        d = QFileDialog.getExistingDirectory(self, "Folder the scanner exports frames into", self.image_folder.text())
        if d:
            self.image_folder.setText(d)

    def _browse_folder(self) -> None:
        d = QFileDialog.getExistingDirectory(self, "Folder to record into (a new, empty folder)",
                                             str(Path(self.out_folder.text()).parent))
        if d:
            self.out_folder.setText(d)

    def protocol(self) -> Protocol:
        text = self.frames_at.text().replace(";", ",")
        frames = tuple(float(x) for x in text.replace(",", " ").split() if x)
        return Protocol(depth_mm=self.depth_spin.value(), speed_mm_s=self.speed.value(), hold_s=self.hold.value(),
                        unload=self.unload.isChecked(), frames_at_mm=frames or (0.0,))

    def run_protocol(self) -> None:
        try:
            proto = self.protocol()
        except ValueError:
            self.error.emit(ValueError(f"'Frames at' must be displacements in mm separated by commas, got "
                                       f"{self.frames_at.text()!r}"), "")
            return
        folder = Path(self.out_folder.text()).expanduser()
        problem = new_folder_problem(folder)
        if problem:
            self.error.emit(ValueError(f"{folder} {problem}"), "")
            return
        self._save_settings()
        template = self.session.experiment
        self.controller.run_protocol(proto, folder, template)
        self.run_state.setText(f"Recording into {folder}")
        log.info("protocol: %.2f mm at %.2f mm/s, hold %.1f s, frames at %s mm, into %s", proto.depth_mm,
                 proto.speed_mm_s, proto.hold_s, list(proto.frames_at_mm), folder)

    def emergency_stop(self) -> None:
        self.controller.emergency_stop()
        log.warning("EMERGENCY STOP pressed")
        self.status.emit("EMERGENCY STOP: feed hold sent to the stage")

    def _open_recording(self) -> None:
        if self._last_recording is None:
            return
        try:
            self.session.open_experiment(self._last_recording)
        except Exception as exc:
            self.error.emit(exc, "")

    # ---- events from the rig thread ---------------------------------------------------------------------
    def _on_event(self, kind: str, payload) -> None:
        if kind == "progress":
            text = str(payload)
            self.conn_state.setText(text[:1].upper() + text[1:] + "...")
            self.status.emit(text)
            log.info("rig: %s", text)
            return
        if kind == "started":
            self.status.emit(f"rig: {OPERATION_TEXT.get(payload, payload)}")
            if payload in ("contact", "run", "connect"):
                self.busy.emit(f"Rig: {OPERATION_TEXT.get(payload, payload)}", 0, 0)
        elif kind == "finished":
            name, result = payload
            self.busy.emit("", 0, 0)
            if name == "run":
                self._run_finished(result)
            else:
                text = str(result)
                log.info("rig: %s", text)
                self.status.emit(text)
                if name == "connect":
                    st = self.controller.settings
                    if self.controller.status.simulated:
                        self.stage_port.setCurrentText(st.stage_port)
                        self.force_port.setCurrentText(st.force_port)
                    self.conn_state.setText(text[:1].upper() + text[1:])
                    self._save_settings()
                elif name == "disconnect":
                    self.conn_state.setText("Not connected.")
        elif kind == "failed":
            name, exc = payload
            self.busy.emit("", 0, 0)
            from app.core.errors import Cancelled
            from app.devices.errors import EmergencyStop

            if isinstance(exc, (Cancelled, EmergencyStop)):
                log.warning("%s", exc)
                self.status.emit(str(exc))
                self._refresh_enabled()
                return
            log.error("rig (%s): %s", name, exc)
            if name != "monitor" or not isinstance(exc, Exception):
                self.error.emit(exc, "")
            else:
                self.error.emit(exc, "The live force stream stopped; it resumes with the next rig operation.")
        self._refresh_enabled()

    def _run_finished(self, result) -> None:
        self._last_recording = Path(result.folder) if result.folder else None
        self.open_button.setEnabled(self._last_recording is not None and result.frames > 0)
        msg = result.message.strip().rstrip(".")
        text = (f"{msg[:1].upper() + msg[1:]}: {result.samples} samples, {result.frames} frames, max force "
                f"{result.max_force_N:.3f} N, recorded in {result.folder}")
        self.run_state.setText(text)
        (log.info if result.ok else log.warning)("rig run: %s", text)
        self.status.emit(f"protocol {result.outcome}: {result.message}")
        if not result.ok:
            self.error.emit(RuntimeError(text) if result.error is None else result.error, text)
        self.out_folder.setText(str(default_recording_folder()))

    # ---- drawing (timer) --------------------------------------------------------------------------------
    def redraw(self) -> None:
        st = self.controller.status
        self.force_label.setText(_fmt(st.force_N, 3))
        self.disp_label.setText(_fmt(st.displacement_mm, 3))
        self.travel_label.setText(_fmt(st.travel_mm, 3))
        op = OPERATION_TEXT.get(st.operation, st.operation)
        state = f" - {st.state}" if st.state and st.operation not in ("idle", "disconnected") else ""
        contact = f"; contact at travel {st.contact_mm:.3f} mm" if st.contact_mm is not None else "; contact not set"
        sim = " (simulated)" if st.simulated else ""
        msg = f"<br><span style='color:{STOP_RED}'>{st.message}</span>" if st.message else ""
        limits = f"<br>limits {self.force_limit.value():g} N, {self.travel_limit.value():g} mm from contact"
        self.op_label.setText(f"<b>{op}{state}</b>{sim}{contact if st.connected else ''}"
                              f"{limits if st.connected else ''}{msg}")
        key = (st.connected, st.operation)
        if key != getattr(self, "_enabled_key", None):
            self._enabled_key = key
            self._refresh_enabled()
        buf = self.controller.buffer
        gen = buf.generation
        if gen == self._gen:
            return
        self._gen = gen
        data = buf.snapshot(int(WINDOW_S * self.controller.settings.rate_hz))
        if len(data) == 0:
            self.curve_t.setData([], [])
            self.curve_d.setData([], [])
            return
        self.curve_t.setData(data[:, T], data[:, FORCE])
        disp = data[:, DISP]
        ok = np.isfinite(disp)
        # a label set again re-lays the axis out: only when it changes, not 25 times a second
        contact = bool(ok.any())
        label = "displacement from contact" if contact else "stage travel (contact not set)"
        if label != self._pd_label:
            self._pd_label = label
            self.pd.setLabel("bottom", label, units="mm")
        xd, fd = (disp[ok], data[ok, FORCE]) if contact else (data[:, TRAVEL], data[:, FORCE])
        self.curve_d.setData(xd, fd)
        f = data[:, FORCE]
        self._follow(self.pt, "y", float(np.nanmin(f)), float(np.nanmax(f)), 0.05)
        self._follow(self.pd, "y", float(np.nanmin(fd)), float(np.nanmax(fd)), 0.05)
        self._follow(self.pd, "x", float(np.nanmin(xd)), float(np.nanmax(xd)), 0.1)

    def _follow(self, plot, axis: str, lo: float, hi: float, min_span: float) -> None:
        """Move ``plot``'s ``axis`` range by steps with the data, unless the user zoomed or
        panned it; its "A" (auto-range) button hands it back."""
        vb = plot.getViewBox()
        k = 0 if axis == "x" else 1
        key = (id(plot), axis)
        ours = self._ranges.get(key)
        if vb.state["autoRange"][k]:  # the "A" button: follow the data again
            vb.enableAutoRange(axis=vb.XAxis if k == 0 else vb.YAxis, enable=False)
            ours = None
        elif ours is not None:
            shown = vb.viewRange()[k]
            tol = 1e-6 * (ours[1] - ours[0])
            if abs(shown[0] - ours[0]) > tol or abs(shown[1] - ours[1]) > tol:
                return  # the user's zoom or pan: leave it
        new = steady_range(ours, lo, hi, min_span)
        if new is not None:
            self._ranges[key] = new
            (plot.setYRange if axis == "y" else plot.setXRange)(*new, padding=0)

    def _refresh_enabled(self) -> None:
        st = self.controller.status
        connected = st.connected
        busy = st.operation not in ("idle", "disconnected", "paused")
        for w in (self.up_button, self.down_button, self.contact_button, self.zero_button, self.unlock_button):
            w.setEnabled(connected)
        self.run_button.setEnabled(connected)
        self.disconnect_button.setEnabled(connected)
        self.stop_button.setEnabled(connected)
        self.connect_button.setEnabled(not busy or not connected)

    def shutdown(self) -> None:
        self.timer.stop()
        self._save_settings()
        self.worker.shutdown()


def _big() -> QLabel:
    lab = QLabel("--")
    lab.setObjectName("big")
    lab.setAlignment(Qt.AlignRight | Qt.AlignVCenter)
    lab.setMinimumWidth(110)
    return lab


def _unit(text: str) -> QLabel:
    lab = QLabel(text)
    lab.setObjectName("unit")
    return lab


def _fmt(v, digits: int) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "--"
    return f"{v:.{digits}f}"
