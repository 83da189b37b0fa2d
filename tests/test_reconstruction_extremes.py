"""Stability of `nrhdr_core.reconstruct(method="fse")` at the extremes: no or one known pixel, constants, 1e-6..1e6 in one frame, NaN/Inf rejection, determinism, odd sizes, 1 x N, tiny images."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

from nrhdr_core import reconstruct

PRESETS = ["preview", "fast"]


@pytest.mark.parametrize("preset", PRESETS)
def test_no_known_pixel_warns_and_is_defined(preset):
    img = np.full((20, 30), np.nan, np.float32)
    known = np.zeros(img.shape, bool)
    with pytest.warns(Warning):
        out = reconstruct(img, known, method="fse", preset=preset)
    assert out.shape == img.shape and out.dtype == np.float32 and np.isfinite(out).all()


def test_no_known_pixel_with_bounds_respects_them():
    img = np.zeros((8, 8), np.float32)
    known = np.zeros(img.shape, bool)
    lower = np.full(img.shape, 5.0, np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = reconstruct(img, known, method="fse", preset="fast", lower=lower)
    assert np.isfinite(out).all() and (out >= 5.0).all()


@pytest.mark.parametrize("preset", PRESETS)
@pytest.mark.parametrize("pos", [(0, 0), (17, 23), (39, 49)])
def test_one_known_pixel_gives_its_value_everywhere(preset, pos):
    img = np.zeros((40, 50), np.float32)
    known = np.zeros(img.shape, bool)
    known[pos] = True
    img[pos] = 42.5
    out = reconstruct(img, known, method="fse", preset=preset)
    assert np.isfinite(out).all()
    np.testing.assert_allclose(out, 42.5, rtol=1e-6)
    assert out[pos] == np.float32(42.5)


@pytest.mark.parametrize("preset", PRESETS + ["balanced"])
@pytest.mark.parametrize("value", [0.0, 1e-6, 3.0, 65535.0, 1e6])
def test_constant_image_exact(preset, value):
    img = np.full((33, 45), value, np.float32)
    known = np.random.default_rng(2).random(img.shape) < 0.3
    out = reconstruct(img, known, method="fse", preset=preset)
    assert np.array_equal(out, img)


@pytest.mark.parametrize("preset", PRESETS + ["balanced"])
def test_twelve_decades_in_one_frame(preset):
    """A smooth log ramp from 1e-6 to 1e6 (40 stops) with 50 % missing: finite, within the data's range
    (up to a small overshoot) and a small error in stops."""
    h, w = 48, 96
    _, xx = np.mgrid[0:h, 0:w]
    img = (10.0 ** (-6.0 + 12.0 * xx / (w - 1))).astype(np.float32)
    known = np.random.default_rng(4).random(img.shape) < 0.5
    out = reconstruct(img, known, method="fse", preset=preset)
    assert np.isfinite(out).all()
    miss = ~known
    assert (out[miss] > 0).all()
    err_stops = np.abs(np.log2(out[miss].astype(np.float64) / img[miss]))
    tol = 0.25 if preset == "preview" else 0.05   # preview: 6 iterations on 8 x 8 blocks
    assert np.median(err_stops) < tol, np.median(err_stops)
    assert err_stops.max() < 1.0, err_stops.max()


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nan_or_inf_rejected(bad):
    img = np.ones((10, 10), np.float32)
    img[3, 4] = bad
    known = np.ones(img.shape, bool)
    known[5, 5] = False
    with pytest.raises(ValueError, match="(?i)nan|inf|finite"):
        reconstruct(img, known, method="fse", preset="fast")


def test_bad_shapes_and_types_rejected():
    with pytest.raises(ValueError):
        reconstruct(np.ones((4, 4, 3)), np.ones((4, 4, 3), bool), method="fse")
    with pytest.raises(ValueError):
        reconstruct(np.ones((4, 4)), np.ones((4, 5), bool), method="fse")
    with pytest.raises(ValueError):
        reconstruct(np.ones((4, 4)), np.eye(4, dtype=bool), method="fse", preset="nope")


@pytest.mark.parametrize("shape", [(37, 53), (1, 61), (61, 1), (1, 1), (2, 3), (5, 7), (15, 17),
                                   (31, 9), (70, 33)])
@pytest.mark.parametrize("preset", PRESETS)
def test_odd_sizes(shape, preset):
    rng = np.random.default_rng(sum(shape))
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float32)
    img = 10 + 0.3 * xx + 0.2 * yy + rng.normal(0, 0.5, shape).astype(np.float32)
    known = rng.random(shape) < 0.5
    known.flat[0] = True
    out = reconstruct(img, known, method="fse", preset=preset)
    assert out.shape == shape and out.dtype == np.float32
    assert np.isfinite(out).all()
    assert np.array_equal(out[known], img[known])
    lo, hi = img[known].min(), img[known].max()
    span = max(hi - lo, 1.0)
    assert (out >= lo - span).all() and (out <= hi + span).all()


def test_deterministic_repeat_and_fully_known_is_identity():
    rng = np.random.default_rng(9)
    img = rng.random((50, 70)).astype(np.float32) * 1000
    known = rng.random(img.shape) < 0.5
    a = reconstruct(img, known, method="fse", preset="fast")
    b = reconstruct(img, known, method="fse", preset="fast")
    assert np.array_equal(a, b)
    full = np.ones(img.shape, bool)
    assert np.array_equal(reconstruct(img, full, method="fse"), img)
