"""The hyperelastic correction with many frames: all their travels against MAX_LOAD_STEPS.

    python bench/many_frames.py [EXPERIMENT]

EXPERIMENT defaults to bench/out/paper_effects/slip-31, the paper's phantom with
a frame every half millimetre (written by ``python bench/paper_effects.py --cases
slip-31``, which also diagnoses it and prints the time and peak memory). Refreshes
the hyperelastic model at E_B 17.6 and E_A 66 kPa asking the solver for every
frame's travel (MAX_LOAD_STEPS raised to 1000), then for MAX_LOAD_STEPS of them,
each cold and then warm (E_A +5%), and prints a table: the travels asked for, the
cold and warm seconds, factorizations, and how far the interpolated correction at
the frames between the steps (px, control points) and the force (N) are from the
solve at every travel.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main() -> int:
    import numpy as np

    import app.core.effects.model as model
    from app.core.diagnose import current_model
    from app.core.experiment import read_experiment

    folder = Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT / "bench" / "out" / "paper_effects" / "slip-31"
    p = current_model(read_experiment(folder), ("hyperelastic",))
    params = p.complete({"E_B_kPa": 17.6, "E_A_kPa": 66.0})
    cap = model.MAX_LOAD_STEPS
    rows, ref = [], None
    for n in (1000, cap):
        model.MAX_LOAD_STEPS = n
        if p._hyper_model is not None:  # a cold solver (the last one's factors freed)
            p._hyper_model.free()
            p._hyper_model = None
        t = time.perf_counter()
        p.refresh_hyperelastic(params)
        cold = time.perf_counter() - t
        n_fact = p._hyper_model.n_factorizations
        px = np.stack([np.column_stack([(c @ p._lat) / p._sc, -c[:, 2] / p._sr])
                       for c in (p._pair_correction("__ctrl__", pair) for pair in p.pairs)])
        F = p.model_force_N(params)
        t = time.perf_counter()
        p.refresh_hyperelastic({**params, "E_A_kPa": 1.05 * params["E_A_kPa"]})
        warm = time.perf_counter() - t
        ref = ref or (px, F)
        rows.append([str(len(p._hyper.depths_mm)), f"{cold:.1f}", str(n_fact), f"{warm:.2f}",
                     f"{np.abs(px - ref[0]).max():.4f} (of {np.abs(ref[0]).max():.2f})",
                     f"{np.abs(F - ref[1]).max():.4f} (of {np.abs(ref[1]).max():.2f})"])
    model.MAX_LOAD_STEPS = cap
    head = ["travels asked for", "cold s", "factorizations", "warm s", "correction off by (px)", "force off by (N)"]
    print(f"{folder.name}: {len(p.pairs)} frame pairs")
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for r in rows:
        print("| " + " | ".join(r) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
