"""Speckle tracking pieces against known shifts, and the noise estimate against known noise."""

import numpy as np
import pytest
from scipy.ndimage import fourier_shift, gaussian_filter

from app.core.compare import _block_match, robust_noise


def _speckle(shape, seed):
    rng = np.random.default_rng(seed)
    return gaussian_filter(rng.standard_normal(shape), (0.8, 1.5))


@pytest.mark.parametrize("shift", [(0.3, -0.7), (-1.25, 0.5), (2.0, 1.6)])
def test_block_match_recovers_a_known_translation(shift):
    """The content of the block moved by ``shift`` (row, col) in the search window."""
    big = _speckle((64, 64), 2)
    block = big[24:40, 24:40]
    moved = np.real(np.fft.ifftn(fourier_shift(np.fft.fftn(big), np.asarray(shift))))[20:44, 20:44]
    t, ncc = _block_match(block, moved)
    assert np.allclose(t, shift, atol=0.12), (t, shift)
    assert ncc > 0.8


def test_robust_noise_finds_the_noise_under_a_smooth_field_and_outliers():
    rng = np.random.default_rng(0)
    R, C = np.mgrid[0:20, 0:20]
    grid = np.column_stack([R.ravel(), C.ravel()])
    smooth = 0.5 * np.sin(R / 6.0) + 0.02 * C  # a smooth misfit is not noise
    vals = (smooth.ravel()[:, None] + 0.3 * rng.standard_normal((400, 2)))
    vals[rng.choice(400, 12, replace=False)] += 8.0  # a few decorrelated blocks
    assert robust_noise(vals, grid) == pytest.approx(0.3, rel=0.15)
