"""The welcome page: three ways to start."""

from __future__ import annotations

from pathlib import Path

from PySide6.QtCore import Qt, Signal
from PySide6.QtWidgets import QFrame, QHBoxLayout, QLabel, QPushButton, QVBoxLayout, QWidget

from app import __version__


class WelcomePage(QWidget):
    open_demo = Signal()
    run_demo = Signal()  # open the demo and identify it: one click to a result
    start_rig = Signal()
    open_folder = Signal()
    open_recent = Signal(str, str)  # (kind "experiment" | "session", path)

    def __init__(self, demo_available: bool, parent=None):
        super().__init__(parent)
        self.setObjectName("welcome")
        self.setStyleSheet("""
            QWidget#welcome { background: #f4f5f7; }
            QFrame#card { background: white; border: 1px solid #d3d7de; border-radius: 6px; }
            QLabel#title { font-size: 20pt; font-weight: 700; color: #1b2a44; }
            QLabel#subtitle { font-size: 11pt; color: #44506a; }
            QLabel#cardtitle { font-size: 12pt; font-weight: 600; color: #1b2a44; }
            QLabel#cardtext { color: #5b6478; }
        """)
        outer = QVBoxLayout(self)
        outer.addStretch(1)
        title = QLabel("ElastoID")
        title.setObjectName("title")
        title.setAlignment(Qt.AlignCenter)
        sub = QLabel("Young's modulus of each tissue region from a robotic ultrasound indentation")
        sub.setObjectName("subtitle")
        sub.setAlignment(Qt.AlignCenter)
        outer.addWidget(title)
        outer.addWidget(sub)
        outer.addSpacing(24)
        row = QHBoxLayout()
        row.addStretch(1)
        self.run_demo_button = self._card(row, "Run the demo",
                                          "A synthetic twin of the paper phantom with a stiff inclusion. One click "
                                          "opens it and identifies both moduli; or open it to go step by step.",
                                          "Run the demo", self.run_demo)
        self.run_demo_button.setToolTip("Open the demo experiment and run the identification (the paper's six "
                                        "starts); the result appears in the Identification panel")
        self.demo_button = QPushButton("Open demo only")
        self.demo_button.setToolTip("Open the demo experiment without running anything")
        self.demo_button.clicked.connect(self.open_demo.emit)
        self.run_demo_button.parentWidget().layout().addWidget(self.demo_button)
        for b in (self.run_demo_button, self.demo_button):
            b.setEnabled(demo_available)
            if not demo_available:
                b.setToolTip("The demo experiment is not installed (resources/demo)")
        self.rig_button = self._card(row, "Start the simulated rig",
                                     "A simulated stage and force sensor: jog, find contact and record an "
                                     "indentation without hardware.", "Start simulated rig", self.start_rig)
        self.folder_button = self._card(row, "Open an experiment folder",
                                        "A folder with experiment.toml, force.csv and images/ "
                                        "(from the rig or your own recordings).", "Open folder...", self.open_folder)
        row.addStretch(1)
        outer.addLayout(row)
        outer.addSpacing(14)
        self.recent_box = QVBoxLayout()
        self.recent_box.setAlignment(Qt.AlignHCenter)
        outer.addLayout(self.recent_box)
        outer.addSpacing(14)
        foot = QLabel(f"Version {__version__}. ElastoID never changes an experiment folder; your work is saved as a "
                      f"session file.")
        foot.setObjectName("cardtext")
        foot.setAlignment(Qt.AlignCenter)
        outer.addWidget(foot)
        outer.addStretch(2)

    def set_recent(self, items: list[tuple[str, Path]]) -> None:
        """Links to the last experiments and sessions that still exist."""
        while self.recent_box.count():
            w = self.recent_box.takeAt(0).widget()
            if w is not None:
                w.deleteLater()
        items = [(k, p) for k, p in items if p.exists()][:5]
        if not items:
            return
        head = QLabel("Recent")
        head.setObjectName("cardtitle")
        head.setAlignment(Qt.AlignCenter)
        self.recent_box.addWidget(head)
        for kind, path in items:
            b = QPushButton(f"{path.name}   ({'session' if kind == 'session' else 'experiment'}, {path.parent})")
            b.setFlat(True)
            b.setCursor(Qt.PointingHandCursor)
            b.setStyleSheet("QPushButton { color: #1f5fa8; text-align: center; } "
                            "QPushButton:hover { text-decoration: underline; }")
            b.clicked.connect(lambda _=False, k=kind, p=str(path): self.open_recent.emit(k, p))
            self.recent_box.addWidget(b)

    def _card(self, row, title: str, text: str, button: str, signal) -> QPushButton:
        card = QFrame()
        card.setObjectName("card")
        card.setFixedWidth(260)
        lay = QVBoxLayout(card)
        lay.setContentsMargins(16, 14, 16, 14)
        t = QLabel(title)
        t.setObjectName("cardtitle")
        t.setWordWrap(True)
        d = QLabel(text)
        d.setObjectName("cardtext")
        d.setWordWrap(True)
        d.setMinimumHeight(60)
        b = QPushButton(button)
        b.setObjectName("primary")
        b.clicked.connect(signal.emit)
        lay.addWidget(t)
        lay.addWidget(d, 1)
        lay.addWidget(b)
        row.addWidget(card)
        return b
