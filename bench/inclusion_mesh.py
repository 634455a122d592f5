"""Meshing the demo with a located inclusion: the specimen meshes' fTetWild
envelope against the looser one a diagnosis uses for a located sphere.

    python bench/inclusion_mesh.py [--repeats 3] [--center X,Y,Z] [--radius R]

The sphere defaults to the one the demo's diagnosis locates (57.5, 45.0, 82.0 mm,
radius 13.5 mm). Each mesh is made anew (no cache) in fTetWild's child process
with one thread, as the application does. Prints, per envelope, the median
meshing time over the repeats, and the mesh of the last repeat: nodes,
tetrahedra, smallest dihedral angle and the sphere's volume against its
geometric volume.

Measured 2026-11-25, `--repeats 1` (times of the whole build_mesh, outline
conforming included): 35.7 s with 5e-4 (3,782 nodes, smallest dihedral 8.3
degrees, sphere volume -0.09%) and 15.1 s with 1e-3 (3,465 nodes, 11.8 degrees,
-0.35%). An earlier scratch run that timed fTetWild alone: 48.2 s and 18.5 s.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--center", default="57.5,45.0,82.0")
    ap.add_argument("--radius", type=float, default=13.5)
    args = ap.parse_args(argv)

    from app.core.diagnose import LOCATED_EPSILON, located_inclusion_settings
    from app.core.experiment import read_experiment
    from app.core.geometry import Region
    from app.core.mesh import build_mesh, quality

    exp = read_experiment(ROOT / "resources" / "demo")
    sphere = Region("I", "sphere", center_mm=tuple(float(c) for c in args.center.split(",")),
                    radius_mm=args.radius)
    exp = replace(exp, specimen=exp.specimen.with_region(sphere))
    located = located_inclusion_settings(exp)
    rect = exp.probe.face_rect_mm()
    rows = []
    for label, settings in (("specimen meshes' envelope", replace(located, epsilon=5e-4)),
                            (f"located inclusion's ({LOCATED_EPSILON:g})", located)):
        times = []
        for _ in range(args.repeats):
            t = time.perf_counter()
            mesh = build_mesh(exp.specimen.size_mm, rect, exp.specimen.regions, settings, use_cache=False)
            times.append(time.perf_counter() - t)
        q = quality(mesh, exp.specimen.regions)
        geo = q.region_geometric_volume_mm3["I"]
        rows.append((f"{label}, epsilon {settings.epsilon:g}", statistics.median(times), mesh.n_nodes, mesh.n_tets,
                     q.min_dihedral_deg, 100 * (q.region_volume_mm3["I"] / geo - 1)))
    width = max(len(r[0]) for r in rows)
    print(f"{'envelope':{width}s} {'seconds':>8s} {'nodes':>7s} {'tets':>7s} {'min dihedral':>12s} {'sphere volume':>13s}")
    for name, sec, nn, nt, dih, vol in rows:
        print(f"{name:{width}s} {sec:8.1f} {nn:7d} {nt:7d} {dih:11.1f}° {vol:+12.2f}%")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
