"""Identification panel: parameters (free/fixed, start, bounds, units), cost, starts,
Run and Cancel; live convergence (cost per evaluation, each parameter's path per
start with the reference dashed), the current overlay, and the identifiability report.

The computation runs in a :class:`~app.gui.workers.Task`; evaluations come back
through the job's queue, drawn by a timer, so a fast optimizer cannot flood the GUI.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import replace

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import Qt, QTimer
from PySide6.QtGui import QColor
from PySide6.QtWidgets import (QAbstractItemView, QCheckBox, QComboBox, QFormLayout, QGroupBox, QHBoxLayout,
                               QHeaderView, QLabel, QLineEdit, QPlainTextEdit, QProgressBar, QPushButton, QSplitter,
                               QTableWidget, QTableWidgetItem, QVBoxLayout, QWidget)

from ..models.identification import IdentificationJob, _accepts
from ..models.session import COSTS, IdentificationSettings, SessionModel
from ..style import FORCE_KEY, force_pens, mono_font, start_color, style_plot
from ..workers import Task
from .base import Panel
from .common import hint, ispin, red_green, scrolled, spin

log = logging.getLogger("elastoid.gui")

DRAW_PERIOD_MS = 150  # progress redraws: often enough to watch, rare enough to leave the GIL to the worker
COLS = ["Parameter", "Free", "Fixed at", "Bounds", "Unit", "Reference", "Identified", "\u00b1 s.e."]


def core_bounds_kPa() -> tuple[float, float]:
    try:
        from app.core.identify import BOUNDS_KPA

        return tuple(BOUNDS_KPA)
    except Exception:
        return (0.1, 1.0e4)


def parse_starts(text: str) -> tuple[float, ...]:
    """'10, 20 30;40' -> (10.0, 20.0, 30.0, 40.0); ValueError naming the bad entry."""
    parts = [p for p in text.replace(";", " ").replace(",", " ").split() if p]
    if not parts:
        raise ValueError("give at least one start value in kPa, e.g. 10, 20, 30")
    out = []
    for p in parts:
        try:
            v = float(p)
        except ValueError:
            raise ValueError(f"start {p!r} is not a number (kPa)") from None
        if not (v > 0 and math.isfinite(v)):
            raise ValueError(f"start {p!r} must be a positive modulus in kPa")
        out.append(v)
    return tuple(out)


class IdentificationPanel(Panel):
    title = "Identification"

    def __init__(self, session: SessionModel, parent=None, *, backend=None):
        super().__init__(parent)
        self.session = session
        self.backend = backend
        self.task: Task | None = None
        self.job: IdentificationJob | None = None
        self._updating = False
        self._t_start = 0.0
        self._ended = True  # the last run has delivered its outcome (or failed, or was cancelled)
        self._overlay_seen = 0
        self._reset_traces()
        self._build()
        self.timer = QTimer(self)
        self.timer.setInterval(DRAW_PERIOD_MS)
        self.timer.timeout.connect(self._drain)
        session.experiment_changed.connect(self._on_experiment)
        session.identification_changed.connect(self._on_settings)
        session.specimen_changed.connect(self._on_experiment)
        session.outcome_changed.connect(self._on_outcome)
        session.frames_changed.connect(lambda *_: self._check_settings())
        session.lock_changed.connect(lambda *_: self._check_settings())
        self._on_experiment()

    # ---- layout -------------------------------------------------------------------------
    def _build(self) -> None:
        outer = QHBoxLayout(self)
        outer.setContentsMargins(4, 4, 4, 4)
        split = QSplitter(Qt.Horizontal)
        outer.addWidget(split)

        side = QWidget()
        sl = QVBoxLayout(side)
        sl.setContentsMargins(0, 0, 0, 0)
        params = QGroupBox("Parameters")
        pl = QVBoxLayout(params)
        self.table = QTableWidget(0, len(COLS))
        self.table.setHorizontalHeaderLabels(COLS)
        self.table.verticalHeader().setVisible(False)
        self.table.setEditTriggers(QAbstractItemView.NoEditTriggers)
        self.table.setSelectionMode(QAbstractItemView.NoSelection)
        self.table.horizontalHeader().setSectionResizeMode(QHeaderView.ResizeToContents)
        self.table.horizontalHeader().setStretchLastSection(True)
        self.table.setHorizontalScrollBarPolicy(Qt.ScrollBarAlwaysOff)
        self.table.setVerticalScrollBarPolicy(Qt.ScrollBarAlwaysOff)
        pl.addWidget(self.table)
        pl.addWidget(hint("Each start sets every free modulus to the start value; a fixed modulus stays at its "
                          "value. Images alone fix only the ratios of the moduli: the force fixes the level."))
        sl.addWidget(params)

        setup = QGroupBox("Cost and starts")
        f = QFormLayout(setup)
        self.cost_box = QComboBox()
        for key, label in COSTS.items():
            self.cost_box.addItem(label, key)
        self.cost_box.currentIndexChanged.connect(self._controls_edited)
        f.addRow("Cost", self.cost_box)
        self.frames_box = QComboBox()
        self.frames_box.addItem("Source vs every deformed frame", True)
        self.frames_box.addItem("Source vs target frame only", False)
        from app.core.identify import MAX_DEFAULT_FRAMES

        self.frames_box.setToolTip(f"Every frame with more probe travel than the source; of more than "
                                   f"{MAX_DEFAULT_FRAMES - 1}, {MAX_DEFAULT_FRAMES - 1} spread along the probe's "
                                   "travel, a hold's frames counting as one (the target and the deepest among "
                                   "them): frames that close add little, and each costs time and memory")
        self.frames_box.currentIndexChanged.connect(self._controls_edited)
        f.addRow("Frames", self.frames_box)
        self.starts_edit = QLineEdit()
        self.starts_edit.setToolTip("Start values in kPa, separated by commas")
        self.starts_edit.editingFinished.connect(self._controls_edited)
        self.starts_unit = QLabel("kPa")
        srow = QHBoxLayout()
        srow.addWidget(self.starts_edit, 1)
        srow.addWidget(self.starts_unit)
        f.addRow("Starts", srow)
        self.max_evals = ispin(5, 5000, 200, tip="Nelder-Mead stops a start after this many cost evaluations")
        self.max_evals.valueChanged.connect(self._controls_edited)
        f.addRow("Evaluations per start (max)", self.max_evals)
        self.nu = spin(0.30, 0.4999, 0.49, decimals=4, step=0.005,
                       tip="Poisson's ratio of the model (an assumption of the model, not data)")
        self.nu.valueChanged.connect(self._controls_edited)
        f.addRow("Poisson's ratio (model)", self.nu)
        self.settings_note = hint("")
        f.addRow(self.settings_note)
        sl.addWidget(setup)

        run = QGroupBox("Run")
        rl = QVBoxLayout(run)
        b = QHBoxLayout()
        self.run_button = QPushButton("Run identification")
        self.run_button.setObjectName("primary")
        self.cancel_button = QPushButton("Cancel")
        self.cancel_button.setEnabled(False)
        self.mesh_check_button = QPushButton("Check the mesh")
        self.mesh_check_button.setToolTip(
            "Identify the result again on a mesh 0.7 times the size: how far each modulus moves is the mesh's "
            "own error, which the standard errors do not include (about two minutes at the paper's size)")
        self.mesh_check_button.setEnabled(False)
        b.addWidget(self.run_button)
        b.addWidget(self.cancel_button)
        b.addWidget(self.mesh_check_button)
        b.addStretch(1)
        rl.addLayout(b)
        self.progress = QProgressBar()
        self.progress.setRange(0, 1000)
        self.progress.setValue(0)
        self.progress.setTextVisible(True)
        self.progress.setFormat("idle")
        rl.addWidget(self.progress)
        self.state = hint("")
        rl.addWidget(self.state)
        self.run_button.clicked.connect(self.run)
        self.cancel_button.clicked.connect(self.cancel)
        self.mesh_check_button.clicked.connect(self.check_mesh)
        sl.addWidget(run)
        starts_box = QGroupBox("Starts (the best of each, in the plots' colours; bold: the best overall)")
        stl = QVBoxLayout(starts_box)
        self.starts_table = QTableWidget(0, 0)
        self.starts_table.verticalHeader().setVisible(False)
        self.starts_table.setEditTriggers(QAbstractItemView.NoEditTriggers)
        self.starts_table.horizontalHeader().setSectionResizeMode(QHeaderView.ResizeToContents)
        self.starts_table.horizontalHeader().setStretchLastSection(True)
        stl.addWidget(self.starts_table)
        sl.addWidget(starts_box, 1)
        side.setMinimumWidth(590)
        side.setMaximumWidth(680)
        split.addWidget(scrolled(side))

        right = QSplitter(Qt.Vertical)
        self.plots = pg.GraphicsLayoutWidget()
        self.plots.setMinimumHeight(260)
        right.addWidget(self.plots)
        bottom = QSplitter(Qt.Horizontal)
        ov = pg.GraphicsLayoutWidget()
        self.overlay_plot = ov.addPlot(title="Overlay: red target, green warped")
        self.overlay_plot.getViewBox().setAspectLocked(True)
        self.overlay_plot.getViewBox().invertY(True)
        self.overlay_plot.hideAxis("bottom")
        self.overlay_plot.hideAxis("left")
        self.overlay_image = pg.ImageItem()
        self.overlay_plot.addItem(self.overlay_image)
        ov.setMinimumWidth(220)
        ov.setMaximumWidth(420)
        bottom.addWidget(ov)
        rep = QWidget()
        rl2 = QVBoxLayout(rep)
        rl2.setContentsMargins(0, 0, 0, 0)
        rl2.addWidget(QLabel("<b>Result and identifiability</b>"))
        self.report = QPlainTextEdit()
        self.report.setObjectName("report")
        self.report.setReadOnly(True)
        self.report.setFont(mono_font())
        self.report.setLineWrapMode(QPlainTextEdit.WidgetWidth)
        self.report.setPlaceholderText("The identified moduli, the cost and the identifiability report "
                                       "appear here when a run ends.")
        rl2.addWidget(self.report, 1)
        bottom.addWidget(rep)
        bottom.setStretchFactor(1, 2)
        bottom.setSizes([330, 700])
        right.addWidget(bottom)
        right.setStretchFactor(0, 5)
        right.setStretchFactor(1, 4)
        split.addWidget(right)
        split.setStretchFactor(1, 1)

    # ---- plots --------------------------------------------------------------------------------
    def _reset_traces(self) -> None:
        self._n_total = 0
        self._traces: dict[int, dict] = {}
        self._best = (math.inf, None)

    def _build_plots(self, names: tuple[str, ...]) -> None:
        g = self.plots
        g.clear()
        self.cost_plot = g.addPlot(row=0, col=0, title="Cost per evaluation (lower is better)")
        self.cost_plot.setLabel("bottom", "evaluation")
        self.cost_plot.setLabel("left", "cost")
        style_plot(self.cost_plot)
        self.best_marker = pg.ScatterPlotItem([], [], symbol="star", size=14, brush="#ffd400", pen=pg.mkPen("#333"))
        self.best_marker.setZValue(10)
        self.cost_plot.addItem(self.best_marker)
        # no legend: six starts made it taller than the plot (cut) or, in columns, as wide (over
        # the curves); the starts run in turn, left to right, and the Starts table has their colours
        self.force_plot = g.addPlot(row=1, col=0, title=f"Force: {FORCE_KEY}")
        self.force_plot.setLabel("bottom", "probe travel", units="mm")
        self.force_plot.setLabel("left", "force", units="N")
        style_plot(self.force_plot)
        self.param_plots: dict[str, pg.PlotItem] = {}
        refs = self.session.reference_kPa()
        n = max(1, len(names))
        for i, name in enumerate(names):
            p = g.addPlot(row=i, col=1, rowspan=2 if n == 1 else 1,
                          title=f"{name} per start")  # the reference line is labelled (the title was cut)
            p.setLabel("bottom", "evaluation within the start")
            p.setLabel("left", name.replace("_kPa", ""), units="kPa")
            style_plot(p)
            if name in refs:
                p.addItem(pg.InfiniteLine(refs[name], angle=0, pen=pg.mkPen("#222", width=1.5, style=Qt.DashLine),
                                          label=f"reference {refs[name]:g}", labelOpts={"position": 0.6, "color": "#222"}))
            self.param_plots[name] = p
        if n > 2:
            g.removeItem(self.force_plot)
            g.addItem(self.force_plot, row=1, col=0, rowspan=n - 1)
            g.removeItem(self.cost_plot)
            g.addItem(self.cost_plot, row=0, col=0)

    def _trace(self, start: int) -> dict:
        tr = self._traces.get(start)
        if tr is None:
            color = start_color(start)
            pen = pg.mkPen(color, width=1)  # 1 px: antialiased wide pens triple the paint time
            starts = self.job.settings.starts_kPa if self.job else ()
            label = f"start {starts[start]:g} kPa" if start < len(starts) else f"start {start + 1}"
            tr = {"x": [], "within": [], "cost": [], "params": {n: [] for n in self.param_plots},
                  "cost_curve": self.cost_plot.plot([], [], pen=pen, name=label),
                  "curves": {n: p.plot([], [], pen=pen) for n, p in self.param_plots.items()}}
            self._traces[start] = tr
        return tr

    def _drain(self) -> None:
        job = self.job
        if job is None:
            return
        reports = job.drain()
        touched = set()
        for rep in reports:
            self._n_total += 1
            tr = self._trace(int(rep.start))
            tr["x"].append(self._n_total)
            tr["within"].append(int(getattr(rep, "evaluation", len(tr["within"]) + 1)))
            total = float(rep.cost.get("total", math.nan))
            tr["cost"].append(total)
            for n in tr["params"]:
                tr["params"][n].append(float(rep.parameters.get(n, math.nan)))
            if total < self._best[0]:
                self._best = (total, rep)
            touched.add(int(rep.start))
        for k in touched:
            tr = self._traces[k]
            tr["cost_curve"].setData(tr["x"], tr["cost"])
            for n, c in tr["curves"].items():
                c.setData(tr["within"], tr["params"][n])
        if touched:
            self._frame_cost_axis()
        seq, ov = job.latest_overlay(self._overlay_seen)
        if ov is not None:
            self._overlay_seen = seq
            self._show_overlay(ov)
        self._update_progress()

    def _frame_cost_axis(self) -> None:
        """Y range from the bulk of the costs: the first simplex of a far start would squash the rest."""
        costs = np.concatenate([np.asarray(t["cost"], float) for t in self._traces.values()])
        costs = costs[np.isfinite(costs)]
        if len(costs) < 3:
            return
        lo, hi = float(costs.min()), float(np.quantile(costs, 0.9))
        pad = 0.08 * max(hi - lo, 1e-6)
        self.cost_plot.setYRange(lo - pad, hi + pad, padding=0)
        best = self._best[1]
        if best is not None:
            k = int(best.start)
            tr = self._traces.get(k)
            idx = next((i for i, c in enumerate(tr["cost"]) if c == self._best[0]), None) if tr else None
            if idx is not None:
                self.best_marker.setData([tr["x"][idx]], [tr["cost"][idx]])

    def _update_progress(self) -> None:
        job = self.job
        if job is None or self._ended:  # the end's own text ("done", "failed", ...) stays
            return
        s = job.settings
        n_starts = max(1, len(s.starts_kPa))
        k = max(self._traces) if self._traces else 0
        within = len(self._traces[k]["x"]) if self._traces else 0
        frac = (k + min(1.0, within / max(1, s.max_evaluations))) / n_starts if self._traces else 0.0
        self.progress.setValue(int(1000 * min(frac, 1.0)))
        elapsed = time.monotonic() - self._t_start
        if self._traces:
            best = self._best[1]
            nmi = best.cost.get("nmi", math.nan) if best is not None else math.nan
            self.progress.setFormat(f"start {k + 1}/{n_starts} - {self._n_total} evaluations")
            self.state.setText(f"Best so far: cost {self._best[0]:.5f}, NMI {nmi:.4f}. Elapsed {elapsed:.0f} s.")
            self.busy.emit(f"Identifying: start {k + 1}/{n_starts}, {self._n_total} evaluations",
                           int(1000 * min(frac, 1.0)), 1000)

    def _show_overlay(self, ov) -> None:
        warped, target = np.asarray(ov[0], float), np.asarray(ov[1], float)
        mask = np.asarray(ov[3], bool) if len(ov) > 3 and ov[3] is not None else np.ones(warped.shape, bool)
        rgb = red_green(target, np.where(mask, warped, np.nanmin(warped)))
        rgb[~mask] = (rgb[~mask] * 0.3).astype(np.uint8)
        self.overlay_image.setImage(rgb, autoLevels=False, levels=(0, 255))
        self.overlay_plot.getViewBox().autoRange(padding=0.01)

    # ---- settings <-> controls -------------------------------------------------------------------
    def _on_experiment(self, *_):
        has = self.session.has_experiment
        self.run_button.setEnabled(has and not self.running)
        self._on_settings(self.session.identification)
        names = tuple(p.name for p in self.session.identification.parameters)
        if not self.running:
            self._reset_traces()
            self._build_plots(names)
            self.overlay_image.clear()
        self._on_outcome()

    def _on_settings(self, settings: IdentificationSettings) -> None:
        self._updating = True
        try:
            refs = self.session.reference_kPa()
            lo, hi = core_bounds_kPa()
            self.table.setRowCount(len(settings.parameters))
            for i, p in enumerate(settings.parameters):
                self.table.setItem(i, 0, QTableWidgetItem(p.name))
                free = QCheckBox()
                free.setChecked(p.free)
                free.setObjectName(f"free_{p.name}")
                free.toggled.connect(self._controls_edited)
                self.table.setCellWidget(i, 1, _centered(free))
                val = spin(0.01, 1e5, p.value, decimals=1, step=1.0)
                val.setMinimumWidth(78)
                val.setObjectName(f"value_{p.name}")
                val.setEnabled(not p.free)
                val.setToolTip("The value this modulus is held at when it is not free")
                val.valueChanged.connect(self._controls_edited)
                self.table.setCellWidget(i, 2, val)
                rng = QTableWidgetItem(f"{lo:g} - {hi:g}")
                rng.setToolTip("The optimizer searches log-moduli within these bounds (set by the core for "
                               "every modulus)")
                self.table.setItem(i, 3, rng)
                self.table.setItem(i, 4, QTableWidgetItem(p.unit))
                ref = refs.get(p.name)
                self.table.setItem(i, 5, QTableWidgetItem("" if ref is None else f"{ref:.1f}"))
            self.cost_box.setCurrentIndex(max(0, self.cost_box.findData(settings.cost)))
            self.frames_box.setCurrentIndex(0 if settings.all_frames else 1)
            self.starts_edit.setText(", ".join(f"{s:g}" for s in settings.starts_kPa))
            self.max_evals.setValue(settings.max_evaluations)
            self.nu.setValue(settings.nu)
        finally:
            self._updating = False
        self._fill_result_columns()
        self._check_settings()
        self.table.resizeColumnsToContents()
        h = self.table.horizontalHeader().height() + sum(self.table.rowHeight(i) for i in range(self.table.rowCount()))
        self.table.setFixedHeight(h + 4)

    def _free_box(self, row: int) -> QCheckBox:
        return self.table.cellWidget(row, 1).findChild(QCheckBox)

    def _controls_edited(self, *_):
        if self._updating or not self.session.has_experiment:
            return
        old = self.session.identification
        params = []
        for i, p in enumerate(old.parameters):
            free = self._free_box(i).isChecked()
            value = self.table.cellWidget(i, 2).value()
            self.table.cellWidget(i, 2).setEnabled(not free)
            params.append(replace(p, free=free, value=value))
        try:
            starts = parse_starts(self.starts_edit.text())
        except ValueError as exc:
            self.settings_note.setText(f"<span style='color:#c62828'>{exc}</span>")
            starts = old.starts_kPa
        new = replace(old, parameters=tuple(params), cost=self.cost_box.currentData(),
                      all_frames=bool(self.frames_box.currentData()), starts_kPa=starts,
                      max_evaluations=self.max_evals.value(), nu=self.nu.value())
        self.session.set_identification(new)
        self._check_settings()

    def problems(self) -> list[str]:
        """What stops a run now, in words (empty when it can run)."""
        s = self.session
        out = []
        if not s.has_experiment:
            return ["open an experiment first"]
        if s.locked_by and not self.running:
            out.append(f"wait: {s.locked_by}")
        ident = s.identification
        try:
            parse_starts(self.starts_edit.text())
        except ValueError as exc:
            out.append(str(exc))
        if not any(p.free for p in ident.parameters):
            out.append("every modulus is fixed: free at least one")
        fixed = [p for p in ident.parameters if not p.free]
        if fixed and not _accepts(self._backend().identify, "fixed"):
            out.append("this version of the core cannot hold moduli fixed")
        exp = s.experiment
        d_src = exp.frames[s.source_frame].displacement_mm
        d_tgt = exp.frames[s.target_frame].displacement_mm
        if s.target_frame == s.source_frame or d_tgt <= d_src:
            out.append("choose a target frame taken deeper than the source frame (Images panel)")
        return out

    def _backend(self):
        if self.backend is not None:
            return self.backend
        from app.core import identify

        return identify

    def _check_settings(self) -> None:
        probs = self.problems() if self.session.has_experiment else []
        ident = self.session.identification
        notes = []
        if ident.cost == "nmi" and all(p.free for p in ident.parameters):
            notes.append("With NMI only, the images fix the ratios of the moduli but not their level: "
                         "fix one modulus or use the joint cost.")
        if probs:
            self.settings_note.setText("<span style='color:#c62828'>" + "; ".join(probs) + ".</span>")
        else:
            self.settings_note.setText(" ".join(notes))
        self.run_button.setEnabled(self.session.has_experiment and not self.running and not probs)

    # ---- outcome --------------------------------------------------------------------------------
    def _fill_result_columns(self) -> None:
        out = self.session.outcome
        for i, p in enumerate(self.session.identification.parameters):
            v = out.parameters.get(p.name) if out else None
            item = QTableWidgetItem("" if v is None else f"{v:.2f}")
            if v is not None:
                f = item.font()
                f.setBold(True)
                item.setFont(f)
            self.table.setItem(i, 6, item)
            se = out.standard_error_rel.get(p.name) if out else None
            text = "" if se is None else ("undetermined" if not math.isfinite(se) else f"+/-{_pct(se)}")
            self.table.setItem(i, 7, QTableWidgetItem(text))

    def _on_outcome(self) -> None:
        self._fill_result_columns()
        out = self.session.outcome
        self.mesh_check_button.setEnabled(out is not None and not self.running)
        if out is None:
            if not self.running:
                self.report.setPlainText("")
                self.starts_table.setRowCount(0)
            return
        self.report.setPlainText("\n".join(self._report_lines(out)))
        self._fill_starts(out)
        if self.session.overlay is not None:
            self._show_overlay(self.session.overlay)

    def _report_lines(self, out) -> list[str]:
        refs = self.session.reference_kPa()
        lines = []
        for n, v in out.parameters.items():
            ref = refs.get(n)
            extra = f"   (reference {ref:.1f}, {100 * (v - ref) / ref:+.1f}%)" if ref else ""
            lines.append(f"{n} = {v:8.2f}{extra}")
        c = out.cost
        lines.append(f"cost {c.get('total', math.nan):.5f}: NMI {c.get('nmi', math.nan):.4f}, "
                     f"force RMS {c.get('force_rms_N', math.nan):.4f} N")
        cost_name = COSTS.get(out.settings.cost, out.settings.cost) if out.settings else ""
        lines.append(f"{out.evaluations} evaluations in {out.seconds:.1f} s ({cost_name})")
        if out.identifiability:
            lines.append("")
            lines.append("Identifiability")
            lines += [f"  {x}" for x in out.identifiability]
        if out.mesh_check:
            lines += ["", "Mesh check", *(f"  {x}" for x in out.mesh_check)]
        return lines

    def _fill_starts(self, out) -> None:
        names = list(out.parameters)
        cols = ["Start (kPa)"] + names + ["Cost", "NMI", "Evaluations"]
        self.starts_table.setColumnCount(len(cols))
        self.starts_table.setHorizontalHeaderLabels(cols)
        self.starts_table.setRowCount(len(out.starts))
        best = min(range(len(out.starts)), key=lambda i: out.starts[i].get("cost", {}).get("total", math.inf),
                   default=None)
        for i, st in enumerate(out.starts):
            vals = [f"{st.get('start_kPa', st.get('start', ''))}"]
            vals += [f"{st.get('parameters', {}).get(n, math.nan):.2f}" for n in names]
            cost = st.get("cost", {})
            vals += [f"{cost.get('total', math.nan):.5f}", f"{cost.get('nmi', math.nan):.4f}", f"{st.get('evaluations', '')}"]
            for j, v in enumerate(vals):
                item = QTableWidgetItem(v)
                if j == 0:  # the key to the plots' colours
                    item.setForeground(QColor(start_color(i)))
                if i == best:
                    f = item.font()
                    f.setBold(True)
                    item.setFont(f)
                if st.get("note"):  # e.g. a start that shared an earlier one's large-deformation fit
                    item.setToolTip(st["note"])
                self.starts_table.setItem(i, j, item)

    # ---- run ----------------------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        return self.task is not None

    def run(self) -> None:
        if self.running:
            return
        self._controls_edited()
        probs = self.problems()
        if probs:
            self.error.emit(ValueError("Cannot run the identification: " + "; ".join(probs) + "."), "")
            return
        s = self.session
        settings = s.identification
        self.job = job = IdentificationJob(
            s.analysis_experiment(), settings, mesh=s.mesh, mesh_settings=s.effective_mesh_settings(), roi_px=s.roi_px,
            frames=s.analysis_frames(), target_frame=s.target_frame, backend=self.backend)
        need_quality = s.mesh is None
        regions = s.specimen.regions

        def work(progress, cancel):
            result = job.run(progress, cancel)
            lines = ()
            if need_quality and result.mesh is not None:
                from app.core.mesh import quality

                lines = tuple(quality(result.mesh, regions).lines())
            return result, lines

        self._reset_traces()
        self._build_plots(tuple(p.name for p in settings.parameters))
        self.overlay_image.clear()
        self._overlay_seen = 0
        self.report.setPlainText("")
        self.starts_table.setRowCount(0)
        self.session.set_outcome(None)
        self.task = Task(work, "identify")
        self.task.progress.connect(self._task_progress)
        self.task.succeeded.connect(self._task_done)
        self.task.failed.connect(self._task_failed)
        self.task.cancelled.connect(self._task_cancelled)
        self.task.finished.connect(self._task_finished)
        self._set_running(True)
        self.session.set_locked("an identification is running")
        self._t_start = time.monotonic()
        self._ended = False
        self.progress.setValue(0)
        self.progress.setFormat("preparing the model")
        self.busy.emit("Identification: preparing the model", 0, 0)
        log.info("identification: %s cost, starts %s kPa, frames %s, ROI %s", settings.cost,
                 ", ".join(f"{x:g}" for x in settings.starts_kPa), job.frames, s.roi_px)
        self.task.start()
        self.timer.start()

    def cancel(self) -> None:
        if self.task is not None:
            self.task.cancel()
            self.state.setText("Cancelling...")

    def _set_running(self, on: bool) -> None:
        for w in (self.table, self.cost_box, self.frames_box, self.starts_edit, self.max_evals, self.nu):
            w.setEnabled(not on)
        self.cancel_button.setEnabled(on)
        self.run_button.setEnabled(not on and self.session.has_experiment)
        self.mesh_check_button.setEnabled(not on and self.session.outcome is not None)

    def _task_progress(self, text: str) -> None:
        self.state.setText(text[:1].upper() + text[1:])
        if not self._traces:
            self.progress.setFormat(text[:60])
        self.status.emit(text)
        log.info("%s", text)

    def _task_done(self, payload) -> None:
        result, lines = payload
        self._drain()
        self._ended = True  # a draw tick before ``finished`` stops the timer must not put the running text back
        s = self.session
        job = self.job
        if job is not None and s.specimen != job.experiment.specimen:
            self.state.setText("The specimen was edited during the run: the result is discarded; run again.")
            self.progress.setFormat("discarded")
            log.warning("identification result discarded: the specimen changed during the run")
            return
        if job is not None and (tuple(s.roi_px) != tuple(job.roi_px) or s.analysis_frames() != tuple(job.frames)):
            log.warning("the ROI or the frames changed during the run; the result is for ROI %s, frames %s",
                        job.roi_px, job.frames)
        if s.mesh is None and result.mesh is not None:
            s.set_mesh(result.mesh, lines)
        s.set_outcome(result.outcome, result.overlay, result.deformed)
        if result.force is not None:
            t, measured, model = result.force
            s.model_force_N = model  # kept for the report
            d = s.experiment.force_log.displacement_mm
            pen_measured, pen_model = force_pens()
            self.force_plot.plot(d, measured, pen=pen_measured, name="measured")
            self.force_plot.plot(d, model, pen=pen_model, name="model")
        self.progress.setValue(1000)
        self.progress.setFormat(f"done - {result.outcome.evaluations} evaluations")
        text = ", ".join(f"{k} = {v:.1f}" for k, v in result.outcome.parameters.items())
        self.state.setText(f"Done in {time.monotonic() - self._t_start:.1f} s: {text}.")
        self.status.emit(f"identification done: {text}")
        c = result.outcome.cost
        log.info("identification done: %s; NMI %.4f, force RMS %.4f N, %d evaluations in %.1f s", text,
                 c.get("nmi", math.nan), c.get("force_rms_N", math.nan), result.outcome.evaluations,
                 result.outcome.seconds)

    def check_mesh(self) -> None:
        """The result identified again on a finer mesh (app.core.mesh_check), on a
        worker; its lines join the report."""
        s, out = self.session, self.session.outcome
        if self.running or out is None:
            return
        settings = out.settings or s.identification
        exp, params = s.analysis_experiment(), dict(out.parameters)
        nodes = s.mesh.n_nodes if s.mesh is not None else None
        kw = dict(mesh_settings=s.effective_mesh_settings(), roi_px=s.roi_px, frames=s.analysis_frames(),
                  cost=settings.cost, nu=settings.nu, fixed=tuple(p.name for p in settings.parameters if not p.free))

        def work(progress, cancel):
            from app.core.mesh_check import mesh_check

            return mesh_check(exp, (), params, nodes, progress=progress, cancel=cancel, **kw)

        self.task = Task(work, "mesh check")
        self.task.progress.connect(self._task_progress)
        self.task.succeeded.connect(self._mesh_checked)
        self.task.failed.connect(self._task_failed)
        self.task.cancelled.connect(lambda: self.state.setText("Mesh check cancelled."))
        self.task.finished.connect(self._task_finished)
        self._set_running(True)
        self.session.set_locked("a mesh check is running")
        self.progress.setFormat("checking the mesh")
        self.busy.emit("Identification: checking the mesh", 0, 0)
        log.info("mesh check of the identified moduli %s", params)
        self.task.start()

    def _mesh_checked(self, check) -> None:
        out = self.session.outcome
        lines = check.lines(out.standard_error_rel if out is not None else None)
        self.session.set_mesh_check(lines)  # the report shows it; the session file and the HTML report keep it
        self.progress.setFormat("mesh check done")
        self.state.setText(f"Mesh check done in {check.seconds:.0f} s (in the report).")
        self.status.emit(lines[0])
        log.info("%s", "; ".join(lines))

    def _task_failed(self, exc, details) -> None:
        self._ended = True
        self.state.setText(f"Failed: {exc}")
        self.progress.setFormat("failed")
        self.error.emit(exc, details)

    def _task_cancelled(self) -> None:
        self._drain()
        self._ended = True
        self.state.setText(f"Cancelled after {self._n_total} evaluations.")
        self.progress.setFormat("cancelled")
        self.status.emit("identification cancelled")
        log.info("identification cancelled after %d evaluations", self._n_total)

    def _task_finished(self) -> None:
        self.timer.stop()
        self.task = None
        self.session.set_locked(None)
        self._set_running(False)
        self._check_settings()
        self.busy.emit("", 0, 0)

    def shutdown(self) -> None:
        self.timer.stop()
        self.cancel()


def _pct(x: float) -> str:
    """A relative error as a percentage with two significant digits (0.042% stays 0.042%)."""
    v = 100.0 * x
    return f"{v:.2g}%" if v < 10 else f"{v:.0f}%"


def _centered(w: QWidget) -> QWidget:
    box = QWidget()
    lay = QHBoxLayout(box)
    lay.setContentsMargins(0, 0, 0, 0)
    lay.setAlignment(Qt.AlignCenter)
    lay.addWidget(w)
    return box
