"""A hidden sphere's size against its stiffness: the identification's cost and the
fitted E_I along the trade-off, at the sphere's true centre.

    ELASTOID_CACHE_DIR=DIR python bench/inclusion_valley.py FOLDER --sphere X,Y,Z,R
                                       [--radii 4.5,5,5.5,6,6.5,7] [--region-scale S]

FOLDER is an experiment written by `elastoid simulate FOLDER --seed S --hidden
sphere:X,Y,Z,R,E_kPa` (its truth.toml gives the sphere's modulus). The true
sphere is meshed as a region with the located inclusion's automatic settings
(``--region-scale``: the regions' automatic sizes times this, as ``elastoid
diagnose --region-scale`` does) and the model identified there (NMI and force, every
modulus). Then each trial radius is laid on that one mesh as the placement's
trials are (the tets whose centroid lies in the sphere relabelled) and the
sphere's modulus alone refitted, as ``place_by_identification`` does. Prints,
per radius: the labelled volume's equivalent radius, E_I against the truth, and
the cost against the true radius's with the jackknife standard error of that
difference (``jackknife_se``, over the groups of ROI blocks ``_place_spread`` uses).

Measured 2026-12-02 (docs/model-check.md, "A stiff sphere's modulus needs a
finer mesh about it"), seed 42014 (a 70 kPa sphere at (30, 45, 82) r 6): with
the automatic region sizes (``--region-scale 1``) the true sphere fitted 57.1
kPa and the cost was lowest at r 5.5 (73.0 kPa), 3 standard errors below the
true radius's; with them halved (``--region-scale 0.5``), 71.1 kPa at the
true radius, the lowest cost, r 5.5 1.5 and r 6.5 3 standard errors above it.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--sphere", required=True, help="the hidden sphere's centre and radius, X,Y,Z,R in mm")
    ap.add_argument("--radii", default="4.5,5,5.5,6,6.5,7", help="trial radii in mm (the true one is added)")
    ap.add_argument("--region-scale", type=float, help="the regions' automatic sizes times this (default 1)")
    args = ap.parse_args(argv)

    import tomllib
    from dataclasses import replace

    import numpy as np

    from app.core.diagnose import (_cost_without_groups, _trial_builder, _with_inclusion, current_model,
                                    jackknife_se)
    from app.core.effects.model import fit
    from app.core.experiment import read_experiment

    x, y, z, r_true = (float(v) for v in args.sphere.split(","))
    truth = tomllib.loads((args.folder / "truth.toml").read_text())
    hidden = [h["name"] for h in truth.get("hidden_regions", [])]
    E_true = float(truth["moduli_kPa"][hidden[0]]) if hidden else math.nan
    exp = read_experiment(args.folder)
    sphere = {"name": "I", "center_mm": [x, y, z], "radius_mm": r_true}
    _, settings = _with_inclusion(exp, sphere, None)
    if args.region_scale is not None:
        settings = replace(settings, region_scale=args.region_scale)
    t0 = time.perf_counter()
    P = current_model(exp, ("inclusion",), inclusion=sphere, mesh_settings=settings)
    start = {**{f"E_{n}_kPa": float(v) for n, v in truth["moduli_kPa"].items() if n not in hidden},
             "E_I_kPa": E_true}
    params = fit(P, start, max_evaluations=300, step=0.15).parameters
    print(f"model at the true sphere: {P.mesh.n_nodes:,} vertices, {P.fe.space.n_dofs:,} dofs, built and identified "
          f"in {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    build = _trial_builder(P, params, None, "the valley")
    made = P.rm.factorize(P.theta(params))
    rows = []
    try:
        for r in sorted({float(v) for v in args.radii.split(",")} | {r_true}):
            tp = build({**sphere, "radius_mm": r})
            if tp is None:
                continue
            try:
                res = fit(tp, params, free=("E_I_kPa",), max_evaluations=60, step=0.3)
                groups = _cost_without_groups(tp, res.parameters)
                inside = tp.mesh.labels == list(tp.mesh.region_names).index("I")
                volume = float(np.abs(tp.mesh.tet_volumes_mm3()[inside]).sum())
            finally:
                tp.release()
            rows.append((r, (3 * volume / (4 * math.pi)) ** (1 / 3), res.parameters["E_I_kPa"], res.cost["total"],
                         groups))
            print(f"radius {r:g}: E_I {rows[-1][2]:.1f} kPa", file=sys.stderr, flush=True)
    finally:
        if made:
            P.rm.release()
    ref = next(row for row in rows if row[0] == r_true)
    print(f"{args.folder.name}: sphere ({x:g}, {y:g}, {z:g}) r {r_true:g} mm, E_I {E_true:g} kPa; region sizes "
          f"x{settings.region_scale:g}; at the true sphere (all moduli fitted): "
          + ", ".join(f"{k[:-4]} {v:.2f}" for k, v in params.items() if k.startswith("E_")) + " kPa")
    print("| radius (mm) | labelled volume's radius | E_I (kPa) | against the truth | cost - the true radius's "
          "| its standard error |")
    print("|---|---|---|---|---|---|")
    for r, r_eff, E, cost, groups in rows:
        se = math.nan if groups is None or ref[4] is None else jackknife_se(groups - ref[4])
        print(f"| {r:g} | {r_eff:.2f} | {E:.1f} | {100 * (E / E_true - 1):+.1f}% | {cost - ref[3]:+.2e} | "
              f"{se:.1e} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
