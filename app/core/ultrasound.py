"""A scatterer-based B-mode simulator for synthetic experiments.

Point scatterers fill a slab around the image plane; each frame carries them by
the true displacement field (so speckle decorrelates as real speckle does; it is
not a warp of the first frame). A frame is the envelope of the scatterers
convolved with a Gaussian-modulated pulse (axial) and Gaussian beam (lateral,
elevation), log-compressed to 8 bits.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import fftconvolve


@dataclass(frozen=True)
class Transducer:
    center_frequency_MHz: float = 7.5
    sound_speed_m_s: float = 1540.0
    axial_sigma_mm: float = 0.15  # pulse envelope
    lateral_sigma_mm: float = 0.30  # beam width
    elevation_sigma_mm: float = 0.50  # slice thickness
    dynamic_range_dB: float = 50.0
    noise_level: float = 0.02  # electronic noise, relative to the mean envelope

    @property
    def wavenumber_per_mm(self) -> float:
        return 2 * np.pi * self.center_frequency_MHz * 1e6 / (self.sound_speed_m_s * 1e3)


@dataclass(frozen=True)
class Scatterers:
    points_mm: np.ndarray  # (n, 3) undeformed positions
    amplitude: np.ndarray  # (n,)


def make_scatterers(exp, rng: np.random.Generator, max_travel_mm: float, density_per_mm3: float = 25.0,
                    echogenicity: dict | None = None, transducer: Transducer = Transducer()) -> Scatterers:
    """Random scatterers in the slab the image plane sweeps through, with amplitudes
    scaled per region by ``echogenicity`` (name -> factor)."""
    from app.core.geometry import paint_labels

    im, pr = exp.imaging, exp.probe
    sx, sy, sz = exp.specimen.size_mm
    lat = np.asarray(pr.lateral_axis, float)
    elev = np.cross([0.0, 0.0, 1.0], lat)
    shape_cols = 2 * im.probe_face_px[0] + 1
    half_w = 0.5 * shape_cols * im.pixel_spacing_mm[0] + 3.0
    depth = min(sz, 512 * im.pixel_spacing_mm[1] + max_travel_mm + 3.0)
    thick = 4.0 * transducer.elevation_sigma_mm
    vol = 2 * half_w * depth * 2 * thick
    n = int(rng.poisson(density_per_mm3 * vol))
    l = rng.uniform(-half_w, half_w, n)
    e = rng.uniform(-thick, thick, n)
    z = sz - rng.uniform(0, depth, n)
    c = np.array([pr.center_mm[0], pr.center_mm[1], 0.0])
    pts = c + l[:, None] * lat + e[:, None] * elev + z[:, None] * np.array([0, 0, 1.0])
    inside = np.all((pts >= 0) & (pts <= [sx, sy, sz]), axis=1)
    pts = pts[inside]
    amp = rng.standard_normal(len(pts))
    if echogenicity:
        labels = paint_labels(pts, exp.specimen.regions)
        for k, r in enumerate(exp.specimen.regions):
            amp[labels == k] *= echogenicity.get(r.name, 1.0)
    return Scatterers(pts, amp)


def render(points_mm: np.ndarray, amplitude: np.ndarray, exp, displacement_mm: float, shape: tuple[int, int],
           transducer: Transducer = Transducer(), reference: float | None = None,
           rng: np.random.Generator | None = None) -> tuple[np.ndarray, float]:
    """B-mode frame (uint8, rows = depth) of scatterers at their current positions,
    imaged with the probe at travel ``displacement_mm``. Returns (image, reference
    envelope level); pass the reference of the first frame to later frames so all
    frames share one gain."""
    im, pr = exp.imaging, exp.probe
    rows, cols = shape
    sc, sr = im.pixel_spacing_mm
    c0, r0 = im.probe_face_px
    lat = np.asarray(pr.lateral_axis, float)
    elev = np.cross([0.0, 0.0, 1.0], lat)
    origin = np.array([pr.center_mm[0], pr.center_mm[1], exp.specimen.size_mm[2] - displacement_mm])
    d = points_mm - origin
    lateral = d @ lat
    depth = -d[:, 2]
    el = d @ elev
    # fine grid: 2 samples per column laterally, 4 per row axially. Each scatterer
    # is splatted bilinearly onto its four nearest grid points (so its envelope
    # moves continuously with it, not in grid steps), and each share carries the
    # round-trip phase from that grid point to the scatterer, exp(-j 2k (z - z_g)):
    # with the kernel's carrier exp(j 2k (z_out - z_g)) the echo's phase at the
    # output is exactly exp(j 2k (z_out - z)), whatever the grid.
    fl, fa = 2, 4
    dl, da = sc / fl, sr / fa
    xl = (lateral / sc + c0) * fl  # fine-grid coordinates
    xa = (depth / sr + r0) * fa
    T = transducer
    keep = (np.abs(el) < 3 * T.elevation_sigma_mm) & (xl >= -8) & (xl < cols * fl + 7) & (xa >= -16) & (xa < rows * fa + 15)
    k2 = 2 * T.wavenumber_per_mm
    xl, xa = xl[keep], xa[keep]
    base = amplitude[keep] * np.exp(-0.5 * (el[keep] / T.elevation_sigma_mm) ** 2)
    il, ia = np.floor(xl).astype(np.int64), np.floor(xa).astype(np.int64)
    fl_w, fa_w = xl - il, xa - ia
    nl, na = cols * fl + 16, rows * fa + 32
    grid = np.zeros((na, nl), complex)
    for oa, wa in ((0, 1.0 - fa_w), (1, fa_w)):
        # the phase from grid row ia + oa to the scatterer: 2k (xa - ia - oa) da
        phase = np.exp(-1j * k2 * (fa_w - oa) * da)
        for ol, wl in ((0, 1.0 - fl_w), (1, fl_w)):
            np.add.at(grid, (ia + oa + 16, il + ol + 8), base * wa * wl * phase)
    za = np.arange(-int(4 * T.axial_sigma_mm / da), int(4 * T.axial_sigma_mm / da) + 1) * da
    zl = np.arange(-int(4 * T.lateral_sigma_mm / dl), int(4 * T.lateral_sigma_mm / dl) + 1) * dl
    ka = np.exp(-0.5 * (za / T.axial_sigma_mm) ** 2) * np.exp(1j * k2 * za)
    kl = np.exp(-0.5 * (zl / T.lateral_sigma_mm) ** 2)
    env = np.abs(fftconvolve(fftconvolve(grid, ka[:, None], mode="same"), kl[None, :], mode="same"))
    env = env[16: 16 + rows * fa: fa, 8: 8 + cols * fl: fl]
    if reference is None:
        reference = float(np.mean(env)) if np.mean(env) > 0 else 1.0
    if rng is not None and T.noise_level > 0:
        env = np.abs(env + T.noise_level * reference * (rng.standard_normal(env.shape) + 1j * rng.standard_normal(env.shape)))
    db = 20 * np.log10(np.maximum(env, 1e-12) / (4.0 * reference))
    img = np.clip((db + T.dynamic_range_dB) / T.dynamic_range_dB, 0, 1)
    return np.round(img * 255).astype(np.uint8), reference
