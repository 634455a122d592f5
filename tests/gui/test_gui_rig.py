"""Rig panel against the simulated rig on virtual serial ports, in real time."""

from __future__ import annotations

import numpy as np
import pytest
from lateness import TimerLateness

from app.devices.sim import ptys_available


def _connected(win, qtbot):
    panel = win.rig_panel
    win.raise_panel("rig")
    panel.sim_button.click()
    qtbot.waitUntil(lambda: win.rig.status.connected and "GRBL" in panel.conn_state.text()
                    and panel.up_button.isEnabled(), timeout=20_000)
    return panel


def _wait_op(win, qtbot, events, name, timeout_ms=30_000):
    qtbot.waitUntil(lambda: any(k in ("finished", "failed") and p[0] == name for k, p in events), timeout=timeout_ms)
    return next(p for k, p in events if k in ("finished", "failed") and p[0] == name)


@pytest.fixture
def rig_window(make_window):
    # the simulated rig is served on pseudo-terminals: a machine without them cannot run these tests
    assert ptys_available(), "pseudo-terminals are not available"
    return make_window()


def test_live_force_at_100_hz_drawn_at_25_hz(rig_window, qtbot):
    win = rig_window
    panel = _connected(win, qtbot)
    assert "simulated" in panel.conn_state.text().lower()
    assert panel.stage_port.currentText().startswith(("/dev/", "socket://"))
    # measure the event loop while the 100 Hz stream is drawn
    timer = TimerLateness()
    timer.start()
    qtbot.wait(1500)
    lateness = timer.stop()
    # the ranges follow the data by steps (their cost: bench/live_plot.py); a user's zoom
    # stays, and the plot's "A" button hands the range back to the data
    vb = panel.pt.getViewBox()
    vb.setYRange(5.0, 6.0, padding=0)  # away from the force (about 0 N)
    qtbot.wait(300)
    assert vb.viewRange()[1] == pytest.approx([5.0, 6.0])
    vb.enableAutoRange(axis=vb.YAxis)
    qtbot.wait(300)
    lo, hi = vb.viewRange()[1]
    assert lo < panel.controller.status.force_N < hi and hi - lo < 1.0 and not vb.state["autoRange"][1]
    data = win.rig.buffer.snapshot()
    assert len(data) >= 100
    rate = 1.0 / np.median(np.diff(data[-100:, 0]))
    assert 80 <= rate <= 120
    x, y = panel.curve_t.getData()
    assert x is not None and len(x) >= 100  # the timer drew the buffer
    assert panel.force_label.text() != "--"
    assert np.percentile(lateness, 95) <= 50.0


def test_jog_contact_protocol_and_open_the_recording(rig_window, qtbot, tmp_path):
    win = rig_window
    panel = _connected(win, qtbot)
    events = []
    panel.worker.rig_event.connect(lambda k, p: events.append((k, p)))
    panel.step_box.setCurrentIndex(panel.step_box.findData(1.0))
    panel.down_button.click()
    _wait_op(win, qtbot, events, "jog")
    assert win.rig.status.travel_mm == pytest.approx(1.0, abs=0.05)
    panel.contact_button.click()
    kind_payload = _wait_op(win, qtbot, events, "contact")
    assert win.rig.status.contact_mm == pytest.approx(2.0, abs=0.2), kind_payload  # the simulated gap is 2 mm
    assert panel.pd.getAxis("bottom").labelText.startswith("displacement")
    panel.depth_spin.setValue(1.0)
    panel.speed.setValue(2.0)
    panel.hold.setValue(0.2)
    panel.frames_at.setText("0, 0.5, 1")
    out = tmp_path / "recording"
    panel.out_folder.setText(str(out))
    panel.run_button.click()
    _, result = _wait_op(win, qtbot, events, "run", 40_000)
    assert result.ok, result.message
    assert result.frames == 3 and result.samples > 50
    assert "completed" in panel.run_state.text()
    assert panel.open_button.isEnabled()
    panel.open_button.click()
    assert win.session.has_experiment and len(win.session.experiment.frames) == 3
    assert win.session.experiment.path == out


def test_stop_halts_a_move_at_once(rig_window, qtbot):
    win = rig_window
    panel = _connected(win, qtbot)
    events = []
    panel.worker.rig_event.connect(lambda k, p: events.append((k, p)))
    panel.step_box.setCurrentIndex(panel.step_box.findData(5.0))
    panel.jog_speed.setValue(1.0)
    panel.down_button.click()
    qtbot.waitUntil(lambda: win.rig.status.travel_mm > 0.3, timeout=10_000)
    win.stop_button.click()  # the toolbar STOP
    name, exc = _wait_op(win, qtbot, events, "jog", 10_000)
    from app.devices.errors import EmergencyStop

    assert isinstance(exc, EmergencyStop)
    qtbot.wait(300)
    travel = win.rig.status.travel_mm
    assert travel < 2.0  # far from the 5 mm target
    qtbot.wait(500)
    assert win.rig.status.travel_mm == pytest.approx(travel, abs=0.02)  # and it stays there
    assert "emergency stop" in win.rig.status.message.lower()
    assert not win.error_boxes  # a stop the user asked for is not an error
    # the stream resumes after the stop
    n = win.rig.buffer.generation
    qtbot.waitUntil(lambda: win.rig.buffer.generation > n + 20, timeout=5_000)


def test_keyboard_jog_and_esc_stop_are_bound(rig_window):
    win = rig_window
    keys = {a.shortcut().toString() for a in [win.act_stop]}
    assert "Esc" in keys
    from PySide6.QtGui import QShortcut

    seqs = {sc.key().toString() for sc in win.rig_panel.findChildren(QShortcut)}
    assert {"Ctrl+Up", "Ctrl+Down", "Ctrl+K"} <= seqs


def test_a_port_that_does_not_exist_is_reported(window, qtbot):
    panel = window.rig_panel
    window.raise_panel("rig")
    panel.stage_port.setCurrentText("/dev/elastoid-no-such-port")
    panel.force_port.setCurrentText("/dev/elastoid-no-such-port-2")
    panel.connect_button.click()
    qtbot.waitUntil(lambda: bool(window.error_boxes), timeout=10_000)
    text = window.error_boxes[-1].informativeText()
    assert "/dev/elastoid-no-such-port" in text and "cannot open port" in text
    assert not window.rig.status.connected


def test_real_ports_with_a_scanner_folder(rig_window, qtbot, tmp_path):
    """Connect by port names (here the simulated rig's own ports) with frames from an export folder."""
    from app.devices.sim import SimRig

    sim = SimRig()
    server = sim.serve()
    try:
        scans = tmp_path / "scans"
        scans.mkdir()
        win = rig_window
        panel = win.rig_panel
        panel.stage_port.setCurrentText(server.urls["stage"])
        panel.force_port.setCurrentText(server.urls["force"])
        panel.image_folder.setText(str(scans))
        panel.connect_button.click()
        qtbot.waitUntil(lambda: "GRBL" in panel.conn_state.text(), timeout=20_000)
        assert str(scans) in panel.conn_state.text()
        assert win.rig.rig.images is not None and not win.rig.status.simulated
    finally:
        rig_window.rig.disconnect()
        qtbot.waitUntil(lambda: not rig_window.rig.status.connected, timeout=10_000)
        sim.stop()


def test_steady_range_moves_only_when_the_data_leave_it_or_shrink():
    from app.gui.panels.rig import steady_range

    first = steady_range(None, 0.0, 1.0, 0.05)
    assert first == pytest.approx((-0.1, 1.1))  # 10% margins
    assert steady_range(first, 0.02, 0.98, 0.05) is None  # noise inside: no change
    assert steady_range(first, 0.5, 0.9, 0.05) is None  # a third or more of it still used
    grown = steady_range(first, 0.0, 1.5, 0.05)
    assert grown[0] <= 0.0 and grown[1] >= 1.5  # the data left it: it grows
    shrunk = steady_range(first, 0.40, 0.42, 0.05)
    assert shrunk is not None and shrunk[1] - shrunk[0] == pytest.approx(1.2 * 0.05)  # at least min_span
    assert steady_range(first, float("nan"), 1.0, 0.05) is None
