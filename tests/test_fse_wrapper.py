"""FSE's passes around the block kernels against independent numpy/scipy expectations: the fallback for
blocks whose support held no usable pixel (`fill.nearest_fill`, `fallback.fill_left`: every left pixel takes
the value of a source pixel at the Euclidean-nearest distance, checked against scipy's exact distance
transform; both strategies, ring search and transform; the tie rule: tests/test_fill.py), `domain.finish_at`, and the statistics passes
`domain.stats` / `domain.finite_max`."""
import numpy as np
import pytest
from scipy import ndimage

from nrhdr_core import fill, fse
from nrhdr_core.fse import domain, fallback
from nrhdr_core.fse.params import KNOWN, MISSING, NOISY, RECONSTRUCTED, SKIP


def _check(work, left, src, got):
    s = ~left if src is None else src
    if not s.any():
        assert (got[left] == 0).all()
        return
    dist = ndimage.distance_transform_edt(~s)
    sy, sx = np.nonzero(s)
    for y, x in zip(*np.nonzero(left)):
        d2 = (sy - y) ** 2 + (sx - x) ** 2
        same = work[sy, sx] == got[y, x]            # the sources holding the value it took
        assert same.any() and d2[same].min() == round(dist[y, x] ** 2)
    assert np.array_equal(got[~left], work[~left])


@pytest.mark.parametrize("ring_max", [10**9, 0])   # ring search, distance transform
def test_nearest_fill_takes_a_nearest_source(ring_max, rng, monkeypatch):
    monkeypatch.setattr(fill, "NEAREST_RING_MAX", ring_max)
    for trial in range(60):
        h, w = rng.integers(1, 40, 2)
        work = rng.random((h, w)).astype(np.float32)
        left = rng.random((h, w)) < rng.random() * 0.5
        src = None if trial % 3 == 0 else (~left) & (rng.random((h, w)) < rng.random())
        got = work.copy()
        fill.nearest_fill(got, left, src)
        _check(work, left, src, got)


def test_nearest_fill_far_source():
    """One source in a corner of a 300 x 200 frame, a left pixel in the opposite corner."""
    work = np.zeros((200, 300), np.float32)
    work[0, 0] = 7.0
    src = np.zeros_like(work, bool)
    src[0, 0] = True
    left = np.zeros_like(src)
    left[199, 299] = True
    fill.nearest_fill(work, left, src)
    assert work[199, 299] == 7.0


@pytest.mark.parametrize("with_c,logd", [(True, True), (False, True), (False, False)])
def test_finish_at_equals_the_whole_frame_finish(with_c, logd, rng):
    """The fallback's pixels are finished alone (`finish_at`): the values `finish_c` / `finish` give them."""
    work = (rng.random((20, 30)) * 10).astype(np.float32)
    state = np.full((20, 30), KNOWN, np.uint8)
    ys, xs = np.nonzero(rng.random((20, 30)) < 0.2)
    state[ys, xs] = RECONSTRUCTED
    c = np.float32(3.5)
    ref = np.zeros((20, 30), np.float32)
    if with_c:
        domain.finish_c(ref, work, state, c)
    else:
        domain.finish(ref, work, state, logd)
    got = np.zeros_like(ref)
    domain.finish_at(got, work, ys, xs, c if with_c else np.float32(0.0), with_c, logd)
    assert np.array_equal(got, ref)


def test_fse_far_from_any_sample_gets_a_nearest_value(rng):
    """A 24 x 24 area whose every support window holds only skipped pixels: no block can fill it, so the
    fallback gives each of its pixels the value of a known pixel (the only sources: columns 0-7)."""
    h, w = 64, 64
    v = (2.0 ** (rng.random((h, w)) * 8)).astype(np.float32)
    k = np.zeros((h, w), bool)
    k[:, :8] = rng.random((h, 8)) < 0.6
    skip = ~k
    skip[20:44, 36:60] = False                 # missing, surrounded by skipped pixels only
    out = fse.fse_reconstruct(v.copy(), k, preset="fast", skip=skip)
    area = out[20:44, 36:60]
    assert np.isfinite(area).all()
    # (to float rounding: the value went through FSE's log2(x + c) working domain and back)
    known_vals = np.unique(v[k]).astype(np.float64)
    for a in np.unique(area).astype(np.float64):
        assert np.min(np.abs(known_vals - a)) <= 1e-5 * a


def test_fill_left_sources_by_state(rng, monkeypatch):
    """`fill_left` (the driver's fallback): sources are known, reconstructed and noisy pixels, never
    skipped ones; nearest by `fill`'s rule, both strategies; no source: 0."""
    for ring_max in (10**9, 0):
        monkeypatch.setattr(fill, "NEAREST_RING_MAX", ring_max)
        state = rng.choice(np.array([MISSING, KNOWN, RECONSTRUCTED, NOISY, SKIP], np.uint8), size=(30, 40),
                           p=[0.1, 0.3, 0.2, 0.1, 0.3])
        work = rng.random((30, 40)).astype(np.float32)
        got, st = work.copy(), state.copy()
        ys, xs = fallback.fill_left(got, st)
        assert np.array_equal(np.argwhere(state == MISSING), np.stack([ys, xs], 1))
        assert (st[ys, xs] == RECONSTRUCTED).all()
        _check(work, state == MISSING, np.isin(state, (KNOWN, RECONSTRUCTED, NOISY)), got)
    st = np.where(rng.random((8, 9)) < 0.5, MISSING, SKIP).astype(np.uint8)
    got = np.ones((8, 9), np.float32)
    fallback.fill_left(got, st)
    assert (got[st == RECONSTRUCTED] == 0).all() and (got[st == SKIP] == 1).all()


def test_stats_and_finite_max_equal_numpy(rng):
    """Known count, min, max, smallest positive (integer-key passes) against numpy, signed zeros, empty
    masks; the largest finite value with NaN and infinities around."""
    for _ in range(150):
        h, w = rng.integers(1, 50, 2)
        v = ((rng.random((h, w)) - 0.3) * 10 ** rng.uniform(-3, 5)).astype(np.float32)
        v[rng.random((h, w)) < 0.05] = 0.0
        v[rng.random((h, w)) < 0.02] = -0.0
        k = rng.random((h, w)) < rng.random()
        nk, kmin, kmax, minpos = domain.stats(v, k)
        kv = v[k].astype(np.float64)
        assert nk == kv.size
        if nk:
            pv = kv[kv > 0]
            assert (kmin, kmax, minpos) == (kv.min(), kv.max(), pv.min() if pv.size else 0.0)
        else:
            assert (kmin, kmax, minpos) == (np.inf, -np.inf, 0.0)
        b = v.copy()
        for val, share in ((np.nan, 0.3), (np.inf, 0.1), (-np.inf, 0.1)):
            b[rng.random((h, w)) < share] = val
        found, m = domain.finite_max(b)
        fb = b[np.isfinite(b)]
        assert found == (fb.size > 0) and m == (fb.max() if fb.size else -np.inf)


def test_noisy_level_is_the_mean_of_the_usable_neighbours(rng):
    """`reconstruction._noisy_level`: each skipped, unknown pixel gets the mean of its 3 x 3 neighbours that
    are known or not skipped (itself included when usable), else max(own value, 0); others untouched."""
    from scipy import ndimage
    from nrhdr_core import reconstruction as R
    for shape in [(1, 1), (2, 7), (33, 41)]:
        out = (rng.random(shape) * 100 - 10).astype(np.float32)
        known = rng.random(shape) < 0.4
        skip = ~known & (rng.random(shape) < 0.7)
        ok = (known | ~skip).astype(np.float64)
        box = lambda a: ndimage.uniform_filter(a, 3, mode="constant") * 9  # noqa: E731
        n, t = box(ok), box(ok * out.astype(np.float64))
        with np.errstate(invalid="ignore", divide="ignore"):
            lv = np.where(n > 0.5, (t / n).astype(np.float32), np.maximum(out, 0))
        want = np.where(skip & ~known, lv, out)
        got = out.copy()
        R._noisy_level(got, known, skip)
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-5)
