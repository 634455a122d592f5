"""What refining the located inclusion's centre and radius gives.

    ELASTOID_CACHE_DIR=DIR python bench/inclusion_refine.py EXPERIMENT [--fresh-meshes] [--trials 16] [--truth]

By default, as a user does it in the Model check: identify, diagnose with the
inclusion candidate, add it, then "Refine the inclusion's place"
(ModelCheck.refine_inclusion: a compass search with every trial on the added
version's mesh, the best then meshed as a region and refitted). Prints each
trial, then the versions' errors and the time.

With --fresh-meshes, the search that came first: every trial sphere meshed
anew (fTetWild) and fitted as the diagnosis' candidate is, by the same compass
search (diagnose.compass_search: steps of 2% of the smallest specimen side in
x and z and a factor 1.15 on the radius, halved when no neighbour is better). A fresh mesh moves chi2 by itself, so that search
follows each mesh's error as well as the sphere (docs/model-check.md, "The
inclusion locator"). With --truth, the hidden sphere of the experiment's
truth.toml is also meshed and fitted the way the candidate is.
"""
import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("experiment")
    ap.add_argument("--trials", type=int, default=16, help="most spheres to mesh and fit (default 16)")
    ap.add_argument("--truth", action="store_true", help="also fit the truth's hidden sphere")
    ap.add_argument("--fresh-meshes", action="store_true", help="mesh every trial sphere anew (the first search)")
    a = ap.parse_args()
    if not a.fresh_meshes:
        return same_mesh(a)

    from app.core.diagnose import REFINE_STEP, _fitted, compass_search, current_model, diagnose
    from app.core.experiment import read_experiment
    from app.core.simulate import read_truth

    exp = read_experiment(a.experiment)
    t0 = time.perf_counter()
    d = diagnose(exp, candidates=("inclusion",))
    c = d.candidate("inclusion")
    print(f"diagnosis: {time.perf_counter() - t0:.0f} s; baseline error beyond the noise "
          f"{d.baseline.misfit['displacement_excess_px']:.3f} px, chi2 {d.baseline.misfit['chi2']:.1f}")
    y = float(c.inclusion["center_mm"][1])
    seen = {}

    def fit(x, z, r, label):
        key = (round(x, 2), round(z, 2), round(r, 2))
        if key in seen:
            return seen[key]
        t = time.perf_counter()
        inc = dict(c.inclusion, center_mm=[round(x, 3), y, round(z, 3)], radius_mm=round(r, 3))
        cp = current_model(exp, ("inclusion",), inclusion=inc, near_kPa=list(c.parameters.values())[:3])
        try:
            f = _fitted(cp, "inclusion", c.parameters, c.n_parameters, d.tracked, d.noise, 200, lambda s: None, None,
                        label)
        finally:
            cp.release()
        m = f.misfit
        seen[key] = m["chi2"]
        mod = ", ".join(f"{k[2:-4]} {v:.1f}" for k, v in f.parameters.items())
        print(f"{label:<10} ({x:6.2f}, {z:6.2f}) r {r:5.2f}  chi2 {m['chi2']:9.1f}  beyond the noise "
              f"{m['displacement_excess_px']:.3f} px  kPa: {mod}  {time.perf_counter() - t:.0f} s", flush=True)
        return m["chi2"]

    x, _, z = c.inclusion["center_mm"]
    print(f"{'':<10} {'centre (x, z) mm':>16} {'radius':>8}")
    n = [0]  # spheres asked for, a repeat included

    def value(x, z, r):
        n[0] += 1
        return fit(x, z, r, "located" if n[0] == 1 else f"trial {n[0]}")

    x, z, r = compass_search(value, x, z, float(c.inclusion["radius_mm"]), REFINE_STEP * min(exp.specimen.size_mm),
                             lambda: n[0] < a.trials)
    print(f"best: ({x:.2f}, {z:.2f}) r {r:.2f}, chi2 {seen[(round(x, 2), round(z, 2), round(r, 2))]:.1f}; "
          f"{len(seen)} spheres in {time.perf_counter() - t0:.0f} s")
    if a.truth:
        h = read_truth(exp.path)["hidden_regions"][0]
        fit(h["center_mm"][0], h["center_mm"][2], float(h["radius_mm"]), "truth")


def same_mesh(a) -> None:
    from app.core.diagnose import ModelCheck, RefinementRefused
    from app.core.experiment import read_experiment

    exp = read_experiment(a.experiment)
    mc = ModelCheck(exp)
    t0 = time.perf_counter()
    mc.identify(())
    d = mc.diagnose(("inclusion",))
    print(f"diagnosis: {d.candidate('inclusion').evidence}")
    mc.add("inclusion")
    t1 = time.perf_counter()
    try:
        refined = mc.refine_inclusion(max_trials=a.trials, progress=lambda s: print("  " + s, flush=True))
        print(f"warning: {refined.warning or 'none'}")
    except RefinementRefused as exc:  # an answer: the versions stay as they were
        print(f"refused: {exc}")
    t2 = time.perf_counter()
    print(f"\n{'version':<34} {'sphere':>34} {'chi2':>9} {'beyond the noise (px)':>22}  moduli (kPa)")
    for v in mc.history.versions:
        sph = (f"({', '.join(f'{c:.1f}' for c in v.inclusion['center_mm'])}) r {v.inclusion['radius_mm']:.2f}"
               if v.inclusion else "")
        mod = ", ".join(f"{k[2:-4]} {x:.1f}" for k, x in v.parameters.items() if k.startswith("E_"))
        print(f"{v.index}: {v.note or 'identified':<31} {sph:>34} {v.misfit['chi2']:>9.1f} "
              f"{v.misfit['displacement_excess_px']:>22.3f}  {mod}")
    print(f"identify, diagnose and add: {t1 - t0:.0f} s; refine: {t2 - t1:.0f} s")


if __name__ == "__main__":
    main()
