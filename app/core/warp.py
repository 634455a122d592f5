"""Warping the source frame by the FE displacement field, as the paper does.

The FE displacement, sampled at control points on the image plane, is carried
to pixels by a thin-plate spline (TPS). The exact TPS is :class:`TPS`; the fast
path evaluates that same TPS on a coarse pixel grid (every ``step`` pixels, 3 by default)
and upsamples it with separable cubic interpolation. Because the TPS is linear
in the control values, the whole chain is a few small matrix products per
evaluation. Its error against the exact TPS on every pixel is measured in the
tests and in bench/ (well under 0.1 px on the ROI).

Pixel displacement: a material point seen at source pixel p (frame at probe
travel d0) appears in the target frame (travel d1) at q = p + delta(p) with
    delta_col = (u1 - u0) . lateral / spacing_col
    delta_row = (-(d1 - d0) - (u1z - u0z)) / spacing_row
The warped source W(q) = S(p) needs the inverse map, found by fixed-point
iteration p = q - delta(p).
"""

from __future__ import annotations

import hashlib
import threading
import weakref
from dataclasses import astuple, dataclass

import numpy as np


def _tps_kernel(r2: np.ndarray) -> np.ndarray:
    """phi(r) = r^2 log r, written with r^2 (0 at r = 0), as scipy's thin_plate_spline."""
    out = np.zeros_like(r2)
    m = r2 > 0
    out[m] = 0.5 * r2[m] * np.log(r2[m])
    return out


class TPS:
    """Exact 2-D thin-plate spline through control points (n, 2)."""

    def __init__(self, ctrl: np.ndarray):
        self.ctrl = np.asarray(ctrl, float)
        n = len(self.ctrl)
        d2 = ((self.ctrl[:, None, :] - self.ctrl[None, :, :]) ** 2).sum(-1)
        L = np.zeros((n + 3, n + 3))
        L[:n, :n] = _tps_kernel(d2)
        P = np.column_stack([np.ones(n), self.ctrl])
        L[:n, n:] = P
        L[n:, :n] = P.T
        self._Linv = np.linalg.inv(L)

    def basis(self, pts: np.ndarray) -> np.ndarray:
        """(m, n+3) kernel and polynomial terms at points."""
        pts = np.asarray(pts, float)
        d2 = ((pts[:, None, :] - self.ctrl[None, :, :]) ** 2).sum(-1)
        return np.column_stack([_tps_kernel(d2), np.ones(len(pts)), pts])

    def matrix(self, pts: np.ndarray) -> np.ndarray:
        """(m, n): values at pts = matrix @ control values."""
        n = len(self.ctrl)
        return self.basis(pts) @ self._Linv[:, :n]

    def __call__(self, pts: np.ndarray, values: np.ndarray) -> np.ndarray:
        return self.matrix(pts) @ values


def cubic_matrix(n_fine: int, coarse_pos: np.ndarray) -> np.ndarray:
    """Dense (n_fine, n_coarse) interpolation with the Catmull-Rom cubic from
    samples at positions coarse_pos (uniform, in fine-pixel units) to 0..n_fine-1."""
    step = coarse_pos[1] - coarse_pos[0]
    x = (np.arange(n_fine) - coarse_pos[0]) / step
    nc = len(coarse_pos)
    U = np.zeros((n_fine, nc))
    i0 = np.clip(np.floor(x).astype(int), 0, nc - 2)
    t = x - i0
    w = [(-t**3 + 2 * t**2 - t) / 2, (3 * t**3 - 5 * t**2 + 2) / 2, (-3 * t**3 + 4 * t**2 + t) / 2, (t**3 - t**2) / 2]
    for k, wk in zip((-1, 0, 1, 2), w):
        j = i0 + k
        # reflect at the ends (linear extrapolation of the ghost samples)
        jl = np.clip(j, 0, nc - 1)
        np.add.at(U, (np.arange(n_fine), jl), wk * (j == jl))
        lo = j < 0
        np.add.at(U, (np.arange(n_fine)[lo], np.zeros(lo.sum(), int)), 2 * wk[lo])
        np.add.at(U, (np.arange(n_fine)[lo], np.ones(lo.sum(), int)), -wk[lo])
        hi = j > nc - 1
        np.add.at(U, (np.arange(n_fine)[hi], np.full(hi.sum(), nc - 1)), 2 * wk[hi])
        np.add.at(U, (np.arange(n_fine)[hi], np.full(hi.sum(), nc - 2)), -wk[hi])
    return U


@dataclass
class WarpGrid:
    """Pixel region (col0, row0, col1, row1), exclusive ends, where the warp is computed."""

    col0: int
    row0: int
    col1: int
    row1: int

    @property
    def shape(self) -> tuple[int, int]:
        return (self.row1 - self.row0, self.col1 - self.col0)


class FastTPSField:
    """TPS from control values to every pixel of a grid, via a coarse grid and
    separable cubic upsampling: ``field(values (n, 2)) -> (rows, cols, 2)``."""

    def __init__(self, tps: TPS, grid: WarpGrid, step: int = 4):
        rows, cols = grid.shape
        rc = np.arange(0, rows - 1 + step, step, dtype=float)
        cc = np.arange(0, cols - 1 + step, step, dtype=float)
        self.rc, self.cc = rc, cc
        R, C = np.meshgrid(rc + grid.row0, cc + grid.col0, indexing="ij")
        self.M = tps.matrix(np.column_stack([C.ravel(), R.ravel()]))  # points as (col, row)
        self.Ur = cubic_matrix(rows, rc)
        self.Uc = cubic_matrix(cols, cc)
        self.coarse_shape = (len(rc), len(cc))

    def coarse(self, values: np.ndarray) -> np.ndarray:
        return (self.M @ values).reshape(*self.coarse_shape, -1)

    def upsample(self, coarse: np.ndarray) -> np.ndarray:
        return np.einsum("ir,rck,jc->ijk", self.Ur, coarse, self.Uc, optimize=True)

    def __call__(self, values: np.ndarray) -> np.ndarray:
        return self.upsample(self.coarse(values))


def bilinear(image: np.ndarray, r: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of a 2-D array at (row, col) points, clamped to its
    edges: scipy.ndimage.map_coordinates(image, [r, c], order=1, mode="nearest") to
    1e-9 of a pixel at the border, about twice as fast (one gather per corner)."""
    H, W = image.shape
    flat = image.ravel()
    r = np.clip(r, 0.0, H - 1 - 1e-9)
    c = np.clip(c, 0.0, W - 1 - 1e-9)
    i = r.astype(np.intp)
    j = c.astype(np.intp)
    fr, fc = r - i, c - j
    k = i * W + j
    a, b = flat[k], flat[k + 1]
    top = a + fc * (b - a)
    a, b = flat[k + W], flat[k + W + 1]
    return top + fr * (a + fc * (b - a) - top)


def _grid_points(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    R, C = np.meshgrid(rows, cols, indexing="ij")
    return np.column_stack([C.ravel(), R.ravel()])  # (col, row)


# The inverse map's fixed-point iteration runs until no point moves by more than
# this (px). It contracts by about the largest displacement gradient: under the
# demo's probe at 14.8 mm (15% compression) by about 0.6 per iteration, so a
# fixed count of 10 iterations left up to 0.1-0.2 px there (the last step still
# moved points by 0.09 px); about 20 reach this tolerance.
INVERSE_TOL_PX = 1e-3
INVERSE_MAX_ITERATIONS = 60


def _fixed_point_inverse(sample, q_rows, q_cols, iterations=INVERSE_MAX_ITERATIONS, tol_px=INVERSE_TOL_PX):
    """e(q) with q - e(q) = p and q = p + delta(p): iterate e = delta(q - e) at each
    point until it moves by less than ``tol_px`` (at most ``iterations`` times).
    Points far from the probe converge in a few iterations and stop there; only
    the strongly compressed band beside the probe needs about 20 (on the demo's
    deep frame 30,500 samples instead of 77,000 when every point iterated until
    the slowest had converged)."""
    qr, qc = q_rows.ravel(), q_cols.ravel()
    e_c = np.zeros_like(qr)
    e_r = np.zeros_like(qr)
    active = np.arange(len(qr))
    for _ in range(iterations):
        n_c, n_r = sample(qr[active] - e_r[active], qc[active] - e_c[active])
        change = np.maximum(np.abs(n_c - e_c[active]), np.abs(n_r - e_r[active]))
        e_c[active], e_r[active] = n_c, n_r
        active = active[change >= tol_px]
        if not len(active):
            break
    return np.stack([e_c.reshape(q_rows.shape), e_r.reshape(q_rows.shape)], axis=-1)


class FastWarp:
    """The fast warp of a source frame onto a target frame's ROI.

    The forward displacement delta is evaluated (exact TPS) on a coarse grid over
    the whole source image and carried to every source pixel by separable
    Catmull-Rom interpolation (two small matrix products); the inverse is found by
    fixed-point iteration on a coarse grid over the target ROI, sampling that
    field bilinearly, then upsampled to every ROI pixel with separable cubic
    interpolation, and ``polish`` fixed-point iterations at every pixel correct
    the upsampling. (Until 2026-11-25 delta was sampled from the coarse grid with
    cubic B-splines: as accurate against the exact TPS, three times slower.)

    Against the exact TPS inverse on every pixel of the demo's deep frame (the
    probe's edge in view, bench/core.py): without the polish the upsampled
    inverse was off by up to 0.06-0.11 px beside the probe's edge (depending on
    the mesh; p99 0.018 px); one polish iteration halves that (0.034-0.044 px).
    """

    def __init__(self, tps: TPS, image_shape: tuple[int, int], roi: WarpGrid, step: int = 3,
                 iterations: int = INVERSE_MAX_ITERATIONS, polish: int = 1):
        H, W = image_shape
        self.step, self.iterations, self.roi, self.polish = step, iterations, roi, polish
        self.src_rows = np.arange(0, H - 1 + step, step, dtype=float)
        self.src_cols = np.arange(0, W - 1 + step, step, dtype=float)
        self.M = tps.matrix(_grid_points(self.src_rows, self.src_cols))
        # the forward field is carried from the coarse grid to every source pixel by
        # separable Catmull-Rom (two small matrix products), then sampled bilinearly:
        # 4-5x cheaper per sample than cubic-spline sampling of the coarse grid
        self.Usr, self.Usc = cubic_matrix(H, self.src_rows), cubic_matrix(W, self.src_cols)
        rows, cols = roi.shape
        # one extra coarse sample beyond each end: the cubic then needs no ghost values
        rq = np.arange(-step, rows - 1 + 2 * step, step, dtype=float)
        cq = np.arange(-step, cols - 1 + 2 * step, step, dtype=float)
        self.Ur, self.Uc = cubic_matrix(rows, rq), cubic_matrix(cols, cq)
        self.q_rows, self.q_cols = np.meshgrid(rq + roi.row0, cq + roi.col0, indexing="ij")
        self._R, self._C = np.mgrid[roi.row0:roi.row1, roi.col0:roi.col1].astype(float)

    def forward_coarse(self, values_px: np.ndarray) -> np.ndarray:
        return (self.M @ values_px).reshape(len(self.src_rows), len(self.src_cols), 2)

    def inverse(self, values_px: np.ndarray | None = None, coarse: np.ndarray | None = None) -> np.ndarray:
        """Inverse displacement (rows, cols, 2) px on every ROI pixel, from control
        values (n, 2) px or from the forward field already on the coarse grid."""
        F = self.forward_coarse(values_px) if coarse is None else coarse
        D0 = self.Usr @ F[..., 0] @ self.Usc.T  # (H, W) forward field on every source pixel
        D1 = self.Usr @ F[..., 1] @ self.Usc.T

        def sample(r, c):
            return bilinear(D0, r, c), bilinear(D1, r, c)

        e = _fixed_point_inverse(sample, self.q_rows, self.q_cols, self.iterations)
        e = np.stack([self.Ur @ e[..., k] @ self.Uc.T for k in (0, 1)], axis=-1)
        for _ in range(self.polish):  # e = delta(q - e) at every pixel
            e = np.stack(sample(self._R - e[..., 1], self._C - e[..., 0]), axis=-1)
        return e

    def sample_positions(self, values_px=None, coarse=None) -> tuple[np.ndarray, np.ndarray]:
        e = self.inverse(values_px, coarse)
        return self._R - e[..., 1], self._C - e[..., 0]

    def __call__(self, source: np.ndarray, values_px=None, coarse=None) -> np.ndarray:
        r, c = self.sample_positions(values_px, coarse)
        return bilinear(np.asarray(source, float), r, c)


# the warps in use, by what they are made of: every frame pair of a model warps the same
# source image with the same control points, and so does every model of one
# experiment and ROI (a diagnosis holds seven or eight). Each FastWarp's matrices
# take 31 MB on the paper-size images. A model built one per pair, 0.94 GB with 30
# pairs; sharing them took that experiment's diagnosis from 19.0 to 10.6 GB at its peak.
_WARPS: "weakref.WeakValueDictionary[tuple, FastWarp]" = weakref.WeakValueDictionary()
_WARPS_LOCK = threading.Lock()


def shared_warp(tps: TPS, image_shape: tuple[int, int], roi: WarpGrid) -> FastWarp:
    """The :class:`FastWarp` of ``tps`` over ``image_shape`` onto ``roi``, one object
    for every caller with the same control points, image shape and ROI, for as long
    as one of them holds it (a FastWarp is not changed by warping)."""
    key = (hashlib.sha1(np.ascontiguousarray(tps.ctrl).tobytes()).hexdigest(), len(tps.ctrl),
           tuple(int(v) for v in image_shape), astuple(roi))
    with _WARPS_LOCK:
        warp = _WARPS.get(key)
        if warp is None:
            warp = FastWarp(tps, tuple(image_shape), roi)
            _WARPS[key] = warp
        return warp


def exact_inverse(evaluate, image_shape, roi: WarpGrid, iterations: int = INVERSE_MAX_ITERATIONS) -> np.ndarray:
    """Reference inverse displacement on the ROI: the fixed point e = delta(q - e)
    with ``evaluate(points (n, 2) as (col, row)) -> (n, 2)`` the exact TPS
    evaluated at the iterated sub-pixel points themselves (no grid, no upsampling)."""
    q_rows, q_cols = np.mgrid[roi.row0:roi.row1, roi.col0:roi.col1].astype(float)

    def sample(r, c):
        v = evaluate(np.column_stack([c.ravel(), r.ravel()]))
        return v[:, 0].reshape(r.shape), v[:, 1].reshape(r.shape)

    return _fixed_point_inverse(sample, q_rows, q_cols, iterations)
