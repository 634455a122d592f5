"""Normalized mutual information (Studholme): (H(A) + H(B)) / H(A, B), in [1, 2].

Binning follows numpy.histogramdd exactly (edges = linspace(min, max, bins + 1),
the maximum in the last bin), so values equal skimage's
normalized_mutual_information on the same bins; the joint histogram is one
bincount, and the fixed image's bins are computed once.
"""

from __future__ import annotations

import numpy as np


def bin_indices(x: np.ndarray, bins: int) -> np.ndarray:
    """Bin index of each value, identical to numpy.histogramdd's assignment."""
    x = np.asarray(x, float).ravel()
    lo, hi = float(x.min()), float(x.max())
    if lo == hi:
        lo, hi = lo - 0.5, hi + 0.5
    t = (x - lo) * (bins / (hi - lo))
    idx = t.astype(np.int64)  # t >= 0, so truncation is floor
    frac = t - idx
    np.minimum(idx, bins - 1, out=idx)
    # values within rounding of an edge: decide exactly as histogramdd does
    near = np.flatnonzero((frac < 1e-6) | (frac > 1 - 1e-6))
    if len(near):
        edges = np.linspace(lo, hi, bins + 1)
        idx[near] = np.clip(np.searchsorted(edges, x[near], side="right") - 1, 0, bins - 1)
    return idx


def _entropy(counts: np.ndarray) -> float:
    p = counts[counts > 0] / counts.sum()
    return float(-(p * np.log(p)).sum())


def nmi(a: np.ndarray, b: np.ndarray, bins: int = 100) -> float:
    """Studholme's NMI of two images of the same shape."""
    ia, ib = bin_indices(a, bins), bin_indices(b, bins)
    joint = np.bincount(ia * bins + ib, minlength=bins * bins).astype(float)
    return (_entropy(np.bincount(ia, minlength=bins).astype(float))
            + _entropy(np.bincount(ib, minlength=bins).astype(float))) / _entropy(joint)


class NMI:
    """NMI against a fixed image: ``NMI(fixed)(moving)``.

    The hot path of the identification: the fixed image's bins (premultiplied
    into joint-histogram rows) and its entropy are computed once; entropies use
    a table of n ln n, so H = ln N - sum(n ln n) / N needs no logarithm per call;
    the moving image's marginal is summed from the joint histogram; the exact
    histogramdd tie-break runs only when a value lies within 1e-6 bin of an edge.
    Equal to skimage's value to round-off (tests/core/test_similarity.py)."""

    def __init__(self, fixed: np.ndarray, bins: int = 100):
        self.bins = bins
        self.shape = fixed.shape
        self._if = bin_indices(fixed, bins)
        self.n = n = self._if.size
        self._rows = self._if * bins
        k = np.arange(n + 1, dtype=float)
        self._nlogn = k * np.log(np.maximum(k, 1.0))
        self._hf = self._entropy(np.bincount(self._if, minlength=bins))

    def _entropy(self, counts: np.ndarray) -> float:
        return float(np.log(self.n) - self._nlogn[counts].sum() / self.n)

    def __call__(self, moving: np.ndarray) -> float:
        bins = self.bins
        x = np.asarray(moving, float).ravel()
        if x.size != self.n:
            raise ValueError(f"moving image has {x.size} values, the fixed one {self.n}")
        lo, hi = float(x.min()), float(x.max())
        if lo == hi:
            lo, hi = lo - 0.5, hi + 0.5
        t = np.subtract(x, lo)
        t *= bins / (hi - lo)
        whole = np.floor(t)
        t -= whole  # fractional part
        idx = whole.astype(np.int64)
        near = np.less(t, 1e-6)
        near |= np.greater(t, 1 - 1e-6)  # also catches the maximum (t == bins)
        if near.any():
            k = np.flatnonzero(near)
            edges = np.linspace(lo, hi, bins + 1)
            idx[k] = np.clip(np.searchsorted(edges, x[k], side="right") - 1, 0, bins - 1)
        idx += self._rows
        joint = np.bincount(idx, minlength=bins * bins)
        hm = self._entropy(joint.reshape(bins, bins).sum(axis=0))
        return (self._hf + hm) / self._entropy(joint)


class SmoothNMI:
    """Studholme's NMI with the moving image binned by linear (partial-volume)
    weights over a fixed intensity range.

    Hard bins make the identification cost a staircase: a parameter change moves
    pixel values across bin edges one at a time, and a simplex stalls on the
    steps (local optima a few percent apart in the moduli ratio). Here each moving
    value splits its count between the two nearest bin centres in proportion to
    its distance, and the range is fixed (the source frame's, not the warped
    image's own min and max), so the value is continuous and piecewise smooth in
    the moving image. The fixed image keeps hard bins on its own range.
    It is not skimage's estimator (that is :class:`NMI`); both lie in [1, 2]."""

    def __init__(self, fixed: np.ndarray, bins: int, moving_range: tuple[float, float]):
        self.bins = bins
        f = bin_indices(fixed, bins)
        self.n = f.size
        # int32 (bins * bins is small): an estimator is kept per frame pair and per jackknife group
        self._rows = (f * bins).astype(np.int32)
        lo, hi = (float(v) for v in moving_range)
        if not hi > lo:
            lo, hi = lo - 0.5, hi + 0.5
        self.lo, self.scale = lo, (bins - 1) / (hi - lo)
        self._hf = _entropy(np.bincount(f, minlength=bins).astype(float))

    def __call__(self, moving: np.ndarray) -> float:
        bins = self.bins
        t = np.subtract(np.asarray(moving, float).ravel(), self.lo)
        t *= self.scale
        np.clip(t, 0.0, bins - 1 - 1e-9, out=t)
        k = t.astype(np.int64)
        w1 = t - k
        k += self._rows
        joint = np.bincount(k, weights=1.0 - w1, minlength=bins * bins)
        joint[1:] += np.bincount(k, weights=w1, minlength=bins * bins)[:-1]
        hm = _entropy(joint.reshape(bins, bins).sum(axis=0))
        return (self._hf + hm) / _entropy(joint)


def local_similarity(a: np.ndarray, b: np.ndarray, window: int = 15) -> np.ndarray:
    """Windowed normalized cross-correlation map in [-1, 1] (for residual maps)."""
    from scipy.ndimage import uniform_filter

    a = np.asarray(a, float)
    b = np.asarray(b, float)
    ma, mb = uniform_filter(a, window), uniform_filter(b, window)
    va = uniform_filter(a * a, window) - ma**2
    vb = uniform_filter(b * b, window) - mb**2
    cov = uniform_filter(a * b, window) - ma * mb
    return cov / np.sqrt(np.maximum(va * vb, 1e-12))
