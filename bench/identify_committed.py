"""Identification of the committed test experiments on the committed identification
meshes (the cases of tests/core/test_identify.py): joint cost and NMI-only cost, the
paper's six starts; prints each modulus's error, the ratio's error and each start's ratio.

    python bench/identify_committed.py

Uses a fresh mesh cache seeded with tests/data/meshes, as the tests do.
"""
import glob, os, shutil, sys, tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

if __name__ == "__main__":
    cache = tempfile.mkdtemp()
    os.environ["ELASTOID_CACHE_DIR"] = cache
    os.makedirs(Path(cache) / "meshes")
    for f in glob.glob(str(ROOT / "tests" / "data" / "meshes" / "*.npz")):
        shutil.copy(f, Path(cache) / "meshes")
    from app.core.experiment import read_experiment
    from app.core.identify import Problem, identify
    from app.core.simulate import read_truth
    from tests.core import synthetic

    for geometry, seed in synthetic.COMMITTED_CASES:
        folder = synthetic.committed(geometry, seed)
        exp, truth = read_experiment(folder), read_truth(folder)["moduli_kPa"]
        joint = Problem.from_experiment(exp, cost="joint")
        nmi = Problem(exp, joint.mesh, joint.fe, joint.rm, nu=0.49, cost="nmi", frames=joint.frames,
                      roi_px=None, force_weight=1.0, bins=joint.bins)
        rj, rn = identify(joint), identify(nmi)
        R = truth["A"] / truth["B"]
        errs = " ".join(f"E_{k} {100 * (rj.parameters[f'E_{k}_kPa'] / v - 1):+.2f}%" for k, v in truth.items())
        ratio_n = rn.parameters["E_A_kPa"] / rn.parameters["E_B_kPa"] / R - 1
        starts = [round(s["parameters"]["E_A_kPa"] / s["parameters"]["E_B_kPa"], 3) for s in rj.starts]
        print(f"{geometry} seed {seed}: joint {errs}; NMI-only ratio {100 * ratio_n:+.2f}%; "
              f"joint starts' ratios {starts} (truth {R:.3f})", flush=True)
