"""The hereditary integral of the viscoelastic effect against the closed form of a ramp-hold."""

import numpy as np
import pytest

from app.core.effects.viscoelastic import exponential_filter, holds, prony_force, ramp_hold_closed_form


@pytest.mark.parametrize("uniform", [True, False])
def test_ramp_hold_force_matches_the_closed_form(uniform):
    rng = np.random.default_rng(3)
    if uniform:
        t = np.linspace(0.0, 12.0, 1201)
    else:
        t = np.sort(np.concatenate([[0.0, 5.0, 12.0], rng.uniform(0, 12, 700)]))
    v, tr, k, g1, tau = 1.0, 5.0, 0.4, 0.35, 1.7
    d = np.clip(v * t, 0, v * tr)
    F = prony_force(t, k * d, g1, tau)
    assert np.allclose(F, ramp_hold_closed_form(t, v, tr, k, g1, tau), atol=1e-9)
    # relaxes by g1 (1 - exp(-tr/tau)) ... towards the long-term force (1 - g1) k d
    assert F[-1] == pytest.approx((1 - g1) * k * v * tr, rel=0.02)


def test_filter_of_a_step_decays_exponentially():
    t = np.linspace(0, 5, 501)
    x = np.where(t > 0, 1.0, 0.0)
    h = exponential_filter(t, x, 2.0)
    # the jump happens in the first interval (linear ramp over it); afterwards pure decay
    assert np.allclose(h[10:] / h[10], np.exp(-(t[10:] - t[10]) / 2.0), rtol=1e-12)


def test_holds_are_found():
    t = np.arange(0, 20, 0.1)
    d = np.clip(t, 0, 5) - np.clip(t - 12, 0, None)
    hs = holds(t, d)
    assert len(hs) == 1
    i0, i1 = hs[0]
    assert t[i0] == pytest.approx(5.0, abs=0.11) and t[i1] == pytest.approx(12.0, abs=0.11)
