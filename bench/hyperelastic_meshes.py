"""The cold hyperelastic solve of the demo on fresh meshes, with the 4-point rule
everywhere and with 8 points beside the probe's outline (the default).

    python bench/hyperelastic_meshes.py [--meshes 3]

fTetWild's meshes differ from run to run, and the neo-Hookean load path under a
bonded probe depends on the few elements beside the probe's edges: each mesh is
made anew in an empty cache, then solved cold to the demo's 14.8 mm with either
rule. Prints one row per mesh and rule: seconds, factorizations, the force at
the deepest travel or where the walk stopped.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    import numpy as np

    from app.core.errors import ElastoidError
    from app.core.experiment import read_experiment
    from app.core.forward import build_model
    from app.core.hyperelastic import HyperelasticModel
    from app.core.mesh import specimen_mesh

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--meshes", type=int, default=3)
    args = ap.parse_args(argv)
    exp = read_experiment(ROOT / "resources" / "demo")
    steps = np.array([3.7, 7.4, 11.1, 14.8])
    print(f"{'mesh':>4s} {'vertices':>8s} {'rule':>10s} {'seconds':>8s} {'factorizations':>14s}  result")
    for k in range(args.meshes):
        with tempfile.TemporaryDirectory() as tmp:
            os.environ["ELASTOID_CACHE_DIR"] = tmp  # an empty cache: a fresh mesh
            mesh = specimen_mesh(exp)
        fe = build_model(mesh)
        for edge_rule in (False, True):
            hm = HyperelasticModel(fe, edge_rule=edge_rule)
            t = time.perf_counter()
            try:
                sol = hm.solve([18.0, 63.0], 0.49, steps)
                result = f"reached {steps[-1]:.1f} mm, F {sol.force_N[-1]:.3f} N"
            except ElastoidError as exc:
                result = f"stopped: {exc}"
            print(f"{k:4d} {mesh.n_nodes:8d} {'edge 8-pt' if edge_rule else '4-pt':>10s} "
                  f"{time.perf_counter() - t:8.1f} {hm.n_factorizations:14d}  {result}", flush=True)
            hm.free()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
