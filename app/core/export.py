"""Exports of a calibrated model and of an identification report.

- VTU (through meshio): the tetrahedral mesh with region label, Young's
  modulus (kPa) and Poisson's ratio per cell, for visualization and for the
  simulators that read VTK.
- FEBio input (.feb, FEBio 4 format): one isotropic elastic material and one
  solid domain per region; the paper's boundary conditions (bottom fixed, probe
  face bonded and pushed down). Units: mm, N, MPa (E_MPa = E_kPa / 1000).
- HTML report: parameters with their uncertainties and references, the cost,
  the identifiability report, the force curve (inline SVG) and the overlays
  (inline PNG); with a model check, its versions and their errors (a table and
  a chart) and the last diagnosis (the verdict, the ranked effects, the evidence).
"""

from __future__ import annotations

import base64
import html
import io
from datetime import datetime
from pathlib import Path
from xml.etree import ElementTree as ET

import numpy as np

from app.core.identify import percent_text
from app.core.mesh import TetMesh


def region_moduli(mesh: TetMesh, parameters: dict) -> np.ndarray:
    """E (kPa) of each region of the mesh from ``E_<region>_kPa`` parameters."""
    try:
        return np.array([float(parameters[f"E_{n}_kPa"]) for n in mesh.region_names])
    except KeyError as exc:
        raise ValueError(f"no modulus for region {exc.args[0][2:-4]!r} among {sorted(parameters)}") from None


def write_vtu(path: str | Path, mesh: TetMesh, parameters: dict, nu: float = 0.49) -> Path:
    import meshio

    E = region_moduli(mesh, parameters)
    cells = [("tetra", mesh.tets.astype(np.int64))]
    data = {"region": [mesh.labels.astype(np.int32)], "E_kPa": [E[mesh.labels]],
            "nu": [np.full(mesh.n_tets, float(nu))]}
    meshio.write(str(path), meshio.Mesh(mesh.points_mm, cells, cell_data=data), file_format="vtu")
    return Path(path)


def write_feb(path: str | Path, mesh: TetMesh, parameters: dict, nu: float = 0.49,
              probe_travel_mm: float = 1.0, steps: int = 10) -> Path:
    """FEBio 4 input: static solid analysis of the indentation by ``probe_travel_mm``."""
    E = region_moduli(mesh, parameters)
    root = ET.Element("febio_spec", version="4.0")
    ET.SubElement(root, "Module", type="solid")
    ctrl = ET.SubElement(root, "Control")
    for k, v in (("analysis", "STATIC"), ("time_steps", str(steps)), ("step_size", f"{1.0 / steps:g}")):
        ET.SubElement(ctrl, k).text = v
    mats = ET.SubElement(root, "Material")
    for r, name in enumerate(mesh.region_names):
        m = ET.SubElement(mats, "material", id=str(r + 1), name=name, type="isotropic elastic")
        ET.SubElement(m, "density").text = "1"
        ET.SubElement(m, "E").text = f"{E[r] / 1000.0:.9g}"
        ET.SubElement(m, "v").text = f"{nu:.6g}"
    geo = ET.SubElement(root, "Mesh")
    nodes = ET.SubElement(geo, "Nodes", name="specimen")
    for i, p in enumerate(mesh.points_mm):
        ET.SubElement(nodes, "node", id=str(i + 1)).text = ",".join(f"{x:.9g}" for x in p)
    eid = 1
    for r, name in enumerate(mesh.region_names):
        els = ET.SubElement(geo, "Elements", type="tet4", name=name)
        for t in mesh.tets[mesh.labels == r]:
            ET.SubElement(els, "elem", id=str(eid)).text = ",".join(str(int(i) + 1) for i in t)
            eid += 1
    bottom = np.flatnonzero(mesh.points_mm[:, 2] < 1e-6) + 1
    probe = np.flatnonzero(mesh.probe_nodes()) + 1
    ET.SubElement(geo, "NodeSet", name="bottom").text = ",".join(map(str, bottom))
    ET.SubElement(geo, "NodeSet", name="probe").text = ",".join(map(str, probe))
    domains = ET.SubElement(root, "MeshDomains")
    for name in mesh.region_names:
        ET.SubElement(domains, "SolidDomain", name=name, mat=name)
    bcs = ET.SubElement(root, "Boundary")
    fix = ET.SubElement(bcs, "bc", name="table", node_set="bottom", type="zero displacement")
    for d in ("x_dof", "y_dof", "z_dof"):
        ET.SubElement(fix, d).text = "1"
    lat = ET.SubElement(bcs, "bc", name="probe_bonded", node_set="probe", type="zero displacement")
    for d, v in (("x_dof", "1"), ("y_dof", "1"), ("z_dof", "0")):
        ET.SubElement(lat, d).text = v
    push = ET.SubElement(bcs, "bc", name="probe_travel", node_set="probe", type="prescribed displacement")
    ET.SubElement(push, "dof").text = "z"
    ET.SubElement(push, "value", lc="1").text = f"{-float(probe_travel_mm):.9g}"
    ET.SubElement(push, "relative").text = "0"
    loads = ET.SubElement(root, "LoadData")
    lc = ET.SubElement(loads, "load_controller", id="1", name="ramp", type="loadcurve")
    ET.SubElement(lc, "interpolate").text = "LINEAR"
    pts = ET.SubElement(lc, "points")
    ET.SubElement(pts, "pt").text = "0,0"
    ET.SubElement(pts, "pt").text = "1,1"
    out = ET.SubElement(root, "Output")
    plot = ET.SubElement(out, "plotfile", type="febio")
    for v in ("displacement", "stress", "reaction forces"):
        ET.SubElement(plot, "var", type=v)
    ET.indent(root)
    Path(path).write_text('<?xml version="1.0" encoding="ISO-8859-1"?>\n' + ET.tostring(root, encoding="unicode")
                          + "\n", encoding="iso-8859-1")
    return Path(path)


def _norm(a) -> np.ndarray:
    """Grey levels scaled to [0, 1] between the 1st and 99th percentiles."""
    a = np.asarray(a, float)
    lo, hi = np.percentile(a, [1, 99])
    return np.clip((a - lo) / max(hi - lo, 1e-12), 0, 1)


def overlay_rgb(warped: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The paper's subtraction view: target in red, warped source in green (uint8 RGB)."""
    rgb = np.zeros(target.shape + (3,))
    rgb[..., 0] = _norm(target)
    rgb[..., 1] = _norm(warped)
    return (rgb * 255).astype(np.uint8)


# matplotlib's "inferno" (the window's residual map) at nine points, interpolated between
_INFERNO = np.array([(0, 0, 4), (31, 12, 72), (85, 15, 109), (136, 34, 106), (186, 54, 85), (227, 89, 51),
                     (249, 140, 10), (249, 201, 50), (252, 255, 164)], float) / 255.0
OUTLINE_RGB = (57, 230, 57)  # the window's outline green
# on and off lengths (px of the drawn image) of the outlines' line styles
_DASHES = {"region": None, "located": (8.0, 6.0), "also fits": (2.0, 5.0)}


def residual_map_rgb(residual: np.ndarray, frame_roi: np.ndarray, lines=(), scale: int = 2) -> np.ndarray:
    """The window's residual map as an image (uint8 RGB, ``scale`` times the ROI):
    1 - local correlation in inferno over the dimmed frame (the frame alone where
    the map is NaN), and ``lines``, each (polyline (n, 2) of (col, row) px in the
    ROI, kind: "region" solid, "located" dashed, "also fits" dotted), in green."""
    res = np.asarray(residual, float)
    grey = 0.55 * _norm(frame_roi)
    t = np.clip(np.nan_to_num(res, nan=0.0), 0.0, 1.0) * (len(_INFERNO) - 1)
    i = np.minimum(t.astype(int), len(_INFERNO) - 2)
    w = (t - i)[..., None]
    color = (1 - w) * _INFERNO[i] + w * _INFERNO[i + 1]
    rgb = np.where(np.isfinite(res)[..., None], 0.15 * grey[..., None] + 0.85 * color, grey[..., None])
    rgb = np.repeat(np.repeat(rgb, scale, axis=0), scale, axis=1)
    H, W = rgb.shape[:2]
    for line, kind in lines:
        pts = (np.asarray(line, float) + 0.5) * scale  # pixel centres
        seg = np.diff(pts, axis=0)
        length = np.hypot(seg[:, 0], seg[:, 1])
        along = np.concatenate([[0.0], np.cumsum(length)])
        s = np.arange(0.0, along[-1] + 0.25, 0.25)
        xy = np.column_stack([np.interp(s, along, pts[:, 0]), np.interp(s, along, pts[:, 1])])
        dash = _DASHES[kind]
        if dash is not None:
            xy = xy[np.mod(s, dash[0] + dash[1]) < dash[0]]
        for dc, dr in ((0, 0), (1, 0), (0, 1), (1, 1)):  # two pixels wide
            c = np.clip(np.floor(xy[:, 0] - 0.5).astype(int) + dc, 0, W - 1)
            r = np.clip(np.floor(xy[:, 1] - 0.5).astype(int) + dr, 0, H - 1)
            rgb[r, c] = np.asarray(OUTLINE_RGB) / 255.0
    return np.clip(np.round(rgb * 255), 0, 255).astype(np.uint8)


def _png_b64(rgb: np.ndarray) -> str:
    import imageio.v3 as iio

    buf = io.BytesIO()
    iio.imwrite(buf, rgb, extension=".png")
    return base64.b64encode(buf.getvalue()).decode()


def _force_svg(d_mm, measured_N, model_N, width=560, height=300) -> str:
    d = np.asarray(d_mm, float)
    f = np.asarray(measured_N, float)
    m = None if model_N is None else np.asarray(model_N, float)
    xs = (d.min(), d.max() if d.max() > d.min() else d.min() + 1)
    allf = f if m is None else np.concatenate([f, m])
    ys = (min(0.0, allf.min()), allf.max() if allf.max() > 0 else 1.0)
    L, R, T, B = 60, 15, 15, 45

    def px(x, y):
        return (L + (x - xs[0]) / (xs[1] - xs[0]) * (width - L - R),
                height - B - (y - ys[0]) / (ys[1] - ys[0]) * (height - T - B))

    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" font-family="sans-serif" '
             f'font-size="12"><rect width="100%" height="100%" fill="white"/>']
    x0, y0 = px(xs[0], ys[0])
    x1, y1 = px(xs[1], ys[1])
    parts.append(f'<rect x="{x0}" y="{y1}" width="{x1 - x0}" height="{y0 - y1}" fill="none" stroke="#888"/>')
    for k in range(5):
        xv = xs[0] + k * (xs[1] - xs[0]) / 4
        yv = ys[0] + k * (ys[1] - ys[0]) / 4
        parts.append(f'<text x="{px(xv, ys[0])[0]:.1f}" y="{y0 + 16}" text-anchor="middle">{xv:.3g}</text>')
        parts.append(f'<text x="{L - 6}" y="{px(xs[0], yv)[1] + 4:.1f}" text-anchor="end">{yv:.3g}</text>')
    parts.append(f'<text x="{(x0 + x1) / 2}" y="{height - 8}" text-anchor="middle">probe travel (mm)</text>')
    parts.append(f'<text x="14" y="{(y0 + y1) / 2}" transform="rotate(-90 14 {(y0 + y1) / 2})" '
                 f'text-anchor="middle">force (N)</text>')
    step = max(1, len(d) // 800)
    pts = " ".join(f"{a:.1f},{b:.1f}" for a, b in (px(x, y) for x, y in zip(d[::step], f[::step])))
    parts.append(f'<polyline points="{pts}" fill="none" stroke="#1f77b4" stroke-width="1.5"/>')
    if m is not None:
        pts = " ".join(f"{a:.1f},{b:.1f}" for a, b in (px(x, y) for x, y in zip(d[::step], m[::step])))
        parts.append(f'<polyline points="{pts}" fill="none" stroke="#d62728" stroke-width="1.5" '
                     f'stroke-dasharray="6,3"/>')
    parts.append(f'<text x="{L + 10}" y="{T + 14}" fill="#1f77b4">measured</text>')
    if m is not None:
        parts.append(f'<text x="{L + 10}" y="{T + 30}" fill="#d62728">model</text>')
    parts.append("</svg>")
    return "".join(parts)


def _fmt(v, digits: int = 3) -> str:
    if v is None or not isinstance(v, (int, float)) or not np.isfinite(v):
        return "&ndash;"
    return f"{v:.{digits}g}" if abs(v) < 1000 else f"{v:,.0f}"


def _versions_svg(labels, series, width=560, height=220) -> str:
    """The errors across versions: one polyline per (name, colour, values, unit),
    each scaled to its own largest value (the axis reads as a fraction of it)."""
    n = len(labels)
    L, R, T, B = 45, 15, 44, 40
    xs = [L + (k + 0.5) * (width - L - R) / max(n, 1) for k in range(n)]
    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" font-family="sans-serif" '
             f'font-size="12"><rect width="100%" height="100%" fill="white"/>',
             f'<rect x="{L}" y="{T}" width="{width - L - R}" height="{height - T - B}" fill="none" stroke="#888"/>']
    for k in range(3):
        y = T + k * (height - T - B) / 2
        parts.append(f'<text x="{L - 6}" y="{y + 4:.1f}" text-anchor="end">{1 - k / 2:g}</text>')
    for x, lab in zip(xs, labels):
        parts.append(f'<text x="{x:.1f}" y="{height - B + 16}" text-anchor="middle">{html.escape(lab)}</text>')
    legend_y = 14
    for name, colour, values, unit in series:
        vals = [v if isinstance(v, (int, float)) and np.isfinite(v) else None for v in values]
        top = max((v for v in vals if v is not None), default=0.0)
        if top <= 0:
            continue
        pts = [(x, T + (1 - v / top) * (height - T - B)) for x, v in zip(xs, vals) if v is not None]
        parts.append(f'<polyline points="{" ".join(f"{a:.1f},{b:.1f}" for a, b in pts)}" fill="none" '
                     f'stroke="{colour}" stroke-width="2"/>')
        parts.extend(f'<circle cx="{a:.1f}" cy="{b:.1f}" r="3.5" fill="{colour}"/>' for a, b in pts)
        text = f"{name} (1 = {_fmt(top)} {unit})"
        parts.append(f'<text x="{L}" y="{legend_y}" fill="{colour}">{html.escape(text)}</text>')
        legend_y += 15
    parts.append("</svg>")
    return "".join(parts)


def verdict_html(parts: tuple[str, str, str, str], tie_style: str = "") -> str:
    """A diagnosis' verdict in words (head, the rest, the masked pair's sentence or
    "", the advice (near tie, probe contact) or ""; app.gui.models.modelcheck.verdict_parts)
    as HTML paragraphs: the head in bold, then the rest; the masked pair's sentence
    with its first word ("But", "Or") in bold; the advice after a warning sign, in
    ``tie_style`` (a CSS declaration). The window's verdict box and the report."""
    head, rest, masked, tie = parts
    out = f"<b>{html.escape(head)}</b>{html.escape(rest)}"
    if masked:
        first, _, after = masked.partition(" ")
        out += f"<br><br><b>{html.escape(first)}</b> {html.escape(after)}"
    if tie:
        style = f" style='{tie_style}'" if tie_style else ""
        out += f"<br><br><span{style}>\u26a0 {html.escape(tie)}</span>"
    return out


def _model_check_html(mc: dict) -> str:
    """The model check section: the versions and their errors (as the window's
    history), the error chart, and the last diagnosis. ``mc`` is plain data (see
    app.gui.models.modelcheck.report_data)."""
    e = html.escape
    rows = []
    for v in mc["versions"]:
        mark = "&#9654; " if v["current"] else ""
        note = e(v.get("note") or "") + (f'<br><span style="color:#b26a00">warning: {e(v["warning"])}</span>'
                                        if v.get("warning") else "")
        rows.append(f"<tr><td>{mark}{v['index']}</td><td style='text-align:left'>{e(v['label'])}</td>"
                    f"<td style='text-align:left'>{e(v['parameters'])}</td><td>{_fmt(v.get('force_rms_N'))}</td>"
                    f"<td>{_fmt(v.get('displacement_rms_px'))}</td><td>{_fmt(v.get('force_excess_N'))}</td>"
                    f"<td>{_fmt(v.get('displacement_excess_px'))}</td><td>{_fmt(v.get('chi2'), 5)}</td>"
                    f"<td style='text-align:left'>{note}</td></tr>")
    labels = [f"{v['index']}: {v['label']}" for v in mc["versions"]]
    chart = _versions_svg(labels, [
        ("displacement beyond the noise", "#1f77b4", [v.get("displacement_excess_px") for v in mc["versions"]], "px"),
        ("force beyond the noise", "#d62728", [v.get("force_excess_N") for v in mc["versions"]], "N")])
    out = [f"""<h2>Model check</h2>
<p>Version {mc['current']} is current (&#9654;). The errors are RMS over the force log and the tracked speckle;
&ldquo;beyond the noise&rdquo; is the part the stated noise model cannot explain (0 for a model as good as the
data allow).</p>
<table><tr><th>#</th><th>model</th><th>parameters</th><th>force RMS (N)</th><th>displacement RMS (px)</th>
<th>force beyond noise (N)</th><th>displacement beyond noise (px)</th><th>chi2</th><th>note</th></tr>
{"".join(rows)}</table>
<h3>Error across versions</h3>{chart}"""]
    for v in mc["versions"]:
        if v.get("mesh_check"):
            head, *rest = v["mesh_check"]
            out.append(f"<h3>Mesh check of {e(head)}</h3><pre>{e(chr(10).join(rest))}</pre>")
    maps = mc.get("maps") or []
    if maps:
        figs = "".join(f'<figure><img src="data:image/png;base64,{_png_b64(m["rgb"])}"/>'
                       f"<figcaption>{e(m['caption'])}</figcaption></figure>" for m in maps)
        out.append(f"""<h3>Where the current model fails</h3>
<p>Per frame, the residual map over the ROI: where the source warped by the model still disagrees with the
frame (dark: they match; yellow: unrelated). Green outlines: where the model puts its regions in that frame;
dashed, an inclusion the last diagnosis located; dotted, where it would fit nearly as well.</p>{figs}""")
    d = mc.get("diagnosis")
    if d is not None:
        bold = ' style="font-weight:bold"'
        cands = "".join(
            f"<tr{bold if c['verdict'] else ''}><td>{c['rank']}</td><td style='text-align:left' title='{e(c['title'])}'>{e(c['effect'])}</td>"
            f"<td>{e(c['score_text'])}</td><td style='text-align:left'>{e(c['parameters'])}</td>"
            f"<td style='text-align:left'>{e(c['evidence'])}</td></tr>" for c in d["candidates"])
        verdict = verdict_html((d["head"], d["rest"], d.get("masked", ""), d.get("tie", "")))
        out.append(f"""<h3>Last diagnosis (of version {d['version']}, {d['seconds']:.0f} s)</h3>
<p style="background:#fff6d6;padding:8px">{verdict}</p>
<p>Noise model: {e(d['noise'])}.</p>
<table><tr><th>#</th><th>effect</th><th>score (BIC)</th><th>key parameters</th><th>evidence</th></tr>
{cands}</table>""")
    return "\n".join(out)


def write_report_html(path: str | Path, *, experiment, parameters: dict | None, cost: dict | None = None,
                      standard_error_rel: dict | None = None, identifiability_lines=(), effects=(),
                      model_force_N=None, overlays=(), mesh_lines=(), nu: float = 0.49,
                      model_check: dict | None = None, mesh_check_lines=()) -> Path:
    """A self-contained HTML report of one identification and, given
    ``model_check`` (see :func:`_model_check_html`), of the model check.
    ``parameters`` None: no identification was run (a model check only).
    ``mesh_check_lines``: the identification's mesh check in words
    (app.core.mesh_check.MeshCheck.lines), if one was run."""
    e = html.escape
    cost = cost or {}
    ref = experiment.reference_moduli_kPa(nu)
    se = standard_error_rel or {}
    rows = []
    for name, val in (parameters or {}).items():
        s = se.get(name)
        s_txt = "undetermined" if s is None or not np.isfinite(s) else f"&plusmn;{percent_text(s)}"
        region = name[2:-4] if name.startswith("E_") and name.endswith("_kPa") else None
        r_txt = f"{ref[region]:.1f}" if region in ref else "&ndash;"
        rows.append(f"<tr><td>{e(name)}</td><td>{val:.2f}</td><td>{s_txt}</td><td>{r_txt}</td></tr>")
    log = experiment.force_log
    svg = _force_svg(log.displacement_mm, log.force_N, model_force_N)
    imgs = "".join(f'<figure><img src="data:image/png;base64,{_png_b64(overlay_rgb(w, t))}"/>'
                   f"<figcaption>{e(cap)}: red target, green warped source</figcaption></figure>"
                   for cap, w, t in overlays)
    model_line = f"linear elasticity, P2 tetrahedra, Poisson's ratio {nu:g}; effects: " + \
        e(", ".join(effects) or "none (baseline)")
    if parameters is None and model_check:
        current = next(v for v in model_check["versions"] if v["current"])
        model_line = (f"the model check's current version, {current['index']} ({e(current['label'])}); P2 "
                      f"tetrahedra, Poisson's ratio {nu:g}")
    if parameters is None:
        ident = ("<h2>Parameters</h2><p>No identification was run in the Identification panel; the model "
                 "check below has the fitted parameters of each version.</p>")
    else:
        ident = f"""<h2>Parameters</h2><table><tr><th>parameter</th><th>identified</th><th>standard error</th>
<th>reference</th></tr>{"".join(rows)}</table>
<p>Cost: total {cost.get("total", float("nan")):.5f}, NMI {cost.get("nmi", float("nan")):.4f},
force RMS misfit {cost.get("force_rms_N", float("nan")):.4f} N.</p>
<h2>Identifiability</h2><pre>{e(chr(10).join(identifiability_lines))}</pre>"""
        if mesh_check_lines:
            ident += f"""
<h2>Mesh check</h2><pre>{e(chr(10).join(mesh_check_lines))}</pre>"""
    doc = f"""<!DOCTYPE html><html><head><meta charset="utf-8"><title>ElastoID report: {e(experiment.name)}</title>
<style>body{{font-family:sans-serif;max-width:980px;margin:2em auto;color:#222}}table{{border-collapse:collapse}}
td,th{{border:1px solid #ccc;padding:4px 10px;text-align:right}}th{{background:#eef}}figure{{display:inline-block;margin:8px}}
img{{image-rendering:pixelated;max-width:420px}}pre{{background:#f6f6f6;padding:8px;white-space:pre-wrap}}</style></head><body>
<h1>ElastoID report</h1>
<p><b>Experiment:</b> {e(experiment.name)}<br><b>Folder:</b> {e(str(experiment.path or ""))}<br>
<b>Model:</b> {model_line}<br>
<b>Made:</b> {datetime.now().isoformat(timespec="seconds")}</p>
{ident}
<h2>Force</h2>{svg}
<h2>Overlays</h2>{imgs or "<p>(none)</p>"}
{_model_check_html(model_check) if model_check else ""}
<h2>Mesh</h2><pre>{e(chr(10).join(mesh_lines)) or "(no identification mesh in this session)"}</pre>
</body></html>"""
    Path(path).write_text(doc, encoding="utf-8")
    return Path(path)
