"""The GUI's Qt-free models and the layering rules of app/gui."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

GUI = Path(__file__).resolve().parents[2] / "app" / "gui"


def test_ring_buffer_keeps_the_newest_rows_in_order():
    from app.gui.models.ringbuffer import RingBuffer

    rb = RingBuffer(5, 2)
    assert rb.snapshot().shape == (0, 2)
    rb.extend([[i, 10 * i] for i in range(3)])
    assert rb.snapshot()[:, 0].tolist() == [0, 1, 2]
    rb.extend([[i, 10 * i] for i in range(3, 8)])
    assert rb.snapshot()[:, 0].tolist() == [3, 4, 5, 6, 7]
    assert rb.snapshot(2)[:, 0].tolist() == [6, 7]
    rb.extend([[i, 0] for i in range(100, 120)])  # more than the capacity at once
    assert rb.snapshot()[:, 0].tolist() == [115, 116, 117, 118, 119]
    assert rb.generation == 28


def test_ring_buffer_from_a_writer_thread():
    from app.gui.models.ringbuffer import RingBuffer

    rb = RingBuffer(1000, 1)

    def write():
        for i in range(5000):
            rb.append(float(i))

    t = threading.Thread(target=write)
    t.start()
    while t.is_alive():
        snap = rb.snapshot()[:, 0]
        assert np.all(np.diff(snap) == 1.0)  # never a torn or unordered read
    t.join()
    assert rb.snapshot()[-1, 0] == 4999.0


def test_parse_starts():
    from app.gui.panels.identification import parse_starts

    assert parse_starts("10, 20 30;40") == (10.0, 20.0, 30.0, 40.0)
    for bad in ("", "10, x", "-5", "0"):
        with pytest.raises(ValueError):
            parse_starts(bad)


def test_session_json_and_bad_session_files(noise_experiment, tmp_path):
    from app.gui.models.session import SessionError, SessionModel

    s = SessionModel()
    s.open_experiment(noise_experiment)
    assert [p.name for p in s.identification.parameters] == ["E_B_kPa", "E_A_kPa"]
    assert s.analysis_frames() == (0, 1, 2)
    s.set_frames(0, 1)
    assert s.analysis_frames() == (0, 1, 2)  # every deformed frame by default
    from dataclasses import replace

    s.set_identification(replace(s.identification, all_frames=False))
    assert s.analysis_frames() == (0, 1)
    exp = s.analysis_experiment()
    assert exp.imaging.roi_px == s.roi_px and exp.path == Path(noise_experiment)
    path = s.save_session(tmp_path / "a.json")
    d = json.loads(path.read_text())
    assert d["identification"]["all_frames"] is False and d["result"] is None

    bad = tmp_path / "bad.json"
    bad.write_text("{not json", encoding="utf-8")
    with pytest.raises(SessionError, match="not valid JSON"):
        SessionModel().load_session(bad)
    bad.write_text(json.dumps({"format": "something/9"}), encoding="utf-8")
    with pytest.raises(SessionError, match="format"):
        SessionModel().load_session(bad)

    # frames at video rate (90 here, a 5 s ramp and a hold): thinned as the core's
    # default is (later_frames), with the chosen target and the deepest frame kept
    from app.core.experiment import Frame
    from app.core.identify import MAX_DEFAULT_FRAMES

    s.experiment = replace(s.experiment, frames=tuple(Frame(f"images/frame_{i:03d}.png", 0.1 * i, min(0.1 * i, 5.0))
                                                      for i in range(90)))
    s.set_identification(replace(s.identification, all_frames=True))
    s.set_frames(0, 37)
    got = s.analysis_frames()
    assert got[0] == 0 and 37 in got and 50 in got and list(got[1:]) == sorted(set(got[1:]))
    assert len(got) == MAX_DEFAULT_FRAMES, got


def test_models_are_qt_free():
    code = ("import sys; import app.gui.models.session, app.gui.models.rig, app.gui.models.identification, "
            "app.gui.models.ringbuffer; "
            "bad = [m for m in sys.modules if m.startswith(('PySide6', 'pyqtgraph', 'pyvistaqt'))]; "
            "print(bad); sys.exit(1 if bad else 0)")
    root = GUI.parents[1]
    r = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            mod = node.module or ""
            out.add("." * node.level + mod)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
    return out


def test_panels_never_import_each_other():
    panels = {p.stem for p in (GUI / "panels").glob("*.py")} - {"__init__", "base", "common"}
    for p in (GUI / "panels").glob("*.py"):
        for imp in _imports(p):
            target = imp.lstrip(".").split(".")[0] if imp.startswith(".") and not imp.startswith("..") else None
            assert target not in panels or target == p.stem, f"{p.name} imports panel {imp}"


def test_core_and_devices_never_import_the_gui():
    root = GUI.parent
    for layer in ("core", "devices"):
        for p in (root / layer).rglob("*.py"):
            for imp in _imports(p):
                assert not imp.startswith(("app.gui", "PySide6", "pyqtgraph", "pyvistaqt")), f"{p} imports {imp}"
