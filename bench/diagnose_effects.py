"""Diagnose a small synthetic phantom with one hidden effect; print the ranking, the moduli
errors and how much each candidate lowers each misfit.

    python bench/diagnose_effects.py EFFECT SEED [candidates]   (EFFECT: an effect id, a+b, or none)

With two effects hidden (EFFECT a+b), the verdict is added and a second diagnosis
runs on top of it: it should name the other one.

The experiment is simulated once into a temporary folder and reused; set TAG=x for a
fresh one (the truth mesh differs each time: fTetWild is not deterministic).
IMG=192x180 sets the image size, INCL=x,y,z,radius,E_kPa the hidden inclusion, TRUTHSCALE the truth mesh's scale of the
identification mesh (0.7 by default), IDSCALE the identification mesh's scale.
"""
import os, sys, tempfile, time
from pathlib import Path
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import numpy as np
if __name__ == "__main__":
    eff, seed = sys.argv[1], int(sys.argv[2])
    cands = tuple(sys.argv[3].split(",")) if len(sys.argv) > 3 and sys.argv[3] else None
    pass
    from app.core.diagnose import diagnose
    from app.core.experiment import read_experiment
    from app.core.geometry import Region
    from app.core.mesh import MeshSettings
    from app.core.simulate import SyntheticSpec, simulate_experiment
    ID_MESH = MeshSettings(edge_mm=6.0, probe_edge_mm=2.5, region_edge_mm=2.5)
    BASE = dict(size_mm=(40.0, 40.0, 30.0),
                regions=(Region("B", "background"), Region("A", "sphere", center_mm=(20.0, 20.0, 18.0), radius_mm=7.0)),
                moduli_kPa={"B": 15.0, "A": 45.0}, face_mm=(24.0, 8.0), depth_mm=5.0, frames_at_mm=(0.0, 2.5, 5.0),
                image_shape=(128, 120), truth_mesh=ID_MESH.with_scale(0.7))
    kw = {}
    if eff == "compressibility": kw = dict(nu=0.3)
    elif eff == "hyperelastic":  # DEPTH=mm presses deeper (before 2026-11-24 the truth solve stalled near 6.6 mm)
        dd = float(os.environ.get("DEPTH", "6"))
        kw = dict(effects=("hyperelastic",), depth_mm=dd, frames_at_mm=(0.0, dd / 2, dd))
    elif eff == "inclusion":
        # INCL=x,y,z,radius,E_kPa: another hidden sphere (default 26,20,14,4,60)
        x, y, z, r, e = (float(v) for v in os.environ.get("INCL", "26,20,14,4,60").split(","))
        kw = dict(hidden_regions=(Region("C", "sphere", center_mm=(x, y, z), radius_mm=r),), moduli_kPa={"B": 15.0, "A": 45.0, "C": e})
    elif "+" in eff: kw = dict(effects=tuple(eff.split("+")))  # two (or more) hidden at once
    elif eff != "none": kw = dict(effects=(eff,))
    folder = Path(tempfile.gettempdir()) / f"elastoid-bench-{eff}-{seed}{os.environ.get('TAG', '')}"
    if os.environ.get("TRUTHSCALE"):
        BASE["truth_mesh"] = ID_MESH.with_scale(float(os.environ["TRUTHSCALE"]))
    if os.environ.get("IMG"):
        BASE["image_shape"] = tuple(int(v) for v in os.environ["IMG"].split("x"))
    mesh_scale = float(os.environ.get("IDSCALE", "1"))
    ID_MESH = ID_MESH.with_scale(mesh_scale)
    if not (folder / "experiment.toml").exists():
        simulate_experiment(folder, SyntheticSpec(seed=seed, **{**BASE, **kw}), overwrite=True)
    exp = read_experiment(folder)
    t0 = time.time()
    d = diagnose(exp, candidates=cands, mesh_settings=ID_MESH, progress=lambda s: print("  ..", s, flush=True))
    print("\n".join(d.lines()))
    truth = {"B": 15.0, "A": 45.0}
    def errs(p): return {k: round(100 * (p.get(f"E_{k}_kPa", np.nan) / v - 1), 1) for k, v in truth.items()}
    b = d.baseline
    print("BASE", errs(b.parameters), {k: round(v, 4) for k, v in b.misfit.items() if isinstance(v, float)})
    for c in d.candidates:
        if not c.misfit: continue
        red = {k: round(b.misfit[k] / max(c.misfit[k], 1e-12), 2) for k in ("force_rms_N", "displacement_rms_px", "displacement_systematic_px", "force_excess_N", "displacement_excess_px", "chi2")}
        print("CAND", c.effect, errs(c.parameters), "reduction", red, {k: round(v, 3) for k, v in c.parameters.items() if not k.startswith("E_")})
    print("seconds", round(time.time() - t0))
    if "+" in eff and d.verdict != "none":
        c = d.candidate(d.verdict)
        t1 = time.time()
        d2 = diagnose(exp, effects=(d.verdict,), candidates=tuple(x for x in (cands or ()) if x != d.verdict) or None,
                      problem=c.problem, start=c.parameters, mesh_settings=ID_MESH, inclusion=c.inclusion,
                      tracked=d.tracked, progress=lambda s: print("  ..", s, flush=True))
        print(f"SECOND diagnosis with {d.verdict} added:")
        print("\n".join(d2.lines()))
        b2 = d2.baseline
        print("BASE2", errs(b2.parameters))
        for c2 in d2.candidates:
            if not c2.misfit: continue
            red = {k: round(b.misfit[k] / max(c2.misfit[k], 1e-12), 2) for k in ("force_rms_N", "displacement_rms_px", "force_excess_N", "displacement_excess_px", "chi2")}
            print("CAND2", c2.effect, errs(c2.parameters), "reduction from the first baseline", red)
        print("seconds", round(time.time() - t1))
