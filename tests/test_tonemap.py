"""Logarithmic tone mapping (paper section 5) and its flicker-free normalisers."""
import math

import numpy as np
import pytest

from nrhdr_core import tonemap


def test_matches_log_operator():
    white, q = 1000.0, 100.0
    vals = np.array([[0.0, 1.0, 10.0, 100.0, 1000.0, 5000.0]], np.float32)
    out = tonemap.log_tonemap(vals, white, contrast=q)
    expect = [round(255 * math.log1p(q * min(v / white, 1)) / math.log1p(q)) for v in vals[0]]
    assert out[0].tolist() == expect
    assert out.dtype == np.uint8


def test_exposure_is_a_factor_of_two_per_stop_and_uint16():
    vals = np.linspace(0, 500, 64, dtype=np.float32).reshape(8, 8)
    a = tonemap.log_tonemap(vals * 2, 1000.0, dtype=np.uint16)
    b = tonemap.log_tonemap(vals, 1000.0, exposure_stops=1.0, dtype=np.uint16)
    assert a.dtype == np.uint16 and np.array_equal(a, b)
    assert (np.diff(a.ravel().astype(int)) >= 0).all()  # monotone


def test_nan_and_negative_map_to_black():
    out = tonemap.log_tonemap(np.array([[np.nan, -5.0]], np.float32), 10.0)
    assert out.tolist() == [[0, 0]]


def test_fixed_normaliser_does_not_flicker():
    # a bright object entering the frame must not change the rest of the picture
    a = np.full((32, 32), 200.0, np.float32)
    b = a.copy()
    b[:4, :4] = 1e6
    ta, tb = tonemap.log_tonemap(a, 26000.0), tonemap.log_tonemap(b, 26000.0)
    assert np.array_equal(ta[8:, 8:], tb[8:, 8:])


def test_white_tracker_smooths():
    tr = tonemap.WhiteTracker(speed=0.25, percentile=50)
    assert tr.update(np.full((8, 8), 100.0)) == pytest.approx(100.0)
    w = tr.update(np.full((8, 8), 500.0))
    assert w == pytest.approx(0.25 * 500 + 0.75 * 100)
    with pytest.raises(ValueError):
        tonemap.WhiteTracker(speed=0)


def test_bad_parameters():
    with pytest.raises(ValueError, match="white"):
        tonemap.log_tonemap(np.ones((2, 2)), 0.0)
    with pytest.raises(ValueError, match="contrast"):
        tonemap.log_tonemap(np.ones((2, 2)), 1.0, contrast=-1)
