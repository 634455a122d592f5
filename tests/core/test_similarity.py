import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from skimage.metrics import normalized_mutual_information as sk_nmi

from app.core.similarity import NMI, bin_indices, local_similarity, nmi


@pytest.mark.parametrize("bins", [8, 32, 64, 100])
def test_nmi_equals_skimage(bins):
    rng = np.random.default_rng(bins)
    a = rng.random((96, 80))
    b = 0.7 * a + 0.3 * rng.random((96, 80))
    assert nmi(a, b, bins) == pytest.approx(sk_nmi(a, b, bins=bins), abs=1e-12)
    assert NMI(a, bins)(b) == pytest.approx(sk_nmi(a, b, bins=bins), abs=1e-12)


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 10**6), levels=st.integers(1, 300), bins=st.integers(2, 120))
def test_nmi_equals_skimage_on_quantized_images(seed, levels, bins):
    """Quantized values put many pixels exactly on bin edges: the binning must agree."""
    rng = np.random.default_rng(seed)
    a = np.round(rng.random((40, 30)) * levels) / levels
    b = np.round(rng.random((40, 30)) * levels) / max(levels, 1) * 3.7
    assert nmi(a, b, bins) == pytest.approx(sk_nmi(a, b, bins=bins), abs=1e-9)
    assert NMI(a, bins)(b) == pytest.approx(sk_nmi(a, b, bins=bins), abs=1e-9)
    assert NMI(b, bins)(a) == pytest.approx(sk_nmi(b, a, bins=bins), abs=1e-9)


def test_bin_indices_match_histogramdd_on_edges():
    x = np.linspace(0, 1, 101)  # every value on an edge
    idx = bin_indices(x, 100)
    h, _ = np.histogram(x, bins=100)
    assert np.array_equal(np.bincount(idx, minlength=100), h)


def test_nmi_range():
    rng = np.random.default_rng(0)
    a = rng.random((64, 64))
    assert nmi(a, a) == pytest.approx(2.0)
    assert nmi(a, rng.random((64, 64)), bins=16) < 1.05  # few bins: little small-sample bias
    assert nmi(a, np.ones_like(a)) == pytest.approx(1.0)


def test_local_similarity_finds_the_disagreeing_patch():
    rng = np.random.default_rng(0)
    a = rng.random((80, 80))
    b = a.copy()
    b[20:40, 50:70] = rng.random((20, 20))
    m = local_similarity(a, b, 9)
    assert m[30, 60] < 0.3 and m[60, 20] > 0.99


def test_smooth_nmi_has_no_bin_edge_steps():
    """The identification's estimator is continuous in the moving image: shifting
    the moving image changes it smoothly, where hard bins step (the steps a
    simplex stalls on); both peak at the aligned image."""
    from scipy.ndimage import gaussian_filter, shift

    from app.core.similarity import SmoothNMI

    rng = np.random.default_rng(3)
    src = gaussian_filter(rng.random((80, 90)), 1.5)
    fixed = src + 0.02 * rng.standard_normal(src.shape)  # the frame: same tissue, new speckle noise
    s = np.linspace(-0.6, 0.6, 121)
    smooth = SmoothNMI(fixed, 32, (src.min(), src.max()))
    hard = NMI(fixed, 32)
    vs = np.array([smooth(shift(src, (0.0, x), order=3)) for x in s])
    vh = np.array([hard(shift(src, (0.0, x), order=3)) for x in s])
    assert np.all((vs > 1) & (vs <= 2))
    assert abs(s[np.argmax(vs)]) < 0.02 and abs(s[np.argmax(vh)]) < 0.1
    # roughness: largest second difference relative to the curve's range
    rough_s = np.abs(np.diff(vs, 2)).max() / (vs.max() - vs.min())
    rough_h = np.abs(np.diff(vh, 2)).max() / (vh.max() - vh.min())
    assert rough_h > 2 * rough_s, (rough_s, rough_h)
    # no local optimum: strictly rising to the peak and falling after it
    i = int(np.argmax(vs))
    assert np.all(np.diff(vs[: i + 1]) > 0) and np.all(np.diff(vs[i:]) < 0)
