"""Refinement study of the probe force on the paper's phantom (docs/method.md).

    python bench/refinement.py [--levels 1.4,1.0,0.8,0.65]

Meshes the demo specimen at several scales of the automatic sizes, solves the
baseline model at the paper's moduli (B 18 kPa, A 63 kPa) and prints the probe
force at 14.8 mm with its change from the previous level and an extrapolated
limit (Richardson, from the last three levels).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from app.core.experiment import read_experiment  # noqa: E402
from app.core.forward import build_model  # noqa: E402
from app.core.mesh import auto_settings, specimen_mesh  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--levels", default="1.4,1.0,0.8,0.65")
    ap.add_argument("--experiment", default=str(ROOT / "resources" / "demo"))
    args = ap.parse_args(argv)
    exp = read_experiment(args.experiment)
    base = auto_settings(exp.specimen.size_mm, exp.probe.face_rect_mm(), exp.specimen.regions)
    rows = []
    for s in (float(x) for x in args.levels.split(",")):
        settings = base.with_scale(s)
        mesh = specimen_mesh(exp, settings)
        t0 = time.perf_counter()
        model = build_model(mesh)
        _, g = model.solve([18.0, 63.0])
        rows.append((s, settings.edge_mm, settings.probe_edge_mm, mesh.n_nodes, mesh.n_tets,
                     int(mesh.probe_nodes().sum()), model.space.n_dofs, 14.8 * g, time.perf_counter() - t0))
    print("| scale | edge mm | probe edge mm | vertices | tets | probe-face vertices | P2 dofs | force at 14.8 mm (N) | change | solve s |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    prev = None
    for r in rows:
        change = "" if prev is None else f"{100 * (r[7] - prev) / prev:+.2f}%"
        print(f"| {r[0]:.2f} | {r[1]:.2f} | {r[2]:.2f} | {r[3]} | {r[4]} | {r[5]} | {r[6]} | {r[7]:.3f} | {change} | {r[8]:.1f} |")
        prev = r[7]
    if len(rows) >= 3:
        f1, f2, f3 = (r[7] for r in rows[-3:])
        if (f2 - f1) * (f3 - f2) > 0 and abs(f2 - f1) > abs(f3 - f2):
            ratio = (f2 - f1) / (f3 - f2)
            print(f"Richardson-style limit from the last three levels: {f3 + (f3 - f2) / (ratio - 1):.3f} N")


if __name__ == "__main__":
    main()
