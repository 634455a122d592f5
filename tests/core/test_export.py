import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from app.core.experiment import read_experiment
from app.core.export import overlay_rgb, write_feb, write_report_html, write_vtu
from tests.core.helpers import cube_mesh

ROOT = Path(__file__).resolve().parents[2]


def _mesh():
    return cube_mesh(3, size=(30.0, 30.0, 20.0), probe_rect=(10.0, 20.0, 10.0, 20.0),
                     labels=lambda c: (np.linalg.norm(c - [15, 15, 10], axis=1) < 6).astype(np.int32))


def test_vtu_carries_regions_and_moduli(tmp_path):
    import meshio

    mesh = _mesh()
    p = write_vtu(tmp_path / "m.vtu", mesh, {"E_R0_kPa": 18.0, "E_R1_kPa": 63.0})
    back = meshio.read(p)
    assert np.allclose(back.points, mesh.points_mm)
    E = back.cell_data["E_kPa"][0]
    assert np.allclose(E, np.where(mesh.labels == 1, 63.0, 18.0))
    with pytest.raises(ValueError, match="R1"):
        write_vtu(tmp_path / "x.vtu", mesh, {"E_R0_kPa": 18.0})


def test_feb_follows_febio4_structure(tmp_path):
    mesh = _mesh()
    p = write_feb(tmp_path / "m.feb", mesh, {"E_R0_kPa": 18.0, "E_R1_kPa": 63.0}, nu=0.49, probe_travel_mm=14.8)
    root = ET.parse(p).getroot()
    assert root.tag == "febio_spec" and root.get("version") == "4.0"
    mats = {m.get("name"): float(m.find("E").text) for m in root.iter("material")}
    assert mats == {"R0": pytest.approx(0.018), "R1": pytest.approx(0.063)}  # MPa in mm-N-MPa units
    n_nodes = len(root.find("Mesh/Nodes"))
    n_elems = sum(len(els) for els in root.iter("Elements"))
    assert (n_nodes, n_elems) == (mesh.n_nodes, mesh.n_tets)
    ids = [int(x) for els in root.iter("Elements") for el in els for x in el.text.split(",")]
    assert min(ids) == 1 and max(ids) == mesh.n_nodes
    sets = {s.get("name"): s.text.split(",") for s in root.iter("NodeSet")}
    assert len(sets["probe"]) == int(mesh.probe_nodes().sum())
    push = [bc for bc in root.iter("bc") if bc.get("type") == "prescribed displacement"][0]
    assert float(push.find("value").text) == pytest.approx(-14.8) and push.find("dof").text == "z"
    assert {d.get("name") for d in root.iter("SolidDomain")} == {"R0", "R1"}


def test_html_report_holds_parameters_force_and_overlays(tmp_path):
    exp = read_experiment(ROOT / "resources" / "demo")
    rng = np.random.default_rng(0)
    w, t = rng.random((40, 50)), rng.random((40, 50))
    p = write_report_html(tmp_path / "r.html", experiment=exp, parameters={"E_B_kPa": 17.9, "E_A_kPa": 62.1},
                          cost={"total": -1.05, "nmi": 1.05, "force_rms_N": 0.02},
                          standard_error_rel={"E_B_kPa": 0.01, "E_A_kPa": float("inf")},
                          identifiability_lines=["E_A_kPa: weakly constrained"],
                          model_force_N=0.63 * np.clip(exp.force_log.displacement_mm, 0, None),
                          overlays=[("frame 2", w, t)])
    text = p.read_text()
    assert "62.10" in text and "63.0" in text and "undetermined" in text and "&plusmn;1.0%" in text
    assert text.count("<polyline") == 2 and "data:image/png;base64," in text
    assert overlay_rgb(w, t).shape == (40, 50, 3)
    assert "<h2>Mesh check</h2>" not in text  # none was run
    line = "mesh check: on a mesh 0.7 times the size (6,266 vertices against 2,558; 25 s): E_B 18.07 kPa (+0.9%)"
    text = write_report_html(tmp_path / "m.html", experiment=exp, parameters={"E_B_kPa": 17.9},
                             mesh_check_lines=[line]).read_text()
    assert f"<h2>Mesh check</h2><pre>{line}</pre>" in text


def test_html_report_holds_the_model_check(tmp_path):
    exp = read_experiment(ROOT / "resources" / "demo")
    version = dict(label="baseline", parameters="B 15.4 kPa", force_rms_N=0.0198, displacement_rms_px=1.10,
                   force_excess_N=0.0, displacement_excess_px=0.233, chi2=650.3, note="identified", warning="")
    mc = {"current": 1, "versions": [
        dict(version, index=0, current=False),
        dict(version, index=1, current=True, label="+ inclusion", displacement_excess_px=0.0, chi2=536.6,
             note="added inclusion", warning="it fits worse <than> version 0",
             mesh_check=["version 1 (+ inclusion)", "mesh check: on a mesh 0.7 times the size: E_B 15.4 -> 15.9"])],
        "diagnosis": {"version": 0, "verdict": "inclusion", "head": "Verdict: inclusion",
                      "rest": ", an undescribed inclusion. A region ...", "tie": "", "noise": "force: 0.02 N",
                      "seconds": 108.0, "candidates": [
                          dict(rank=1, effect="inclusion", title="t", score_text="+88.1", parameters="I 125.7 kPa",
                               evidence="deforms less", verdict=True),
                          dict(rank=2, effect="compressibility", title="t", score_text="+8.2", parameters="nu 0.47",
                               evidence="changes volume", verdict=False)]}}
    text = write_report_html(tmp_path / "r.html", experiment=exp, parameters=None, model_check=mc,
                             mesh_lines=()).read_text()
    assert "No identification was run" in text and "(no identification mesh in this session)" in text
    assert "<b>Model:</b> the model check's current version, 1 (+ inclusion)" in text
    section = text[text.index("<h2>Model check</h2>"):]
    assert "Version 1 is current" in section and "<td>&#9654; 1</td>" in section and "<td>0</td>" in section
    assert "warning: it fits worse &lt;than&gt; version 0" in section  # escaped
    assert section.count("<polyline") == 1  # the force error is 0 in both versions: nothing to chart
    assert "displacement beyond the noise (1 = 0.233 px)" in section
    assert "<b>Verdict: inclusion</b>, an undescribed inclusion." in section
    assert section.count("<h3>Mesh check of") == 1  # only the version that was checked
    assert ("<h3>Mesh check of version 1 (+ inclusion)</h3><pre>mesh check: on a mesh 0.7 times the size: "
            "E_B 15.4 -&gt; 15.9</pre>") in section
    assert '<tr style="font-weight:bold"><td>1</td>' in section and ">compressibility</td>" in section
    # without a model check the report is the identification's, as before
    plain = write_report_html(tmp_path / "p.html", experiment=exp, parameters={"E_B_kPa": 17.9},
                              cost={"nmi": 1.05}).read_text()
    assert "<h2>Model check</h2>" not in plain and "17.90" in plain


def test_the_residual_map_image_has_the_windows_colours_and_outlines():
    """The report's residual map: inferno's ends at 0 and 1, the dimmed frame where
    the map is NaN, a solid outline green all along, a dashed one green only in part."""
    from app.core.export import OUTLINE_RGB, residual_map_rgb

    res = np.zeros((40, 60))
    res[:, 30:] = 1.0
    res[:5, :5] = np.nan
    frame = np.tile(np.linspace(0.0, 1.0, 60), (40, 1))
    square = np.array([[10.0, 10], [20, 10], [20, 20], [10, 20], [10, 10]])
    across = np.array([[2.0, 30], [57, 30]])
    rgb = residual_map_rgb(res, frame, [(square, "region"), (across, "located")], scale=2)
    assert rgb.shape == (80, 120, 3) and rgb.dtype == np.uint8
    green = np.all(rgb == OUTLINE_RGB, axis=-1)
    lo, hi = np.percentile(frame, [1, 99])
    grey = 0.55 * 255 * np.clip((frame - lo) / (hi - lo), 0, 1)  # the frame, dimmed
    # 0: inferno's black and 1: its pale yellow, over 15% of the frame
    assert np.allclose(rgb[70, 40], 0.15 * grey[35, 20] + 0.85 * np.array([0, 0, 4]), atol=1)
    assert np.allclose(rgb[70, 100], 0.15 * grey[35, 50] + 0.85 * np.array([252, 255, 164]), atol=1)
    assert np.allclose(rgb[9, 9], grey[4, 4], atol=1) and np.ptp(rgb[9, 9]) == 0  # NaN: the frame alone
    # the square's edges (ROI px 10..20, drawn at 2x around pixel centres) are green throughout
    assert green[21:41, 21].all() and green[21, 21:41].all() and not green[25:37, 25:37].any()
    row = green[61]  # the dashed line along ROI row 30: dashes and gaps
    assert 0.4 < row[5:115].mean() < 0.8
