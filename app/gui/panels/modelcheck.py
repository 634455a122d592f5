"""Model check panel: compare the identified model with the measurements, diagnose
which physical effect it misses, add it, and watch the error fall across versions.

Everything runs through :class:`app.core.diagnose.ModelCheck` (via the Qt-free
:class:`~app.gui.models.modelcheck.ModelCheckModel`) on a
:class:`~app.gui.workers.Task`: identify, diagnose, add and revert never block
the window, report their progress lines here and in the log, and stop at Cancel.

- Compare: the force over the whole log (loading, hold, unloading), measured and
  modelled; per frame, the residual map over the ROI, the tracked displacement
  against the model's (vector map) and each region's share of the misfit.
- Diagnosis: the ranked candidates (score, key parameters, evidence), the noise
  model, the verdict; add the verdict or another candidate.
- History: the versions, the error across them, a comparison of two, revert.
"""

from __future__ import annotations

import html
import logging
import math
import time

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import Qt
from PySide6.QtGui import QBrush, QColor
from PySide6.QtWidgets import (QAbstractItemView, QCheckBox, QComboBox, QGridLayout, QGroupBox, QHBoxLayout,
                               QHeaderView, QLabel, QPlainTextEdit, QPushButton, QSplitter,
                               QTableWidget, QTableWidgetItem, QTabWidget, QVBoxLayout, QWidget)

from app.core.diagnose import MATERIAL_CHI2_PER_COMPONENT, MATERIAL_FRACTION, NEAR_TIE, UNRESOLVED_SHIFT
from app.core.effects import EFFECT_IDS, INFO
from app.core.effects.compressibility import NU_NEGLIGIBLE
from app.core.effects.inclusion import NEGLIGIBLE_RATIO as INCLUSION_RATIO
from app.core.export import verdict_html

from ..models.modelcheck import (ModelCheckModel, arrow_segments, auto_difference_scale, compare_text,
                                 diagnosis_rows, frame_label, frame_outlines, history_rows, label_place,
                                 mesh_check_text, outline_shapes, outlines_note, parameters_text, verdict_parts)
from ..models.session import SessionModel
from ..style import FORCE_KEY, force_pens, mono_font, region_color, style_plot
from ..workers import Task
from .base import Panel
from .common import BusyBar, hint, ispin, normalized, scrolled

log = logging.getLogger("elastoid.gui")

LOCK_REASON = "a model check is running"
MEASURED, MODEL, DIFFERENCE = "#0072b2", "#d55e00", "#c2185b"
SUSPECT = "#9e9e9e"  # a difference at a block that disagrees with its neighbours
OUTLINE = "#39e639"  # the regions' outlines: a green that neither the arrows nor the residual map use
OUTLINE_TEXT = "#1f8f1f"  # the same green, dark enough to read on the window's light background
# the outlines' pen by kind: dashes and dots (in pen widths) long enough to tell apart over speckle
OUTLINE_STYLES = {"region": (Qt.SolidLine, None), "located": (Qt.DashLine, [4.0, 3.0]),
                  "also fits": (Qt.DotLine, [1.0, 2.5])}
VERDICT_BG = "#fff3c4"
ACTIONS = {"identify": "Identifying", "diagnose": "Diagnosing", "add": "Adding", "revert": "Reverting",
           "refine": "Refining the inclusion's place", "restore": "Restoring the saved model check",
           "mesh-check": "Checking the mesh"}


def _item(text: str, *, bold: bool = False, tip: str = "", align=None) -> QTableWidgetItem:
    it = QTableWidgetItem(text)
    if bold:
        f = it.font()
        f.setBold(True)
        it.setFont(f)
    if tip:
        it.setToolTip(tip)
    if align is not None:
        it.setTextAlignment(align)
    return it


def _table(cols: list[str]) -> QTableWidget:
    t = QTableWidget(0, len(cols))
    t.setHorizontalHeaderLabels(cols)
    t.verticalHeader().setVisible(False)
    t.setEditTriggers(QAbstractItemView.NoEditTriggers)
    t.setSelectionBehavior(QAbstractItemView.SelectRows)
    t.setSelectionMode(QAbstractItemView.SingleSelection)
    t.setWordWrap(True)
    return t


def _image_plot(graphics: pg.GraphicsLayoutWidget, title: str) -> pg.PlotItem:
    p = graphics.addPlot(title=title)
    p.getViewBox().setAspectLocked(True)
    p.getViewBox().invertY(True)
    p.setLabel("bottom", "column", units="px")
    p.setLabel("left", "row", units="px")
    for name in ("left", "bottom"):
        p.getAxis(name).enableAutoSIPrefix(False)
    return p


class ModelCheckPanel(Panel):
    title = "Model check"

    def __init__(self, session: SessionModel, parent=None, *, model: ModelCheckModel | None = None):
        super().__init__(parent)
        self.session = session
        self.model = model or ModelCheckModel()
        self.task: Task | None = None
        self._action = ""
        self._gen = 0
        self._owns_lock = False
        self._pending_restore: dict | None = None  # a session's model check, waiting for a task to end
        self._t_start = 0.0
        self._updating = False
        self._build()
        session.experiment_changed.connect(self._on_experiment)
        for sig in (session.specimen_changed, session.roi_changed, session.mesh_settings_changed,
                    session.identification_changed):
            sig.connect(self._on_inputs)
        session.lock_changed.connect(lambda *_: self._refresh_enabled())
        self._on_experiment()

    # ---- layout ------------------------------------------------------------------------------
    def _build(self) -> None:
        outer = QHBoxLayout(self)
        outer.setContentsMargins(4, 4, 4, 4)
        split = QSplitter(Qt.Horizontal)
        outer.addWidget(split)
        split.addWidget(scrolled(self._build_side()))
        self.tabs = QTabWidget()
        self.tabs.addTab(self._build_compare(), "Compare")
        self.tabs.addTab(self._build_diagnosis(), "Diagnosis")
        self.tabs.addTab(self._build_history(), "History")
        split.addWidget(self.tabs)
        split.setStretchFactor(1, 1)

    def _effect_boxes(self, grid: QGridLayout, prefix: str, checked: bool) -> dict[str, QCheckBox]:
        boxes = {}
        for k, e in enumerate(EFFECT_IDS):
            cb = QCheckBox(e)
            cb.setObjectName(f"{prefix}_{e}")
            cb.setChecked(checked)
            tip = f"{INFO[e].title}; relaxes the assumption: {INFO[e].assumption}"
            if (e, prefix) == ("inclusion", "identify"):
                tip += ("; to identify with it, the current version's inclusion is kept, else one is located "
                        "from the misfit of the model without it")
            cb.setToolTip(tip)
            grid.addWidget(cb, k // 2, k % 2)
            boxes[e] = cb
        return boxes

    def _build_side(self) -> QWidget:
        side = QWidget()
        sl = QVBoxLayout(side)
        sl.setContentsMargins(0, 0, 0, 0)

        mbox = QGroupBox("Model")
        ml = QVBoxLayout(mbox)
        self.version_label = QLabel("No model yet.")
        self.version_label.setWordWrap(True)
        ml.addWidget(self.version_label)
        ml.addWidget(hint("Effects to identify with (none: the paper's baseline model):"))
        g = QGridLayout()
        self.identify_boxes = self._effect_boxes(g, "identify", False)
        ml.addLayout(g)
        b = QHBoxLayout()
        self.identify_button = QPushButton("Identify")
        self.identify_button.setObjectName("primary")
        self.identify_button.setToolTip("Fit the model with the ticked effects to the images and the force log; "
                                        "it becomes a new version")
        self.cancel_button = QPushButton("Cancel")
        self.cancel_button.setEnabled(False)
        b.addWidget(self.identify_button)
        b.addWidget(self.cancel_button)
        b.addStretch(1)
        ml.addLayout(b)
        self.identify_button.clicked.connect(self.identify)
        self.cancel_button.clicked.connect(self.cancel)
        sl.addWidget(mbox)

        dbox = QGroupBox("Diagnose")
        dl = QVBoxLayout(dbox)
        dl.addWidget(hint("Candidate effects to try on top of the current model:"))
        g2 = QGridLayout()
        self.candidate_boxes = self._effect_boxes(g2, "candidate", True)
        for cb in self.candidate_boxes.values():
            cb.toggled.connect(lambda *_: self._refresh_enabled())
        dl.addLayout(g2)
        self.diagnose_button = QPushButton("Diagnose")
        self.diagnose_button.setObjectName("primary")
        self.diagnose_button.setToolTip("Refit the current model with each candidate effect and rank them by an "
                                        "information criterion (BIC) under the stated noise model")
        self.diagnose_button.clicked.connect(self.diagnose)
        dl.addWidget(self.diagnose_button)
        sl.addWidget(dbox)

        self.progress = BusyBar()
        self.progress.setRange(0, 1)
        self.progress.setValue(0)
        self.progress.setTextVisible(True)
        self.progress.setFormat("idle")
        sl.addWidget(self.progress)
        self.state = hint("")
        sl.addWidget(self.state)
        self.note = hint("Open an experiment, then identify the baseline model here.")
        sl.addWidget(self.note)
        sl.addStretch(1)
        side.setMinimumWidth(270)
        side.setMaximumWidth(300)
        return side

    def _build_compare(self) -> QWidget:
        w = QWidget()
        lay = QVBoxLayout(w)
        lay.setContentsMargins(2, 2, 2, 2)
        self.compare_summary = hint("The comparison of the current model with the measurements appears here.")
        lay.addWidget(self.compare_summary)
        vsplit = QSplitter(Qt.Vertical)
        self.force_graphics = pg.GraphicsLayoutWidget()
        self.force_graphics.setMinimumHeight(150)
        self.force_time = self.force_graphics.addPlot(row=0, col=0, title=f"Force over the log: {FORCE_KEY}")
        self.force_time.setLabel("bottom", "time", units="s")
        self.force_time.setLabel("left", "force", units="N")
        self.force_travel = self.force_graphics.addPlot(row=0, col=1, title=f"Force vs probe travel: {FORCE_KEY}")
        self.force_travel.setLabel("bottom", "probe travel", units="mm")
        self.force_travel.setLabel("left", "force", units="N")
        self.force_curves = {}
        for key, plot in (("time", self.force_time), ("travel", self.force_travel)):
            style_plot(plot)
            measured, model = force_pens()
            self.force_curves[key] = (plot.plot([], [], pen=measured, name="measured"),
                                      plot.plot([], [], pen=model, name="model"))
        vsplit.addWidget(self.force_graphics)

        frame_w = QWidget()
        fl = QVBoxLayout(frame_w)
        fl.setContentsMargins(0, 0, 0, 0)
        row = QHBoxLayout()
        row.addWidget(QLabel("Frame"))
        self.frame_box = QComboBox()
        self.frame_box.setSizeAdjustPolicy(QComboBox.AdjustToContents)
        self.frame_box.currentIndexChanged.connect(self._draw_frame)
        row.addWidget(self.frame_box)
        row.addSpacing(10)
        self.show_boxes = {}
        for key, text, color in (("measured", "tracked", MEASURED), ("model", "model", MODEL),
                                 ("difference", "difference", DIFFERENCE), ("outlines", "outlines", OUTLINE_TEXT)):
            cb = QCheckBox(text)
            cb.setChecked(True)
            cb.setStyleSheet(f"QCheckBox {{ color: {color}; font-weight: 600; }}")
            cb.toggled.connect(self._draw_frame)
            self.show_boxes[key] = cb
            row.addWidget(cb)
        self.show_boxes["outlines"].setToolTip(
            "The regions' outlines on both maps, where the model puts them in each frame; and the inclusion the "
            "last diagnosis located (dashed), with where it would fit nearly as well (dotted)")
        self.diff_scale = ispin(0, 1000, 0, suffix="x", tip="Difference arrows drawn this many times longer "
                                "(0: automatic)")
        self.diff_scale.setSpecialValueText("auto")
        self.diff_scale.valueChanged.connect(self._draw_frame)
        row.addWidget(QLabel("difference scale"))
        row.addWidget(self.diff_scale)
        row.addStretch(1)
        fl.addLayout(row)
        maps = QSplitter(Qt.Horizontal)
        self.residual_graphics = pg.GraphicsLayoutWidget()
        self.residual_plot = _image_plot(self.residual_graphics, "Residual map: 1 - local correlation")
        self.residual_background = pg.ImageItem()
        self.residual_image = pg.ImageItem()
        self.residual_image.setOpacity(0.85)
        self.residual_plot.addItem(self.residual_background)
        self.residual_plot.addItem(self.residual_image)
        self.residual_bar = pg.ColorBarItem(values=(0.0, 1.0), colorMap=pg.colormap.get("inferno"), width=12,
                                            interactive=False, colorMapMenu=False)
        self.residual_bar.setImageItem(self.residual_image, insert_in=self.residual_plot)
        self.residual_graphics.setMinimumWidth(200)
        maps.addWidget(self.residual_graphics)
        # the regions' outlines on each map (PlotDataItems made per frame), and a cache of them
        self.outline_items = {"target": [], "source": []}
        self._outline_cache: dict = {}
        self._snapshot = None  # what _show showed last (the outlines depend on its diagnosis)

        self.vector_graphics = pg.GraphicsLayoutWidget()
        self.vector_plot = _image_plot(self.vector_graphics, "Displacement: tracked, model, difference")
        # the coloured check boxes above are the legend
        self.vector_background = pg.ImageItem()
        self.vector_plot.addItem(self.vector_background)
        self.roi_outline = self.vector_plot.plot([], [], pen=pg.mkPen("#ffd400", width=1, style=Qt.DashLine))
        self.vector_curves = {}
        # the model under the tracked arrows (they mostly coincide), the difference on top
        for key, color, width, name in (("model", MODEL, 2.4, "model"), ("measured", MEASURED, 1.3, "tracked"),
                                        ("difference", DIFFERENCE, 1.8, "difference x scale")):
            c = pg.PlotDataItem([], [], connect="pairs", pen=pg.mkPen(color, width=width), name=name)
            self.vector_plot.addItem(c)
            self.vector_curves[key] = c
        # the difference at a block that disagrees with its neighbours (a suspected wrong
        # speckle match, or a sharp real misfit): drawn, but grey
        self.outlier_curve = pg.PlotDataItem([], [], connect="pairs", pen=pg.mkPen(SUSPECT, width=1.8),
                                             name="difference, suspected tracking outlier")
        self.vector_plot.addItem(self.outlier_curve)
        self.vector_graphics.setMinimumWidth(200)
        maps.addWidget(self.vector_graphics)

        share = QWidget()
        sl = QVBoxLayout(share)
        sl.setContentsMargins(0, 0, 0, 0)
        self.share_graphics = pg.GraphicsLayoutWidget()
        self.share_plot = self.share_graphics.addPlot(title="Misfit by region")
        self.share_plot.setLabel("left", "share", units="%")
        self.share_plot.getAxis("left").enableAutoSIPrefix(False)
        self.share_plot.setMouseEnabled(False, False)
        self.share_plot.showGrid(x=False, y=True, alpha=0.22)
        self.share_bars = pg.BarGraphItem(x=[], height=[], width=0.38)
        self.share_bars_all = pg.BarGraphItem(x=[], height=[], width=0.38)
        self.share_plot.addItem(self.share_bars_all)
        self.share_plot.addItem(self.share_bars)
        sl.addWidget(self.share_graphics, 1)
        self.share_table = _table(["Region", "Frame", "All", "Map"])
        self.share_table.setSelectionMode(QAbstractItemView.NoSelection)
        self.share_table.horizontalHeader().setSectionResizeMode(QHeaderView.ResizeToContents)
        self.share_table.setMaximumHeight(110)
        self.share_table.setToolTip("Each region's share of the squared displacement misfit (tracked minus model): "
                                    "Frame, this frame; All, all frames; Map, its share of the residual map")
        sl.addWidget(self.share_table)
        share.setMinimumWidth(170)
        share.setMaximumWidth(230)
        maps.addWidget(share)
        maps.setStretchFactor(0, 2)
        maps.setStretchFactor(1, 2)
        maps.setStretchFactor(2, 1)
        fl.addWidget(maps, 1)
        self.frame_note = hint("")
        fl.addWidget(self.frame_note)
        vsplit.addWidget(frame_w)
        vsplit.setStretchFactor(0, 2)
        vsplit.setStretchFactor(1, 5)
        lay.addWidget(vsplit, 1)
        return w

    def _build_diagnosis(self) -> QWidget:
        w = QWidget()
        lay = QVBoxLayout(w)
        lay.setContentsMargins(4, 4, 4, 4)
        self.verdict_label = QLabel("No diagnosis yet: identify a model, then press Diagnose.")
        self.verdict_label.setWordWrap(True)
        self.verdict_label.setTextFormat(Qt.RichText)
        self.verdict_label.setStyleSheet(f"QLabel {{ background: {VERDICT_BG}; border: 1px solid #e0c76a; "
                                         f"border-radius: 4px; padding: 6px; font-size: 11pt; }}")
        lay.addWidget(self.verdict_label)
        self.diagnosis_current = hint("")
        lay.addWidget(self.diagnosis_current)
        self.noise_label = hint("")
        lay.addWidget(self.noise_label)
        self.diagnosis_table = _table(["#", "Effect", "Score (BIC)", "Key parameters", "Evidence"])
        hh = self.diagnosis_table.horizontalHeader()
        for c in range(3):
            hh.setSectionResizeMode(c, QHeaderView.ResizeToContents)
        # the parameters wrap within about 40 characters, and each evidence shows its
        # first clause: at 1280 x 800 one candidate's whole evidence had filled the view
        hh.setSectionResizeMode(3, QHeaderView.Interactive)
        hh.setSectionResizeMode(4, QHeaderView.Stretch)
        self.diagnosis_table.itemSelectionChanged.connect(self._refresh_enabled)
        self.diagnosis_table.itemSelectionChanged.connect(self._show_evidence)
        hh.sectionResized.connect(lambda *_: self.diagnosis_table.resizeRowsToContents())
        lay.addWidget(self.diagnosis_table, 1)
        self.evidence_label = hint("")
        self.evidence_label.setTextFormat(Qt.RichText)
        self.evidence_label.setTextInteractionFlags(Qt.TextSelectableByMouse)
        lay.addWidget(self.evidence_label)
        self.rule_label = hint("Score = chi2(current) - chi2(current + effect) - k ln N: the drop of the misfit "
                               "under the noise model, less what the effect's k parameters cost (BIC). The verdict "
                               "is the best positive score among the effects that also remove at least "
                               f"{MATERIAL_FRACTION:.0%} of the error beyond the noise or lower the chi2 by "
                               f"{MATERIAL_CHI2_PER_COMPONENT:g} per measurement (and move a Poisson's ratio at "
                               f"least {NU_NEGLIGIBLE} from the model's, or make a located inclusion at least "
                               f"{INCLUSION_RATIO:g} times stiffer or softer than its tissue), else none. Among "
                               f"those scoring at least {NEAR_TIE:.0%} of the best (a near tie), the verdict is the "
                               "one still needed when the two best are fitted together, else the one whose pattern "
                               "the misfit has most closely (a located inclusion, placed where the misfit is, does "
                               "not win by its pattern over a better score). A verdict of none names any other "
                               "effect that fits at least as well and would move a modulus by more than "
                               f"{UNRESOLVED_SHIFT:.0%}: the moduli then rest on the setup ruling it out.")
        self.rule_label.setVisible(False)
        self.rule_toggle = hint("")
        self.rule_toggle.setTextFormat(Qt.RichText)
        self.rule_toggle.linkActivated.connect(lambda *_: self.show_rule(not self.rule_label.isVisibleTo(w)))
        self.diagnosis_table.horizontalHeaderItem(2).setToolTip(self.rule_label.text())
        lay.addWidget(self.rule_toggle)
        lay.addWidget(self.rule_label)
        self.show_rule(False)
        b = QHBoxLayout()
        self.add_verdict_button = QPushButton("Add verdict")
        self.add_verdict_button.setObjectName("primary")
        self.add_verdict_button.clicked.connect(lambda: self.add(None))
        self.add_selected_button = QPushButton("Add selected effect")
        self.add_selected_button.clicked.connect(self.add_selected)
        b.addWidget(self.add_verdict_button)
        b.addWidget(self.add_selected_button)
        b.addStretch(1)
        lay.addLayout(b)
        return w

    def _build_history(self) -> QWidget:
        w = QWidget()
        lay = QVBoxLayout(w)
        lay.setContentsMargins(4, 4, 4, 4)
        vs = QSplitter(Qt.Vertical)
        top = QWidget()
        tl = QVBoxLayout(top)
        tl.setContentsMargins(0, 0, 0, 0)
        self.history_table = _table(["#", "Model", "Parameters", "Force RMS (N)", "Displacement RMS (px)", "chi2",
                                     "Note"])
        self.history_table.setWordWrap(False)
        hh = self.history_table.horizontalHeader()
        for c in (0, 1, 3, 4, 5, 6):
            hh.setSectionResizeMode(c, QHeaderView.ResizeToContents)
        hh.setSectionResizeMode(2, QHeaderView.Stretch)
        self.history_table.itemSelectionChanged.connect(self._refresh_enabled)
        self.history_table.setMinimumHeight(80)
        tl.addWidget(self.history_table, 1)
        row = QHBoxLayout()
        self.revert_button = QPushButton("Make the selected version current")
        self.revert_button.setToolTip("Revert: the selected version becomes the current model again "
                                      "(later versions are kept, to compare)")
        self.revert_button.clicked.connect(self.revert_selected)
        row.addWidget(self.revert_button)
        self.refine_button = QPushButton("Refine the inclusion's place")
        self.refine_button.setToolTip("For a version with an inclusion: tries the sphere a little moved and "
                                      "resized, each on the current mesh,\nand makes the best of them, meshed, a "
                                      "new version (one to two minutes at the paper's size)")
        self.refine_button.clicked.connect(self.refine)
        row.addWidget(self.refine_button)
        self.mesh_check_button = QPushButton("Check the mesh")
        self.mesh_check_button.setToolTip(
            "Identifies the current version again on a mesh 0.7 times the size (the same effects, inclusion,\n"
            "frames and ROI) and shows how far each parameter moves: how much of it is the mesh's own error.\n"
            "About a minute or two at the paper's size; minutes more with large deformation")
        self.mesh_check_button.clicked.connect(self.check_mesh)
        row.addWidget(self.mesh_check_button)
        row.addWidget(hint("\u25b6 marks the current version; reverting keeps the later ones."))
        row.addStretch(1)
        tl.addLayout(row)
        vs.addWidget(top)

        bottom = QSplitter(Qt.Horizontal)
        self.error_graphics = pg.GraphicsLayoutWidget()
        self.error_graphics.setMinimumSize(260, 200)
        self.error_plots = {}
        self.error_curves = {}
        self.error_noise = {}
        self.error_current = {}
        for r, (key, title, unit) in enumerate((("force_rms_N", "Force misfit across versions", "N RMS"),
                                                ("displacement_rms_px", "Displacement misfit across versions",
                                                 "px RMS"))):
            p = self.error_graphics.addPlot(row=r, col=0, title=title)
            p.setLabel("left", unit)
            style_plot(p)
            p.setMouseEnabled(False, False)
            p.hideButtons()
            self.error_curves[key] = p.plot([], [], pen=pg.mkPen("#1f5fa8", width=2), symbol="o", symbolSize=8,
                                            symbolBrush="#1f5fa8")
            self.error_noise[key] = pg.InfiniteLine(0, angle=0, pen=pg.mkPen("#555", width=1, style=Qt.DashLine),
                                                    label="noise", labelOpts={"position": 0.93, "color": "#555"})
            self.error_noise[key].setVisible(False)
            p.addItem(self.error_noise[key], ignoreBounds=True)
            self.error_current[key] = pg.ScatterPlotItem([], [], symbol="star", size=16, brush="#ffd400",
                                                         pen=pg.mkPen("#333"))
            p.addItem(self.error_current[key])
            self.error_plots[key] = p
        bottom.addWidget(self.error_graphics)

        cmpw = QWidget()
        cl = QVBoxLayout(cmpw)
        cl.setContentsMargins(0, 0, 0, 0)
        row = QHBoxLayout()
        row.addWidget(QLabel("Compare"))
        self.compare_a = QComboBox()
        self.compare_b = QComboBox()
        for box in (self.compare_a, self.compare_b):
            box.setSizeAdjustPolicy(QComboBox.AdjustToContents)
        row.addWidget(self.compare_a, 1)
        row.addWidget(QLabel("with"))
        row.addWidget(self.compare_b, 1)
        self.compare_button = QPushButton("Compare")
        self.compare_button.clicked.connect(self.compare_versions)
        row.addWidget(self.compare_button)
        cl.addLayout(row)
        self.compare_text = QPlainTextEdit()
        self.compare_text.setObjectName("report")
        self.compare_text.setReadOnly(True)
        self.compare_text.setFont(mono_font())
        self.compare_text.setLineWrapMode(QPlainTextEdit.WidgetWidth)  # the mesh check's long lines
        self.compare_text.setPlaceholderText("Choose two versions and press Compare: what was added, how the "
                                             "parameters moved, and the ratio of each error.")
        cl.addWidget(self.compare_text, 1)
        bottom.addWidget(cmpw)
        bottom.setStretchFactor(0, 1)
        bottom.setStretchFactor(1, 1)
        bottom.setSizes([480, 460])
        vs.addWidget(bottom)
        vs.setStretchFactor(0, 1)
        vs.setStretchFactor(1, 3)
        lay.addWidget(vs, 1)
        return w

    # ---- session -> view ----------------------------------------------------------------------
    def _on_experiment(self, *_) -> None:
        self._pending_restore = None  # for the previous experiment (a session opens it before restoring)
        if self.task is not None:  # its result is for the previous experiment
            self._gen += 1
            self.task.cancel()
        self.model.reset()
        self._show(None)
        has = self.session.has_experiment
        self.note.setText("Identify the baseline model first (no effect ticked), then compare, diagnose and add "
                          "effects." if has else "Open an experiment, then identify the baseline model here.")
        self._refresh_enabled()

    def _on_inputs(self, *_) -> None:
        if self.model.stale(self.session):
            self.note.setText("<span style='color:#b26a00'>The ROI, specimen, mesh or Poisson's ratio changed since "
                              "this model check: Identify starts a new one.</span>")
        self._refresh_enabled()

    def _refresh_enabled(self, *_) -> None:
        s, m = self.session, self.model
        has = s.has_experiment
        running = self.task is not None
        other_lock = s.locked_by is not None and not self._owns_lock
        stale = m.stale(s)
        free = has and not running and not other_lock
        cur = set(m.current_effects)
        for e, cb in self.identify_boxes.items():
            cb.setEnabled(free)
        for e, cb in self.candidate_boxes.items():
            cb.setEnabled(free and e not in cur)
        self.identify_button.setEnabled(free)
        self.cancel_button.setEnabled(running)
        can_diag = free and m.n_versions > 0 and not stale
        self.diagnose_button.setEnabled(can_diag and bool(self.chosen_candidates()))
        diag_ok = can_diag and m.diagnosis_is_current()
        d = m.snapshot.diagnosis if m.snapshot else None
        self.add_verdict_button.setEnabled(bool(diag_ok and d is not None and d.verdict != "none"))
        self.add_verdict_button.setText(f"Add verdict ({d.verdict})" if d is not None and d.verdict != "none"
                                        else "Add verdict")
        sel = self.selected_candidate()
        self.add_selected_button.setEnabled(bool(diag_ok and sel is not None and sel["fitted"]))
        self.add_selected_button.setText(f"Add selected effect ({sel['effect']})" if sel else "Add selected effect")
        h = m.history
        hsel = self.selected_version()
        self.revert_button.setEnabled(bool(free and h is not None and not stale and hsel is not None
                                           and hsel != h.current))
        self.compare_button.setEnabled(h is not None and len(h) >= 2)
        self.refine_button.setEnabled(bool(free and not stale and "inclusion" in cur))
        self.mesh_check_button.setEnabled(bool(free and not stale and h is not None and len(h) > 0))
        if other_lock:
            self.state.setText(f"Waiting: {s.locked_by}.")

    def chosen_candidates(self) -> tuple[str, ...]:
        cur = set(self.model.current_effects)
        return tuple(e for e, cb in self.candidate_boxes.items() if cb.isChecked() and e not in cur)

    def chosen_effects(self) -> tuple[str, ...]:
        return tuple(e for e, cb in self.identify_boxes.items() if cb.isChecked())

    def selected_candidate(self, rows: list | None = None) -> dict | None:
        """The selected row of the diagnosis (``rows``: its :func:`diagnosis_rows`, when made already)."""
        s = self.model.snapshot
        if s is None or s.diagnosis is None:
            return None
        sel = self.diagnosis_table.selectionModel().selectedRows()
        if not sel:
            return None
        r = sel[0].row()
        dr = diagnosis_rows(s.diagnosis) if rows is None else rows
        return dr[r] if r < len(dr) else None

    def selected_version(self) -> int | None:
        rows = self.history_table.selectionModel().selectedRows()
        return rows[0].row() if rows else None

    # ---- actions ------------------------------------------------------------------------------------
    def identify(self) -> None:
        self._start("identify", lambda: self.model.identify_work(self.session, self.chosen_effects()))

    def diagnose(self) -> None:
        self._start("diagnose", lambda: self.model.diagnose_work(self.chosen_candidates()))

    def add(self, effect: str | None = None) -> None:
        self._start("add", lambda: self.model.add_work(effect))

    def add_selected(self) -> None:
        sel = self.selected_candidate()
        if sel is not None:
            self.add(sel["effect"])

    def model_force_N(self):
        """The current version's force over the log (its comparison), or None."""
        snap = self.model.snapshot
        cmp = snap.comparison if snap is not None else None
        return None if cmp is None else cmp.force_model_N

    def restore(self, state: dict) -> None:
        """Rebuild the model check a session file kept (its versions and its last diagnosis).
        While a task still runs (opening the session cancelled it), the restore waits for its end."""
        if self.task is not None:
            self._pending_restore = state
            self.state.setText("Waiting for the last task to stop, then restoring the saved model check...")
            return
        self._start("restore", lambda: self.model.restore_work(self.session, state))

    def revert(self, index: int) -> None:
        self._start("revert", lambda: self.model.revert_work(int(index)))

    def refine(self) -> None:
        self._start("refine", self.model.refine_work)

    def check_mesh(self) -> None:
        self._start("mesh-check", self.model.mesh_check_work)

    def revert_selected(self) -> None:
        i = self.selected_version()
        if i is not None:
            self.revert(i)

    def compare_versions(self) -> None:
        h = self.model.history
        if h is None or len(h) < 2:
            return
        i, j = self.compare_a.currentIndex(), self.compare_b.currentIndex()
        if i < 0 or j < 0:
            return
        self.compare_text.setPlainText(compare_text(h, i, j))

    def cancel(self) -> None:
        if self.task is not None:
            self.task.cancel()
            self.state.setText("Cancelling...")

    @property
    def running(self) -> bool:
        return self.task is not None

    def _start(self, action: str, make_work) -> None:
        if self.task is not None:
            return
        try:
            work = make_work()
        except Exception as exc:  # the core's message, shown as it is
            self.error.emit(exc, "")
            return
        self._action = action
        gen = self._gen
        self.task = Task(work, f"modelcheck-{action}")
        self.task.progress.connect(self._task_progress)
        self.task.succeeded.connect(lambda r, gen=gen: self._task_done(r, gen))
        self.task.failed.connect(lambda e, d, gen=gen: self._task_failed(e, d, gen))
        self.task.cancelled.connect(self._task_cancelled)
        self.task.finished.connect(self._task_finished)
        if self.session.locked_by is None:
            self._owns_lock = True
            self.session.set_locked(LOCK_REASON)
        self._t_start = time.monotonic()
        self.progress.setRange(0, 0)
        self.progress.setFormat(ACTIONS[action])
        self.state.setText(f"{ACTIONS[action]}...")
        self.busy.emit(f"Model check: {ACTIONS[action].lower()}", 0, 0)
        log.info("model check: %s", {"identify": f"identify with {', '.join(self.chosen_effects()) or 'no effect'}",
                                     "diagnose": f"diagnose, candidates {', '.join(self.chosen_candidates())}",
                                     "add": "add an effect", "revert": "revert",
                                     "refine": "refine the inclusion's place",
                                     "restore": "restore the saved versions",
                                     "mesh-check": "check the current version's mesh"}[action])
        self._refresh_enabled()
        self.task.start()

    def _task_progress(self, text: str) -> None:
        line = text[:1].upper() + text[1:]
        self.state.setText(line)
        self.progress.setFormat(line[:48])
        self.status.emit(f"model check: {text}")
        log.info("model check: %s", text)

    def _task_done(self, result, gen: int) -> None:
        if gen != self._gen:
            log.info("model check result discarded: the experiment changed during the run")
            return
        snap = self.model.apply(result)
        self._show(snap)
        secs = time.monotonic() - self._t_start
        self.state.setText(f"Done in {secs:.1f} s: {snap.message}.")
        self.status.emit(f"model check: {snap.message}")
        log.info("model check: %s (%.1f s)", snap.message, secs)
        if snap.action == "diagnose":
            self.tabs.setCurrentIndex(1)
        elif snap.action in ("add", "refine"):
            self.tabs.setCurrentIndex(2)
        elif snap.action == "mesh-check":
            self.compare_text.setPlainText(mesh_check_text(snap.mesh_check))
            self.tabs.setCurrentIndex(2)
        elif snap.action == "restore":
            self.tabs.setCurrentIndex(2)
        elif snap.action == "identify" and len(snap.history) == 1:
            self.tabs.setCurrentIndex(0)
        self.note.setText("")

    def _task_failed(self, exc, details, gen: int) -> None:
        if gen != self._gen:
            return
        self.state.setText(f"Failed: {exc}")
        self.error.emit(exc, details)

    def _task_cancelled(self) -> None:
        secs = time.monotonic() - self._t_start
        self.state.setText(f"Cancelled after {secs:.1f} s; the model is as it was.")
        self.status.emit("model check cancelled")
        log.info("model check: %s cancelled after %.1f s", self._action, secs)

    def _task_finished(self) -> None:
        self.task = None
        if self._owns_lock:
            self._owns_lock = False
            if self.session.locked_by == LOCK_REASON:
                self.session.set_locked(None)
        self.progress.setRange(0, 1)
        self.progress.setValue(0)
        self.progress.setFormat("idle")
        self.busy.emit("", 0, 0)
        self._refresh_enabled()
        pending, self._pending_restore = self._pending_restore, None
        if pending is not None:
            self.restore(pending)

    def shutdown(self) -> None:
        self.cancel()

    # ---- drawing ------------------------------------------------------------------------------------
    def _show(self, snap) -> None:
        self._snapshot = snap
        self._outline_cache = {}
        self._show_version(snap)
        self._show_comparison(snap.comparison if snap else None)
        self._show_diagnosis(snap)
        self._show_history(snap.history if snap else None, snap.comparison if snap else None)
        self._refresh_enabled()

    def _show_version(self, snap) -> None:
        h = snap.history if snap else None
        v = h.current_version if h is not None else None
        if v is None:
            self.version_label.setText("No model yet.")
            return
        warning = (f"<br><span style='color:#b26a00'>\u26a0 {html.escape(v.warning[:1].upper() + v.warning[1:])}."
                   f"</span>" if v.warning else "")
        self.version_label.setText(f"<b>Current: version {v.index}, {v.label}</b><br>"
                                   f"{html.escape(parameters_text(v.parameters, v.inclusion))}<br>"
                                   f"force misfit {v.misfit.get('force_rms_N', math.nan):.4f} N RMS, displacement "
                                   f"misfit {v.misfit.get('displacement_rms_px', math.nan):.3f} px RMS{warning}")
        self._updating = True
        try:
            for e, cb in self.identify_boxes.items():
                cb.setChecked(e in v.effects)
        finally:
            self._updating = False

    def _show_comparison(self, cmp) -> None:
        self.comparison = cmp
        if cmp is None:
            for measured, model in self.force_curves.values():
                measured.setData([], [])
                model.setData([], [])
            self.frame_box.blockSignals(True)
            self.frame_box.clear()
            self.frame_box.blockSignals(False)
            self.compare_summary.setText("The comparison of the current model with the measurements appears here "
                                         "after an identification.")
            self._draw_frame()
            return
        t, d = np.asarray(cmp.time_s, float), np.asarray(cmp.displacement_mm, float)
        Fm, Fs = np.asarray(cmp.force_measured_N, float), np.asarray(cmp.force_model_N, float)
        self.force_curves["time"][0].setData(t, Fm)
        self.force_curves["time"][1].setData(t, Fs)
        self.force_curves["travel"][0].setData(d, Fm)
        self.force_curves["travel"][1].setData(d, Fs)
        label = "baseline" if not cmp.effects else "+ " + ", ".join(cmp.effects)
        self.compare_summary.setText(
            f"Model <b>{label}</b>: force misfit <b>{cmp.force_rms_N:.4f} N</b> RMS (noise "
            f"{cmp.force_noise_N:.4f} N); displacement misfit <b>{cmp.displacement_rms_px:.3f} px</b> RMS (tracking "
            f"noise {cmp.noise_px:.3f} px). A model that explains the data leaves misfits near the noise.")
        keep = self.frame_box.currentIndex()
        self.frame_box.blockSignals(True)
        self.frame_box.clear()
        for fc in cmp.frames:
            self.frame_box.addItem(frame_label(fc))
        self.frame_box.setCurrentIndex(keep if 0 <= keep < len(cmp.frames) else len(cmp.frames) - 1)
        self.frame_box.blockSignals(False)
        self._draw_frame()

    def current_frame(self):
        cmp = getattr(self, "comparison", None)
        i = self.frame_box.currentIndex()
        if cmp is None or not (0 <= i < len(cmp.frames)):
            return None
        return cmp.frames[i]

    def difference_scale(self) -> float:
        fc = self.current_frame()
        if fc is None:
            return 1.0
        v = self.diff_scale.value()
        if v > 0:
            return float(v)
        c0, r0, c1, r1 = fc.roi_px
        block = max(8.0, math.sqrt((c1 - c0) * (r1 - r0) / max(1, len(fc.valid))))
        return auto_difference_scale(fc, 0.6 * block)

    def _draw_frame(self, *_) -> None:
        fc = self.current_frame()
        if fc is None:
            for item in (self.residual_image, self.residual_background, self.vector_background):
                item.clear()
            for c in self.vector_curves.values():
                c.setData([], [])
            self.outlier_curve.setData([], [])
            self.roi_outline.setData([], [])
            self.share_bars.setOpts(x=[], height=[])
            self.share_bars_all.setOpts(x=[], height=[])
            self.share_table.setRowCount(0)
            self.frame_note.setText("")
            self._draw_outlines(None)
            return
        s, cmp = self.session, self.comparison
        c0, r0, c1, r1 = fc.roi_px
        # residual map over the ROI, on the (dimmed) target frame
        tgt = normalized(s.frame(fc.target))
        self.residual_background.setImage(0.55 * tgt, levels=(0, 1), autoLevels=False)
        res = np.asarray(fc.residual_map, float)
        self.residual_image.setImage(res, autoLevels=False)
        self.residual_image.setRect(c0, r0, c1 - c0, r1 - r0)
        self.residual_bar.setLevels((0.0, 1.0))
        self.residual_plot.getViewBox().setRange(xRange=(c0, c1), yRange=(r0, r1), padding=0.02)
        # the displacement field at the tracked blocks (valid ones only)
        src = normalized(s.frame(fc.source))
        self.vector_background.setImage(0.35 + 0.5 * src, levels=(0, 1), autoLevels=False)
        self.roi_outline.setData([c0, c1, c1, c0, c0], [r0, r0, r1, r1, r0])
        valid = np.asarray(fc.valid, bool)
        outlier = np.asarray(fc.outlier, bool)
        kept = fc.kept
        every = np.asarray(fc.points_px, float)
        diff = np.asarray(fc.difference_px, float)
        scale = self.difference_scale()
        # (curve, the check box that shows it, blocks, vectors, length scale); the outliers'
        # differences go with the difference box, in grey
        arrows = ((self.vector_curves["measured"], "measured", valid, np.asarray(fc.measured_px, float), 1.0),
                  (self.vector_curves["model"], "model", valid, np.asarray(fc.model_px, float), 1.0),
                  (self.vector_curves["difference"], "difference", kept, diff, scale),
                  (self.outlier_curve, "difference", outlier, diff, scale))
        for curve, box, sel, v, k in arrows:
            if self.show_boxes[box].isChecked():
                curve.setData(*arrow_segments(every[sel], v[sel], k, head_px=2.5))
            else:
                curve.setData([], [])
        self.vector_plot.getViewBox().setRange(xRange=(c0, c1), yRange=(r0, r1), padding=0.02)
        # each region's share of the misfit
        names = list(cmp.region_share)
        xs = np.arange(len(names), dtype=float)
        this = np.array([100 * fc.region_share.get(n, 0.0) for n in names])
        allf = np.array([100 * cmp.region_share.get(n, 0.0) for n in names])
        regions = s.specimen.region_names if s.specimen is not None else ()
        brushes = [region_color(regions.index(n) if n in regions else k) for k, n in enumerate(names)]
        self.share_bars.setOpts(x=xs - 0.2, height=this, width=0.38, brushes=brushes, pen=pg.mkPen("#333"))
        self.share_bars_all.setOpts(x=xs + 0.2, height=allf, width=0.38, brush=pg.mkBrush(0, 0, 0, 0),
                                    pen=pg.mkPen("#333", width=1.5, style=Qt.DashLine))
        self.share_plot.getAxis("bottom").setTicks([[(float(x), n) for x, n in zip(xs, names)]])
        self.share_plot.setYRange(0, 100, padding=0.02)
        self.share_plot.setXRange(-0.7, len(names) - 0.3, padding=0)
        self.share_table.setRowCount(len(names))
        for k, n in enumerate(names):
            self.share_table.setItem(k, 0, _item(n))
            for col, v in ((1, this[k]), (2, allf[k]), (3, 100 * cmp.image_region_share.get(n, math.nan))):
                self.share_table.setItem(k, col, _item(f"{v:.0f}%", align=Qt.AlignRight | Qt.AlignVCenter))
        self.share_table.resizeColumnsToContents()
        outlined = self._draw_outlines(self.frame_box.currentIndex())
        n_valid, n_out = int(valid.sum()), int(outlier.sum())
        rms = fc.difference_rms_px
        out_text = (f"{n_out} of them disagree with their neighbours (grey differences: a wrong speckle match, "
                    f"or a sharp misfit; left out of the shares); " if n_out else "")
        self.frame_note.setText(
            f"Frame {fc.target} (probe travel {fc.displacement_mm:.2f} mm) against frame {fc.source}: "
            f"{n_valid} of {len(valid)} tracked blocks kept (the others left the image or matched too weakly "
            f"to trust); {out_text}difference {rms:.2f} px RMS, drawn "
            f"{scale:g}x longer. "
            f"Residual map: 0 where the warped source matches the frame, 1 where they are unrelated. "
            f"Bars: this frame (filled), all frames (dashed). {outlined}".rstrip())

    def outlines_of(self, k: int, frame: str) -> dict:
        """The outlines (app.core.compare.outlines) on frame ``k`` of the comparison,
        ``frame`` "target" (the residual map) or "source" (the vector map), kept
        until the next comparison or diagnosis is shown."""
        key = (k, frame)
        if key not in self._outline_cache:
            self._outline_cache[key] = frame_outlines(self._snapshot, k, frame)
        return self._outline_cache[key]

    def _draw_outlines(self, k: int | None) -> str:
        """Outline the regions on both maps for frame ``k`` (None: clear); returns the legend."""
        plots = {"target": self.residual_plot, "source": self.vector_plot}
        for frame, items in self.outline_items.items():
            for item in items:
                plots[frame].removeItem(item)
            items.clear()
        shapes = outline_shapes(self._snapshot)
        if k is None or not shapes or not self.show_boxes["outlines"].isChecked():
            return ""
        drawn = set()
        for frame, plot in plots.items():
            lines = self.outlines_of(k, frame)
            drawn |= set(lines)
            taken = []  # the labels' points on this map
            for o in shapes:
                parts = lines.get(o.region.name, [])
                if not parts:
                    continue
                xy = np.vstack([np.vstack([p, [np.nan, np.nan]]) for p in parts])
                style, dashes = OUTLINE_STYLES[o.kind]
                pen = pg.mkPen(OUTLINE, width=1.8, style=style)
                if dashes:
                    pen.setDashPattern(dashes)
                item = pg.PlotDataItem(xy[:, 0], xy[:, 1], connect="finite", pen=pen)
                # the name above the outline's top, or elsewhere on it when that is taken (label_place)
                at, anchor = label_place(parts, taken, self.comparison.frames[k].roi_px[1])
                taken.append(at)
                label = pg.TextItem(html=f"<b>{html.escape(o.label)}</b>", anchor=anchor,
                                    fill=pg.mkBrush(0, 0, 0, 120))  # readable over bright speckle
                label.setColor(OUTLINE)
                label.setPos(float(at[0]), float(at[1]))
                for it in (item, label):
                    it.setZValue(5)
                    plot.addItem(it)
                    self.outline_items[frame].append(it)
        return outlines_note(shapes, drawn, lambda region: self.comparison.outside_text(k, region))

    def _show_diagnosis(self, snap) -> None:
        d = snap.diagnosis if snap else None
        self.diagnosis_table.setRowCount(0)
        if d is None:
            self.verdict_label.setText("No diagnosis yet: identify a model, then press Diagnose.")
            self.noise_label.setText("")
            self.diagnosis_current.setText("")
            self.evidence_label.setText("")
            return
        self.verdict_label.setText(verdict_html(verdict_parts(d), "color:#b26a00"))
        b = d.baseline
        self.diagnosis_current.setText(
            f"Diagnosed version {snap.diagnosed_version} ({', '.join(b.effects) or 'baseline'}) in {d.seconds:.0f} s. "
            f"Refitted by maximum likelihood for the scores, it leaves a force misfit of "
            f"{b.misfit.get('force_rms_N', math.nan):.4f} N and a displacement misfit of "
            f"{b.misfit.get('displacement_rms_px', math.nan):.3f} px (the Compare tab shows the version as "
            "identified)."
            + ("" if self.model.diagnosis_is_current() else
               "  <span style='color:#b26a00'>The current version is another one: diagnose again to add to it."
               "</span>")
            + (f"<br><span style='color:#555'>{html.escape(d.memory_note[:1].upper() + d.memory_note[1:])}.</span>"
               if d.memory_note else "")
            + (f"<br><span style='color:#b26a00'>{html.escape(d.mesh_note[:1].upper() + d.mesh_note[1:])}.</span>"
               if d.mesh_note else ""))
        self.noise_label.setText(f"Noise model: {d.noise.describe()}.")
        rows = diagnosis_rows(d)
        self.diagnosis_table.setRowCount(len(rows))
        for i, r in enumerate(rows):
            cells = [str(r["rank"]), r["effect"], r["score_text"], r["parameters"], r["evidence_head"]]
            tips = ["", r["title"], "", r["parameters"], r["evidence"]]
            for col, text in enumerate(cells):
                it = _item(text, bold=r["verdict"], tip=tips[col] or text)
                if col == 2:
                    it.setTextAlignment(Qt.AlignRight | Qt.AlignVCenter)
                if r["verdict"]:
                    it.setBackground(QBrush(QColor(VERDICT_BG)))
                self.diagnosis_table.setItem(i, col, it)
        tb = self.diagnosis_table
        tb.setColumnWidth(3, min(tb.sizeHintForColumn(3), 40 * tb.fontMetrics().averageCharWidth()))
        tb.resizeRowsToContents()
        self._show_evidence()

    def show_rule(self, visible: bool) -> None:
        """Show or hide how the scores and the verdict are made (hidden at first)."""
        self.rule_label.setVisible(visible)
        self.rule_toggle.setText(f"<a href='#'>{'Hide' if visible else 'Show'} how the scores and the verdict are "
                                 "made</a>")

    def _show_evidence(self) -> None:
        """Beside the table, the whole evidence of the selected candidate, else of the verdict's (else the first)."""
        s = self.model.snapshot
        rows = diagnosis_rows(s.diagnosis) if s is not None and s.diagnosis is not None else []
        if not rows:
            self.evidence_label.setText("")
            return
        sel = self.selected_candidate(rows)
        r = sel or next((r for r in rows if r["verdict"]), rows[0])
        text = r["evidence"] or "no evidence recorded"
        self.evidence_label.setText(f"<b>{html.escape(r['effect'])}</b> ({html.escape(r['score_text'])}): "
                                    f"{html.escape(text[:1].upper() + text[1:])}."
                                    + ("" if sel else " <i>(Select a row to read another candidate's evidence.)</i>"))

    def verdict_row(self) -> int | None:
        """The table row holding the verdict (None when the verdict is none)."""
        for i in range(self.diagnosis_table.rowCount()):
            it = self.diagnosis_table.item(i, 1)
            if it is not None and it.font().bold():
                return i
        return None

    def _show_history(self, h, cmp) -> None:
        self.history_table.setRowCount(0)
        for key in self.error_curves:
            self.error_curves[key].setData([], [])
            self.error_current[key].setData([], [])
            self.error_noise[key].setVisible(False)
        for box in (self.compare_a, self.compare_b):
            box.clear()
        if h is None or len(h) == 0:
            self.compare_text.setPlainText("")
            return
        rows = history_rows(h)
        self.history_table.setRowCount(len(rows))
        for i, r in enumerate(rows):
            mark = "\u25b6 " if r["current"] else ""
            note = f"\u26a0 {r['note']}: {r['status']}" if r["warning"] else r["note"]
            if r["mesh_check"]:  # its figures in the tooltip
                note = f"{note}; mesh checked" if note else "mesh checked"
            cells = [f"{mark}{r['index']}", r["label"], r["parameters"], _fmt(r["force_rms_N"], 4),
                     _fmt(r["displacement_rms_px"], 3), _fmt(r["chi2"], 1), note]
            for col, text in enumerate(cells):
                tip = ("the current version" if r["current"] and col == 0
                       else r["warning"] if r["warning"] and col in (1, 6) else "")
                if col == 6 and r["mesh_check"]:
                    tip = "\n\n".join(x for x in (tip, mesh_check_text(r["mesh_check"])) if x)
                it = _item(text, bold=r["current"], tip=tip)
                if r["warning"] and col == 6:
                    it.setForeground(QColor("#b26a00"))
                if col in (3, 4, 5):
                    it.setTextAlignment(Qt.AlignRight | Qt.AlignVCenter)
                self.history_table.setItem(i, col, it)
        self.history_table.resizeRowsToContents()
        errs = h.errors()
        x = np.asarray(errs["index"], float)
        ticks = [[(float(i), f"{i}: {lab}") for i, lab in zip(errs["index"], errs["label"])]]
        noise = {"force_rms_N": cmp.force_noise_N if cmp is not None else None,
                 "displacement_rms_px": cmp.noise_px if cmp is not None else None}
        for key, curve in self.error_curves.items():
            y = np.array([v if v is not None else np.nan for v in errs[key]], float)
            curve.setData(x, y)
            self.error_current[key].setData([float(h.current)], [float(y[h.current])])
            p = self.error_plots[key]
            p.getAxis("bottom").setTicks(ticks)
            p.setXRange(-0.3, max(1.0, len(x) - 1) + 0.3, padding=0)
            top = np.nanmax(y) if np.isfinite(y).any() else 1.0
            nz = noise[key]
            if nz is not None and math.isfinite(nz) and nz > 0:
                self.error_noise[key].setValue(nz)
                self.error_noise[key].setVisible(True)
            p.setYRange(0, 1.12 * max(top, nz or 0), padding=0)
        for box in (self.compare_a, self.compare_b):
            for r in rows:
                box.addItem(f"{r['index']}: {r['label']}")
        self.compare_a.setCurrentIndex(max(0, len(rows) - 2))
        self.compare_b.setCurrentIndex(len(rows) - 1)
        self.compare_text.setPlainText("")
        if len(rows) >= 2:
            self.compare_versions()


def _fmt(v, digits: int) -> str:
    if v is None or not isinstance(v, (int, float)) or not math.isfinite(v):
        return "-"
    return f"{v:.{digits}f}"

