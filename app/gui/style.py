"""Look and feel: one light, plain style for every panel and plot."""

from __future__ import annotations

import pyqtgraph as pg
from PySide6.QtGui import QColor, QFont, QPalette
from PySide6.QtWidgets import QApplication

# one colour per region, in paint order (background first); colour-blind friendly (Okabe-Ito)
REGION_COLORS = ["#b8c4d6", "#d55e00", "#0072b2", "#009e73", "#cc79a7", "#e69f00", "#56b4e9", "#f0e442"]
START_COLORS = ["#0072b2", "#d55e00", "#009e73", "#cc79a7", "#e69f00", "#56b4e9", "#000000", "#f0e442"]
ACCENT = "#1f5fa8"
STOP_RED = "#c62828"
# measured and modelled force: the model dashed over the measured curve (a model that
# fits hid a solid one), both named in the plot's title (a legend box hid the curves
# in these short plots)
MEASURED_GREY, MODEL_ORANGE = "#555555", "#d55e00"
FORCE_KEY = (f"<span style='color:{MEASURED_GREY}'>measured</span> and "
             f"<span style='color:{MODEL_ORANGE}'>model (dashed)</span>")


def force_pens():
    """(measured, model) pens of the force plots."""
    import pyqtgraph as pg
    from PySide6.QtCore import Qt

    return pg.mkPen(MEASURED_GREY, width=1.5), pg.mkPen(MODEL_ORANGE, width=2, style=Qt.DashLine)


def region_color(index: int) -> str:
    return REGION_COLORS[index % len(REGION_COLORS)]


def start_color(index: int) -> str:
    return START_COLORS[index % len(START_COLORS)]


def style_plot(plot, *, grid: bool = True) -> None:
    """A light grid on the major ticks only (minor-tick grids cost most of a plot's paint time)."""
    if grid:
        plot.showGrid(x=True, y=True, alpha=0.22)
    for name in ("left", "bottom"):
        plot.getAxis(name).setStyle(maxTickLevel=0 if grid else 1)
    # every axis, the hidden top and right ones too: with an SI prefix an axis sets its
    # label's HTML again at every range change (each frame of a live plot)
    for name in ("left", "bottom", "top", "right"):
        plot.getAxis(name).enableAutoSIPrefix(False)


def configure_pyqtgraph() -> None:
    pg.setConfigOptions(imageAxisOrder="row-major", background="w", foreground="#222222", antialias=True)


def apply_style(app: QApplication) -> None:
    app.setStyle("Fusion")
    pal = QPalette()
    pal.setColor(QPalette.Window, QColor("#f4f5f7"))
    pal.setColor(QPalette.Base, QColor("#ffffff"))
    pal.setColor(QPalette.AlternateBase, QColor("#f0f2f5"))
    pal.setColor(QPalette.Button, QColor("#eceef1"))
    pal.setColor(QPalette.Highlight, QColor(ACCENT))
    pal.setColor(QPalette.HighlightedText, QColor("#ffffff"))
    pal.setColor(QPalette.ToolTipBase, QColor("#ffffe8"))
    app.setPalette(pal)
    f = app.font()
    if f.pointSizeF() < 9.5:
        f.setPointSizeF(9.5)
    app.setFont(f)
    app.setStyleSheet(STYLESHEET)
    configure_pyqtgraph()


STYLESHEET = f"""
QGroupBox {{ font-weight: 600; border: 1px solid #d3d7de; border-radius: 4px; margin-top: 10px; padding-top: 6px; }}
QGroupBox::title {{ subcontrol-origin: margin; left: 8px; padding: 0 3px; color: #33415c; }}
QDockWidget::title {{ background: #e3e7ee; padding: 4px 6px; font-weight: 600; color: #22304a; }}
QPushButton#primary {{ background: {ACCENT}; color: white; border: 1px solid #174a86; border-radius: 3px;
    padding: 4px 14px; font-weight: 600; }}
QPushButton#primary:disabled {{ background: #9fb3cc; border-color: #9fb3cc; }}
QToolButton#estop, QPushButton#estop {{ background: {STOP_RED}; color: white; font-weight: 800; font-size: 13pt;
    border: 2px solid #8e0000; border-radius: 5px; padding: 4px 18px; }}
QToolButton#estop:pressed, QPushButton#estop:pressed {{ background: #8e0000; }}
QLabel#hint {{ color: #5b6478; }}
QLabel#big {{ font-size: 15pt; font-weight: 600; color: #1b2a44; font-family: monospace; }}
QLabel#unit {{ color: #5b6478; }}
QPlainTextEdit#report {{ font-family: monospace; }}
"""


def mono_font() -> QFont:
    f = QFont("DejaVu Sans Mono")
    f.setStyleHint(QFont.Monospace)
    return f
