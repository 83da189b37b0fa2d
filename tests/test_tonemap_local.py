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


def _box_reference(src, r):
    """`tonemap._box` one row at a time in Python floats (the same running sums, in the same order)."""
    h, w = src.shape
    tmp = np.empty((h, w))
    for y in range(h):
        s = 0.0
        for x in range(min(r, w - 1) + 1):
            s += src[y, x]
        for x in range(w):
            tmp[y, x] = s / (min(x + r, w - 1) - max(x - r, 0) + 1)
            if x + r + 1 < w:
                s += src[y, x + r + 1]
            if x - r >= 0:
                s -= src[y, x - r]
    dst = np.empty((h, w))
    acc = [0.0] * w
    for y in range(min(r, h - 1) + 1):
        for x in range(w):
            acc[x] += tmp[y, x]
    for y in range(h):
        inv = 1.0 / (min(y + r, h - 1) - max(y - r, 0) + 1)
        for x in range(w):
            dst[y, x] = acc[x] * inv
        for x in range(w):
            if y + r + 1 < h:
                acc[x] += tmp[y + r + 1, x]
            if y - r >= 0:
                acc[x] -= tmp[y - r, x]
    return dst


@pytest.mark.parametrize("shape", [(1, 1), (1, 9), (3, 1), (5, 7), (8, 6), (11, 13)])
@pytest.mark.parametrize("r", [1, 2, 5, 40])
def test_box_is_the_row_by_row_running_mean_bit_for_bit(shape, r):
    """`_box` (rows summed four at a time, divided in a pass of their own) gives the bits of the plain running
    sums row by row, for heights that are not a multiple of four and windows larger than the frame."""
    src = np.random.default_rng(r).standard_normal(shape) * 7.0
    dst = np.empty(shape)
    tonemap._box(src, r, np.empty(shape), np.empty(shape[1]), dst)
    assert np.array_equal(dst.view(np.int64), _box_reference(src, r).view(np.int64))


def test_mean_level_bounds_give_the_plain_bisection_with_fewer_sums(monkeypatch):
    """The offset s solved with `_level_bounds` standing in for `_mean_level` where they decide the comparison
    is the plain bisection's, bit for bit, with fewer full sums (also for flat and two-valued statistics)."""
    rng = np.random.default_rng(5)
    lut = tonemap._lut()
    calls = []
    plain = tonemap._mean_level
    monkeypatch.setattr(tonemap, "_mean_level", lambda *a: calls.append(1) or plain(*a))
    for n, spread in [(14400, 4.0), (300, 0.5), (2, 3.0), (50, 0.0), (1000, 40.0)]:
        rel = rng.normal(0.0, spread, n) if spread else np.full(n, -2.0)
        wgt = rng.uniform(0.0, 1.0, n)
        wgt /= wgt.sum()
        ref = tonemap._bisect(lambda s: plain(rel, wgt, s, lut), -60.0, 60.0, tonemap.LOCAL_MEAN, 1e-3)
        calls.clear()
        got = tonemap._bisect(tonemap._mean_level_for_bisect(rel, wgt, lut, tonemap.LOCAL_MEAN), -60.0, 60.0,
                              tonemap.LOCAL_MEAN, 1e-3)
        assert got == ref
        assert len(calls) < 19
