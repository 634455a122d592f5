"""What the located inclusion's placement costs, by how its trials' reduced models are trained.

    ELASTOID_CACHE_DIR=DIR python bench/inclusion_place.py EXPERIMENT [--repeats 2] [--trials 16]

The placement (diagnose.place_by_identification) follows a diagnosis whose
verdict is the inclusion: a compass search of the sphere's centre and radius,
each trial sphere relabelled on the located sphere's mesh and its modulus alone
fitted by the identification's objective (NMI and force). Each trial trains a
reduced model first. This bench locates the sphere (as ``elastoid identify
--effects inclusion`` does), then runs the placement with the trials' reduced
models trained two ways, alternately, ``--repeats`` times each:

- ``line``: on the inclusion's modulus alone (the product's, since 2026-12-02);
- ``box``: on a box of every ratio within a factor 1.5 (the peer: the product before).

Prints a table: wall time of the placement, seconds a trial, basis vectors and
back-substitutions of the trials' reduced models (their medians), the sphere
found, and the inclusion's modulus. Run it alone: the times are the machine's.
"""
import argparse
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("experiment")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--trials", type=int, default=16)
    a = ap.parse_args()

    import app.core.diagnose as D
    from app.core.effects import model as M
    from app.core.effects.model import identify_with_effects
    from app.core.experiment import read_experiment

    exp = read_experiment(a.experiment)
    t = time.perf_counter()
    inclusion = D.locate_inclusion(exp, ("inclusion",))
    problem = D.current_model(exp, ("inclusion",), inclusion=inclusion)
    located = identify_with_effects(problem)
    params = {k: v for k, v in located.parameters.items() if k in problem.moduli_names}
    print(f"located and identified in {time.perf_counter() - t:.1f} s: sphere {inclusion}, {params}")

    built = []  # each trial's reduced model: (basis vectors, back-substitutions)
    inner = M.EffectProblem.from_experiment.__func__
    way = ["line"]

    def from_experiment(cls, *args, **kw):
        if way[0] == "box":
            kw.pop("near_alone", None)
        p = inner(cls, *args, **kw)
        if kw.get("near_kPa") is not None:
            built.append((p.rm.k, p.rm.n_back_solves))
        return p

    M.EffectProblem.from_experiment = classmethod(from_experiment)
    rows = []
    for _ in range(a.repeats):
        for w in ("line", "box"):
            way[0] = w
            built.clear()
            t = time.perf_counter()
            sphere, res, n, _ = D.place_by_identification(problem, params, max_trials=a.trials)
            s = time.perf_counter() - t
            own = f"E_{sphere['name']}_kPa"
            rows.append((w, s, n, statistics.median(b[0] for b in built), statistics.median(b[1] for b in built),
                         sphere, res.parameters[own]))
            print(f"{w}: {s:.1f} s", flush=True)
    print()
    print("| trials' training | placement s | trials | s a trial | basis vectors | back-substitutions | sphere "
          "(centre mm, radius mm) | E_I kPa |")
    print("|---|---|---|---|---|---|---|---|")
    for w, s, n, k, b, sphere, e in rows:
        c = ", ".join(f"{v:.1f}" for v in sphere["center_mm"])
        print(f"| {w} | {s:.1f} | {n} | {s / n:.2f} | {k:.0f} | {b:.0f} | ({c}), {sphere['radius_mm']:.2f} | {e:.2f} |")
    for w in ("line", "box"):
        print(f"median {w}: {statistics.median(r[1] for r in rows if r[0] == w):.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
