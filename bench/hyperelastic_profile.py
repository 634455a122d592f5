"""Where a cold hyperelastic solve at paper size spends its time.

    python bench/hyperelastic_profile.py [--linear-only]

Times the solver's pieces (factorizations, tangent assemblies, back-substitutions,
residuals) during one cold solve of the demo (moduli 18 and 63 kPa, 4 load steps
to 14.8 mm) and prints a table, on the demo's mesh shipped in resources/meshes.

``--linear-only``: the experiment of a cold solve that factorizes nothing but
the linear stiffness (what a 2-second cold solve would need): every tangent
refused (so the linear factor serves throughout), slowness counted only when the
residual rises to twice its lowest (the reform rate out of play), up to 150
iterations a step. Prints how far it gets.
"""

from __future__ import annotations

import collections
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main() -> int:
    import argparse

    import numpy as np

    import app.core.hyperelastic as H
    from app.core.experiment import read_experiment
    from app.core.forward import build_model
    from app.core.mesh import specimen_mesh
    from app.core.solver import SymmetricFactor

    seconds, calls = collections.Counter(), collections.Counter()

    def timed(owner, name, key):
        inner = getattr(owner, name)

        def wrapper(*a, **k):
            t = time.perf_counter()
            try:
                return inner(*a, **k)
            finally:
                seconds[key] += time.perf_counter() - t
                calls[key] += 1

        setattr(owner, name, wrapper)

    timed(H.HyperelasticModel, "internal_force", "residual")
    timed(H.HyperelasticModel, "tangent_upper", "tangent assembly")
    timed(SymmetricFactor, "__init__", "new factor (analysis + factorization)")
    timed(SymmetricFactor, "refactor", "refactorization")
    timed(SymmetricFactor, "solve", "back-substitution")

    exp = read_experiment(ROOT / "resources" / "demo")
    fe = build_model(specimen_mesh(exp))
    _, g = fe.solve([18.0, 63.0])
    steps = np.array([3.7, 7.4, 11.1, 14.8])
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--linear-only", action="store_true")
    if ap.parse_args().linear_only:
        hm = H.HyperelasticModel(fe, max_iterations=150, reform_rate=10.0)  # never "slow" by its rate
        hm._try_factor = lambda data, ratios: None  # any tangent refused: the linear factor throughout
    else:
        hm = H.HyperelasticModel(fe)
    seconds.clear()
    calls.clear()
    t = time.perf_counter()
    try:
        sol = hm.solve([18.0, 63.0], 0.49, steps)
    except H.ElastoidError as e:
        print(f"{time.perf_counter() - t:.1f} s: {e}")
        hm.free()
        return 1
    total = time.perf_counter() - t
    hm.free()
    print(f"cold solve: {total:.2f} s, {hm.n_factorizations} factorizations, "
          f"F/F_linear {sol.force_N[-1] / (g * steps[-1]):.4f}")
    width = max(len(k) for k in seconds)
    print(f"{'piece':{width}s} {'calls':>6s} {'seconds':>8s} {'ms each':>8s}")
    for key in seconds:
        print(f"{key:{width}s} {calls[key]:6d} {seconds[key]:8.2f} {1e3 * seconds[key] / calls[key]:8.1f}")
    print(f"{'the rest':{width}s} {'':6s} {total - sum(seconds.values()):8.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
