"""The main window: welcome page, opening experiments, errors, sessions, recent files, layout."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import folder_digest
from PySide6.QtCore import QSettings


def test_main_is_exposed():
    import app.gui

    assert callable(app.gui.main)
    from app.gui.mainwindow import demo_path

    assert demo_path() == Path(__file__).resolve().parents[2] / "resources" / "demo"


def test_welcome_then_open_experiment(window, noise_experiment, qtbot):
    assert window.welcome.isVisible()
    assert not window.docks["images"].isVisible()
    assert window.welcome.folder_button.isEnabled() and window.welcome.rig_button.isEnabled()
    assert window.open_experiment(noise_experiment)
    assert not window.welcome.isVisible()
    assert window.docks["images"].isVisible()
    assert "Noise frames (test)" in window.windowTitle()
    assert window.session.roi_px == (10, 8, 110, 90)  # the experiment's own ROI
    assert window.images_panel.source_box.count() == 3


def test_bad_folder_error_names_file_and_field(window, tmp_path):
    bad = tmp_path / "bad"
    (bad / "images").mkdir(parents=True)
    (bad / "experiment.toml").write_text('format = "elastoid-experiment/1"\nname = "x"\n[specimen]\n'
                                         'size_mm = [1, 2]\n', encoding="utf-8")
    assert not window.open_experiment(bad)
    box = window.error_boxes[-1]
    text = box.informativeText()
    assert "experiment.toml" in text and "specimen.size_mm" in text
    assert "3 numbers" in text
    assert window.welcome.isVisible()  # nothing was opened


def test_session_round_trip_never_touches_the_experiment(make_window, noise_experiment, tmp_path):
    before = folder_digest(noise_experiment)
    win = make_window()
    win.open_experiment(noise_experiment)
    s = win.session
    s.set_roi((12, 10, 100, 80))
    s.set_frames(0, 1)
    from dataclasses import replace

    s.set_mesh_settings(replace(s.effective_mesh_settings(), edge_mm=7.5))
    win.mesh_panel._add_region()
    path = tmp_path / "work.json"
    assert win._save_to(path)
    d = json.loads(path.read_text())
    assert d["format"] == "elastoid-session/1"
    assert Path(d["experiment"]) == Path(noise_experiment).resolve()
    assert d["roi_px"] == [12, 10, 100, 80] and d["mesh_settings"]["edge_mm"] == 7.5
    assert [r["name"] for r in d["specimen_regions"]] == ["B", "A", "C"]

    other = make_window()
    assert other.open_session(path)
    s2 = other.session
    assert s2.roi_px == (12, 10, 100, 80)
    assert (s2.source_frame, s2.target_frame) == (0, 1)
    assert s2.mesh_settings.edge_mm == 7.5
    assert s2.specimen.region_names == ("B", "A", "C")
    assert other.images_panel.spins["col1"].value() == 100
    assert folder_digest(noise_experiment) == before
    kinds = [k for k, _ in other.recent_items()]
    assert "session" in kinds and "experiment" in kinds


def test_session_inside_experiment_is_refused(window, noise_experiment):
    window.open_experiment(noise_experiment)
    before = folder_digest(noise_experiment)
    assert not window._save_to(Path(noise_experiment) / "session.json")
    assert folder_digest(noise_experiment) == before
    assert "not saved inside the experiment folder" in window.error_boxes[-1].informativeText()


def test_layout_is_saved_and_restored(make_window, noise_experiment):
    win = make_window(restore_layout=True)
    win.open_experiment(noise_experiment)
    win.docks["log"].hide()
    win.close()
    assert QSettings().value("window/state") is not None
    again = make_window(restore_layout=True)
    again.open_experiment(noise_experiment)
    assert not again.docks["log"].isVisible()
    assert again.docks["images"].isVisible()
    again.reset_layout()
    assert again.docks["log"].isVisible()


def test_demo_opens(window):
    from app.gui.mainwindow import demo_path

    assert (demo_path() / "experiment.toml").is_file()  # the demo ships with the project
    window.open_demo()
    assert window.session.has_experiment, [b.informativeText() for b in window.error_boxes]
    assert window.session.reference_kPa() == {"E_A_kPa": 63.0, "E_B_kPa": 18.0}


def test_main_opens_the_folder_given_and_returns_the_exit_code(noise_experiment, tmp_path):
    """``app.gui.main(argv)`` in a fresh process: it shows the window with the experiment open."""
    import os
    import subprocess
    import sys

    script = tmp_path / "run_main.py"
    script.write_text(
        "import sys\n"
        "from PySide6.QtCore import QTimer\n"
        "from PySide6.QtWidgets import QApplication\n"
        "qapp = QApplication(sys.argv[:1])\n"
        "def check():\n"
        "    wins = [w for w in QApplication.topLevelWidgets() if w.objectName() == 'ElastoIDMainWindow']\n"
        "    print('TITLE', wins[0].windowTitle() if wins else None, flush=True)\n"
        "    for w in wins: w.close()\n"
        "    qapp.exit(7)\n"
        "QTimer.singleShot(1500, check)\n"
        "import app.gui\n"
        "sys.exit(app.gui.main([sys.argv[1]]))\n", encoding="utf-8")
    root = Path(__file__).resolve().parents[2]
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen", ELASTOID_NO_3D="1", PYTHONPATH=str(root),
               XDG_CONFIG_HOME=str(tmp_path / "config"), HOME=str(tmp_path))
    r = subprocess.run([sys.executable, str(script), str(noise_experiment)], cwd=root, env=env,
                       capture_output=True, text=True, timeout=120)
    assert "TITLE ElastoID - Noise frames (test)" in r.stdout, r.stdout + r.stderr
    assert r.returncode == 7


def test_welcome_lists_recent_experiments(make_window, noise_experiment):
    first = make_window()
    first.open_experiment(noise_experiment)
    first.close()
    win = make_window()
    from PySide6.QtWidgets import QPushButton

    links = [b for b in win.welcome.findChildren(QPushButton) if "experiment," in b.text()]
    assert links and Path(noise_experiment).name in links[0].text()
    links[0].click()
    assert win.session.has_experiment and not win.welcome.isVisible()


def test_mesh_and_identification_choices_are_remembered(make_window, noise_experiment):
    from dataclasses import replace

    win = make_window()
    win.open_experiment(noise_experiment)
    s = win.session
    s.set_mesh_settings(replace(s.effective_mesh_settings(), edge_mm=6.5))
    s.set_identification(replace(s.identification, starts_kPa=(15.0, 45.0), cost="joint"))
    win.close()
    again = make_window()
    again.open_experiment(noise_experiment)
    assert again.session.mesh_settings.edge_mm == 6.5
    assert again.session.identification.starts_kPa == (15.0, 45.0)
    assert again.session.identification.cost == "joint"
    assert [p.name for p in again.session.identification.parameters] == ["E_B_kPa", "E_A_kPa"]
    assert again.identification_panel.starts_edit.text() == "15, 45"


def test_run_the_demo_with_one_click(window, qtbot):
    """The welcome page offers the demo, the simulated rig and a folder; one click on Run the demo
    opens the demo and identifies it (default settings: the paper's six starts) to within 5% of its truth."""
    import tomllib

    from conftest import wait_task_done
    from PySide6.QtCore import Qt

    from app.gui.mainwindow import demo_path

    w = window.welcome
    assert w.isVisible()
    for b in (w.run_demo_button, w.demo_button, w.rig_button, w.folder_button):
        assert b.isVisible() and b.isEnabled()
    qtbot.mouseClick(w.run_demo_button, Qt.LeftButton)  # the one click
    panel = window.identification_panel
    assert window.session.has_experiment and not w.isVisible() and panel.running
    assert window.docks["identification"].isVisible()
    wait_task_done(qtbot, panel, 400)
    assert not window.error_boxes, [b.informativeText() for b in window.error_boxes]
    out = window.session.outcome
    assert out is not None, panel.state.text()
    truth = tomllib.loads((demo_path() / "truth.toml").read_text(encoding="utf-8"))["moduli_kPa"]
    for region, modulus in truth.items():
        assert out.parameters[f"E_{region}_kPa"] == pytest.approx(modulus, rel=0.05), (region, out.parameters)
    assert len(out.starts) == 6  # the paper's starts, untouched
    assert "Identifiability" in panel.report.toPlainText()


def test_busy_bars_step_twice_a_second_instead_of_animating(window, qtbot):
    """Qt's busy animation (a progress bar's range 0..0) repaints about 55 times a
    second, and each repaint composes the whole window, OpenGL view included: on
    software OpenGL two such bars took 44 CPU-seconds of an 87-second diagnosis.
    The window's busy bars step every PULSE_MS instead."""
    from PySide6.QtCore import QEvent, QObject

    from app.gui.panels.common import PULSE_MS, PULSE_STEPS, BusyBar

    assert isinstance(window.progress, BusyBar) and isinstance(window.modelcheck_panel.progress, BusyBar)
    bar = BusyBar()
    qtbot.addWidget(bar)
    bar.show()
    paints, values = [0], set()

    class Count(QObject):
        def eventFilter(self, obj, ev):
            if obj is bar and ev.type() == QEvent.Paint:
                paints[0] += 1
            return False

    counter = Count()
    bar.installEventFilter(counter)
    bar.setRange(0, 0)
    assert bar.busy and bar.maximum() == PULSE_STEPS
    paints[0] = 0
    for _ in range(8):
        qtbot.wait(PULSE_MS // 2)
        values.add(bar.value())
    assert len(values) >= 3  # it moves
    assert paints[0] <= 2 * 2000 // PULSE_MS + 2, paints[0]  # 2 s: a few repaints, not ~110
    bar.hide()  # hidden (the status bar's when nothing runs, a panel in another tab): nothing to move
    held = bar.value()
    qtbot.wait(PULSE_MS + 100)
    assert bar.busy and bar.value() == held
    bar.show()
    qtbot.waitUntil(lambda: bar.value() != held, timeout=3 * PULSE_MS)
    bar.setRange(0, 4)  # a known total: a plain progress bar again
    bar.setValue(3)
    assert not bar.busy and bar.value() == 3
    qtbot.wait(PULSE_MS + 100)
    assert bar.value() == 3
