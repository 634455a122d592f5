"""How much a slipping probe changes the tracked field of a committed hidden-effect case.

    python bench/probe_slip_signal.py CASE [CASE ...]     (names of tests/core/synthetic.DIAGNOSE_CASES)

For each case: speckle is tracked with the baseline at the truth's described
moduli, and the bonded and slipping models are evaluated there (no noise, no
refit). Prints the RMS and largest difference between the two models at the
tracked blocks, per frame pair. Use ELASTOID_CACHE_DIR with a copy of
tests/data/meshes for the committed meshes.
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    import numpy as np

    from app.core.compare import track
    from app.core.diagnose import Likelihood, current_model, noise_model
    from app.core.experiment import read_experiment
    from app.core.simulate import read_truth
    from tests.core import synthetic

    print(f"{'case':18s} {'pair':>4s} {'RMS px':>7s} {'max px':>7s} {'lateral RMS px':>15s}")
    for name in (argv if argv is not None else sys.argv[1:]):
        folder = synthetic.diagnose_case(name)
        exp, truth = read_experiment(folder), read_truth(folder)
        hidden = {r["name"] for r in truth.get("hidden_regions", [])}
        at = {f"E_{k}_kPa": v for k, v in truth["moduli_kPa"].items() if k not in hidden}
        bonded = current_model(exp, (), mesh_settings=synthetic.DIAGNOSE_ID_MESH)
        slipping = current_model(exp, ("probe-slip",), mesh_settings=synthetic.DIAGNOSE_ID_MESH)
        tracked = track(bonded, bonded.complete(at))
        noise = noise_model(bonded, tracked)
        m0 = Likelihood(bonded, tracked, noise).model_px(bonded.complete(at))
        m1 = Likelihood(slipping, tracked, noise).model_px(slipping.complete(at))
        for j, (a, b, tp) in enumerate(zip(m0, m1, tracked.pairs)):
            d = (b - a)[tp.valid]
            print(f"{name:18s} {j:4d} {np.sqrt((d**2).sum(1).mean()):7.3f} {np.abs(d).max():7.3f} "
                  f"{np.sqrt((d[:, 1]**2).mean()):15.3f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
