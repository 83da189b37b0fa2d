"""The reconstruction dispatcher and its non-FSE methods on analytic cases."""
import numpy as np
import pytest

from nrhdr_core import reconstruct
from nrhdr_core.reconstruction import FUSIONS, METHODS, ReconstructionWarning


@pytest.fixture
def ramp_case(rng):
    yy, xx = np.mgrid[0:40, 0:50].astype(np.float32)
    img = 3.0 * xx - 2.0 * yy + 100.0
    known = rng.random(img.shape) < 0.4
    known[[0, 0, -1, -1], [0, -1, 0, -1]] = True  # corners: the hull covers the image
    return img, known


def test_linear_is_exact_on_planes(ramp_case):
    img, known = ramp_case
    out = reconstruct(img, known, method="linear")
    assert np.abs(out - img).max() < 1e-3


@pytest.mark.parametrize("method", ["linear", "nearest", "preview"])
def test_known_pixels_bit_exact_and_constant_exact(method, ramp_case, rng):
    img, known = ramp_case
    noisy = img + rng.normal(0, 1, img.shape).astype(np.float32)
    out = reconstruct(noisy, known, method=method)
    assert out.dtype == np.float32 and np.array_equal(out[known], noisy[known])
    const = np.full(img.shape, 7.25, np.float32)
    assert np.array_equal(reconstruct(const, known, method=method), const)


def test_nearest_takes_nearest_known_value():
    img = np.zeros((5, 5), np.float32)
    known = np.zeros((5, 5), bool)
    known[0, 0], known[4, 4] = True, True
    img[0, 0], img[4, 4] = 1.0, 2.0
    out = reconstruct(img, known, method="nearest")
    assert out[1, 1] == 1.0 and out[3, 3] == 2.0 and out[0, 1] == 1.0


def test_preview_is_a_convex_combination(rng):
    img = rng.random((33, 47)).astype(np.float32) * 100
    known = rng.random(img.shape) < 0.3
    out = reconstruct(img, known, method="preview")
    assert out.min() >= img[known].min() - 1e-4 and out.max() <= img[known].max() + 1e-4


@pytest.mark.parametrize("method", ["linear", "nearest", "preview"])
def test_bounds_respected(method, rng):
    img = np.full((20, 20), 10.0, np.float32)
    known = rng.random(img.shape) < 0.5
    lower = np.where(~known, 50.0, np.nan).astype(np.float32)
    out = reconstruct(img, known, method=method, lower=lower)
    assert (out[~known] >= 50).all() and np.array_equal(out[known], img[known])
    upper = np.where(~known, 4.0, np.nan).astype(np.float32)
    out = reconstruct(img, known, method=method, upper=upper)
    assert (out[~known] <= 4).all()


def test_nothing_missing_is_identity_and_all_missing_warns():
    img = np.arange(12, dtype=np.float32).reshape(3, 4)
    assert np.array_equal(reconstruct(img, np.ones((3, 4), bool), method="linear"), img)
    with pytest.warns(ReconstructionWarning):
        out = reconstruct(img, np.zeros((3, 4), bool), method="preview")
    assert np.isfinite(out).all()


def test_input_errors():
    img = np.ones((4, 4), np.float32)
    k = np.ones((4, 4), bool)
    k[0, 0] = False
    with pytest.raises(ValueError, match="method"):
        reconstruct(img, k, method="magic")
    with pytest.raises(ValueError, match="shape"):
        reconstruct(img, np.ones((3, 4), bool), method="linear")
    bad = img.copy()
    bad[1, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        reconstruct(bad, k, method="nearest")
    with pytest.raises(ValueError, match="boolean"):
        reconstruct(img, k.astype(int), method="nearest")


def test_one_row_images():
    img = np.arange(10, dtype=np.float32)[None, :] * 2
    k = np.zeros((1, 10), bool)
    k[0, [0, 9]] = True
    assert np.allclose(reconstruct(img, k, method="linear"), img)


@pytest.mark.parametrize("pos", [(0, 0), (17, 23), (39, 49)])
def test_preview_of_one_known_pixel_is_its_value_everywhere(pos):
    img = np.zeros((40, 50), np.float32)
    known = np.zeros(img.shape, bool)
    known[pos] = True
    img[pos] = 42.5
    assert np.array_equal(reconstruct(img, known, method="preview"), np.full(img.shape, 42.5, np.float32))


def test_preview_on_a_checkerboard_is_the_mean_of_the_four_neighbours(ramp_case):
    """Known where y + x is even: every missing pixel has its four edge neighbours known and its corners
    missing, so it gets their mean; on a plane that is the plane's value (interior pixels)."""
    img, _ = ramp_case
    yy, xx = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    known = (yy + xx) % 2 == 0
    out = reconstruct(img, known, method="preview")
    np.testing.assert_allclose(out[1:-1, 1:-1], img[1:-1, 1:-1], rtol=0, atol=1e-4)
    pad = np.pad(img, 1)
    mean4 = (pad[:-2, 1:-1] + pad[2:, 1:-1] + pad[1:-1, :-2] + pad[1:-1, 2:]) / 4
    np.testing.assert_allclose(out[1:-1, 1:-1], mean4[1:-1, 1:-1], rtol=0, atol=1e-4)


def test_every_method_and_fusion_setting_is_accepted_and_others_rejected(ramp_case):
    img, known = ramp_case
    for method in METHODS:
        for fusion in FUSIONS:
            out = reconstruct(img, known, method=method, preset="fast", fusion=fusion)
            assert np.array_equal(out[known], img[known])
    with pytest.raises(ValueError, match="fusion"):
        reconstruct(img, known, method="preview", fusion="exact")
