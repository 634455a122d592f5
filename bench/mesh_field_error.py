"""How far the identification mesh's linear field is from a finer mesh's, on the image plane.

    python bench/mesh_field_error.py [--reference 0.55] [--variants auto probe=1.0 probe=1.4+grading=0.25 ...]

With nothing hidden, the diagnosis' maximum-likelihood refit (the tracked
displacements and the force) puts E_A about 5% above the truth on the paper's
phantom, while the identification by NMI and force does not: the tracked
displacements ask the model for a field the automatic mesh cannot make at the
true moduli. This bench measures that mesh error directly, at the demo's true
moduli (18 and 63 kPa, nu 0.49): each sizing's linear displacement field at
14.8 mm of travel against the reference mesh's (every length of the automatic
sizing times ``--reference``), on the demo's warp control points, in pixels;
the probe's force per mm against the reference's; and each model's size.

Variants: ``auto`` (the automatic sizing: for the demo, the shipped mesh), or
``+``-joined changes to it: ``scale=s`` (every length times s), ``edge=mm``
(far from the probe), ``probe=mm`` (on the probe face), ``region=mm`` (in and
around region A), ``grading=g`` (mm of element size per mm from the probe),
``outline=mm`` (along the probe face's outline: MeshSettings.outline_edge_mm).
fTetWild makes a different mesh on every run (meshes are cached: set
ELASTOID_CACHE_DIR to an empty folder for fresh ones), so each row stands for
one mesh of its sizing.
"""


from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from app.core.fem import interpolation_matrix  # noqa: E402
from bench.hyperelastic_anp import MODULI_KPA, NU, image_plane_px, rms  # noqa: E402

TRAVEL_MM = 14.8
# a variant's names for MeshSettings' fields (``scale`` is MeshSettings.with_scale)
FIELDS = {"edge": "edge_mm", "probe": "probe_edge_mm", "region": "region_edge_mm", "grading": "grading",
          "outline": "outline_edge_mm"}


def settings_of(variant: str, auto):
    """The automatic sizes ``auto`` with a variant's changes (e.g. probe=1.4+grading=0.25)."""
    if variant == "auto":
        return auto
    out = auto
    for part in variant.split("+"):
        kind, val = part.split("=")
        out = out.with_scale(float(val)) if kind == "scale" else replace(out, **{FIELDS[kind]: float(val)})
    return out


def main() -> int:
    from app.core.experiment import read_experiment
    from app.core.forward import build_model
    from app.core.identify import Problem
    from app.core.mesh import auto_settings, specimen_mesh

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reference", type=float, default=0.55, help="the reference mesh's scale of the automatic sizing")
    ap.add_argument("--variants", nargs="+", default=["auto", "scale=0.8", "edge=8", "edge=6", "region=3", "probe=1.4",
                                                      "probe=1.0", "grading=0.25", "probe=1.4+grading=0.25",
                                                      "outline=1.0"])
    args = ap.parse_args()
    exp = read_experiment(ROOT / "resources" / "demo")
    auto = auto_settings(exp.specimen.size_mm, exp.probe.face_rect_mm(), exp.specimen.regions)
    pr = Problem.from_experiment(exp, mesh=specimen_mesh(exp))
    pts = pr.ctrl_world
    rows = {}
    for v in [f"scale={args.reference:g}"] + list(args.variants):
        t = time.perf_counter()
        mesh = specimen_mesh(exp, settings_of(v, auto))
        t_mesh = time.perf_counter() - t
        fe = build_model(mesh)
        t = time.perf_counter()
        u, k = fe.solve(list(MODULI_KPA), NU)
        t_solve = time.perf_counter() - t
        field = image_plane_px(TRAVEL_MM * (interpolation_matrix(fe.space, pts) @ u).reshape(-1, 3), pr, exp)
        rows[v] = (mesh.n_nodes, fe.space.n_dofs, field, k)
        print(f"{v}: {mesh.n_nodes} vertices, {fe.space.n_dofs} unknowns, meshed in {t_mesh:.0f} s, "
              f"solved in {t_solve:.1f} s", flush=True)
    ref = f"scale={args.reference:g}"
    _, _, f_ref, k_ref = rows[ref]
    print(f"\nlinear field at {TRAVEL_MM} mm, moduli {MODULI_KPA} kPa, against {ref}, on {len(pts)} control points")
    print(f"{'variant':>12s} {'vertices':>8s} {'unknowns':>8s} {'field - ref, rms px':>19s} {'lateral':>7s} "
          f"{'axial':>6s} {'max px':>6s} {'force/mm':>8s} {'vs ref':>7s}")
    for v, (n, dofs, f, k) in rows.items():
        d = f - f_ref
        print(f"{v:>12s} {n:8d} {dofs:8d} {rms(d):19.3f} {np.sqrt((d[:, 0]**2).mean()):7.3f} "
              f"{np.sqrt((d[:, 1]**2).mean()):6.3f} {np.abs(d).max():6.2f} {k:8.4f} {100 * (k / k_ref - 1):+6.2f}%")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
