"""Identification across fresh meshes (fTetWild is not deterministic): joint and NMI-only fits
of synthetic experiments from tests/core/synthetic.py, each on N freshly meshed copies
(the committed experiments of tests/data/experiments when they exist).

    python bench/identify_spread.py smooth medium-sphere:1,medium-ellipsoid:3 2
"""
import os, sys, tempfile, time
from pathlib import Path
ROOT = Path(__file__).resolve().parents[1]; sys.path.insert(0, str(ROOT)); sys.path.insert(0, str(ROOT / "tests" / "core"))
import numpy as np
if __name__ == "__main__":
    sim = sys.argv[1]; cases = [c.split(":") for c in sys.argv[2].split(",")]; nmesh = int(sys.argv[3])
    os.environ["ELASTOID_CACHE_DIR"] = tempfile.mkdtemp()
    import synthetic
    from app.core.experiment import read_experiment
    from app.core.identify import Problem, identify, PAPER_STARTS_KPA
    from app.core.mesh import specimen_mesh
    for geom, seed in cases:
        folder = synthetic.COMMITTED / f"{geom}-seed{seed}"  # the tests' experiment, when committed
        if not (folder / "experiment.toml").is_file():
            folder = Path(tempfile.gettempdir()) / f"elastoid-bench-{geom}-{seed}"
            if not folder.exists():
                synthetic.make(folder, geom, int(seed))
        exp = read_experiment(folder)
        truth = synthetic.GEOMETRIES[geom]["moduli_kPa"]; R = truth["A"] / truth["B"]
        for k in range(nmesh):
            mesh = specimen_mesh(exp, use_cache=False)
            for cost in ("joint", "nmi"):
                pr = Problem.from_experiment(exp, mesh=mesh, cost=cost, similarity=sim)
                res = identify(pr, PAPER_STARTS_KPA)
                p = res.parameters
                eb, ea = p["E_B_kPa"] / truth["B"] - 1, p["E_A_kPa"] / truth["A"] - 1
                ratio = (p["E_A_kPa"] / p["E_B_kPa"]) / R - 1
                st = [round(100 * ((s["parameters"]["E_A_kPa"] / s["parameters"]["E_B_kPa"]) / R - 1), 1) for s in res.starts]
                print(f"{geom} s{seed} mesh{k} n={len(mesh.points_mm)} {sim} {cost:5s} EB {100*eb:+.1f}% EA {100*ea:+.1f}% ratio {100*ratio:+.1f}% starts {st} {res.evaluations} evals {res.seconds:.1f}s", flush=True)
