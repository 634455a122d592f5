"""The ``sliding-bottom`` and ``probe-slip`` effects: relaxed boundary conditions.

Baseline: the bottom face is bonded to the table and the probe face to the
surface. ``sliding-bottom`` keeps only the vertical displacement of the bottom
face (the specimen slides freely on the table); ``probe-slip`` keeps only the
vertical displacement under the probe face (frictionless contact). Neither adds
a continuous parameter: the model switches (charged as one parameter by the
diagnosis). Both make the specimen softer for the same moduli, so the force
alone cannot tell them from lower moduli; the signature is in the field:

- sliding-bottom: the tissue spreads sideways more, increasingly with depth;
  deep points move outwards and rise less than the bonded model says.
- probe-slip: the tissue under the probe spreads sideways from the face
  (the bonded model holds it laterally fixed there).
"""

from __future__ import annotations

import numpy as np

from app.core.effects import misfit_change
from app.core.forward import Boundary


def boundary_for(effects) -> Boundary:
    return Boundary(bottom="sliding" if "sliding-bottom" in effects else "bonded",
                    probe="slip" if "probe-slip" in effects else "bonded")


def evidence(effect: str, lateral_misfit_px: np.ndarray, depth_mm: np.ndarray, spacing_mm: float,
             rms_before_px: float, rms_after_px: float) -> str:
    """A sentence from the lateral displacement misfit (measured - model, px, signed
    away from the probe axis) of tracked blocks at their depths below the probe."""
    lat = np.asarray(lateral_misfit_px, float)
    z = np.asarray(depth_mm, float)
    if effect == "probe-slip":
        near = z <= np.quantile(z, 0.25) if len(z) else z
        where, what = "just under the probe", "stuck to the probe face"
    else:
        near = z >= np.quantile(z, 0.75) if len(z) else z
        where, what = "in the deepest part of the image", "bonded to the table"
    spread = float(np.median(lat[near]) * spacing_mm) if np.any(near) else 0.0
    direction = "outwards" if spread >= 0 else "inwards"
    moves = (f"moves sideways {abs(spread):.2f} mm {direction} more than the model" if abs(spread) >= 0.005
             else "moves sideways as the model says (within 0.01 mm)")
    return (f"{where} the tissue {moves}, which holds it "
            f"{what}; letting it slide, the displacement misfit {misfit_change(rms_before_px, rms_after_px)}")
