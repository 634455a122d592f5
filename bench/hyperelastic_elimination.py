"""Nonlinear elimination at the probe's outline: can a cold hyperelastic solve do
with fewer factorizations of the whole tangent?

    python bench/hyperelastic_elimination.py [--rings 2]

At the predicted states of the load walk the residual sits on the tets beside
the probe face's outline (the share printed first), and iterating with a stale
tangent stalls there. This experiment (not the product's solver) eliminates that
patch: before every global step, one Newton step on the patch's interior
unknowns (those no other tet touches) with its own tangent, shifted towards its
diagonal until positive definite; then one Anderson-accelerated step with a
fixed global matrix, both under a line search on the stored energy. Two global
matrices: the linear stiffness throughout, or the tangent at the last
travel's equilibrium (one factorization per travel). Prints, per travel of the
demo (18 and 63 kPa, nu 0.49), the global iterations and the force against the
product's solver, then the counts. The patch's tangent is taken from the whole
tangent here (an efficient one would assemble the patch alone): compare
iterations and factorizations, not seconds.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

TRAVELS = (3.7, 7.4, 11.1, 14.8)
MAX_GLOBAL = 80


def _run(hm, fe, theta, nu, patch_free, patch, refresh: bool) -> tuple[list, dict]:
    import numpy as np
    import scipy.sparse as sp

    from app.core.fem import coefficients
    from app.core.hyperelastic import anderson_step
    from app.core.solver import SymmetricFactor

    mu_e, lam_e = hm.element_moduli(theta, nu)
    free, fixed = fe.free, fe.fixed
    counts = {"global factorizations": 0, "patch factorizations": 0, "global iterations": 0}
    glob = hm._linear_preconditioner(theta, nu)
    counts["global factorizations"] += 1
    _, b, _, _ = fe.term_blocks(coefficients(theta / theta[0], nu))
    lin = glob.factor.solve(b)

    def patch_step(u, f):
        U = hm._upper_matrix(hm.tangent_upper(u, mu_e, lam_e))
        Kp = (U + sp.triu(U, 1).T)[patch_free][:, patch_free]
        Up = sp.triu(Kp, format="csr")
        fac = SymmetricFactor(Up, single=False, definite=True)
        shift, diag = 1e-3, Up.indptr[:-1]
        while fac.positive_definite is False and shift <= 10:
            data = Up.data.copy()
            data[diag] *= 1 + shift
            fac.refactor(data)
            shift *= 10
        counts["patch factorizations"] += 1
        step = np.zeros(hm.n_dofs)
        step[patch] = -fac.solve(f[free][patch_free])
        fac.free()
        return step

    def searched(u, e, step):
        s = 1.0
        for _ in range(8):
            trial = u + s * step
            try:
                ft, et = hm.internal_force(trial, mu_e, lam_e, with_energy=True)
                if et <= e + 1e-10 * abs(e):
                    return trial, ft, et, s == 1.0
            except ValueError:  # an inverted element
                pass
            s *= 0.5
        return trial, ft, et, False

    rows, done = [], []
    for d in TRAVELS:
        u = np.zeros(hm.n_dofs)
        u[fixed] = d * fe.lift
        if len(done) >= 2:
            (d0, u0), (d1, u1) = done[-2], done[-1]
            u[free] = u1[free] + (u1[free] - u0[free]) * (d - d1) / (d1 - d0)
        else:
            u[free] = d * lin
        f, e = hm.internal_force(u, mu_e, lam_e, with_energy=True)
        ref = np.linalg.norm(f[fixed])
        X, G, n = [], [], 0
        while n < MAX_GLOBAL:
            if np.linalg.norm(f[free][patch_free]) > 0.1 * hm.tol * ref:
                u, f, e, _ = searched(u, e, patch_step(u, f))
            r = f[free]
            if np.linalg.norm(r) / ref <= hm.tol:
                break
            n += 1
            g = -glob.factor.solve(r) / (theta[0] * glob.scale)
            x = u[free].copy()
            X.append(x)
            G.append(g)
            del X[:-6], G[:-6]
            step = anderson_step(X, G)
            if r @ step >= 0:
                step, X, G = g, [x], [g]
            full = np.zeros(hm.n_dofs)
            full[free] = step
            u, f, e, whole = searched(u, e, full)
            if not whole:
                X, G = [], []
        counts["global iterations"] += n
        converged = np.linalg.norm(f[free]) / ref <= hm.tol
        rows.append((d, n, converged, -float(fe.probe_z @ f[fixed]) * 1e-3))
        done.append((d, u.copy()))
        if refresh and d != TRAVELS[-1]:
            glob = hm._definite_into(None, hm.tangent_upper(u, mu_e, lam_e) / theta[0], theta / theta[0], True)
            counts["global factorizations"] += 1
    return rows, counts


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rings", type=int, default=2, help="layers of tets around those touching the outline")
    args = ap.parse_args()

    import numpy as np

    from app.core.experiment import read_experiment
    from app.core.fem import coefficients
    from app.core.forward import build_model
    from app.core.hyperelastic import HyperelasticModel, edge_elements
    from app.core.mesh import specimen_mesh
    from app.core.solver import single_threaded_blas

    fe = build_model(specimen_mesh(read_experiment(ROOT / "resources" / "demo")))
    theta, nu = np.array([18.0, 63.0]), 0.49
    hm = HyperelasticModel(fe, warm_starts=False)
    t = time.perf_counter()
    ref = hm.solve(theta, nu, TRAVELS)
    ref_s, ref_fact = time.perf_counter() - t, hm.n_factorizations
    hm.free()

    patch_tets = edge_elements(fe.space.mesh, rings=args.rings)
    others = np.setdiff1d(np.arange(len(hm.elems)), patch_tets)
    in_patch = np.zeros(hm.n_dofs, bool)
    in_patch[hm.dofs[patch_tets].ravel()] = True
    in_others = np.zeros(hm.n_dofs, bool)
    in_others[hm.dofs[others].ravel()] = True
    where = np.full(hm.n_dofs, -1)
    where[fe.free] = np.arange(len(fe.free))
    patch = np.flatnonzero(in_patch & ~in_others & (where >= 0))
    patch_free = where[patch]

    # where the residual sits at the first travel's linear solution
    mu_e, lam_e = hm.element_moduli(theta, nu)
    _, b, _, _ = fe.term_blocks(coefficients(theta / theta[0], nu))
    u = np.zeros(hm.n_dofs)
    u[fe.fixed] = TRAVELS[0] * fe.lift
    u[fe.free] = TRAVELS[0] * hm._linear_preconditioner(theta, nu).factor.solve(b)
    r = hm.internal_force(u, mu_e, lam_e)[fe.free]
    share = float(np.sum(r[np.isin(np.arange(len(r)), where[in_patch & (where >= 0)])] ** 2) / np.sum(r ** 2))
    print(f"patch: {len(patch_tets):,} of {len(hm.elems):,} tets ({args.rings} rings), {len(patch):,} interior "
          f"unknowns of {len(fe.free):,}; at the linear solution of {TRAVELS[0]} mm it holds {share:.0%} of the "
          "residual's square")
    print(f"the product's solver: {ref_s:.1f} s, {ref_fact} factorizations, iterations {ref.iterations}\n")
    print(f"{'global matrix':<34}{'travel mm':>10}{'global its':>12}{'force N':>10}{'product N':>11}")
    for name, refresh in (("linear stiffness", False), ("tangent at the last travel", True)):
        hm.free()
        t = time.perf_counter()
        with single_threaded_blas():
            rows, counts = _run(hm, fe, theta, nu, patch_free, patch, refresh)
        for (d, n, ok, force), fr in zip(rows, ref.force_N):
            print(f"{name:<34}{d:>10.1f}{n:>12}{force:>10.4f}{fr:>11.4f}{'' if ok else '  not converged'}")
        print(f"{'':<34}" + ", ".join(f"{k} {v}" for k, v in counts.items())
              + f"; {time.perf_counter() - t:.0f} s\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
