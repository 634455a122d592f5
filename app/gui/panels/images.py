"""Images panel: the experiment's frames, the source/target choice, the ROI, and the
red/green subtraction and difference views of (warped) source against target."""

from __future__ import annotations

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import QRectF, Qt, Signal
from PySide6.QtWidgets import (QButtonGroup, QComboBox, QFormLayout, QGridLayout, QGroupBox, QHBoxLayout, QLabel,
                               QPushButton, QToolButton, QVBoxLayout, QWidget)

from ..models.session import SessionModel
from .base import Panel
from .common import diverging_lut, hint, ispin, normalized, red_green

MODES = ("source", "target", "overlay", "difference")
MODE_LABELS = {"source": "Source", "target": "Target", "overlay": "Overlay (red/green)", "difference": "Difference"}


class _DrawViewBox(pg.ViewBox):
    """A ViewBox where, in draw mode, a left drag draws a rectangle (image pixels)."""

    rectDrawn = Signal(QRectF)

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.draw_mode = False
        self._rubber = None

    def mouseDragEvent(self, ev, axis=None):
        if not self.draw_mode or ev.button() != Qt.LeftButton:
            return super().mouseDragEvent(ev, axis)
        ev.accept()
        p0 = self.mapSceneToView(ev.buttonDownScenePos())
        p1 = self.mapSceneToView(ev.scenePos())
        rect = QRectF(p0, p1).normalized()
        if self._rubber is None:
            self._rubber = pg.QtWidgets.QGraphicsRectItem()
            self._rubber.setPen(pg.mkPen("#ffd400", width=1.5, style=Qt.DashLine))
            self._rubber.setZValue(20)
            self.addItem(self._rubber, ignoreBounds=True)
        self._rubber.setRect(rect)
        if ev.isFinish():
            self.removeItem(self._rubber)
            self._rubber = None
            self.rectDrawn.emit(rect)


class ImagesPanel(Panel):
    """Observes the session's experiment, ROI, frames and overlay; sets the ROI and frames."""

    title = "Images"

    def __init__(self, session: SessionModel, parent=None):
        super().__init__(parent)
        self.session = session
        self.mode = "overlay"
        self._updating = False
        self._build()
        session.experiment_changed.connect(self._on_experiment)
        session.roi_changed.connect(self._on_roi)
        session.frames_changed.connect(self._on_frames)
        session.overlay_changed.connect(self._refresh_image)
        session.lock_changed.connect(self._on_lock)
        self._on_experiment()

    # ---- layout --------------------------------------------------------------------
    def _build(self) -> None:
        lay = QHBoxLayout(self)
        lay.setContentsMargins(4, 4, 4, 4)

        side = QVBoxLayout()
        frames = QGroupBox("Frames")
        f = QFormLayout(frames)
        self.source_box = QComboBox()
        self.target_box = QComboBox()
        self.source_box.setToolTip("The frame before (or earlier in) the deformation; the model warps it.")
        self.target_box.setToolTip("The frame the warped source is compared with.")
        f.addRow("Source", self.source_box)
        f.addRow("Target", self.target_box)
        self.frame_info = hint("")
        f.addRow(self.frame_info)
        side.addWidget(frames)

        view = QGroupBox("View")
        v = QVBoxLayout(view)
        self.mode_group = QButtonGroup(self)
        grid = QGridLayout()
        self.mode_buttons = {}
        for i, m in enumerate(MODES):
            b = QPushButton(MODE_LABELS[m])
            b.setCheckable(True)
            b.setObjectName(f"mode_{m}")
            self.mode_group.addButton(b)
            self.mode_buttons[m] = b
            grid.addWidget(b, i // 2, i % 2)
            b.clicked.connect(lambda _=False, m=m: self.set_mode(m))
        self.mode_buttons[self.mode].setChecked(True)
        v.addLayout(grid)
        self.legend = hint("")
        v.addWidget(self.legend)
        side.addWidget(view)

        roi = QGroupBox("Region of interest (pixels)")
        g = QGridLayout(roi)
        self.spins = {}
        for i, (key, label) in enumerate((("col0", "Left column"), ("row0", "Top row"),
                                          ("col1", "Right column (excl.)"), ("row1", "Bottom row (excl.)"))):
            s = ispin(0, 100000, 0)
            s.setObjectName(f"roi_{key}")
            s.editingFinished.connect(self._spins_edited)
            self.spins[key] = s
            g.addWidget(QLabel(label), i, 0)
            g.addWidget(s, i, 1)
        self.roi_size = hint("")
        g.addWidget(self.roi_size, 4, 0, 1, 2)
        btns = QHBoxLayout()
        self.draw_button = QToolButton()
        self.draw_button.setText("Draw ROI")
        self.draw_button.setCheckable(True)
        self.draw_button.setToolTip("Then drag a rectangle on the image with the left mouse button.\n"
                                    "The ROI's handles also move and resize it.")
        self.draw_button.toggled.connect(self._set_draw_mode)
        self.reset_roi = QPushButton("Default ROI")
        self.reset_roi.clicked.connect(self._reset_roi)
        btns.addWidget(self.draw_button)
        btns.addWidget(self.reset_roi)
        btns.addStretch(1)
        g.addLayout(btns, 5, 0, 1, 2)
        side.addWidget(roi)

        self.nmi_label = hint("")
        side.addWidget(self.nmi_label)
        side.addStretch(1)
        side_w = QWidget()
        side_w.setLayout(side)
        side_w.setFixedWidth(300)
        lay.addWidget(side_w)

        self.graphics = pg.GraphicsLayoutWidget()
        self.vb = _DrawViewBox(lockAspect=True, invertY=True)
        self.plot = pg.PlotItem(viewBox=self.vb)
        self.plot.setLabel("bottom", "lateral (column, px)")
        self.plot.setLabel("left", "depth (row, px)")
        self.plot.showGrid(x=False, y=False)
        self.graphics.addItem(self.plot)
        self.image = pg.ImageItem()
        self.plot.addItem(self.image)
        self.roi = pg.RectROI([0, 0], [10, 10], pen=pg.mkPen("#ffd400", width=2), hoverPen=pg.mkPen("#fff176", width=3),
                              snapSize=1.0, translateSnap=True, scaleSnap=True, rotatable=False, movable=True)
        self.roi.addScaleHandle([0, 0], [1, 1])
        self.roi.setZValue(10)
        self.plot.addItem(self.roi)
        self.roi.sigRegionChangeFinished.connect(self._roi_dragged)
        self.roi.sigRegionChanged.connect(self._roi_moving)
        self.vb.rectDrawn.connect(self._rect_drawn)
        self.colorbar_lut = diverging_lut()
        self.placeholder = pg.TextItem("Open an experiment to see its frames", color="#5b6478", anchor=(0.5, 0.5))
        self.plot.addItem(self.placeholder)
        lay.addWidget(self.graphics, 1)

        self.source_box.currentIndexChanged.connect(self._frames_edited)
        self.target_box.currentIndexChanged.connect(self._frames_edited)

    # ---- model -> view -----------------------------------------------------------------
    def _on_experiment(self) -> None:
        s = self.session
        exp = s.experiment
        self._updating = True
        try:
            for box in (self.source_box, self.target_box):
                box.clear()
            enabled = exp is not None
            for w in (self.source_box, self.target_box, self.draw_button, self.reset_roi, *self.spins.values()):
                w.setEnabled(enabled)
            self.roi.setVisible(enabled)
            self.placeholder.setVisible(not enabled)
            if not enabled:
                self.image.clear()
                self.legend.setText("")
                self.nmi_label.setText("")
                self.frame_info.setText("")
                return
            for i, fr in enumerate(exp.frames):
                text = f"#{i}   {fr.displacement_mm:.2f} mm   {exp.frame_force_N(i):.3f} N"
                self.source_box.addItem(text)
                self.target_box.addItem(text)
            rows, cols = s.image_shape
            for key, hi in (("col0", cols - 1), ("row0", rows - 1), ("col1", cols), ("row1", rows)):
                self.spins[key].setRange(0, hi)
            self.roi.maxBounds = QRectF(0, 0, cols, rows)
        finally:
            self._updating = False
        self._on_frames(s.source_frame, s.target_frame)
        self._on_roi(s.roi_px)
        self.vb.setRange(QRectF(0, 0, *s.image_shape[::-1]), padding=0.02)

    def _on_frames(self, source: int, target: int) -> None:
        self._updating = True
        try:
            self.source_box.setCurrentIndex(source)
            self.target_box.setCurrentIndex(target)
        finally:
            self._updating = False
        exp = self.session.experiment
        rows, cols = self.session.image_shape
        sc, sr = exp.imaging.pixel_spacing_mm
        fs, ft = exp.frames[source], exp.frames[target]
        self.frame_info.setText(f"{len(exp.frames)} frames of {cols} x {rows} px at {sc:g} x {sr:g} mm/px. "
                                f"Source at t = {fs.time_s:.1f} s, target at t = {ft.time_s:.1f} s: "
                                f"probe travel {ft.displacement_mm - fs.displacement_mm:+.2f} mm.")
        self._refresh_image()

    def _on_roi(self, roi) -> None:
        if roi is None:
            return
        c0, r0, c1, r1 = roi
        self._updating = True
        try:
            for key, val in zip(("col0", "row0", "col1", "row1"), roi):
                self.spins[key].setValue(int(val))
            self.roi.setPos([c0, r0], update=False, finish=False)
            self.roi.setSize([c1 - c0, r1 - r0], update=True, finish=False)
        finally:
            self._updating = False
        exp = self.session.experiment
        sc, sr = exp.imaging.pixel_spacing_mm
        self.roi_size.setText(f"{c1 - c0} x {r1 - r0} px = {(c1 - c0) * sc:.1f} x {(r1 - r0) * sr:.1f} mm")
        self._update_metric()
        if self.mode in ("overlay", "difference"):
            self._refresh_image()

    def _on_lock(self, reason) -> None:
        editable = reason is None and self.session.has_experiment
        for w in (self.source_box, self.target_box, self.draw_button, self.reset_roi, *self.spins.values()):
            w.setEnabled(editable)
        self.roi.setEnabled(editable)
        self.roi.translatable = editable
        for h in self.roi.getHandles():
            h.setVisible(editable)
        if reason:
            self.status.emit(f"the ROI and frames are read-only while {reason}")

    # ---- view -> model -------------------------------------------------------------------
    def _frames_edited(self) -> None:
        if not self._updating and self.session.has_experiment:
            self.session.set_frames(self.source_box.currentIndex(), self.target_box.currentIndex())

    def _spins_edited(self) -> None:
        if not self._updating and self.session.has_experiment:
            self.session.set_roi(tuple(self.spins[k].value() for k in ("col0", "row0", "col1", "row1")))
            self._on_roi(self.session.roi_px)  # show the clamped values

    def _roi_rect(self) -> tuple[int, int, int, int]:
        pos, size = self.roi.pos(), self.roi.size()
        c0, r0 = int(round(pos.x())), int(round(pos.y()))
        return (c0, r0, c0 + int(round(size.x())), r0 + int(round(size.y())))

    def _roi_moving(self) -> None:
        if self._updating:
            return
        c0, r0, c1, r1 = self._roi_rect()
        self.roi_size.setText(f"{c1 - c0} x {r1 - r0} px (release to apply)")

    def _roi_dragged(self) -> None:
        if not self._updating and self.session.has_experiment:
            self.session.set_roi(self._roi_rect())
            self._on_roi(self.session.roi_px)

    def _rect_drawn(self, rect: QRectF) -> None:
        self.draw_button.setChecked(False)
        if rect.width() < 2 or rect.height() < 2:
            return
        self.session.set_roi((rect.left(), rect.top(), rect.right(), rect.bottom()))
        self._on_roi(self.session.roi_px)

    def _set_draw_mode(self, on: bool) -> None:
        self.vb.draw_mode = on
        self.vb.setMouseEnabled(not on, not on)
        self.roi.setEnabled(not on)  # the drag must reach the view, not move the old ROI
        self.graphics.setCursor(Qt.CrossCursor if on else Qt.ArrowCursor)

    def _reset_roi(self) -> None:
        from app.core.images import default_roi

        s = self.session
        s.set_roi(default_roi(s.experiment, s.image_shape))
        self._on_roi(s.roi_px)

    # ---- drawing ---------------------------------------------------------------------------
    def set_mode(self, mode: str) -> None:
        self.mode = mode
        self.mode_buttons[mode].setChecked(True)
        self._refresh_image()

    def _pair(self):
        """(source-or-warped, target, roi, warped?) full-size images for the overlay views."""
        s = self.session
        src, tgt = s.frame(s.source_frame), s.frame(s.target_frame)
        ov = s.overlay
        if ov is not None:
            warped, roi = np.asarray(ov[0], float), tuple(ov[2])
            mask = np.asarray(ov[3], bool) if len(ov) > 3 and ov[3] is not None else None
            if warped.shape == tgt.shape:
                return warped, tgt, roi, True
            c0, r0, c1, r1 = roi
            if warped.shape == (r1 - r0, c1 - c0):
                full = np.full(tgt.shape, np.nan)
                full[r0:r1, c0:c1] = np.where(mask, warped, np.nan) if mask is not None else warped
                return full, tgt, roi, True
        return src, tgt, s.roi_px, False

    def _refresh_image(self) -> None:
        s = self.session
        if not s.has_experiment:
            return
        if self.mode in ("source", "target"):
            img = s.frame(s.source_frame if self.mode == "source" else s.target_frame)
            self.image.setImage(normalized(img), levels=(0, 1), autoLevels=False, lut=None)
            fr = s.source_frame if self.mode == "source" else s.target_frame
            self.legend.setText(f"Frame {fr} as recorded (grey levels between the 1st and 99th percentiles).")
        else:
            src, tgt, roi, warped = self._pair()
            what = "source warped by the identified model" if warped else "source, not warped (no result yet)"
            if self.mode == "overlay":
                filled = np.where(np.isfinite(src), src, np.nan)
                rgb = red_green(tgt, np.nan_to_num(filled, nan=np.nanmin(filled) if np.isfinite(filled).any() else 0))
                if warped:
                    outside = ~np.isfinite(src)
                    rgb[outside] = (0.35 * rgb[outside]).astype(np.uint8)
                self.image.setImage(rgb, autoLevels=False, levels=(0, 255), lut=None)
                self.legend.setText(f"<span style='color:#c62828'><b>red</b></span> = target, "
                                    f"<span style='color:#2e7d32'><b>green</b></span> = {what}; "
                                    f"yellow where they agree.")
            else:
                d = normalized(src) - normalized(tgt)
                self.image.setImage(d, levels=(-1, 1), autoLevels=False, lut=self.colorbar_lut)
                self.legend.setText(f"Difference ({what}) minus target, normalised grey levels: "
                                    f"<span style='color:#c62828'>red</span> brighter in the source, "
                                    f"<span style='color:#1565c0'>blue</span> brighter in the target.")
        self._update_metric()

    def _update_metric(self) -> None:
        s = self.session
        if not s.has_experiment or s.roi_px is None:
            return
        from app.core.similarity import nmi

        src, tgt, _, warped = self._pair()
        c0, r0, c1, r1 = s.roi_px
        a, b = src[r0:r1, c0:c1], tgt[r0:r1, c0:c1]
        ok = np.isfinite(a) & np.isfinite(b)
        if ok.sum() < 16:
            self.nmi_label.setText("")
            return
        value = nmi(a[ok], b[ok], bins=64)
        label = "warped source vs target" if warped else "source vs target (unwarped)"
        self.nmi_label.setText(f"NMI in the ROI, {label}: <b>{value:.4f}</b> (1 = unrelated, 2 = identical)")

    # ---- used by tests and screenshots ------------------------------------------------------
    def roi_from_view(self) -> tuple[int, int, int, int]:
        return self._roi_rect()
