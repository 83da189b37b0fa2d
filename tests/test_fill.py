"""The nearest fill (`nrhdr_core.fill`) against an independent brute force: every target takes the value of
the source at the smallest Euclidean distance, ties to the smallest column, then the smallest row. Every
strategy (ring search, ring search with the transform for what it leaves, the transform alone on a crop
that must grow) gives exactly that source, for random masks sparse and dense, bool masks and FSE states."""
import numpy as np
import pytest

from nrhdr_core import fill
from nrhdr_core.fse import fallback
from nrhdr_core.fse.params import KNOWN, MISSING, NOISY, RECONSTRUCTED, SKIP

STRATEGIES = {                      # (NEAREST_RING_MAX, RING_RADIUS_MAX)
    "ring": (10**9, 10**9),
    "ring+transform": (10**9, 2),   # targets without a source within 2 px take the transform
    "transform": (0, 64),
}


def brute_nearest(vals, left, src):
    """vals with each `left` pixel replaced by the value of its nearest `src` pixel (d^2, then column,
    then row); no source: 0."""
    out = vals.copy()
    sy, sx = np.nonzero(src)
    for y, x in zip(*np.nonzero(left)):
        if sy.size == 0:
            out[y, x] = 0.0
            continue
        d2 = (sy - y) ** 2 + (sx - x) ** 2
        i = np.lexsort((sy, sx, d2))[0]
        out[y, x] = vals[sy[i], sx[i]]
    return out


def _masks(rng, h, w, density, hole):
    src = rng.random((h, w)) < density
    if hole:        # a round hole without sources: far targets, a crop that must grow
        yy, xx = np.mgrid[0:h, 0:w]
        src &= (yy - h / 3) ** 2 + (xx - w / 2) ** 2 > (min(h, w) / 3) ** 2
    return src


def _ids(h, w):
    """Each pixel's value is its own index: the value taken names the source."""
    return np.arange(h * w, dtype=np.float32).reshape(h, w)


@pytest.mark.parametrize("strategy", list(STRATEGIES))
@pytest.mark.parametrize("density", [0.01, 0.3, 0.95])
def test_nearest_fill_takes_the_brute_force_source(strategy, density, rng, monkeypatch):
    ring_max, radius = STRATEGIES[strategy]
    monkeypatch.setattr(fill, "NEAREST_RING_MAX", ring_max)
    monkeypatch.setattr(fill, "RING_RADIUS_MAX", radius)
    for trial in range(24):
        h, w = (int(n) for n in rng.integers(1, 70, 2))
        src = _masks(rng, h, w, density, trial % 3 == 0)
        left = ~src if trial % 2 else ~src & (rng.random((h, w)) < 0.5)
        vals = _ids(h, w)
        got = vals.copy()
        fill.nearest_fill(got, left, None if trial % 2 else src)
        np.testing.assert_array_equal(got, brute_nearest(vals, left, src))


@pytest.mark.parametrize("strategy", list(STRATEGIES))
def test_nearest_of_known_pixels_and_out(strategy, rng, monkeypatch):
    """`fill.nearest` (reconstruct's form): every pixel not known, into a new array or in place."""
    ring_max, radius = STRATEGIES[strategy]
    monkeypatch.setattr(fill, "NEAREST_RING_MAX", ring_max)
    monkeypatch.setattr(fill, "RING_RADIUS_MAX", radius)
    for trial in range(12):
        h, w = (int(n) for n in rng.integers(2, 90, 2))
        known = _masks(rng, h, w, [0.02, 0.5, 0.97][trial % 3], trial % 2 == 0)
        known[0, 0] = True
        vals = _ids(h, w)
        ref = brute_nearest(vals, ~known, known)
        np.testing.assert_array_equal(fill.nearest(vals, known), ref)
        inplace = vals.copy()
        assert fill.nearest(inplace, known, inplace) is inplace
        np.testing.assert_array_equal(inplace, ref)


@pytest.mark.parametrize("strategy", list(STRATEGIES))
def test_fse_fallback_takes_the_brute_force_source(strategy, rng, monkeypatch):
    """FSE's `fill_left`: sources known, reconstructed and noisy pixels, never skipped ones."""
    ring_max, radius = STRATEGIES[strategy]
    monkeypatch.setattr(fill, "NEAREST_RING_MAX", ring_max)
    monkeypatch.setattr(fill, "RING_RADIUS_MAX", radius)
    codes = np.array([MISSING, KNOWN, RECONSTRUCTED, NOISY, SKIP], np.uint8)
    for trial in range(12):
        h, w = (int(n) for n in rng.integers(1, 60, 2))
        p = rng.dirichlet(np.ones(5))
        state = rng.choice(codes, size=(h, w), p=p)
        vals = _ids(h, w)
        got, st = vals.copy(), state.copy()
        ys, xs = fallback.fill_left(got, st)
        left = state == MISSING
        np.testing.assert_array_equal(np.stack([ys, xs], 1), np.argwhere(left))
        np.testing.assert_array_equal(got, brute_nearest(vals, left, np.isin(state, codes[1:4])))


def test_a_far_single_source_grows_the_crop_to_the_frame():
    """One source in a corner of a 300 x 500 frame, a few targets in the far corner (ring search capped,
    then crops of growing margin) and a whole frame of targets (the transform alone)."""
    h, w = 300, 500
    vals = np.zeros((h, w), np.float32)
    vals[0, 0] = 7.0
    src = np.zeros((h, w), bool)
    src[0, 0] = True
    left = np.zeros((h, w), bool)
    left[290:, 480:] = True
    got = vals.copy()
    fill.nearest_fill(got, left, src)
    assert (got[left] == 7.0).all() and np.array_equal(got[~left], vals[~left])
    got = vals.copy()
    fill.nearest_fill(got, ~src, src)
    assert (got == 7.0).all()


def test_no_source_gives_zero_and_coords_are_row_major(rng):
    got = np.ones((5, 6), np.float32)
    left = rng.random((5, 6)) < 0.5
    fill.nearest_fill(got, left, np.zeros((5, 6), bool))
    assert (got[left] == 0).all() and (got[~left] == 1).all()
    ys, xs = fill.coords(left.view(np.uint8), fill.TRUE_CODES)
    np.testing.assert_array_equal(np.stack([ys, xs], 1), np.argwhere(left))


def test_shapes_that_differ_are_refused():
    with pytest.raises(ValueError, match="nearest fill"):
        fill.nearest_fill(np.zeros((4, 5), np.float32), np.zeros((5, 4), bool))
