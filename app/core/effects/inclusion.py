"""The ``inclusion`` effect: a region the experiment does not describe.

Located from the misfit: the tracked displacement misfit (measured - model) of
the frame pair with the largest travel is differentiated on the block grid into
a strain misfit (d/drow of the vertical part + d/dcol of the lateral part). An
inclusion stiffer (softer) than its surroundings is strained less (more) than
the model says, so the strain misfit has one extremum there. Its centre on the
image plane gives the region's centre (in the image plane: the frames see only
that plane), the extent of the blob above half its extreme gives the radius.

The region is a sphere added to the specimen (``Specimen.with_region``), meshed
as a new region; its modulus E_<name>_kPa becomes a parameter. The diagnosis
charges it four parameters: the modulus, two centre coordinates and the radius.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.core.geometry import Region


@dataclass(frozen=True)
class InclusionGuess:
    name: str
    center_mm: tuple[float, float, float]
    radius_mm: float
    stiffer: bool  # the strain misfit says stiffer than the surroundings
    strain_misfit: float  # the extremum (measured - model vertical strain per block)

    def region(self) -> Region:
        return Region(self.name, "sphere", center_mm=tuple(self.center_mm), radius_mm=float(self.radius_mm))

    def as_parameters(self) -> dict:
        return {"center_mm": [round(c, 3) for c in self.center_mm], "radius_mm": round(self.radius_mm, 3)}


def new_region_name(existing) -> str:
    for name in ("I", "I2", "I3", "I4", "I5"):
        if name not in existing:
            return name
    return f"I{len(existing) + 1}"


def strain_misfit_map(tracked_pair, model_px: np.ndarray, block_px: int):
    """(grid of the strain misfit, grid of world points) for one tracked pair.

    Strain misfit per block: d(residual row)/d(row) + d(residual col)/d(col), in
    px per px, NaN where a neighbour is missing."""
    g = tracked_pair.grid_index
    nr, nc = g[:, 0].max() + 1, g[:, 1].max() + 1
    res = np.full((nr, nc, 2), np.nan)
    ok = tracked_pair.valid
    res[g[ok, 0], g[ok, 1]] = (tracked_pair.measured_px - model_px)[ok]
    world = np.full((nr, nc, 3), np.nan)
    world[g[:, 0], g[:, 1]] = tracked_pair.points_world_mm
    # robust: median of the residual in 3 x 3 neighbourhoods before differencing
    from scipy.ndimage import generic_filter

    sm = np.stack([generic_filter(res[..., k], np.nanmedian, size=3, mode="constant", cval=np.nan)
                   for k in range(2)], -1)
    e = np.full((nr, nc), np.nan)
    e_r = np.gradient(sm[..., 1], axis=0) if nr > 1 else np.zeros((nr, nc))
    e_c = np.gradient(sm[..., 0], axis=1) if nc > 1 else np.zeros((nr, nc))
    e = (e_r + e_c) / float(block_px)
    return e, world


def locate(tracked, model_px_per_pair, exp, probe_y_mm: float | None = None) -> InclusionGuess | None:
    """Guess an inclusion from the strain misfit of the deepest-travel pair."""
    k = int(np.argmax([abs(p.measured_px[p.valid, 1]).mean() if p.valid.any() else 0 for p in tracked.pairs]))
    tp = tracked.pairs[k]
    e, world = strain_misfit_map(tp, model_px_per_pair[k], tracked.block_px)
    if not np.any(np.isfinite(e)):
        return None
    # ignore the rows right under the probe and the border blocks (edge effects of differencing)
    e = e.copy()
    e[0, :] = np.nan
    e[:, 0] = np.nan
    e[:, -1] = np.nan
    e[-1, :] = np.nan
    if not np.any(np.isfinite(e)):
        return None
    i, j = np.unravel_index(np.nanargmax(np.abs(e)), e.shape)
    peak = e[i, j]
    from scipy.ndimage import label

    blob, _ = label(np.nan_to_num(np.abs(e)) >= 0.5 * abs(peak))
    members = blob == blob[i, j]
    w = np.abs(np.nan_to_num(e)) * members
    pts = world[members]
    wt = w[members]
    centre = (pts * wt[:, None]).sum(0) / wt.sum()
    area_mm2 = members.sum() * (tracked.block_px * exp.imaging.pixel_spacing_mm[0]) * \
        (tracked.block_px * exp.imaging.pixel_spacing_mm[1])
    radius = float(np.sqrt(area_mm2 / np.pi))
    if probe_y_mm is not None:
        centre[1] = probe_y_mm
    size = np.asarray(exp.specimen.size_mm, float)
    radius = float(np.clip(radius, 1.5, 0.25 * size.min()))
    # keep the sphere inside the specimen and off its faces
    margin = radius + 0.5
    centre = np.clip(centre, margin, size - margin)
    # residual row displacement: rows grow with depth and tissue moves up (negative rows) when pressed;
    # a stiffer inclusion is compressed less: measured d(row disp)/d(row) larger than the model's
    stiffer = bool(peak > 0)
    name = new_region_name(exp.specimen.region_names)
    return InclusionGuess(name, tuple(float(c) for c in centre), radius, stiffer, float(peak))


def evidence(guess: InclusionGuess, depth_mm: float, e_ratio: float) -> str:
    kind = "stiffer" if e_ratio >= 1 else "softer"
    return (f"a region the experiment does not describe, about {2 * guess.radius_mm:.0f} mm across at "
            f"{depth_mm:.0f} mm depth, deforms {'less' if e_ratio >= 1 else 'more'} than its surroundings: "
            f"as an inclusion {e_ratio:.1f} times {kind if e_ratio >= 1 else 'as stiff'} "
            f"it explains the misfit")
