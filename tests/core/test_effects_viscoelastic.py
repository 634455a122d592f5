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


def test_on_one_ramp_at_one_speed_relaxation_is_a_softening_with_travel():
    """On a log that is one loading ramp at one speed the Prony force is a
    function of the travel alone (the closed form below), so on top of the
    large-deformation model, whose force-travel curve has its own error, a
    fitted relaxation is no finding there; a hold, an unloading or a second
    speed tells them apart."""
    from app.core.effects.viscoelastic import negligible, one_speed_ramp

    t = np.linspace(0.0, 14.8, 1481)
    ramp = t.copy()  # 1 mm/s to 14.8 mm, as the paper-size phantoms
    rng = np.random.default_rng(0)
    assert one_speed_ramp(t, ramp)
    assert one_speed_ramp(t, ramp + rng.normal(0.0, 0.002, t.size))  # an encoder's jitter
    # the force is a function of travel alone at one speed: F(d) = k v (d/v - g1 tau (1 - exp(-d/(v tau))))
    k, g1, tau = 0.7, 0.3, 2.0
    force = prony_force(t, k * ramp, g1, tau)
    closed = k * (ramp - g1 * tau * (ramp - tau * (1 - np.exp(-ramp / tau))) / tau)
    assert force == pytest.approx(closed, abs=2e-3 * force.max())
    hold_t = np.linspace(0.0, 20.8, 2081)
    assert not one_speed_ramp(hold_t, np.minimum(hold_t, 14.8))  # a 6 s hold
    unload = np.concatenate([ramp, 14.8 - ramp[1:]])
    assert not one_speed_ramp(np.linspace(0.0, 29.6, unload.size), unload)
    assert not one_speed_ramp(t, np.where(t < 7.4, t, 7.4 + 0.5 * (t - 7.4)))  # a second speed
    assert not one_speed_ramp(t, np.zeros_like(t))
    why = negligible(t, ramp, ("hyperelastic",))
    assert why.startswith("on a log that is one loading ramp at one speed") and "record a hold" in why
    assert negligible(t, ramp, ()) == ""  # the linear model's force is proportional to the travel: a relaxation shows
    assert negligible(hold_t, np.minimum(hold_t, 14.8), ("hyperelastic",)) == ""
    # the diagnosis asks it of the viscoelastic candidate, on the current model's log and effects
    import types

    from app.core.diagnose import Candidate, _negligible

    cand = Candidate("viscoelastic", ("hyperelastic", "viscoelastic"), {"g1": 0.048, "tau1_s": 16.6}, {}, {})
    current = types.SimpleNamespace(log_t=t, log_d=ramp, effects=("hyperelastic",))
    assert _negligible("viscoelastic", current, cand) == why
    assert _negligible("viscoelastic", types.SimpleNamespace(log_t=t, log_d=ramp, effects=()), cand) == ""
