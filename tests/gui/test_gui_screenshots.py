"""Screenshots of every panel after a real session (look at them: tests/gui/screenshots/)."""

from __future__ import annotations

from dataclasses import replace

import pytest
from conftest import SCREENSHOTS, TEST_MESH, wait_task_done

from app.devices.sim import ptys_available


def _save(widget_or_pixmap, name: str):
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    pm = widget_or_pixmap if hasattr(widget_or_pixmap, "save") else widget_or_pixmap.grab()
    path = SCREENSHOTS / f"{name}.png"
    assert pm.save(str(path)), path
    assert path.stat().st_size > 5_000
    return path


@pytest.mark.view3d
def test_screenshots_of_every_panel(make_window, tiny_experiment, qtbot, tmp_path):
    win = make_window(enable_3d=None)
    win.resize(1500, 950)
    qtbot.wait(100)
    _save(win, "00_welcome")

    win.open_experiment(tiny_experiment)
    s = win.session
    s.set_mesh_settings(replace(s.effective_mesh_settings(), **TEST_MESH))
    s.set_identification(replace(s.identification, starts_kPa=(10.0, 30.0, 60.0), max_evaluations=60,
                                 cost="joint"))
    panel = win.identification_panel
    win.raise_panel("identification")
    panel.run()
    wait_task_done(qtbot, panel, 180)
    assert s.outcome is not None, [b.informativeText() for b in win.error_boxes]
    qtbot.wait(100)
    _save(win.identification_panel, "03_identification")
    _save(win, "10_window_after_identification")

    win.raise_panel("images")
    win.images_panel.set_mode("overlay")
    qtbot.wait(50)
    _save(win.images_panel, "01_images_overlay")
    win.images_panel.set_mode("difference")
    qtbot.wait(50)
    _save(win.images_panel, "01_images_difference")
    win.images_panel.set_mode("overlay")

    win.raise_panel("mesh")
    qtbot.wait(200)
    win.mesh_panel._redraw()
    _save(win.mesh_panel.grab_with_3d(), "02_mesh_deformed")

    win.raise_panel("log")
    from PySide6.QtCore import Qt

    win.resizeDocks([win.docks["log"]], [260], Qt.Vertical)
    qtbot.wait(50)
    _save(win.log_panel, "05_log")

    if ptys_available():
        rig = win.rig_panel
        win.raise_panel("rig")
        rig.use_twin.setChecked(False)  # a generic specimen: the twin would mesh for half a minute
        rig.start_simulated()
        qtbot.waitUntil(lambda: rig.up_button.isEnabled() and "GRBL" in rig.conn_state.text(), timeout=20_000)
        events = []
        rig.worker.rig_event.connect(lambda k, p: events.append((k, p)))
        rig.find_contact()
        qtbot.waitUntil(lambda: any(k != "started" and p[0] == "contact" for k, p in events), timeout=30_000)
        rig.depth_spin.setValue(2.0)
        rig.speed.setValue(1.0)
        rig.hold.setValue(1.5)
        rig.frames_at.setText("0, 1, 2")
        rig.out_folder.setText(str(tmp_path / "rec"))
        rig.run_protocol()
        qtbot.waitUntil(lambda: any(k != "started" and p[0] == "run" for k, p in events), timeout=60_000)
        qtbot.wait(300)
        _save(rig, "04_rig")
