"""The evidence sentences say which way the misfit moved."""

from app.core.effects import misfit_change
from app.core.effects.compressibility import evidence


def test_the_misfit_change_reads_the_right_way():
    assert misfit_change(0.89, 0.83) == "falls from 0.89 to 0.83 px"
    # a candidate that fits worse must not read "falls from 0.89 to 1.59"
    assert misfit_change(0.89, 1.59) == "rises from 0.89 to 1.59 px"
    assert misfit_change(0.891, 0.889) == "stays at 0.89 px"
    assert evidence(0.40, 0.49, 0.9, 1.2).endswith("the displacement misfit rises from 0.90 to 1.20 px")


def test_the_inclusion_explains_the_misfit_only_when_the_misfit_falls():
    from app.core.effects.inclusion import InclusionGuess
    from app.core.effects.inclusion import evidence as inclusion_evidence

    g = InclusionGuess("I", (26.0, 20.0, 14.0), 4.0, True, 0.0)
    fits = inclusion_evidence(g, 16.0, 3.2, 0.32, 0.05)
    assert "3.2 times stiffer it explains the misfit" in fits
    assert fits.endswith("on the same mesh the displacement misfit falls from 0.32 to 0.05 px")
    # seen on the demo: the candidate fitted worse, yet the sentence said it explained the misfit
    worse = inclusion_evidence(g, 14.0, 1.3, 0.89, 1.59)
    assert "does not explain the misfit" in worse and "it explains" not in worse
    assert worse.endswith("rises from 0.89 to 1.59 px")
    assert "does not explain" in inclusion_evidence(g, 14.0, 1.3, 0.891, 0.889)  # unchanged to the digit shown
    # seen on a phantom without an inclusion: 0.46 -> 0.45 px is little
    assert "0.7 times as stiff it explains little of the misfit" in inclusion_evidence(g, 4.0, 0.7, 0.463, 0.453)
    # seen at paper size with nothing hidden (boxed-none): the sphere's modulus at the fit's bound
    rigid = inclusion_evidence(g, 39.0, 404.7, 0.27, 0.26, e_kPa=10000.0)
    assert "as an inclusion 404.7 times stiffer (the fit's upper bound, 10,000 kPa: read it as much stiffer) " \
           "it explains little" in rigid, rigid
    assert "0.006 times as stiff (the fit's lower bound, 0.1 kPa: read it as much softer)" in \
        inclusion_evidence(g, 9.0, 0.006, 0.3, 0.1, e_kPa=0.1)
    assert "bound" not in inclusion_evidence(g, 16.0, 3.2, 0.32, 0.05, e_kPa=48.0)


def test_the_hyperelastic_evidence_says_what_large_deformation_would_change():
    import numpy as np

    from app.core.effects.hyperelastic import evidence as hyper_evidence

    d = np.linspace(0.0, 14.8, 200)
    linear = 0.6 * d
    # a neo-Hookean force ratio rising to 1.066 at the deepest travel (the demo's)
    neo = linear * (1 + 0.066 * (d / d[-1]) ** 2)
    s = hyper_evidence(d, linear, linear, neo)
    assert s.startswith("from the first to the second half of the indentation the measured force grows in "
                        "proportion to the travel (within 1%); the model's force grows in proportion"), s
    # slopes over 10-50% and 50-100% of the travel: (1 + 1.75 a) / (1 + 0.31 a) - 1 = 9% for a = 0.066
    assert s.endswith("with large deformation (neo-Hookean) it stiffens by 9%"), s
    assert "neo-Hookean" not in hyper_evidence(d, neo, linear)  # without a candidate: the two forces only


def test_the_poisson_ratio_sentence_says_which_way_the_volume_goes():
    from app.core.effects.compressibility import evidence

    assert "a Poisson's ratio of 0.39 says, where the model keeps it at 0.49" in evidence(0.392, 0.49, 1.8, 1.1)
    assert "a Poisson's ratio of 0.486 says, where the model keeps it at 0.490" in evidence(0.486, 0.49, 0.5, 0.5)
    # above the model's: the tissue changes volume less, and 0.496 must not read 0.50
    above = evidence(0.496, 0.49, 1.3, 1.2)
    assert above.startswith("the tissue keeps its volume under the probe more strictly than the model's "
                            "Poisson's ratio of 0.490 allows (a fit gives 0.496)")
    assert "changes volume" not in above


def test_the_hold_sentence_reads_the_way_the_force_went():
    import numpy as np

    from app.core.effects.viscoelastic import evidence

    t = np.linspace(0.0, 20.0, 2001)
    d = np.clip(t, 0.0, 10.0)  # a 10 mm ramp at 1 mm/s, then a 10 s hold
    model = 0.5 * d
    # 30% relax in all (29.8% by the end of the hold); it once read 26%, from a window average
    # that sat 0.4 s into the fast early relaxation
    relaxing = model * np.where(t > 10.0, 1.0 - 0.3 * (1.0 - np.exp(-(t - 10.0) / 2.0)), 1.0)
    assert evidence(t, d, relaxing, model).startswith("the force relaxes by 30% during the 10 s hold; "
                                                      "the model keeps it constant")
    noisy = relaxing + np.random.default_rng(0).normal(0.0, 0.02, t.size)  # 0.4% of the 5 N peak
    assert evidence(t, d, noisy, model).startswith("the force relaxes by 30% during the 10 s hold")
    fast = model * np.where(t > 10.0, 1.0 - 0.3 * (1.0 - np.exp(-(t - 10.0) / 0.5)), 1.0)  # tau 0.5 s
    assert evidence(t, d, fast, model).startswith("the force relaxes by 30% during the 10 s hold")
    # a model that relaxes too, and a short log (a few samples in the hold)
    assert evidence(t, d, relaxing, relaxing).endswith("the model relaxes it by 30%")
    ts = np.linspace(0.0, 20.0, 41)
    ds = np.clip(ts, 0.0, 10.0)
    short = 0.5 * ds * np.where(ts > 10.0, 1.0 - 0.3 * (1.0 - np.exp(-(ts - 10.0) / 2.0)), 1.0)
    assert evidence(ts, ds, short, 0.5 * ds).startswith("the force relaxes by 30% during the 10 s hold")
    assert evidence(t, d, model * (1 + 0.001 * np.sin(t)), model).startswith(
        "the force holds steady (within 0.5%) during the 10 s hold")
    rising = model * np.where(t > 10.0, 1.0 + 0.05 * (t - 10.0) / 10.0, 1.0)
    assert evidence(t, d, rising, model).startswith("the force rises by 5% during the 10 s hold")


def test_the_boundary_sentences_say_which_way_the_misfit_moved():
    """On the demo, probe-slip read "brings the displacement misfit from 0.92 to
    0.92 px"; a fit that made it worse read "brings ... from 0.92 to 1.84 px"."""
    import numpy as np

    from app.core.effects.boundary import evidence as boundary_evidence

    lateral, depth = np.array([0.1, 0.2, 0.0, 0.1]), np.array([1.0, 2.0, 3.0, 4.0])
    assert boundary_evidence("probe-slip", lateral, depth, 0.1, 0.921, 0.918).endswith(
        "letting it slide, the displacement misfit stays at 0.92 px")
    assert boundary_evidence("sliding-bottom", lateral, depth, 0.1, 0.92, 1.84).endswith(
        "letting it slide, the displacement misfit rises from 0.92 to 1.84 px")
    assert boundary_evidence("probe-slip", lateral, depth, 0.1, 1.40, 0.61).endswith(
        "letting it slide, the displacement misfit falls from 1.40 to 0.61 px")
