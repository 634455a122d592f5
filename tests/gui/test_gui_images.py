"""Images panel: frames, ROI by mouse (handles and drawing) and by typing, overlay views."""

from __future__ import annotations

import numpy as np
from PySide6.QtCore import QEvent, QPointF, Qt
from PySide6.QtGui import QMouseEvent
from PySide6.QtWidgets import QApplication


def _mouse(widget, kind, pos: QPointF, buttons, button=Qt.NoButton):
    ev = QMouseEvent(kind, pos, widget.mapToGlobal(pos), button, buttons, Qt.NoModifier)
    QApplication.sendEvent(widget, ev)


def drag_on_image(panel, qtbot, start_px, end_px, steps: int = 8):
    """A left-button drag on the image between two (column, row) pixel positions."""
    view = panel.graphics
    vp = view.viewport()

    def at(c, r):
        return QPointF(view.mapFromScene(panel.vb.mapViewToScene(QPointF(c, r))))

    p0, p1 = at(*start_px), at(*end_px)
    _mouse(vp, QEvent.MouseButtonPress, p0, Qt.LeftButton, Qt.LeftButton)
    for k in range(1, steps + 1):
        p = p0 + (p1 - p0) * (k / steps)
        _mouse(vp, QEvent.MouseMove, p, Qt.LeftButton)
        qtbot.wait(5)
    _mouse(vp, QEvent.MouseButtonRelease, p1, Qt.NoButton, Qt.LeftButton)
    qtbot.wait(20)


def test_typed_roi_is_exact(window, noise_experiment, qtbot):
    window.open_experiment(noise_experiment)
    panel = window.images_panel
    spin = panel.spins["col0"]
    spin.setFocus()
    spin.lineEdit().selectAll()
    qtbot.keyClicks(spin.lineEdit(), "17")
    qtbot.keyClick(spin.lineEdit(), Qt.Key_Return)
    assert window.session.roi_px == (17, 8, 110, 90)
    panel.spins["row1"].setValue(61)
    panel.spins["row1"].editingFinished.emit()
    assert window.session.roi_px == (17, 8, 110, 61)
    assert panel.roi_from_view() == (17, 8, 110, 61)  # the rectangle on the image follows
    assert "93 x 53 px" in panel.roi_size.text()


def test_roi_is_clamped_to_the_image(window, noise_experiment):
    window.open_experiment(noise_experiment)
    panel = window.images_panel
    panel.spins["col1"].setValue(120)
    panel.spins["col0"].setValue(119)
    panel.spins["col0"].editingFinished.emit()
    c0, r0, c1, r1 = window.session.roi_px
    assert c1 == 120 and c0 <= 118 and c1 - c0 >= 2


def test_roi_dragged_by_its_handles(window, noise_experiment, qtbot):
    window.open_experiment(noise_experiment)
    panel = window.images_panel
    roi = panel.roi
    roi.setPos([30.4, 20.2], finish=False)
    roi.setSize([40.0, 30.0], finish=True)  # what releasing a handle does
    assert window.session.roi_px == (30, 20, 70, 50)
    assert panel.spins["col0"].value() == 30 and panel.spins["row1"].value() == 50


def test_roi_drawn_with_the_mouse(window, noise_experiment, qtbot):
    window.open_experiment(noise_experiment)
    panel = window.images_panel
    window.raise_panel("images")
    qtbot.wait(50)
    panel.draw_button.setChecked(True)
    drag_on_image(panel, qtbot, (20, 15), (80, 70))
    c0, r0, c1, r1 = window.session.roi_px
    assert abs(c0 - 20) <= 1 and abs(r0 - 15) <= 1 and abs(c1 - 80) <= 1 and abs(r1 - 70) <= 1
    assert not panel.draw_button.isChecked()  # one rectangle per click on Draw ROI
    assert panel.spins["col1"].value() == c1


def test_views_and_frames(window, noise_experiment):
    window.open_experiment(noise_experiment)
    panel = window.images_panel
    for mode in ("source", "target", "overlay", "difference"):
        panel.set_mode(mode)
        img = panel.image.image
        assert img is not None and img.shape[:2] == (100, 120)
    panel.set_mode("overlay")
    assert panel.image.image.ndim == 3  # red/green
    panel.target_box.setCurrentIndex(1)
    assert window.session.target_frame == 1
    assert "NMI in the ROI" in panel.nmi_label.text()


def test_model_overlay_is_shown_inside_the_roi(window, noise_experiment):
    window.open_experiment(noise_experiment)
    s = window.session
    c0, r0, c1, r1 = s.roi_px
    tgt = s.frame(s.target_frame)[r0:r1, c0:c1]
    mask = np.ones(tgt.shape, bool)
    mask[:5] = False
    s.set_overlay((tgt.copy(), tgt, s.roi_px, mask))
    panel = window.images_panel
    panel.set_mode("overlay")
    assert "warped by the identified model" in panel.legend.text()
    assert "2.0000" in panel.nmi_label.text() or "1.99" in panel.nmi_label.text()  # warped == target inside the mask
