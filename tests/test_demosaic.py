"""nrhdr_core.demosaic: joint reconstruction of the missing photosites and the missing colours of a Bayer
mosaic under the ND mask (docs/COLOUR.md "Joint reconstruction")."""
from __future__ import annotations

import types
import warnings

import numpy as np
import pytest

from nrhdr_core import cfa, demosaic, validity
from nrhdr_core.states import (ATTENUATED, CLIPPED, DARK, DISCARDED, NOISY, REASON_MASK, RECONSTRUCTED,
                               VALID)

from conftest import shared_data

METHODS = demosaic.METHODS


def _states(h, w, missing, seed=0, reason=DISCARDED):
    rng = np.random.default_rng(seed)
    return np.where(rng.random((h, w)) < missing, reason, VALID).astype(np.uint8)


def _random_mosaic(h, w, pattern, lo, hi, seed):
    """(truth (3, H, W), its mosaic) of uniform random colours in [lo, hi)."""
    rgb = np.random.default_rng(seed).uniform(lo, hi, (3, h, w)).astype(np.float32)
    return rgb, cfa.mosaic(rgb, pattern)


def _own(out, pattern):
    """Each photosite's own channel of a (3, H, W) image."""
    idx = cfa.channel_index(pattern, out.shape[1], out.shape[2])
    return np.take_along_axis(out, idx[None].astype(np.intp), 0)[0]


def _psnr(a, b, peak=255.0):
    return 10 * np.log10(peak ** 2 / np.mean((np.asarray(a, np.float64) - b) ** 2))


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("pattern", cfa.PATTERNS)
def test_constant_colour_reproduced_measured_kept(method, pattern):
    h, w = 24, 30
    rgb = np.empty((3, h, w), np.float32)
    rgb[0], rgb[1], rgb[2] = 300.0, 120.0, 45.0
    m = cfa.mosaic(rgb, pattern)
    st = _states(h, w, 0.4)
    st0 = st.copy()
    out = demosaic.reconstruct_cfa(m, st, pattern, method=method)
    assert out.shape == (3, h, w) and out.dtype == np.float32 and out.flags.c_contiguous
    np.testing.assert_allclose(out, rgb, rtol=1e-5)
    known = st0 == VALID
    np.testing.assert_array_equal(_own(out, pattern)[known], m[known])
    np.testing.assert_array_equal(st, np.where(known, st0, st0 | RECONSTRUCTED))


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("pattern", cfa.PATTERNS)
def test_smooth_colour_ramp(method, pattern):
    """Smooth HDR colour gradients (four stops across the frame: 4.4 % per pixel, hue turning) from 70 % of
    the photosites: mean error below 1 %, 99 % of the pixels within 6 % away from the frame's 2-pixel border
    (where one-sided data extrapolate), FSE within 3 % there."""
    h, w = 48, 64
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    lum = 100.0 * 2.0 ** (4.0 * x / w)
    rgb = np.stack([lum * (1.0 + 0.5 * y / h), lum, lum * (1.5 - 0.5 * x / w)]).astype(np.float32)
    m = cfa.mosaic(rgb, pattern)
    st = _states(h, w, 0.3, seed=1)
    out = demosaic.reconstruct_cfa(m, st, pattern, method=method)
    err = np.abs(out / rgb - 1.0)
    inner = err[:, 2:-2, 2:-2]
    assert err.mean() < 0.01 and np.percentile(inner, 99) < 0.06, (float(err.mean()), float(np.percentile(inner, 99)))
    if method == "fse":
        assert inner.max() < 0.03, float(inner.max())


@pytest.mark.parametrize("method", METHODS)
def test_out_argument_and_scale(method):
    h, w = 20, 26
    _, m = _random_mosaic(h, w, "grbg", 50, 500, 2)
    st = _states(h, w, 0.3, seed=3)
    buf = np.full((3, h, w), np.nan, np.float32)
    res = demosaic.reconstruct_cfa(m, st.copy(), "grbg", method=method, out=buf)
    assert res is buf and np.isfinite(buf).all()
    # k x values -> k x result (the log offset scales with the data)
    res2 = demosaic.reconstruct_cfa(m * np.float32(1024.0), st.copy(), "grbg", method=method)
    np.testing.assert_allclose(res2, buf * 1024.0, rtol=2e-3)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("pattern", ("rggb", "gbrg"))
def test_bounds_respected(method, pattern):
    """A bright patch (clipped photosites whose value is their lower bound, far below the truth) and dark
    ND photosites (value = upper bound, far above the truth): each own channel on the right side of its
    bound (`validity.bounds` with the CFA: the clipped-neighbour rule among one colour's photosites); with
    use_bounds off the clipped ones fall back to the reconstruction from their unclipped neighbours."""
    h, w = 40, 48
    rng = np.random.default_rng(4)
    rgb = rng.uniform(100, 200, (3, h, w)).astype(np.float32)
    rgb[:, 10:26, 12:30] *= 40.0
    truth = cfa.mosaic(rgb, pattern)
    att = rng.random((h, w)) < 0.5
    st = np.where(att, ATTENUATED, 0).astype(np.uint8)
    vals = truth.copy()
    clip = truth > 1000.0
    vals[clip] = np.where(att[clip], 4000.0, 1000.0)        # the clip levels of ND and regular photosites
    st[clip] |= CLIPPED
    dark = att & ~clip & (rng.random((h, w)) < 0.2)
    vals[dark] = 90.0                                       # threshold below the truth... an upper bound
    st[dark] |= DARK
    lo, hi = validity.bounds(vals, st, cfa=pattern)
    for use_bounds in (True, False):
        s = st.copy()
        out = demosaic.reconstruct_cfa(vals, s, pattern, method=method, use_bounds=use_bounds)
        own = _own(out, pattern)
        assert np.isfinite(out).all()
        if use_bounds:
            c = (st & REASON_MASK) == CLIPPED
            assert (own[c] >= lo[c]).all()
            d = (st & REASON_MASK) == DARK
            assert (own[d] <= hi[d]).all()
            # the per-colour neighbour rule raises some regular photosites above their own clip level
            assert (lo[c & ~att] > vals[c & ~att]).any()
            # inside the patch the estimates (from the dim surroundings) sit below the bounds: exactly them
            inner = np.zeros((h, w), bool)
            inner[13:23, 15:27] = True
            np.testing.assert_array_equal(own[c & inner], lo[c & inner])
        known = (st & REASON_MASK) == VALID
        np.testing.assert_array_equal(own[known], vals[known])
        assert ((s & RECONSTRUCTED) != 0).sum() == (~known).sum()


@pytest.mark.parametrize("pattern", cfa.PATTERNS)
@pytest.mark.parametrize("shape", [(23, 37), (24, 36), (5, 9)])
def test_clipped_rule_up_to_the_frame_edges(pattern, shape):
    """Clipped photosites (ND and regular at their own clip levels) over most of a frame of odd or even size,
    touching every edge, the known photosites dim: a missing green clipped photosite's estimate (a mean of
    known dim greens) lies below its bound, so its own channel is exactly its lower bound of
    `validity.bounds(..., cfa=)` (the clipped-neighbour rule among green photosites, edges included); red and
    blue ones at least theirs."""
    h, w = shape
    rng = np.random.default_rng(sum(shape) + len(pattern))
    att = rng.random((h, w)) < 0.5
    clip = rng.random((h, w)) < 0.8
    clip[h // 2, :] = False                                 # some known photosites in every column
    vals = np.where(clip, np.where(att, 4000.0, 1000.0), rng.uniform(50.0, 100.0, (h, w))).astype(np.float32)
    st = (np.where(att, ATTENUATED, 0) | np.where(clip, CLIPPED, VALID)).astype(np.uint8)
    lo, _ = validity.bounds(vals, st, cfa=pattern)
    out = demosaic.reconstruct_cfa(vals, st.copy(), pattern, method="preview")
    own = _own(out, pattern)
    idx = cfa.channel_index(pattern, h, w)
    c = (st & REASON_MASK) == CLIPPED
    g = c & (idx == cfa.G)
    np.testing.assert_array_equal(own[g], lo[g])
    assert (own[c] >= lo[c]).all()
    assert (lo[c & ~att] > vals[c & ~att]).any()            # the rule raises some regular photosites


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("pattern", ("rggb", "grbg"))
def test_clipped_disc_one_saturated_colour(method, pattern):
    """A lamp core (a disc where every photosite is clipped) in a coloured scene: every channel of every
    pixel inside it at least the smallest lower bound (`validity.bounds` with the CFA) of its adjacent
    photosites of that channel (regular and ND photosites at their own clip levels); with one clip level,
    one saturated colour: every channel at the clip level, no pixel-level checkerboard."""
    h, w = 40, 48
    rng = np.random.default_rng(11)
    y, x = np.mgrid[0:h, 0:w]
    rgb = np.stack([rng.uniform(140, 160, (h, w)), rng.uniform(90, 110, (h, w)),
                    rng.uniform(50, 70, (h, w))]).astype(np.float32)
    disc = (y - 20) ** 2 + (x - 24) ** 2 <= 10 ** 2
    inner = (y - 20) ** 2 + (x - 24) ** 2 <= 8 ** 2
    rgb[:, disc] *= 100.0
    truth = cfa.mosaic(rgb, pattern)
    idx = cfa.channel_index(pattern, h, w)
    for nd in (True, False):
        att = (rng.random((h, w)) < 0.5) & (nd | ~disc)
        st = np.where(att, ATTENUATED, 0).astype(np.uint8)
        vals = truth.copy()
        vals[disc] = np.where(att[disc], 4000.0, 1000.0)
        st[disc] |= CLIPPED
        lo, _ = validity.bounds(vals, st, cfa=pattern)
        out = demosaic.reconstruct_cfa(vals, st.copy(), pattern, method=method)
        for ch in range(3):
            # the smallest lower bound of the channel's photosites in each pixel's 3 x 3 (its adjacent ones)
            lc = np.pad(np.where(idx == ch, lo, np.inf), 1, constant_values=np.inf)
            near = np.min([lc[dy:dy + h, dx:dx + w] for dy in range(3) for dx in range(3)], axis=0)
            assert (out[ch][inner] >= near[inner]).all(), (nd, ch)
        if not nd:
            np.testing.assert_array_equal(out[:, inner], 1000.0)


@pytest.mark.parametrize("method", METHODS)
def test_noisy_fast_fusion_between_estimate_and_measurement(method):
    """The fast fusion of a NOISY photosite is e + w (m - e), 0 <= w <= 1: between the estimate without
    fusion and the measurement; with the accurate one the own channel stays finite and non-negative."""
    h, w = 32, 40
    rng = np.random.default_rng(5)
    rgb = np.full((3, h, w), 50.0, np.float32) * np.array([1.5, 1.0, 0.7], np.float32)[:, None, None]
    m = cfa.mosaic(rgb, "rggb") + rng.normal(0, 5, (h, w)).astype(np.float32)
    st = _states(h, w, 0.4, seed=6, reason=NOISY)
    # no read noise: the log offset is the same with and without the noise model (it is at least 2 noise sigmas)
    noise = types.SimpleNamespace(gain=0.5, read_noise=0.0, nd=8.0)
    est = _own(demosaic.reconstruct_cfa(m, st.copy(), "rggb", method=method), "rggb")
    fused = _own(demosaic.reconstruct_cfa(m, st.copy(), "rggb", method=method, noise=noise, fusion="fast"), "rggb")
    nz = st == NOISY
    lo = np.minimum(est, m) - 1e-3
    hi = np.maximum(est, m) + 1e-3
    assert ((fused[nz] >= lo[nz]) & (fused[nz] <= hi[nz])).all()
    assert not np.array_equal(fused[nz], est[nz])
    np.testing.assert_array_equal(fused[~nz], est[~nz])
    acc = demosaic.reconstruct_cfa(m, st.copy(), "rggb", method=method, noise=noise, fusion="accurate")
    assert np.isfinite(acc).all() and (_own(acc, "rggb")[nz] >= 0).all()


@pytest.mark.parametrize("method", METHODS)
def test_channel_without_known_photosite(method):
    """Every red photosite missing: red follows green (a grey hue) and stays finite; every red photosite
    clipped: their clip level stands in as data and red is at least that there."""
    h, w = 24, 28
    rgb = np.empty((3, h, w), np.float32)
    rgb[0], rgb[1], rgb[2] = 200.0, 100.0, 80.0
    m = cfa.mosaic(rgb, "rggb")
    red = cfa.channel_masks("rggb", h, w)[0]
    st = np.where(red, DISCARDED, VALID).astype(np.uint8)
    out = demosaic.reconstruct_cfa(m, st, "rggb", method=method)
    assert np.isfinite(out).all()
    np.testing.assert_allclose(out[0], out[1], rtol=1e-5)
    np.testing.assert_allclose(out[1:], rgb[1:], rtol=1e-5)
    assert ((st & RECONSTRUCTED) != 0).sum() == red.sum()
    st = np.where(red, CLIPPED, VALID).astype(np.uint8)
    m2 = np.where(red, np.float32(150.0), m)
    out = demosaic.reconstruct_cfa(m2, st, "rggb", method=method)
    assert np.isfinite(out).all() and (out[0][red] >= 150.0).all()
    assert ((st & RECONSTRUCTED) != 0).sum() == red.sum()


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("pattern", cfa.PATTERNS)
@pytest.mark.parametrize("shape", [(2, 2), (1, 7), (7, 1), (3, 5), (2, 3)])
def test_tiny_frames(method, pattern, shape):
    h, w = shape
    rng = np.random.default_rng(7)
    m = rng.uniform(1, 100, (h, w)).astype(np.float32)
    st = np.full((h, w), VALID, np.uint8)
    st.flat[0] = DISCARDED
    out = demosaic.reconstruct_cfa(m, st, pattern, method=method)
    assert out.shape == (3, h, w) and np.isfinite(out).all()
    own = _own(out, pattern)
    np.testing.assert_array_equal(own.flat[1:], m.flat[1:])
    assert st.flat[0] == DISCARDED | RECONSTRUCTED


@pytest.mark.parametrize("method", METHODS)
def test_everything_clipped(method):
    h, w = 16, 20
    m = np.where(np.random.default_rng(8).random((h, w)) < 0.5, 4000.0, 1000.0).astype(np.float32)
    st = np.full((h, w), CLIPPED, np.uint8)
    with pytest.warns(demosaic.DemosaicWarning, match="no photosite is known"):
        out = demosaic.reconstruct_cfa(m, st, "bggr", method=method)
    assert np.isfinite(out).all()
    assert (_own(out, "bggr") >= m).all()
    assert (st == CLIPPED | RECONSTRUCTED).all()


@pytest.mark.parametrize("method", METHODS)
def test_zeros_and_nothing_known(method):
    h, w = 12, 14
    z = np.zeros((h, w), np.float32)
    out = demosaic.reconstruct_cfa(z, _states(h, w, 0.5), "rggb", method=method)
    np.testing.assert_array_equal(out, 0.0)
    with pytest.warns(demosaic.DemosaicWarning):
        out = demosaic.reconstruct_cfa(z, np.full((h, w), DISCARDED, np.uint8), "rggb", method=method)
    np.testing.assert_array_equal(out, 0.0)


@pytest.mark.parametrize("method", METHODS)
def test_non_finite_values(method):
    h, w = 16, 16
    m = np.full((h, w), 100.0, np.float32)
    st = _states(h, w, 0.3, seed=9)
    miss = st != VALID
    bad = m.copy()
    bad[np.nonzero(miss)[0][:3], np.nonzero(miss)[1][:3]] = [np.nan, np.inf, -np.inf]
    s = st.copy()
    out = demosaic.reconstruct_cfa(bad, s, "rggb", method=method)
    np.testing.assert_allclose(out, 100.0, rtol=1e-5)
    np.testing.assert_array_equal(s, np.where(miss, st | RECONSTRUCTED, st))
    bad = m.copy()
    bad[~miss] = np.nan
    with pytest.raises(ValueError, match="NaN or Inf at known photosites"):
        demosaic.reconstruct_cfa(bad, st.copy(), "rggb", method=method)


def test_bad_arguments_named():
    m = np.ones((4, 4), np.float32)
    st = np.zeros((4, 4), np.uint8)
    for kw, msg in ((dict(cfa="none"), "monochrome"), (dict(cfa="rgbg"), "cfa"),
                    (dict(method="linear"), "method"), (dict(method="fse", preset="huge"), "preset"),
                    (dict(fusion="slow"), "fusion"), (dict(out=np.zeros((3, 4, 5), np.float32)), "out"),
                    (dict(out=np.zeros((3, 4, 4), np.float64)), "out")):
        args = dict(cfa="rggb")
        args.update(kw)
        with pytest.raises(ValueError, match=msg):
            demosaic.reconstruct_cfa(m, st, **args)
    with pytest.raises(ValueError, match="state"):
        demosaic.reconstruct_cfa(m, st.astype(np.int32), "rggb")
    with pytest.raises(ValueError, match="state"):
        demosaic.reconstruct_cfa(m, st[:, :3], "rggb")
    with pytest.raises(ValueError, match="2-D"):
        demosaic.reconstruct_cfa(np.ones(4, np.float32), st, "rggb")


def test_warmup():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        demosaic.warmup()


def _bilinear(mosaic, known, pattern):
    """Plain bilinear demosaic per channel, written for the test: each channel the normalised convolution
    of its known photosites with the tent [1 2 1] x [1 2 1] (the 5 x 5 tent where that holds none)."""
    from scipy.ndimage import convolve
    h, w = mosaic.shape
    masks = cfa.channel_masks(pattern, h, w)
    out = np.empty((3, h, w), np.float64)
    for c in range(3):
        k = masks[c] & known
        v = np.where(k, mosaic, 0.0)
        est = None
        for t in ([1, 2, 1], [1, 2, 3, 2, 1], [1, 2, 3, 4, 5, 4, 3, 2, 1]):
            ker = np.outer(t, t).astype(np.float64)
            num = convolve(v, ker, mode="mirror")
            den = convolve(k.astype(np.float64), ker, mode="mirror")
            e = np.where(den > 0, num / np.maximum(den, 1e-12), np.nan)
            est = e if est is None else np.where(np.isnan(est), e, est)
        est = np.where(np.isnan(est), v.sum() / max(k.sum(), 1), est)
        out[c] = np.where(k, mosaic, est)
    return out


@pytest.mark.parametrize("missing", [0.0, 0.35])
def test_kodak_fse_beats_preview_beats_bilinear(missing):
    """kodim03, the full Bayer mosaic and one with 35 % of the photosites missing: PSNR of FSE > preview >
    the plain bilinear per-channel demosaic."""
    from nrhdr_core import io
    rgb = io.read_image(shared_data("kodak", "kodim03.png"), np.uint8)[:, :, :3]
    rgb = np.ascontiguousarray(np.moveaxis(rgb, 2, 0), np.float32)
    h, w = rgb.shape[1:]
    m = cfa.mosaic(rgb, "rggb")
    st = _states(h, w, missing, seed=10)
    bil = _psnr(_bilinear(m, st == VALID, "rggb"), rgb)
    pre = _psnr(demosaic.reconstruct_cfa(m, st.copy(), "rggb", method="preview"), rgb)
    acc = _psnr(demosaic.reconstruct_cfa(m, st.copy(), "rggb", method="fse", preset="fast"), rgb)
    assert acc > pre + 0.3 and pre > bil + 0.5, (bil, pre, acc)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("shape", [(70, 90), (301, 90)])
def test_same_result_for_any_thread_count_and_input_untouched(method, shape):
    """Same bits for 1 and all threads (the chunks of the row passes dealt to the threads in turn; 301 rows:
    chunks of several rows, whose inner rows `_colour` lifts one row behind, and clipped regions across
    chunk edges, ND and regular)."""
    from numba import get_num_threads, set_num_threads
    h, w = shape
    _, m = _random_mosaic(h, w, "gbrg", 10, 4000, 11)
    st = _states(h, w, 0.4, seed=12, reason=NOISY)
    st[5:20, 10:40] = CLIPPED
    st[100:230:7, :] = CLIPPED | ATTENUATED
    st[120:260, 50:80] = CLIPPED | np.where(np.arange(30) % 3 == 0, ATTENUATED, 0).astype(np.uint8)
    m0 = m.copy()
    old = get_num_threads()
    try:
        set_num_threads(1)
        s1 = st.copy()
        a = demosaic.reconstruct_cfa(m, s1, "gbrg", method=method, noise=validity.default_noise())
        set_num_threads(old)
        s2 = st.copy()
        b = demosaic.reconstruct_cfa(m, s2, "gbrg", method=method, noise=validity.default_noise())
    finally:
        set_num_threads(old)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(s1, s2)
    np.testing.assert_array_equal(m, m0)
