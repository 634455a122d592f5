"""The moduli a diagnosis reports: its maximum-likelihood fit against the identification from it.

    python bench/identified_moduli.py FOLDER [FOLDER ...]

FOLDER: a simulated experiment (``elastoid simulate``, with truth.toml) that
``elastoid diagnose FOLDER --json FOLDER.json`` has diagnosed
(bench/paper_effects.py writes both). For the model the verdict calls for (the
baseline for ``none``), the table gives each modulus' error against the truth
as the diagnosis fitted it (maximum likelihood on the tracked blocks and the
force: the candidate's ``parameters``) and as :func:`app.core.diagnose.identify_from`
identifies it from there (NMI and force, as ``elastoid identify``: the
``identified`` moduli of the diagnosis, and the version an added effect makes).
The identification runs again here on the diagnosis' fit, so diagnoses written
before ``identified`` existed are measured too. On 26 blind phantoms
(2026-11-30) the fits' E_A were 4.5% off (median of the absolute errors) and up
to +15.5%; identified, 0.8% (docs/model-check.md, "The moduli an added effect
gives"). With the verdict inclusion the identification also places the sphere
by NMI and force (app.core.diagnose.place_by_identification), as the diagnosis
does since 2026-11-30, night.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def errors(params: dict, truth: dict) -> str:
    return ", ".join(f"{k[:-4] if k.startswith('E_') else k} {100 * (params[k] / v - 1):+.1f}%"
                     for k, v in truth.items() if k in params)


def run(folder: Path) -> list[str]:
    from app.core.diagnose import _identified_verdict, current_model
    from app.core.experiment import read_experiment
    from app.core.simulate import read_truth

    exp, truth = read_experiment(folder), read_truth(folder)
    d = json.loads(folder.with_name(folder.name + ".json").read_text())
    v = d["verdict"]
    c = d["baseline"] if v == "none" else next(c for c in d["candidates"] if c["effect"] == v)
    effects = tuple(d["baseline"]["effects"]) + (() if v == "none" else (v,))
    fitted = {k: x for k, x in c["parameters"].items() if k not in ("center_mm", "radius_mm")}
    true = {f"E_{k}_kPa": float(x) for k, x in truth["moduli_kPa"].items()}
    hidden = [r["name"] for r in truth.get("hidden_regions", [])]
    if v == "inclusion" and len(hidden) == 1:  # the located inclusion stands for the hidden region
        true["E_I_kPa"] = true.pop(f"E_{hidden[0]}_kPa")
    true["nu"] = float(truth["nu"])
    t0 = time.perf_counter()
    problem = current_model(exp, effects, inclusion=c.get("inclusion") if "inclusion" in effects else None)
    ident = _identified_verdict(problem, v, fitted, lambda s: None, None)  # as the diagnosis identifies it
    return [folder.name, v, errors(fitted, true), errors(ident["parameters"], true), f"{time.perf_counter() - t0:.0f}"]


def main() -> int:
    folders = [Path(a).resolve() for a in sys.argv[1:]]
    if not folders:
        print(__doc__)
        return 2
    print("| experiment | verdict | the diagnosis' fit vs truth | identified from it vs truth | s (model built and identified) |")
    print("|---|---|---|---|---|")
    for f in folders:
        print("| " + " | ".join(run(f)) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
