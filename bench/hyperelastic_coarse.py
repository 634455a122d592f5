"""How far each discretization's hyperelastic nonlinear part is from a finer mesh's.

    python bench/hyperelastic_coarse.py [--reference 0.7] [--scales 1.0 1.5 2.0] [--no-anp]

The cold hyperelastic solve at paper size factorizes its P2 tangent (52,173
unknowns) about 14 times, at about 1.2 s each on a 2-core machine. The ANP
experiment (bench/hyperelastic_anp.py) put the nonlinear part of linear tets
with an averaged nodal volume 0.63 px rms from the P2 solve's on the image
plane, and left open which of the two is nearer the continuum. This bench
solves the demo (moduli 18 and 63 kPa, travels 3.7 to 14.8 mm) with the P2
solver on meshes of the demo meshed afresh at several scales (every mesh length
times the scale: ``--reference``, finer, stands for the continuum) and with the
ANP on the product's size, and compares each one's nonlinear part (its
hyperelastic field minus its own linear field: what a correction added to the
P2 linear field would add) with the reference's, on the demo's warp control
points, in pixels. Also the linear fields' distance, the forces, and each
walk's time and factorizations (run it with nothing else on the machine).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from app.core.fem import interpolation_matrix  # noqa: E402
from bench.hyperelastic_anp import MODULI_KPA, NU, TRAVELS_MM, AveragedNodalVolume, image_plane_px, rms  # noqa: E402


def walk(fe, travels):
    from app.core.hyperelastic import HyperelasticModel

    t = time.perf_counter()
    hm = HyperelasticModel(fe, warm_starts=False)
    sol = hm.solve(list(MODULI_KPA), NU, travels)
    n = hm.n_factorizations
    hm.free()
    return sol, time.perf_counter() - t, n


def main() -> int:
    from app.core.experiment import read_experiment
    from app.core.fem import assemble, p1_space
    from app.core.forward import build_model
    from app.core.identify import Problem
    from app.core.mesh import MeshSettings, specimen_mesh

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reference", type=float, default=0.7, help="the reference P2 mesh's scale (< 1: finer)")
    ap.add_argument("--scales", type=float, nargs="+", default=[1.0, 1.5, 2.0])
    ap.add_argument("--no-anp", action="store_true", help="skip the ANP walk on the product's mesh")
    args = ap.parse_args()
    exp = read_experiment(ROOT / "resources" / "demo")
    travels = np.array(TRAVELS_MM)
    pr = Problem.from_experiment(exp, mesh=specimen_mesh(exp))
    pts = pr.ctrl_world

    def px(u3):
        return image_plane_px(u3, pr, exp)

    sources = {}  # name -> (linear field per mm at the points (n, 3), [nonlinear part at each travel], forces, k)
    for s in [args.reference] + list(args.scales):
        mesh = specimen_mesh(exp, MeshSettings().with_scale(s))
        fe = build_model(mesh)
        u_lin, k_lin = fe.solve(list(MODULI_KPA), NU)
        sol, t_w, n_f = walk(fe, travels)
        I = interpolation_matrix(fe.space, pts)
        lin = (I @ u_lin).reshape(-1, 3)
        nl = [(I @ sol.fields[k]).reshape(-1, 3) - d * lin for k, d in enumerate(travels)]
        sources[f"P2 x{s:g}"] = (lin, nl, sol.force_N, k_lin)
        print(f"P2 x{s:g}: {mesh.n_nodes} vertices, {len(fe.free)} free dofs; walk {t_w:.1f} s, "
              f"{n_f} factorizations; linear force {k_lin:.4f} N/mm", flush=True)
        if s == 1.0 and not args.no_anp:
            fe1 = build_model(mesh, op=assemble(p1_space(mesh)))
            anp = AveragedNodalVolume(fe1, MODULI_KPA, NU)
            u1, k1 = anp.linear()
            t = time.perf_counter()
            f1, n1 = anp.walk(travels)
            I1 = interpolation_matrix(fe1.space, pts)
            lin1 = (I1 @ u1).reshape(-1, 3)
            sources["ANP x1"] = (lin1, [(I1 @ f1[k]).reshape(-1, 3) - d * lin1 for k, d in enumerate(travels)],
                                 np.array([anp.reaction_N(f) for f in f1]), k1)
            print(f"ANP x1: walk {time.perf_counter() - t:.1f} s, {n1} factorizations; linear force {k1:.4f} N/mm",
                  flush=True)
    ref_name = f"P2 x{args.reference:g}"
    ref_lin, ref_nl, _, _ = sources[ref_name]
    print(f"\nreference {ref_name}; nonlinear part = hyperelastic - linear field, on the demo's "
          f"{len(pts)} warp control points")
    print(f"{'source':>8s} {'travel':>6s} {'F':>7s} {'F nonlin':>8s} {'nonlin px':>9s} "
          f"{'nonlin - ref, rms px':>20s} {'max':>5s} {'linear - ref, rms px':>20s}")
    for name, (lin, nl, f, k) in sources.items():
        for j, d in enumerate(travels):
            diff = px(nl[j] - ref_nl[j])
            print(f"{name:>8s} {d:6.1f} {f[j]:7.3f} {f[j] - d * k:8.3f} {rms(px(nl[j])):9.2f} "
                  f"{rms(diff):20.3f} {np.abs(diff).max():5.2f} {rms(px(d * (lin - ref_lin))):20.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
