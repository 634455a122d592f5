"""Core benchmark on a paper-size model, side by side with the peers.

    python bench/core.py [--repeats 5] [--identify-repeats 3] [--skfem-repeats 1]

Prints one table of medians: one cost evaluation with the paper's two frames
(and its parts), the 6-start identification, the same forward solve through
scikit-fem's usual assemble-and-solve path (same mesh, same P2 element), NMI
against skimage, and the fast warp against the exact TPS on every pixel by
scipy's RBFInterpolator.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


from app.core.experiment import read_experiment  # noqa: E402
from app.core.fem import lame  # noqa: E402
from app.core.identify import PAPER_STARTS_KPA, Problem, identify  # noqa: E402
from app.core.solver import single_threaded_blas  # noqa: E402
from app.core.mesh import MeshSettings, quality  # noqa: E402
from app.core.similarity import NMI  # noqa: E402
from app.core.solver import backend_name  # noqa: E402
from app.core.warp import exact_inverse  # noqa: E402

# the paper's mesh had 2,853 nodes; these sizes give a mesh of that order
PAPER_MESH = MeshSettings(edge_mm=9.0, probe_edge_mm=2.5)


def median_time(fn, repeats):
    ts = []
    out = None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts), out


def skfem_solve(problem, E):
    """scikit-fem's usual path: assemble P2 elasticity per region, condense, spsolve."""
    from skfem import Basis, ElementTetP2, ElementVector, MeshTet, asm, condense, solve
    from skfem.models.elasticity import linear_elasticity

    mesh = problem.mesh
    m = MeshTet(mesh.points_mm.T.copy(), mesh.tets.T.copy())
    e = ElementVector(ElementTetP2())
    K = None
    for r, Er in enumerate(E):
        basis = Basis(m, e, elements=np.flatnonzero(mesh.labels == r), intorder=2)
        mu, lam = lame(Er, problem.nu)
        Kr = asm(linear_elasticity(lam, mu), basis)
        K = Kr if K is None else K + Kr
    basis = Basis(m, e, intorder=2)
    X = basis.doflocs
    comp = np.empty(basis.N, int)
    for c in range(3):
        comp[basis.nodal_dofs[c]] = c
        comp[basis.edge_dofs[c]] = c
    top = np.isclose(X[2], mesh.size_mm[2])
    x0, x1, y0, y1 = mesh.probe_rect_mm
    probe = top & (X[0] >= x0 - 1e-6) & (X[0] <= x1 + 1e-6) & (X[1] >= y0 - 1e-6) & (X[1] <= y1 + 1e-6)
    bottom = np.isclose(X[2], 0.0)
    D = np.flatnonzero(probe | bottom)
    x = np.zeros(basis.N)
    x[probe & (comp == 2)] = -1.0
    u = solve(*condense(K, np.zeros(basis.N), x=x, D=D))
    F = -(K @ u)[probe & (comp == 2)].sum() * 1e-3
    return u, F, basis


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--identify-repeats", type=int, default=3)
    ap.add_argument("--skfem-repeats", type=int, default=1)
    ap.add_argument("--experiment", default=str(ROOT / "resources" / "demo"))
    args = ap.parse_args(argv)

    exp = read_experiment(args.experiment)
    rows = []
    t_setup0 = time.perf_counter()
    problem = Problem.from_experiment(exp, mesh_settings=PAPER_MESH, frames=(0, len(exp.frames) - 1), cost="joint")
    t_setup = time.perf_counter() - t_setup0
    q = quality(problem.mesh, exp.specimen.regions)
    print(f"mesh: {q.n_nodes} nodes, {q.n_tets} tetrahedra ({problem.fe.space.n_dofs} P2 dofs), "
          f"{q.n_probe_nodes} vertices on the probe face; solver {backend_name()}; reduced basis {problem.rm.k}")
    print(f"setup (mesh from cache or fTetWild, assembly, reduced-model training): {t_setup:.1f} s")

    truth = {"E_B_kPa": 18.0, "E_A_kPa": 63.0}
    rng = np.random.default_rng(0)
    samples = [{k: v * float(np.exp(rng.normal(0, 0.2))) for k, v in truth.items()} for _ in range(60)]
    problem.evaluate(truth)  # warm up

    def timed_evals(fn):
        ts = []
        for p in samples:
            t0 = time.perf_counter()
            fn(p)
            ts.append(time.perf_counter() - t0)
        return statistics.median(ts)

    t_eval = timed_evals(problem.evaluate)
    pair = problem.pairs[0]
    with single_threaded_blas():
        t_fwd = timed_evals(lambda p: problem.rm.coords(problem.theta(p)))
        a = problem.rm.coords(problem.theta(truth))
        coarse = problem._coarse_field(pair, a)
        t_warp = timed_evals(lambda p: pair.warp(pair.source_image, coarse=problem._coarse_field(pair, a)))
        w = pair.warp(pair.source_image, coarse=coarse)
        t_nmi = timed_evals(lambda p: pair.nmi(w[pair.mask]))
        t_force = timed_evals(lambda p: problem.model_force_N(p, a))
    rows.append(("one cost evaluation (2 frames: forward, warp, NMI, force)", t_eval * 1e3, "ms", "<= 20 ms"))
    rows.append(("  forward solve (reduced model)", t_fwd * 1e3, "ms", ""))
    rows.append(("  warp of the source ROI", t_warp * 1e3, "ms", ""))
    rows.append(("  NMI on the ROI", t_nmi * 1e3, "ms", ""))
    rows.append(("  force misfit", t_force * 1e3, "ms", ""))

    # full-order solve, ours (assembled once; PARDISO Cholesky per new moduli)
    t_full, (u_ours, F_ours) = median_time(lambda: problem.fe.solve([18.0, 63.0], problem.nu), args.repeats)
    rows.append(("full-order solve, ours (factorize + solve)", t_full * 1e3, "ms", ""))

    # scikit-fem's usual path on the same mesh and element
    t_sk, (u_sk, F_sk, basis) = median_time(lambda: skfem_solve(problem, [18.0, 63.0]), args.skfem_repeats)
    rows.append(("scikit-fem assemble + condense + spsolve", t_sk * 1e3, "ms", ""))
    rows.append(("  speed-up per evaluation vs scikit-fem", t_sk / t_eval, "x", ">= 50x"))
    rows.append(("  probe force: ours vs scikit-fem", abs(F_ours - F_sk) / abs(F_sk), "rel", "same element"))

    # the 6-start identification (after setup)
    t_id, res = median_time(lambda: identify(problem, PAPER_STARTS_KPA), args.identify_repeats)
    rows.append((f"6-start identification ({res.evaluations} evaluations)", t_id, "s", "<= 10 s"))
    rows.append(("  identified E_B, E_A (truth 18, 63 kPa)",
                 f"{res.parameters['E_B_kPa']:.2f}, {res.parameters['E_A_kPa']:.2f}", "kPa", ""))

    # NMI against skimage on 256 x 256
    from skimage.metrics import normalized_mutual_information as sk_nmi

    A = rng.random((256, 256))
    B = 0.6 * A + 0.4 * rng.random((256, 256))
    f = NMI(A, bins=100)
    t_ours = statistics.median(median_time(lambda: f(B), 1)[0] for _ in range(200))
    t_skn = statistics.median(median_time(lambda: sk_nmi(A, B, bins=100), 1)[0] for _ in range(20))
    rows.append(("NMI 256x256, 100 bins: ours", t_ours * 1e3, "ms", ""))
    rows.append(("NMI 256x256, 100 bins: skimage", t_skn * 1e3, "ms", ""))
    rows.append(("  NMI speed-up / |difference|", f"{t_skn / t_ours:.1f}x / {abs(f(B) - sk_nmi(A, B, bins=100)):.1e}",
                 "", ">= 20x, 1e-9"))

    # warp: fast vs exact TPS evaluated on every pixel by scipy's RBFInterpolator
    from scipy.interpolate import RBFInterpolator

    vals = problem.control_displacement_px(a, pair)
    t_fast, e_fast = median_time(lambda: pair.warp.inverse(vals), args.repeats)
    rbf = RBFInterpolator(problem.ctrl_px, vals, kernel="thin_plate_spline")
    t_exact, e_exact = median_time(lambda: exact_inverse(rbf, problem.image_shape, pair.warp.roi), 1)
    err = np.abs(e_fast - e_exact)[pair.mask].max()
    rows.append(("warp field on the ROI: fast TPS", t_fast * 1e3, "ms", ""))
    rows.append(("warp field on the ROI: exact TPS (RBFInterpolator, every pixel)", t_exact * 1e3, "ms", ""))
    rows.append(("  warp speed-up / max difference on the ROI", f"{t_exact / t_fast:.0f}x / {err:.3f} px", "",
                 ">= 100x, < 0.1 px"))

    print()
    print(f"| {'measure':<66} | {'median':>16} | unit | target |")
    print(f"|{'-' * 68}|{'-' * 18}|------|--------|")
    for name, val, unit, target in rows:
        v = f"{val:.3g}" if isinstance(val, float) else str(val)
        print(f"| {name:<66} | {v:>16} | {unit:4} | {target} |")


if __name__ == "__main__":
    main()
