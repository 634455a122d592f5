"""Small widgets the panels share."""

from __future__ import annotations

import numpy as np
from PySide6.QtCore import Qt, QTimer
from PySide6.QtWidgets import (QDoubleSpinBox, QFrame, QHBoxLayout, QLabel, QProgressBar, QScrollArea, QSpinBox,
                               QWidget)

# a busy bar's steps: one every PULSE_MS, back to the start after PULSE_STEPS
PULSE_MS = 500
PULSE_STEPS = 10


class BusyBar(QProgressBar):
    """A progress bar whose busy mode (``setRange(0, 0)``, no known total) moves a
    step every PULSE_MS instead of Qt's animation. That animation repaints about
    55 times a second, and a window holding an OpenGL view (the 3D mesh) is then
    composed anew each time: with software OpenGL (Xvfb here; a remote desktop or
    a PC without a graphics driver) two such bars took 44 CPU-seconds of the
    87-second diagnosis of the demo from its two cores. Any other range is a
    plain progress bar."""

    def __init__(self, parent=None):
        super().__init__(parent)
        self._busy = False
        self._pulse = QTimer(self)
        self._pulse.setInterval(PULSE_MS)
        self._pulse.timeout.connect(self._step)

    @property
    def busy(self) -> bool:
        return self._busy

    def setRange(self, minimum: int, maximum: int) -> None:  # noqa: N802 (Qt's name)
        self._busy = minimum == maximum == 0
        if self._busy:
            super().setRange(0, PULSE_STEPS)
            super().setValue(0)
        else:
            super().setRange(minimum, maximum)
        self._run_pulse()

    def _run_pulse(self) -> None:
        """The pulse runs while busy and shown (a hidden bar, e.g. the status bar's
        when nothing runs, has nothing to move)."""
        if self._busy and self.isVisible():
            if not self._pulse.isActive():
                self._pulse.start()
        else:
            self._pulse.stop()

    def showEvent(self, event) -> None:  # noqa: N802 (Qt's name)
        super().showEvent(event)
        self._run_pulse()

    def hideEvent(self, event) -> None:  # noqa: N802 (Qt's name)
        super().hideEvent(event)
        self._run_pulse()

    def _step(self) -> None:
        super().setValue((self.value() + 1) % (PULSE_STEPS + 1))


def spin(lo: float, hi: float, value: float, *, decimals: int = 2, step: float = 1.0, suffix: str = "",
         tip: str = "") -> QDoubleSpinBox:
    s = QDoubleSpinBox()
    s.setRange(lo, hi)
    s.setDecimals(decimals)
    s.setSingleStep(step)
    s.setValue(value)
    s.setKeyboardTracking(False)
    if suffix:
        s.setSuffix(f" {suffix}")
    if tip:
        s.setToolTip(tip)
    s.setAlignment(Qt.AlignRight)
    return s


def ispin(lo: int, hi: int, value: int, *, suffix: str = "", tip: str = "") -> QSpinBox:
    s = QSpinBox()
    s.setRange(lo, hi)
    s.setValue(value)
    s.setKeyboardTracking(False)
    if suffix:
        s.setSuffix(f" {suffix}")
    if tip:
        s.setToolTip(tip)
    s.setAlignment(Qt.AlignRight)
    return s


def hint(text: str) -> QLabel:
    lab = QLabel(text)
    lab.setObjectName("hint")
    lab.setWordWrap(True)
    return lab


def hline() -> QFrame:
    f = QFrame()
    f.setFrameShape(QFrame.HLine)
    f.setFrameShadow(QFrame.Sunken)
    return f


def row(*widgets, stretch: bool = True) -> QWidget:
    w = QWidget()
    lay = QHBoxLayout(w)
    lay.setContentsMargins(0, 0, 0, 0)
    for x in widgets:
        if isinstance(x, str):
            x = QLabel(x)
        lay.addWidget(x)
    if stretch:
        lay.addStretch(1)
    return w


def scrolled(side: QWidget) -> QScrollArea:
    """A panel's side column in a vertical scroll area, so the window fits small screens
    (its width stays the column's own)."""
    sc = QScrollArea()
    sc.setWidget(side)
    sc.setWidgetResizable(True)
    sc.setHorizontalScrollBarPolicy(Qt.ScrollBarAlwaysOff)
    sc.setFrameShape(QFrame.NoFrame)
    extra = sc.verticalScrollBar().sizeHint().width()
    sc.setMinimumWidth(side.minimumWidth() + extra)
    if side.maximumWidth() < 16777215:
        sc.setMaximumWidth(side.maximumWidth() + extra)
    return sc


def normalized(img: np.ndarray, lo_pct: float = 1.0, hi_pct: float = 99.0) -> np.ndarray:
    """Grey levels scaled to [0, 1] between two percentiles (robust to speckle outliers)."""
    a = np.asarray(img, float)
    finite = a[np.isfinite(a)]
    if finite.size == 0:
        return np.zeros_like(a)
    lo, hi = np.percentile(finite, [lo_pct, hi_pct])
    if hi <= lo:
        hi = lo + 1.0
    return np.clip((a - lo) / (hi - lo), 0.0, 1.0)


def red_green(target: np.ndarray, source: np.ndarray) -> np.ndarray:
    """The subtraction view: target in red, source in green; where they agree the pixel turns yellow."""
    t, s = normalized(target), normalized(source)
    rgb = np.zeros(t.shape + (3,), np.uint8)
    rgb[..., 0] = np.round(255 * t)
    rgb[..., 1] = np.round(255 * s)
    return rgb


def diverging_lut(n: int = 256) -> np.ndarray:
    """Blue - white - red lookup table (n, 3) uint8 for signed differences."""
    x = np.linspace(-1, 1, n)
    r = np.where(x < 0, 1 + x, 1.0)
    b = np.where(x > 0, 1 - x, 1.0)
    g = 1 - np.abs(x)
    lut = np.stack([r, g, b], axis=1)
    lut = 0.15 + 0.85 * lut  # keep the ends from going black
    return np.round(255 * np.clip(lut, 0, 1)).astype(np.uint8)
