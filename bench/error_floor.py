"""What the displacement error left by the right effect is made of.

    python bench/error_floor.py FOLDER [FOLDER ...]

FOLDER: a synthetic experiment (``elastoid simulate``, with truth.toml) that
``elastoid diagnose FOLDER --json FOLDER.json`` has diagnosed
(bench/paper_effects.py writes both). The speckle is tracked once with the
baseline's fit, as the diagnosis does. For the baseline's fit, the verdict's
fit and the truth (the true moduli, Poisson's ratio and boundary, on the
identification mesh, whatever the verdict; skipped for a truth with an effect
the identification mesh cannot hold) the table gives the diagnosis' error beyond the noise
and the RMS of the tracked residual's 3 x 3 medians, the measure behind it,
over every tracked block (as the diagnosis takes it) and over the blocks
whose speckle correlated at least 0.45 or 0.5 after registration (tracking
keeps blocks from 0.3). The last two columns track again without confirming
weak blocks by a larger block (``track(confirm_weak=False)``, the tracking
before 2026-11-29): its error beyond the noise and 3 x 3-median RMS. The
verdict must be an image effect on the identification mesh
(sliding-bottom, probe-slip, compressibility) or none.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

QUALITIES = (0.45, 0.5)
BOUNDARY = ("sliding-bottom", "probe-slip")  # the truth's effects the identification mesh holds


def median_rms(tracked, model_px, qmin: float = 0.0) -> tuple[float, int]:
    """RMS of the 3 x 3 medians of measured - model over the valid blocks that
    correlated at least ``qmin``; and how many blocks that is."""
    import numpy as np

    from app.core.diagnose import _systematic

    sq, n, kept = 0.0, 0, 0
    for tp, m in zip(tracked.pairs, model_px):
        keep = tp.valid & (tp.quality >= qmin)
        kept += int(keep.sum())
        s, _ = _systematic(tp.measured_px - m, keep, tp.grid_index)
        sq += float((s ** 2).sum())
        n += len(s)
    return float(np.sqrt(sq / max(n, 1))), kept


def run(folder: Path) -> list[list[str]]:
    from app.core.compare import track
    from app.core.diagnose import Likelihood, _misfit, current_model, noise_model
    from app.core.experiment import read_experiment
    from app.core.simulate import read_truth

    exp = read_experiment(folder)
    truth = read_truth(folder)
    d = json.loads(folder.with_name(folder.name + ".json").read_text())
    verdict = d["verdict"]
    if verdict not in ("none", "sliding-bottom", "probe-slip", "compressibility"):
        return [[folder.name, verdict, "(not an image effect on the identification mesh: skipped)"]]
    base = current_model(exp)
    pb = base.complete(d["baseline"]["parameters"])
    tracked = track(base, pb)
    unconfirmed = track(base, pb, confirm_weak=False)
    fits = [("baseline", base, pb)]
    models = {(): base}
    if verdict != "none":
        models[(verdict,)] = current_model(exp, effects=(verdict,), base=base)
        cand = next(c for c in d["candidates"] if c["effect"] == verdict)
        fits.append((verdict, models[(verdict,)], models[(verdict,)].complete(cand["parameters"])))
    # the truth: its own effects (not the verdict's, which may be wrong), at its moduli
    true = {f"E_{k}_kPa": float(v) for k, v in truth["moduli_kPa"].items()}
    hidden = truth.get("effects", [])
    effects = [e for e in hidden if e in BOUNDARY]
    if abs(float(truth["nu"]) - base.nu) > 1e-9:
        effects.append("compressibility")
        true["nu"] = float(truth["nu"])
    if set(hidden) - set(BOUNDARY) or truth.get("hidden_regions"):
        fits.append(("truth (not on the identification mesh: skipped)", None, None))
    else:
        key = tuple(effects)
        if key not in models:  # the verdict's model when the verdict is the truth's one effect
            models[key] = current_model(exp, effects=key, base=base)
        fits.append(("truth", models[key], models[key].complete(true)))
    rows = []
    for label, problem, params in fits:
        if problem is None:
            rows.append([folder.name, label])
            continue
        # over every block, the diagnosis' own misfit holds both the error beyond the
        # noise and the 3 x 3-median RMS (displacement_systematic_px)
        lik = Likelihood(problem, tracked, noise_model(problem, tracked))
        m = _misfit(lik, params)
        m_u = _misfit(Likelihood(problem, unconfirmed, noise_model(problem, unconfirmed)), params)
        cols = [folder.name, label, f"{m['displacement_excess_px']:.3f}",
                f"{m['displacement_systematic_px']:.3f} ({tracked.n_valid})"]
        mp = lik.model_px(params)
        for q in QUALITIES:
            r, n = median_rms(tracked, mp, q)
            cols.append(f"{r:.3f} ({n})")
        cols += [f"{m_u['displacement_excess_px']:.3f}", f"{m_u['displacement_systematic_px']:.3f} ({unconfirmed.n_valid})"]
        rows.append(cols)
    return rows


def main() -> int:
    folders = [Path(a).resolve() for a in sys.argv[1:]]
    if not folders:
        print(__doc__)
        return 2
    head = ["case", "model", "error beyond the noise, px (the diagnosis')", "3x3-median RMS px, every block (blocks)",
            *(f"correlation >= {q} (blocks)" for q in QUALITIES),
            "without confirming weak blocks: error beyond the noise, px", "its 3x3-median RMS px (blocks)"]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for f in folders:
        for row in run(f):
            print("| " + " | ".join(row) + " |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
