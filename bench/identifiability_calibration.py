"""Are the identifiability report's standard errors from the data right?

    python bench/identifiability_calibration.py [--seeds 8] [--geometry medium-sphere] [--frames 0,2]

Simulates the same phantom with several speckle and force-noise seeds (one truth
mesh, one identification mesh, so the mesh error is the same in every run and
only the noise differs), identifies each with the joint cost, and compares the
scatter of the estimates over the seeds with the standard errors the report
predicts from each experiment alone (the jackknife over blocks of the ROI, and
the stated 0.25 px noise model). If the report is right, the scatter of the
ratio E_A/E_B over the seeds is about its predicted standard error, and the
z-scores (error over predicted standard error, about the seeds' mean) have
an RMS near 1.

Uses a mesh cache seeded with tests/data/meshes (the committed identification
meshes) in a temporary folder; the truth mesh is meshed once and reused.
"""

from __future__ import annotations

import argparse
import glob
import os
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--geometry", default="medium-sphere")
    ap.add_argument("--frames", default="", help="frame indices (default: all)")
    args = ap.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="elastoid-calibration-"))
    os.environ["ELASTOID_CACHE_DIR"] = str(work / "cache")
    (work / "cache" / "meshes").mkdir(parents=True)
    for f in glob.glob(str(ROOT / "tests" / "data" / "meshes" / "*.npz")):
        shutil.copy(f, work / "cache" / "meshes")
    from app.core.experiment import read_experiment
    from app.core.identify import Problem, identify
    from tests.core import synthetic

    frames = tuple(int(v) for v in args.frames.split(",")) if args.frames else None
    rows = []
    for seed in range(1, args.seeds + 1):
        folder, spec = synthetic.make(work / f"seed{seed}", args.geometry, seed)
        exp = read_experiment(folder)
        problem = Problem.from_experiment(exp, cost="joint", frames=frames)
        res = identify(problem)
        truth = spec.moduli_kPa
        ident = res.identifiability
        names, regions = problem.parameter_names, problem.region_names  # E_<region>_kPa, <region>
        ratio_name = f"{names[1]}/{names[0]}"
        ratio = res.parameters[names[1]] / res.parameters[names[0]]
        rows.append({
            "seed": seed,
            "err": {n: res.parameters[n] / truth[r] - 1 for n, r in zip(names, regions)},
            "ratio_err": ratio / (truth[regions[1]] / truth[regions[0]]) - 1,
            "se_data": ident.standard_error_rel_data,
            "se_ratio_data": ident.ratio_standard_error_rel_data[ratio_name],
            "se_model": ident.standard_error_rel,
        })
        r = rows[-1]
        print(f"seed {seed}: " + ", ".join(f"{n} {100 * r['err'][n]:+.2f}% (data +/-{100 * r['se_data'][n]:.2f}%, "
                                           f"model +/-{100 * r['se_model'][n]:.2f}%)" for n in names)
              + f"; ratio {100 * r['ratio_err']:+.2f}% (data +/-{100 * r['se_ratio_data']:.2f}%)", flush=True)
    print()
    print("| quantity | scatter over seeds (sd) | mean error | predicted from the data (RMS) | "
          "z-score RMS (data) | predicted by the 0.25 px model (RMS) |")
    print("|---|---|---|---|---|---|")
    for key in list(rows[0]["err"]) + ["ratio"]:
        e = np.array([r["ratio_err"] if key == "ratio" else r["err"][key] for r in rows])
        sd = np.array([r["se_ratio_data"] if key == "ratio" else r["se_data"][key] for r in rows])
        sm = "" if key == "ratio" else f"{100 * np.sqrt(np.mean([r['se_model'][key] ** 2 for r in rows])):.2f}%"
        z = (e - e.mean()) / sd
        print(f"| {key} | {100 * e.std(ddof=1):.2f}% | {100 * e.mean():+.2f}% | {100 * np.sqrt(np.mean(sd ** 2)):.2f}% | "
              f"{np.sqrt(np.mean(z ** 2)):.2f} | {sm} |")
    shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
