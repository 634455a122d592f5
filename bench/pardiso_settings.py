"""PARDISO settings for the tangent factorizations of the hyperelastic walk: the
demo's stiffness (P2, free-free upper triangle, 18 / 63 kPa, nu 0.49) factorized
as SymmetricFactor does (Cholesky, single precision, METIS), with MKL's other
settings beside it: variable block rows (VBSR, iparm[36] = -t: 3 dofs per node
make 3-row blocks), the two-level parallel factorization (iparm[23]) and
parallel METIS (iparm[1] = 3).

    /work/venv/bin/python bench/pardiso_settings.py [--repeats 3]

Prints a table: per setting, the analysis, the numeric factorization and the
back-substitution (medians over repeats), the factor's memory, and the solution's
relative difference from the current setting's.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SETTINGS = {  # name -> {iparm index: value} on top of solver._configure's
    "current (METIS, iparm[23]=0)": {},
    "VBSR, iparm[36]=-80": {36: -80},
    "VBSR, iparm[36]=-90": {36: -90},
    "two-level factorization, iparm[23]=1": {23: 1},
    "improved two-level, iparm[23]=10": {23: 10},
    "parallel METIS, iparm[1]=3": {1: 3},
    "VBSR -90 + iparm[23]=10": {36: -90, 23: 10},
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    import numpy as np

    from app.core import solver
    from app.core.experiment import read_experiment
    from app.core.fem import coefficients
    from app.core.forward import build_model
    from app.core.mesh import specimen_mesh

    exp = read_experiment(ROOT / "resources" / "demo")
    fe = build_model(specimen_mesh(exp))
    A, b, _, _ = fe.term_blocks(coefficients([18.0, 63.0], 0.49))
    import scipy.sparse as sp

    U = sp.triu(A, format="csr")
    U.sort_indices()
    base = solver._configure
    rows, ref = [], None
    for name, extra in SETTINGS.items():
        def configure(s, single=False, extra=extra):
            base(s, single)
            for k, v in extra.items():
                s.iparm[k] = v

        solver._configure = configure
        try:
            ana, fac, sol = [], [], []
            x = None
            for _ in range(args.repeats):
                t = time.perf_counter()
                f = solver.SymmetricFactor(U, single=True, definite=True)  # analysis + factorization
                total = time.perf_counter() - t
                t = time.perf_counter()
                f.refactor(U.data)
                fac.append(time.perf_counter() - t)
                ana.append(total - fac[-1])
                for _ in range(3):
                    t = time.perf_counter()
                    x = f.solve(b)
                    sol.append(time.perf_counter() - t)
                mem = f.memory_bytes
                f.free()
        except Exception as exc:  # a setting MKL refuses
            rows.append((name, f"failed: {exc}"))
            continue
        finally:
            solver._configure = base
        if ref is None:
            ref = x
        diff = float(np.linalg.norm(x - ref) / np.linalg.norm(ref))
        rows.append((name, f"{statistics.median(ana):8.2f} s {statistics.median(fac):8.2f} s "
                           f"{1e3 * statistics.median(sol):8.1f} ms {mem / 1e9:6.3f} GB {diff:9.1e}"))
    print(f"demo stiffness: {A.shape[0]} unknowns, {U.nnz} upper entries; medians of {args.repeats} "
          f"(back-substitutions: of {3 * args.repeats})")
    print(f"{'setting':40s} {'analysis':>10s} {'factorize':>10s} {'solve':>11s} {'factor':>9s} {'vs current':>9s}")
    for name, text in rows:
        print(f"{name:40s} {text}")


if __name__ == "__main__":
    main()
