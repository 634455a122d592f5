"""The ``hyperelastic`` effect: large deformation with a neo-Hookean law.

The solver is :mod:`app.core.hyperelastic` (Newton-type iteration with load
steps on the same P2 space and sparsity pattern as the linear model); inside a
fit :class:`app.core.effects.model.EffectProblem` uses it as a correction that
is refreshed at the optimum. No parameter of its own: it reuses the moduli
(the neo-Hookean law has the linear model's moduli at small strain).

Signature: the force-travel curve bends (it stiffens as the probe goes deeper
under a bonded face); the linear model's force is proportional to the travel.
"""

from __future__ import annotations

import numpy as np

from app.core.hyperelastic import HyperelasticModel, HyperelasticSolution, neo_hookean_stress, uniaxial_stress_kPa

__all__ = ["HyperelasticModel", "HyperelasticSolution", "neo_hookean_stress", "uniaxial_stress_kPa",
           "stiffening", "evidence"]


def stiffening(d_mm: np.ndarray, force_N: np.ndarray) -> float:
    """Relative change of the secant stiffness (N/mm) of the loading part of a log
    between its first and second half of travel: k_late / k_early - 1."""
    d, F = np.asarray(d_mm, float), np.asarray(force_N, float)
    peak = int(np.argmax(d))
    d, F = d[: peak + 1], F[: peak + 1]
    dmax = d.max() if len(d) else 0.0
    if dmax <= 0:
        return 0.0

    def slope(lo, hi):
        m = (d >= lo * dmax) & (d <= hi * dmax)
        if m.sum() < 3:
            return np.nan
        return np.polyfit(d[m], F[m], 1)[0]

    k1, k2 = slope(0.1, 0.5), slope(0.5, 1.0)
    if not np.isfinite(k1) or not np.isfinite(k2) or k1 <= 0:
        return 0.0
    return float(k2 / k1 - 1.0)


def evidence(d_mm, measured_N, model_N, candidate_N=None) -> str:
    """The measured force's stiffening against the current model's and, with
    ``candidate_N``, against the fitted neo-Hookean model's (which says why the
    effect is or is not needed)."""
    def says(s):
        if abs(s) < 0.01:
            return "grows in proportion to the travel (within 1%)"
        return f"{'stiffens' if s >= 0 else 'softens'} by {100 * abs(s):.0f}%"

    out = (f"from the first to the second half of the indentation the measured force "
           f"{says(stiffening(d_mm, measured_N))}; the model's force {says(stiffening(d_mm, model_N))}")
    if candidate_N is not None:
        out += f"; with large deformation (neo-Hookean) it {says(stiffening(d_mm, candidate_N))}"
    return out
