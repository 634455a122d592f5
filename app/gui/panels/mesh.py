"""Mesh panel: the specimen and its regions (edited in memory only), meshing in a
worker, mesh statistics, and a 3-D view of regions, probe face, image plane and
the deformed shape after an identification."""

from __future__ import annotations

import logging
import traceback

import numpy as np
from PySide6.QtCore import Qt
from PySide6.QtGui import QColor, QImage, QPainter, QPixmap
from PySide6.QtWidgets import (QAbstractItemView, QCheckBox, QComboBox, QFormLayout, QGridLayout, QGroupBox,
                               QHBoxLayout, QHeaderView, QLabel, QPlainTextEdit, QPushButton, QSplitter,
                               QTableWidget, QTableWidgetItem, QVBoxLayout, QWidget)

from app.core.geometry import Region
from app.core.mesh import MeshSettings

from ..models.session import SessionModel, region_summary
from ..style import mono_font, region_color
from ..view3d import can_use_3d
from ..workers import Task
from .base import Panel
from .common import hint, scrolled, spin

log = logging.getLogger("elastoid.gui")

EDITABLE = ("sphere", "box", "ellipsoid", "cylinder")


class MeshPanel(Panel):
    title = "Specimen & mesh"

    def __init__(self, session: SessionModel, parent=None, *, enable_3d: bool | None = None):
        super().__init__(parent)
        self.session = session
        self.task: Task | None = None
        self._updating = False
        self.plotter = None
        self._enable_3d = can_use_3d() if enable_3d is None else enable_3d
        self._build()
        session.experiment_changed.connect(self._on_experiment)
        session.specimen_changed.connect(self._on_specimen)
        session.mesh_changed.connect(self._on_mesh)
        session.mesh_settings_changed.connect(self._on_mesh_settings)
        session.deformed_changed.connect(self._redraw)
        session.frames_changed.connect(lambda *_: self._redraw())
        session.roi_changed.connect(lambda *_: self._redraw())
        session.lock_changed.connect(self._on_lock)
        self._on_experiment()

    # ---- layout ------------------------------------------------------------------------
    def _build(self) -> None:
        outer = QHBoxLayout(self)
        outer.setContentsMargins(4, 4, 4, 4)
        split = QSplitter(Qt.Horizontal)
        outer.addWidget(split)

        side = QWidget()
        sl = QVBoxLayout(side)
        sl.setContentsMargins(0, 0, 0, 0)

        spec = QGroupBox("Specimen and regions")
        s = QVBoxLayout(spec)
        self.size_label = hint("")
        s.addWidget(self.size_label)
        self.table = QTableWidget(0, 3)
        self.table.setHorizontalHeaderLabels(["Region", "Kind", "Geometry (mm)"])
        self.table.verticalHeader().setVisible(False)
        self.table.setSelectionBehavior(QAbstractItemView.SelectRows)
        self.table.setSelectionMode(QAbstractItemView.SingleSelection)
        self.table.setEditTriggers(QAbstractItemView.NoEditTriggers)
        self.table.horizontalHeader().setSectionResizeMode(2, QHeaderView.Stretch)
        self.table.setVerticalScrollBarPolicy(Qt.ScrollBarAsNeeded)
        self.table.setMaximumHeight(150)
        self.table.itemSelectionChanged.connect(self._on_selection)
        s.addWidget(self.table)
        b = QHBoxLayout()
        self.add_button = QPushButton("Add inclusion")
        self.add_button.setToolTip("Adds a sphere in the middle of the specimen; edit it below.\n"
                                   "Edits stay in this session: the experiment folder is never changed.")
        self.remove_button = QPushButton("Remove")
        self.reset_button = QPushButton("Reset to file")
        self.reset_button.setToolTip("Back to the regions described in experiment.toml")
        for w in (self.add_button, self.remove_button, self.reset_button):
            b.addWidget(w)
        b.addStretch(1)
        s.addLayout(b)
        self.add_button.clicked.connect(self._add_region)
        self.remove_button.clicked.connect(self._remove_region)
        self.reset_button.clicked.connect(lambda: self.session.reset_specimen())

        self.editor = QGroupBox("Selected region")
        e = QFormLayout(self.editor)
        self.kind_box = QComboBox()
        self.kind_box.addItems(EDITABLE)
        self.kind_box.currentTextChanged.connect(self._editor_changed)
        e.addRow("Kind", self.kind_box)
        self.center = [spin(-1000, 1000, 0, decimals=1, step=1.0, suffix="mm") for _ in range(3)]
        self.extent = [spin(0.1, 1000, 5, decimals=1, step=0.5, suffix="mm") for _ in range(3)]
        self.radius = spin(0.1, 1000, 5, decimals=1, step=0.5, suffix="mm")
        self.height_spin = spin(0.1, 1000, 10, decimals=1, step=0.5, suffix="mm")
        self._center_row = _triple(self.center, ("x", "y", "z"))
        self._extent_row = _triple(self.extent, ("x", "y", "z"))
        e.addRow("Centre", self._center_row)
        self._radius_label, self._extent_label, self._height_label = QLabel("Radius"), QLabel("Size"), QLabel("Height")
        e.addRow(self._radius_label, self.radius)
        e.addRow(self._extent_label, self._extent_row)
        e.addRow(self._height_label, self.height_spin)
        for w in (*self.center, *self.extent, self.radius, self.height_spin):
            w.valueChanged.connect(self._editor_changed)
        self.edit_note = hint("")
        e.addRow(self.edit_note)
        s.addWidget(self.editor)
        sl.addWidget(spec)

        mesh = QGroupBox("Mesh")
        m = QGridLayout(mesh)
        self.auto_sizes = QCheckBox("Automatic sizes (from the specimen, probe and regions)")
        self.auto_sizes.setChecked(True)
        self.auto_sizes.setToolTip("Element sizes that resolve the probe face and every region; untick to set them")
        self.auto_sizes.toggled.connect(self._auto_toggled)
        m.addWidget(self.auto_sizes, 0, 0, 1, 2)
        self.edge = spin(1.0, 50.0, 10.0, decimals=1, step=0.5, suffix="mm",
                         tip="Target edge length far from the probe")
        self.probe_edge = spin(0.3, 20.0, 2.5, decimals=2, step=0.25, suffix="mm",
                               tip="Target edge length on the probe face (the mesh is graded in between)")
        m.addWidget(QLabel("Element size"), 1, 0)
        m.addWidget(self.edge, 1, 1)
        # the lowest value means no size of its own: the face's
        self.outline_edge = spin(0.0, 20.0, 0.0, decimals=2, step=0.25, suffix="mm",
                                 tip="Target edge length along the probe face's outline, where the model's error "
                                     "is largest (docs/user-guide.md, Specimen and mesh)")
        self.outline_edge.setSpecialValueText("as the face")
        probe_row = QHBoxLayout()  # one row, so that Generate mesh stays in view
        probe_row.addWidget(self.probe_edge, 1)
        probe_row.addWidget(QLabel("outline"))
        probe_row.addWidget(self.outline_edge, 1)
        m.addWidget(QLabel("Under the probe"), 2, 0)
        m.addLayout(probe_row, 2, 1)
        for w in (self.edge, self.probe_edge, self.outline_edge):
            w.valueChanged.connect(self._settings_edited)
        bb = QHBoxLayout()
        self.mesh_button = QPushButton("Generate mesh")
        self.mesh_button.setObjectName("primary")
        self.cancel_button = QPushButton("Cancel")
        self.cancel_button.setEnabled(False)
        bb.addWidget(self.mesh_button)
        bb.addWidget(self.cancel_button)
        bb.addStretch(1)
        m.addLayout(bb, 3, 0, 1, 2)
        self.mesh_button.clicked.connect(self.generate_mesh)
        self.cancel_button.clicked.connect(self.cancel)
        self.mesh_state = hint("No mesh yet.")
        m.addWidget(self.mesh_state, 4, 0, 1, 2)
        self.quality = QPlainTextEdit()
        self.quality.setObjectName("report")
        self.quality.setReadOnly(True)
        self.quality.setFont(mono_font())
        self.quality.setMinimumHeight(90)
        self.quality.setPlaceholderText("Mesh statistics appear here: nodes, elements, dihedral angles, "
                                        "meshed vs geometric volume of each region.")
        m.addWidget(self.quality, 5, 0, 1, 2)
        sl.addWidget(mesh)
        side.setMinimumWidth(380)
        side.setMaximumWidth(460)
        split.addWidget(scrolled(side))

        view = QWidget()
        vl = QVBoxLayout(view)
        vl.setContentsMargins(0, 0, 0, 0)
        opts = QHBoxLayout()
        self.show_mesh = QCheckBox("Mesh (cut at the image plane)")
        self.show_mesh.setChecked(True)
        self.show_deformed = QCheckBox("Deformed at the target frame")
        self.show_deformed.setChecked(True)
        self.show_plane = QCheckBox("Image plane")
        self.show_plane.setChecked(True)
        for c in (self.show_mesh, self.show_deformed, self.show_plane):
            c.toggled.connect(self._redraw)
            opts.addWidget(c)
        opts.addStretch(1)
        vl.addLayout(opts)
        if self._enable_3d:
            from pyvistaqt import QtInteractor

            self.plotter = QtInteractor(view, auto_update=False)
            self.plotter.set_background("white")
            self.plotter.enable_anti_aliasing()
            self.view_widget = self.plotter.interactor
        else:
            self.view_widget = QLabel("The 3-D view needs an OpenGL display.\n"
                                      "Mesh statistics are listed on the left.")
            self.view_widget.setAlignment(Qt.AlignCenter)
            self.view_widget.setObjectName("hint")
        self.view_widget.setMinimumSize(320, 260)
        vl.addWidget(self.view_widget, 1)
        self.legend = QLabel("")
        self.legend.setTextFormat(Qt.RichText)
        self.legend.setWordWrap(True)
        vl.addWidget(self.legend)
        split.addWidget(view)
        split.setStretchFactor(1, 1)

    # ---- model -> view ---------------------------------------------------------------------
    def _on_experiment(self) -> None:
        has = self.session.has_experiment
        for w in (self.add_button, self.remove_button, self.reset_button, self.mesh_button, self.auto_sizes,
                  self.table):
            w.setEnabled(has)
        self._on_mesh_settings()
        self._on_specimen()
        self._on_mesh()

    def _on_lock(self, reason) -> None:
        editable = reason is None and self.session.has_experiment
        for w in (self.add_button, self.remove_button, self.reset_button, self.mesh_button, self.auto_sizes,
                  self.editor):
            w.setEnabled(editable)
        self._on_mesh_settings()
        if editable:
            self._on_selection()

    def _on_mesh_settings(self, settings: MeshSettings | None = None) -> None:
        auto = self.session.mesh_settings is None
        eff = self.session.effective_mesh_settings()
        self._updating = True
        try:
            self.auto_sizes.setChecked(auto)
            self.edge.setValue(eff.edge_mm)
            self.probe_edge.setValue(eff.probe_edge_mm)
            self.outline_edge.setValue(eff.outline_edge_mm or 0.0)
        finally:
            self._updating = False
        editable = self.session.has_experiment and self.session.locked_by is None
        for w in (self.edge, self.probe_edge, self.outline_edge):
            w.setEnabled(editable and not auto)

    def _auto_toggled(self, on: bool) -> None:
        if self._updating:
            return
        self.session.set_mesh_settings(None if on else self.session.effective_mesh_settings())

    def _on_specimen(self) -> None:
        s = self.session
        sel = self.selected_region_name()
        self._updating = True
        try:
            self.table.setRowCount(0)
            if s.specimen is None:
                self.size_label.setText("No experiment open.")
                self.editor.setEnabled(False)
                return
            sx, sy, sz = s.specimen.size_mm
            edited = " (edited in this session; the experiment folder is unchanged)" if s.specimen_edited else ""
            self.size_label.setText(f"Box {sx:g} x {sy:g} x {sz:g} mm, {len(s.specimen.regions)} regions{edited}.")
            self.table.setRowCount(len(s.specimen.regions))
            for i, r in enumerate(s.specimen.regions):
                name = QTableWidgetItem(r.name)
                name.setData(Qt.DecorationRole, QColor(region_color(i)))
                self.table.setItem(i, 0, name)
                self.table.setItem(i, 1, QTableWidgetItem(r.kind))
                self.table.setItem(i, 2, QTableWidgetItem(region_summary(r)))
            self.table.resizeColumnsToContents()
            self.table.horizontalHeader().setSectionResizeMode(2, QHeaderView.Stretch)
        finally:
            self._updating = False
        names = s.specimen.region_names
        self.table.selectRow(names.index(sel) if sel in names else len(names) - 1)
        self._on_selection()
        self._on_mesh_settings()
        self._redraw()

    def _on_mesh(self) -> None:
        s = self.session
        if s.mesh is None:
            self.mesh_state.setText("No mesh yet: the identification meshes the specimen itself, "
                                    "or generate one here to check it first." if s.has_experiment else "No mesh yet.")
            self.quality.setPlainText("")
        else:
            self.mesh_state.setText(f"Mesh ready: {s.mesh.n_nodes} nodes, {s.mesh.n_tets} tetrahedra.")
            self.quality.setPlainText("\n".join(s.mesh_quality))
        self._redraw()

    def selected_region_name(self) -> str | None:
        rows = self.table.selectionModel().selectedRows() if self.table.selectionModel() else []
        if not rows:
            return None
        item = self.table.item(rows[0].row(), 0)
        return item.text() if item else None

    def _selected_region(self) -> Region | None:
        name = self.selected_region_name()
        if name is None or self.session.specimen is None:
            return None
        return next((r for r in self.session.specimen.regions if r.name == name), None)

    def _on_selection(self) -> None:
        if self._updating:
            return
        r = self._selected_region()
        editable = r is not None and r.kind in EDITABLE
        self.editor.setEnabled(editable)
        self.remove_button.setEnabled(r is not None and r.kind != "background")
        if r is None:
            return
        if not editable:
            self.edit_note.setText("The background fills the specimen box." if r.kind == "background"
                                   else "A surface region comes from its file and is not edited here.")
            return
        self.edit_note.setText("Changes apply at once and discard the mesh and results.")
        self._updating = True
        try:
            self.editor.setTitle(f"Selected region: {r.name}")
            self.kind_box.setCurrentText(r.kind)
            for w, v in zip(self.center, r.center_mm):
                w.setValue(v)
            if r.radius_mm is not None:
                self.radius.setValue(r.radius_mm)
            ext = r.size_mm if r.kind == "box" else r.radii_mm if r.kind == "ellipsoid" else None
            if ext is not None:
                for w, v in zip(self.extent, ext):
                    w.setValue(v)
            if r.height_mm is not None:
                self.height_spin.setValue(r.height_mm)
        finally:
            self._updating = False
        self._show_kind_rows(r.kind)

    def _show_kind_rows(self, kind: str) -> None:
        for w, on in ((self.radius, kind in ("sphere", "cylinder")), (self._radius_label, kind in ("sphere", "cylinder")),
                      (self._extent_row, kind in ("box", "ellipsoid")), (self._extent_label, kind in ("box", "ellipsoid")),
                      (self.height_spin, kind == "cylinder"), (self._height_label, kind == "cylinder")):
            w.setVisible(on)
        self._extent_label.setText("Size" if kind == "box" else "Radii")

    # ---- view -> model -------------------------------------------------------------------------
    def _editor_changed(self, *_):
        if self._updating:
            return
        r = self._selected_region()
        if r is None or r.kind not in EDITABLE:
            return
        kind = self.kind_box.currentText()
        self._show_kind_rows(kind)
        c = tuple(w.value() for w in self.center)
        ext = tuple(w.value() for w in self.extent)
        if kind == "sphere":
            new = Region(r.name, "sphere", center_mm=c, radius_mm=self.radius.value())
        elif kind == "box":
            new = Region(r.name, "box", center_mm=c, size_mm=ext)
        elif kind == "ellipsoid":
            new = Region(r.name, "ellipsoid", center_mm=c, radii_mm=ext)
        else:
            new = Region(r.name, "cylinder", center_mm=c, radius_mm=self.radius.value(), height_mm=self.height_spin.value())
        lo, hi = new.bounds_mm()
        size = np.asarray(self.session.specimen.size_mm)
        if np.any(lo < -1e-9) or np.any(hi > size + 1e-9):
            self.edit_note.setText("<span style='color:#c62828'>The region reaches outside the specimen box; "
                                   "not applied.</span>")
            return
        self.edit_note.setText("Changes apply at once and discard the mesh and results.")
        self.session.set_region(new)

    def _add_region(self) -> None:
        s = self.session
        sx, sy, sz = s.specimen.size_mm
        r = round(min(sx, sy, sz) / 6.0, 1)
        region = Region(s.new_region_name(), "sphere", center_mm=(sx / 2, sy / 2, sz / 2), radius_mm=r)
        s.set_region(region)
        self.table.selectRow(len(s.specimen.regions) - 1)
        self.status.emit(f"added inclusion {region.name}: a sphere of radius {r:g} mm at the centre; edit it below")

    def _remove_region(self) -> None:
        name = self.selected_region_name()
        if name:
            self.session.remove_region(name)

    def _settings_edited(self) -> None:
        if self._updating:
            return
        from dataclasses import replace

        base = self.session.effective_mesh_settings()
        self.session.set_mesh_settings(replace(base, edge_mm=self.edge.value(), probe_edge_mm=self.probe_edge.value(),
                                               outline_edge_mm=self.outline_edge.value() or None))

    # ---- meshing (worker) ---------------------------------------------------------------------------
    def generate_mesh(self) -> None:
        s = self.session
        if not s.has_experiment or (self.task is not None and self.task.isRunning()):
            return
        exp, settings = s.analysis_experiment(), s.effective_mesh_settings()
        regions = s.specimen.regions

        def work(progress, cancel):
            from app.core.mesh import quality, specimen_mesh

            mesh = specimen_mesh(exp, settings, progress=progress, cancel=cancel)
            progress("checking the mesh quality")
            return mesh, quality(mesh, regions).lines()

        self.task = Task(work, "mesh")
        self.task.progress.connect(self._task_progress)
        self.task.succeeded.connect(self._task_done)
        self.task.failed.connect(self._task_failed)
        self.task.cancelled.connect(self._task_cancelled)
        self.task.finished.connect(self._task_finished)
        self.mesh_button.setEnabled(False)
        self.cancel_button.setEnabled(True)
        self.mesh_state.setText("Meshing...")
        self.busy.emit("Meshing", 0, 0)
        log.info("meshing with element size %.2f mm, %.2f mm under the probe%s", settings.edge_mm,
                 settings.probe_edge_mm,
                 "" if settings.outline_edge_mm is None else f", {settings.outline_edge_mm:.2f} mm along its outline")
        self.task.start()

    def cancel(self) -> None:
        if self.task is not None:
            self.task.cancel()

    def _task_progress(self, text: str) -> None:
        self.mesh_state.setText(text[:1].upper() + text[1:])
        self.status.emit(text)
        log.info("%s", text)

    def _task_done(self, result) -> None:
        mesh, lines = result
        self.session.set_mesh(mesh, lines)
        self.status.emit(f"mesh ready: {mesh.n_nodes} nodes, {mesh.n_tets} tetrahedra")

    def _task_failed(self, exc, details) -> None:
        self.mesh_state.setText(f"Meshing failed: {exc}")
        self.error.emit(exc, details)

    def _task_cancelled(self) -> None:
        self.mesh_state.setText("Meshing cancelled.")
        self.status.emit("meshing cancelled")

    def _task_finished(self) -> None:
        self.task = None
        self.mesh_button.setEnabled(self.session.has_experiment)
        self.cancel_button.setEnabled(False)
        self.busy.emit("", 0, 0)

    def shutdown(self) -> None:
        self.cancel()
        if self.plotter is not None:
            try:
                self.plotter.close()
            except Exception:
                pass
            self.plotter = None

    # ---- 3-D ------------------------------------------------------------------------------------------
    def _redraw(self, *_):
        s = self.session
        legend = []
        if s.specimen is not None:
            for i, r in enumerate(s.specimen.regions):
                legend.append(f"<span style='color:{region_color(i)}'>&#9632;</span> {r.name}")
            legend.append("<span style='color:#333'>&#9632;</span> probe face")
            if self.show_plane.isChecked():
                legend.append("<span style='color:#e0a800'>&#9632;</span> image plane and ROI")
            if s.deformed is not None and self.show_deformed.isChecked():
                legend.append(f"deformed at {s.deformed[1]:.2f} mm probe travel (displacements to scale)")
        self.legend.setText("&nbsp;&nbsp;".join(legend))
        if self.plotter is None:
            return
        p = self.plotter
        p.clear()
        if s.specimen is None:
            p.render()
            return
        try:
            self._draw_scene(p)
        except Exception:  # a broken view must not take the panel down
            log.warning("3-D view failed:\n%s", traceback.format_exc())
        p.render()

    def _draw_scene(self, p) -> None:
        import pyvista as pv

        s = self.session
        exp = s.experiment
        sx, sy, sz = s.specimen.size_mm
        deformed = s.deformed if self.show_deformed.isChecked() else None
        travel = deformed[1] if deformed is not None else 0.0
        box = pv.Box(bounds=(0, sx, 0, sy, 0, sz))
        p.add_mesh(box.outline(), color="#33415c", line_width=1.5)
        mesh = s.mesh
        cut_y = exp.probe.center_mm[1]
        if mesh is not None and self.show_mesh.isChecked():
            pts = deformed[0] if deformed is not None and len(deformed[0]) == mesh.n_nodes else mesh.points_mm
            cells = np.hstack([np.full((mesh.n_tets, 1), 4), mesh.tets]).ravel()
            grid = pv.UnstructuredGrid(cells, np.full(mesh.n_tets, pv.CellType.TETRA, np.uint8), np.asarray(pts, float))
            grid.cell_data["region"] = mesh.labels
            # cut away the half in front of the image plane: the regions show on the cut face
            part = grid.clip(normal=(0.0, 1.0, 0.0), origin=(0.0, cut_y, 0.0), invert=True)
            colors = [region_color(i) for i in range(len(mesh.region_names))]
            from matplotlib.colors import ListedColormap

            p.add_mesh(part, scalars="region", cmap=ListedColormap(colors), clim=(-0.5, len(colors) - 0.5),
                       show_edges=True, edge_color="#4a4a4a", line_width=0.4, show_scalar_bar=False,
                       opacity=1.0, categories=True)
        else:
            p.add_mesh(box, color=region_color(0), opacity=0.12, show_edges=False)
            for i, r in enumerate(s.specimen.regions):
                if i == 0:
                    continue
                v, f = r.surface(edge_mm=2.0)
                surf = pv.PolyData(np.asarray(v, float), np.hstack([np.full((len(f), 1), 3), f]).ravel())
                p.add_mesh(surf, color=region_color(i), opacity=0.85, smooth_shading=True)
        # probe face, moved with the probe
        x0, x1, y0, y1 = exp.probe.face_rect_mm()
        z = sz - travel + 0.05
        face = pv.Rectangle([[x0, y0, z], [x1, y0, z], [x1, y1, z]])
        p.add_mesh(face, color="#333333", opacity=0.9)
        probe_body = pv.Box(bounds=(x0, x1, y0, y1, z, z + max(5.0, 0.15 * sz)))
        p.add_mesh(probe_body, color="#7a7a7a", opacity=0.35)
        if self.show_plane.isChecked() and s.image_shape is not None:
            self._draw_image_plane(p, travel, textured=mesh is None or not self.show_mesh.isChecked())
        p.add_axes(line_width=2, labels_off=False)
        # look at the image plane (its normal is +y) from the front, a little from above and the side
        c = np.array([sx / 2, cut_y, sz / 2])
        diag = float(np.linalg.norm([sx, sy, sz]))
        p.camera_position = [tuple(c + diag * np.array([0.75, 1.55, 0.95])), tuple(c), (0, 0, 1)]
        p.reset_camera()
        p.camera.zoom(1.2)

    def _draw_image_plane(self, p, travel: float, textured: bool = True) -> None:
        import pyvista as pv

        from app.core.images import pixel_to_world

        s = self.session
        rows, cols = s.image_shape
        corners = pixel_to_world(np.array([0, cols, 0]), np.array([0, 0, rows]), s.experiment, travel)
        o, a, b = corners[0], corners[1] - corners[0], corners[2] - corners[0]
        lift = np.array([0.0, 0.08, 0.0])  # just in front of the cut face, no z-fighting
        outline = np.array([o, o + a, o + a + b, o + b, o]) + lift
        p.add_mesh(pv.lines_from_points(outline), color="#e0a800", line_width=2)
        if textured:  # the frame itself on the plane
            from .common import normalized

            frame = s.frame(s.target_frame if travel else s.source_frame)
            grey = (255 * normalized(frame)).astype(np.uint8)
            quad = pv.PolyData(outline[:4], np.array([4, 0, 1, 2, 3]))
            quad.active_texture_coordinates = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], float)
            rgb = np.repeat(grey[..., None], 3, axis=2)
            p.add_mesh(quad, texture=pv.Texture(rgb[::-1].copy()), opacity=0.9)
        if s.roi_px is not None:
            c0, r0, c1, r1 = s.roi_px
            rc = pixel_to_world(np.array([c0, c1, c1, c0, c0]), np.array([r0, r0, r1, r1, r0]), s.experiment, travel)
            p.add_mesh(pv.lines_from_points(rc + 2 * lift), color="#ffb300", line_width=3)

    def grab_with_3d(self) -> QPixmap:
        """The panel as an image, with the 3-D view painted in (offscreen platforms leave it blank)."""
        pm = self.grab()
        if self.plotter is None:
            return pm
        try:
            img = np.ascontiguousarray(self.plotter.screenshot(None, return_img=True))
        except Exception:
            return pm
        h, w = img.shape[:2]
        qimg = QImage(img.data, w, h, 3 * w, QImage.Format_RGB888).copy()
        top_left = self.view_widget.mapTo(self, self.view_widget.rect().topLeft())
        painter = QPainter(pm)
        painter.drawImage(top_left, qimg.scaled(self.view_widget.size(), Qt.IgnoreAspectRatio, Qt.SmoothTransformation))
        painter.end()
        return pm


def _triple(widgets, labels) -> QWidget:
    w = QWidget()
    lay = QHBoxLayout(w)
    lay.setContentsMargins(0, 0, 0, 0)
    lay.setSpacing(3)
    for sp, lab in zip(widgets, labels):
        sp.setPrefix(f"{lab} ")
        sp.setSuffix("")
        lay.addWidget(sp)
    return w
