"""Which fit the identification mesh's error moves: the moduli of the baseline per mesh sizing.

    python bench/mesh_moduli_bias.py EXPERIMENT [--variants auto probe=1.0 outline=1.0 ...]

EXPERIMENT is a simulated experiment folder with its truth.toml (``elastoid
simulate``, or bench/paper_effects.py's folders). For each mesh sizing (the
variants of bench/mesh_field_error.py) the baseline model is built, identified
as ``elastoid identify`` does (NMI and force, two starts), and refitted by
maximum likelihood on the tracked displacements and the force as a diagnosis
does before it tries any effect. Prints both fits' moduli against the truth.
On two paper phantoms with nothing hidden (seeds 27106 and 25106) the shipped
mesh gave E_A +0.3% / -0.2% by the identification and +5.4% / +5.2% by the
refit; 1.0 mm on the probe face -0.8% / -0.1% by the refit
(docs/model-check.md, "which fit the probe's mesh error moves").
"""

from __future__ import annotations

import argparse
import sys
import time
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.mesh_field_error import settings_of  # noqa: E402


def main() -> int:
    from app.core.diagnose import _current_fit, current_model
    from app.core.effects.model import identify_with_effects
    from app.core.experiment import read_experiment
    from app.core.mesh import auto_settings

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("experiment", type=Path)
    ap.add_argument("--variants", nargs="+", default=["auto", "probe=1.4", "probe=1.0", "outline=1.0", "scale=0.8"])
    args = ap.parse_args()
    truth = tomllib.loads((args.experiment / "truth.toml").read_text())["moduli_kPa"]
    exp = read_experiment(args.experiment)
    auto = auto_settings(exp.specimen.size_mm, exp.probe.face_rect_mm(), exp.specimen.regions)

    def off(params: dict) -> str:
        return "  ".join(f"{100 * (params[f'E_{r}_kPa'] / E - 1):+6.1f}%" for r, E in truth.items())

    names = "  ".join(f"{'E_' + r:>7s}" for r in truth)
    print(f"{args.experiment.name}: truth {truth} kPa")
    print(f"{'sizing':>22s} {'vertices':>8s} {'s':>5s} | identify {names} | ML refit {names}")
    for v in args.variants:
        t = time.perf_counter()
        problem = current_model(exp, (), mesh_settings=settings_of(v, auto))
        start = identify_with_effects(problem, (10.0, 30.0)).parameters
        refit = _current_fit(problem, start, None, None, 200, lambda s: None)[3].parameters
        print(f"{v:>22s} {problem.mesh.n_nodes:8d} {time.perf_counter() - t:5.0f} | identify {off(start)} | "
              f"ML refit {off(refit)}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
