"""Mesh panel: regions edited in memory only, meshing in a worker, statistics, 3-D view."""

from __future__ import annotations

from dataclasses import replace

import pytest
from conftest import TEST_MESH, folder_digest, wait_task_done


def test_edit_regions_in_memory_only(window, noise_experiment):
    before = folder_digest(noise_experiment)
    window.open_experiment(noise_experiment)
    panel = window.mesh_panel
    s = window.session
    assert panel.table.rowCount() == 2
    panel.add_button.click()
    assert s.specimen.region_names == ("B", "A", "C")
    assert s.specimen_edited and panel.table.rowCount() == 3
    assert [p.name for p in s.identification.parameters] == ["E_B_kPa", "E_A_kPa", "E_C_kPa"]
    # move and resize the new inclusion through the editor
    assert panel.selected_region_name() == "C"
    panel.center[0].setValue(15.0)
    panel.radius.setValue(4.0)
    c = next(r for r in s.specimen.regions if r.name == "C")
    assert c.center_mm[0] == 15.0 and c.radius_mm == 4.0
    # a region reaching outside the box is refused, not applied
    panel.radius.setValue(40.0)
    c = next(r for r in s.specimen.regions if r.name == "C")
    assert c.radius_mm == 4.0 and "outside" in panel.edit_note.text()
    # turn it into a box
    panel.kind_box.setCurrentText("box")
    c = next(r for r in s.specimen.regions if r.name == "C")
    assert c.kind == "box"
    panel.remove_button.click()
    assert s.specimen.region_names == ("B", "A")
    panel.reset_button.click()
    assert not s.specimen_edited
    assert folder_digest(noise_experiment) == before


def test_generate_mesh_in_a_worker(window, tiny_experiment, qtbot):
    window.open_experiment(tiny_experiment)
    s = window.session
    s.set_mesh_settings(replace(s.effective_mesh_settings(), **TEST_MESH))
    panel = window.mesh_panel
    assert panel.edge.value() == TEST_MESH["edge_mm"]
    seen = []
    panel.status.connect(seen.append)
    panel.mesh_button.click()
    assert panel.task is not None and not panel.mesh_button.isEnabled()
    qtbot.wait(30)  # the GUI stays live while meshing
    wait_task_done(qtbot, panel, 180)
    assert s.mesh is not None, [b.informativeText() for b in window.error_boxes]
    text = panel.quality.toPlainText()
    assert "tetrahedra" in text and "dihedral" in text and "region A" in text
    assert "Mesh ready" in panel.mesh_state.text()
    assert any("mesh" in x for x in seen)
    # editing the specimen drops the mesh
    panel.add_button.click()
    assert s.mesh is None


def test_cancel_meshing(window, tiny_experiment, qtbot):
    window.open_experiment(tiny_experiment)
    s = window.session
    s.set_mesh_settings(replace(s.effective_mesh_settings(), edge_mm=9.0, probe_edge_mm=2.9))  # not in the cache
    panel = window.mesh_panel
    panel.generate_mesh()
    qtbot.wait(300)
    panel.cancel_button.click()
    wait_task_done(qtbot, panel, 30)
    assert s.mesh is None
    assert "cancelled" in panel.mesh_state.text().lower()
    assert not window.error_boxes


@pytest.mark.view3d
def test_3d_view_draws_regions_mesh_and_deformed_shape(make_window, tiny_experiment, qtbot):
    win = make_window(enable_3d=None)
    panel = win.mesh_panel
    assert panel.plotter is not None, "the 3-D view should exist under Xvfb"
    win.open_experiment(tiny_experiment)
    win.raise_panel("mesh")
    qtbot.wait(50)
    n_actors_regions = len(panel.plotter.renderer.actors)
    assert n_actors_regions >= 5  # outline, box, region, probe face and body, plane...
    from app.core.mesh import MeshSettings, specimen_mesh

    s = win.session
    mesh = specimen_mesh(s.analysis_experiment(), MeshSettings(**TEST_MESH))
    s.set_mesh(mesh, ["test"])
    pts = mesh.points_mm.copy()
    pts[:, 2] -= 0.5 * pts[:, 2] / pts[:, 2].max()
    s.deformed = (pts, 3.0)
    s.deformed_changed.emit()
    img = panel.plotter.screenshot(None, return_img=True)
    assert img.shape[0] > 100 and img.std() > 5  # something was drawn
    assert "deformed at 3.00 mm" in panel.legend.text()


def test_automatic_mesh_sizes_by_default(window, noise_experiment, tmp_path):
    import json

    from app.core.mesh import auto_settings

    window.open_experiment(noise_experiment)
    s, panel = window.session, window.mesh_panel
    exp = s.experiment
    auto = auto_settings(exp.specimen.size_mm, exp.probe.face_rect_mm(), exp.specimen.regions)
    assert s.mesh_settings is None and panel.auto_sizes.isChecked()
    assert panel.edge.value() == pytest.approx(auto.edge_mm, abs=0.05) and not panel.edge.isEnabled()
    assert window._save_to(tmp_path / "auto.json")
    assert json.loads((tmp_path / "auto.json").read_text())["mesh_settings"] is None
    panel.auto_sizes.setChecked(False)  # the automatic sizes become the starting point
    assert s.mesh_settings == auto and panel.edge.isEnabled()
    panel.edge.setValue(7.0)
    assert s.mesh_settings.edge_mm == 7.0
    panel.auto_sizes.setChecked(True)
    assert s.mesh_settings is None


def test_the_outline_size_is_set_in_the_panel(window, tiny_experiment):
    """The "outline" box beside "Under the probe" sets the mesh's outline_edge_mm; its lowest value, "as
    the face", leaves it unset; it is editable only with the sizes not automatic, when it shows the
    automatic size (1.0 mm where the face's is coarser)."""
    from app.core.mesh import FINE_OUTLINE_MM, auto_settings

    window.open_experiment(tiny_experiment)
    s, panel = window.session, window.mesh_panel
    exp = s.experiment
    auto = auto_settings(exp.specimen.size_mm, exp.probe.face_rect_mm(), exp.specimen.regions)
    assert s.mesh_settings is None and not panel.outline_edge.isEnabled()
    if auto.probe_edge_mm > FINE_OUTLINE_MM:
        assert auto.outline_edge_mm == panel.outline_edge.value() == FINE_OUTLINE_MM
    else:
        assert auto.outline_edge_mm is None and panel.outline_edge.text() == "as the face"
    panel.auto_sizes.setChecked(False)
    assert panel.outline_edge.isEnabled()
    assert s.mesh_settings.outline_edge_mm == auto.outline_edge_mm  # unticking keeps the automatic sizes
    panel.outline_edge.setValue(0.5)
    assert s.mesh_settings.outline_edge_mm == 0.5
    assert s.mesh_settings.probe_edge_mm == panel.probe_edge.value()
    panel.outline_edge.setValue(0.0)
    assert s.mesh_settings.outline_edge_mm is None
    s.set_mesh_settings(replace(s.mesh_settings, outline_edge_mm=0.75))  # e.g. a saved session
    assert panel.outline_edge.value() == 0.75
