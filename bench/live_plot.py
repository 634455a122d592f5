"""The live force plot's cost on the GUI thread: the Rig panel drawing a 100 Hz stream at 25 Hz.

The window connects to the simulated rig (served on pseudo-terminals, as its
"Simulated rig" button does) and, for ``--seconds`` per run, the bench reads
two things. The first is the GUI thread's CPU time per second of wall time:
what is left for everything else a lab PC runs. The second is how late a
10 ms timer fires, which is what a user feels.

It compares two configurations side by side:

- steady: ElastoID's. The ranges move by steps (``steady_range``), no axis
  has an SI prefix, and labels are set only when they change.
- follow: pyqtgraph's defaults. Auto-range on both axes and an SI prefix on
  every axis, so each frame lays the axes and their labels out again.

It prints the medians over ``--repeats`` runs, with the two configurations
alternating.

    QT_QPA_PLATFORM=offscreen python bench/live_plot.py [--seconds 3] [--repeats 5]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def _configure(panel, mode: str) -> None:
    from app.gui.panels.rig import RigPanel

    follow = mode == "follow"
    for plot in (panel.pt, panel.pd):
        plot.enableAutoRange(x=True if plot is panel.pt else follow, y=follow)
        for name in ("left", "bottom", "top", "right"):
            plot.getAxis(name).enableAutoSIPrefix(follow)
    panel._ranges = {}
    if follow:
        panel._follow = lambda *a, **k: None
    else:
        panel._follow = RigPanel._follow.__get__(panel)


def _run(seconds: float) -> tuple[float, float, float]:
    """(GUI-thread CPU per wall second, median and 95th percentile lateness in ms) over one run."""
    import numpy as np
    from PySide6.QtCore import QEventLoop, QTimer

    from tests.gui.lateness import TimerLateness  # the GUI tests' measure

    timer = TimerLateness()
    loop = QEventLoop()
    QTimer.singleShot(int(seconds * 1000), loop.quit)
    cpu0, wall0 = time.thread_time(), time.perf_counter()
    timer.start()
    loop.exec()
    late = timer.stop()
    cpu, wall = time.thread_time() - cpu0, time.perf_counter() - wall0
    return cpu / wall, float(np.percentile(late, 50)), float(np.percentile(late, 95))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    os.environ.setdefault("ELASTOID_NO_3D", "1")
    from PySide6.QtCore import QCoreApplication, QEventLoop, QSettings
    from PySide6.QtWidgets import QApplication

    from app.gui.style import apply_style

    app = QApplication.instance() or QApplication([sys.argv[0]])
    app.setOrganizationName("ElastoID-bench")
    app.setApplicationName("ElastoID-bench")
    QSettings.setDefaultFormat(QSettings.IniFormat)
    apply_style(app)
    from app.gui.mainwindow import MainWindow

    win = MainWindow(restore_layout=False)
    win.resize(1400, 900)
    win.show()
    win.raise_panel("rig")
    panel = win.rig_panel
    panel.sim_button.click()
    t_end = time.perf_counter() + 30
    while not (win.rig.status.connected and panel.up_button.isEnabled()):
        QCoreApplication.processEvents(QEventLoop.AllEvents, 50)
        if time.perf_counter() > t_end:
            raise SystemExit("the simulated rig did not connect in 30 s")
    _run(1.0)  # the buffer fills, the first draws
    results = {"steady": [], "follow": []}
    for _ in range(args.repeats):
        for mode in results:
            _configure(panel, mode)
            results[mode].append(_run(args.seconds))
    win.close()
    print(f"Live force plot, Rig panel, simulated rig at 100 Hz drawn at 25 Hz; "
          f"{args.repeats} runs of {args.seconds:g} s each, medians; platform {os.environ['QT_QPA_PLATFORM']}")
    print(f"{'configuration':<46}{'GUI thread busy':>16}{'timer late p50':>16}{'p95':>8}")
    names = {"steady": "steady ranges, no SI prefix (ElastoID)", "follow": "auto-range, SI prefix (pyqtgraph defaults)"}
    for mode, rows in results.items():
        busy = statistics.median(r[0] for r in rows)
        p50 = statistics.median(r[1] for r in rows)
        p95 = statistics.median(r[2] for r in rows)
        print(f"{names[mode]:<46}{100 * busy:>15.1f}%{p50:>13.1f} ms{p95:>5.1f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
