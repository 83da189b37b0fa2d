"""The local tone-mapping operator (base / detail on log luminance, Durand and Dorsey 2002, with a guided
filter) and the automatic white: analytic cases."""
import math

import numpy as np
import pytest

from nrhdr_core import tonemap

WHITE = 4094 * 6.35


def test_monotonic_on_a_ramp():
    h, w = 48, 400
    v = np.tile(np.geomspace(1.0, WHITE * 4, w, dtype=np.float32), (h, 1))
    out = tonemap.local_tonemap(v, WHITE, dtype=np.uint16).astype(np.int64)
    assert (np.diff(out, axis=1) >= 0).all()
    assert out[:, -1].min() > out[:, 0].max() + 30000         # the ramp's 17 stops span most of the range
    assert (out == out[0]).all()                               # rows agree: nothing depends on y


def _texture(h, w):
    yy, xx = np.mgrid[0:h, 0:w]
    return 2.0 ** (0.3 * np.sin(xx / 2.0) * np.sin(yy / 2.0))


def test_detail_preserved_in_shadows_and_highlights():
    """A 0.3-stop texture on two levels 10 stops apart: the log curve flattens it in the highlights (a few
    codes), the local operator shows it on both sides with a similar amplitude."""
    h, w = 96, 256
    tex = _texture(h, w)
    left = np.arange(w) < w // 2
    v = (np.where(left, 30.0, 30.0 * 2 ** 10) * tex).astype(np.float32)
    loc = tonemap.local_tonemap(v, WHITE).astype(float)
    log = tonemap.log_tonemap(v, WHITE).astype(float)
    inner = np.s_[20:-20]
    dark, bright = loc[inner, 20:w // 2 - 20].std(), loc[inner, w // 2 + 20:-20].std()
    assert bright > 10 * log[inner, w // 2 + 20:-20].std()
    assert dark > log[inner, 20:w // 2 - 20].std()
    assert min(dark, bright) > 4 and bright / dark < 5
    # and the levels stay ordered: base compressed, not inverted
    assert loc[:, w // 2 + 20:].mean() > loc[:, :w // 2 - 20].mean() + 100


def test_no_halo_beyond_a_bound_at_a_step_edge():
    """An 8-stop step: away from the edge both sides are flat; the filter's residual shows only within
    3 pixels of the edge, beyond that the picture is within 5 codes of each plateau."""
    h, w = 96, 256
    v = np.full((h, w), 30.0, np.float32)
    v[:, w // 2:] = 30.0 * 2 ** 8
    out = tonemap.local_tonemap(v, WHITE).astype(int)
    assert (out == out[h // 2]).all()
    row = out[h // 2]
    dark, bright = row[0], row[-1]
    assert bright > dark + 150
    assert np.abs(row[:w // 2 - 3] - dark).max() <= 5
    assert np.abs(row[w // 2 + 3:] - bright).max() <= 5


@pytest.mark.parametrize("value, level", [(0.0, "dark"), (1e-30, "dark"), (np.nan, "dark"), (-5.0, "dark"),
                                          (1e30, "mid"), (np.inf, "mid"), (WHITE, "mid")])
def test_flat_frames_at_extremes(value, level):
    """A flat frame has no detail: one code everywhere. Black (0, tiny, NaN, negative: below the toe) stays
    dark (<= a quarter of full scale); a flat lit frame, however bright, is shown at the mean level."""
    out = tonemap.local_tonemap(np.full((40, 60), value, np.float32), WHITE)
    assert out.min() == out.max()
    if level == "dark":
        assert out[0, 0] <= 255 * tonemap.LOCAL_TOE_LEVEL + 1
    else:
        assert abs(int(out[0, 0]) - 116) <= 2


def test_nan_inf_and_negative_pixels_in_a_scene():
    v = np.geomspace(1, 1e5, 64 * 64).reshape(64, 64).astype(np.float32)
    v[5:9, 5:9] = np.nan
    v[30, 30] = -5.0
    v[20, 20] = np.inf
    v[40, 40] = 1e30
    out = tonemap.local_tonemap(v, WHITE)
    clean = tonemap.local_tonemap(np.where(np.isfinite(v), v, 0).astype(np.float32), WHITE)
    assert out[20, 20] == 255 and out[40, 40] == 255          # +inf and 1e30 are brighter than anything
    assert out[6, 6] <= out[0:2, 0:2].max() + 2                # NaN like black (0)
    assert out[30, 30] <= out[0:2, 0:2].max() + 2
    assert out.dtype == np.uint8 and clean.dtype == np.uint8


def test_smoothed_statistics_do_not_flicker():
    """A sudden 2-stop brightening: a per-frame normaliser would show frame 3 exactly as frame 0; the
    smoothed statistics adapt over frames."""
    rng = np.random.default_rng(1)
    base = (np.geomspace(10, 5000, 64 * 96).reshape(64, 96) * _texture(64, 96)).astype(np.float32)
    base *= rng.uniform(0.9, 1.1, base.shape).astype(np.float32)
    op = tonemap.LocalTonemap(speed=0.3)
    means = [float(op(f, WHITE).mean()) for f in [base] * 3 + [base * 4] * 4]
    assert means[0] == means[1] == means[2]
    assert means[3] > means[4] > means[5] > means[6] and means[3] > means[2] + 5
    fresh = tonemap.local_tonemap(base * 4, WHITE).mean()
    assert abs(means[3] - fresh) > 5
    op.reset()
    assert float(op(base, WHITE).mean()) == means[0]


def test_exposure_shifts_and_uint16_matches_uint8():
    v = (np.geomspace(10, 5000, 64 * 96).reshape(64, 96) * _texture(64, 96)).astype(np.float32)
    a8 = tonemap.local_tonemap(v, WHITE).astype(int)
    a16 = tonemap.local_tonemap(v, WHITE, dtype=np.uint16).astype(int)
    assert np.abs(a16 / 257.0 - a8).max() <= 1.0
    assert tonemap.local_tonemap(v, WHITE, exposure_stops=1.0).mean() > a8.mean() + 5


def test_bad_parameters():
    with pytest.raises(ValueError, match="white"):
        tonemap.local_tonemap(np.ones((4, 4)), 0.0)
    with pytest.raises(ValueError, match="contrast"):
        tonemap.local_tonemap(np.ones((4, 4)), 1.0, contrast=math.nan)
    with pytest.raises(ValueError, match="2-D"):
        tonemap.local_tonemap(np.ones(4), 1.0)
    with pytest.raises(ValueError, match="speed"):
        tonemap.LocalTonemap(speed=0.0)


def test_auto_white_shows_the_log_average_at_the_natural_mean():
    rng = np.random.default_rng(2)
    v = (2.0 ** rng.normal(8, 2, (64, 64))).astype(np.float32)
    w = tonemap.auto_white(v, stride=1)
    key = math.exp(np.mean(np.log(v.astype(np.float64))))
    y = math.log1p(1000 * key / w) / math.log1p(1000)
    assert y == pytest.approx(tonemap.AUTO_MEAN_LEVEL, rel=1e-6)
    assert tonemap.auto_white(v * 8, stride=1) == pytest.approx(8 * w, rel=1e-5)   # follows exposure
    assert tonemap.auto_white(np.zeros((8, 8))) is None


def test_auto_white_tracker_smooths_in_log():
    tr = tonemap.AutoWhite(speed=0.5)
    assert tr.update(np.zeros((8, 8))) == 1.0                   # nothing lit yet
    a = tr.update(np.full((8, 8), 100.0, np.float32))
    b = tr.update(np.full((8, 8), 400.0, np.float32))
    assert b == pytest.approx(2 * a, rel=1e-6)                  # halfway in stops: 1 of the 2 stops
    assert tr.update(np.zeros((8, 8))) == b                     # a black frame keeps the white


@pytest.mark.parametrize("shape", [(1, 1), (2, 3), (13, 1), (1, 17), (9, 130)])
def test_small_and_odd_frames(shape):
    """Frames smaller than a cell or not a multiple of it: every pixel written, 1-D ramps stay monotonic."""
    v = np.geomspace(1.0, 1e5, shape[0] * shape[1]).reshape(shape).astype(np.float32)
    out = tonemap.local_tonemap(v, WHITE, dtype=np.uint16)
    assert out.shape == shape
    if 1 in shape:
        assert (np.diff(out.ravel().astype(np.int64)) >= 0).all()
    if out.size > 1:
        assert out.ravel()[-1] > out.ravel()[0]
