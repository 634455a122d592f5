"""The error measures behind materiality, on manufactured block residuals."""

import math

import numpy as np
import pytest

from app.core.diagnose import MATERIAL_FRACTION, explained, is_material, typical_excess


def _ratios(rng, n, sigma, error):
    """Squared block misfits over the noise's share (2 sigma^2): noise of ``sigma``
    per component plus a model error of length ``error`` in a random direction."""
    angle = rng.uniform(0, 2 * math.pi, n)
    s = rng.normal(0, sigma, (n, 2)) + error[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])
    return (s**2).sum(axis=1) / (2 * sigma**2)


def test_typical_excess_is_zero_under_noise_and_recovers_a_spread_error():
    rng = np.random.default_rng(1)
    sigma, n = 0.1, 4000
    floor = math.sqrt(2) * sigma  # the floor's RMS: both components
    assert typical_excess(_ratios(rng, n, sigma, np.zeros(n)), floor) < 0.1 * sigma
    for e in (0.05, 0.2, 1.0, 30.0):  # the same error at every block
        got = typical_excess(_ratios(rng, n, sigma, np.full(n, e)), floor)
        assert got == pytest.approx(e, rel=0.08), e
    assert typical_excess(np.zeros(0), floor) == 0.0


def test_a_few_bad_blocks_move_the_rms_and_not_the_typical_block():
    """An error at 5% of the blocks (like the blocks beside the probe's edges)
    dominates the RMS; at the typical block it stays within half the noise."""
    rng = np.random.default_rng(2)
    sigma, n = 0.1, 2000
    floor = math.sqrt(2) * sigma
    e = np.where(np.arange(n) < n // 20, 1.0, 0.0)
    r = _ratios(rng, n, sigma, e)
    rms = math.sqrt(max(np.mean(r) * floor**2 - floor**2, 0.0))
    assert rms > 0.2
    assert typical_excess(r, floor) < min(0.5 * sigma, rms / 5)


def test_a_candidate_is_material_by_any_one_measure():
    floor = {"force_floor_N": 0.02, "displacement_floor_px": 0.14}
    before = {**floor, "force_excess_N": 0.0, "displacement_excess_px": 0.62,
              "displacement_typical_excess_px": 0.33}
    # the hidden nu 0.47 case: the RMS falls 13%, the typical block 4x
    after = {**floor, "force_excess_N": 0.0, "displacement_excess_px": 0.534,
             "displacement_typical_excess_px": 0.09}
    e = explained(before, after)
    assert e["force"] is None  # nothing beyond the noise to explain there
    assert e["displacement"] < MATERIAL_FRACTION <= e["typical displacement"]
    assert is_material(before, after)
    # a candidate that only trims the worst blocks is not
    assert not is_material(before, {**after, "displacement_excess_px": 0.6, "displacement_typical_excess_px": 0.3})
    # a typical error below half its floor is nothing to explain
    small = {**before, "displacement_typical_excess_px": 0.06}
    assert explained(small, after)["typical displacement"] is None
