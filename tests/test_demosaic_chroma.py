"""nrhdr_core.demosaic: the colour-difference median and the green-guided colour differences of the joint
reconstruction (docs/COLOUR.md "Colour-difference median", "False colour"): less false colour, colour
detail beyond the red and blue lattices' Nyquist limit, measured photosites and bounds kept."""
from __future__ import annotations

import numpy as np
import pytest

from nrhdr_core import cfa, chroma_fse, demosaic, metrics, scene, validity
from nrhdr_core.states import ATTENUATED, CLIPPED, DARK, DISCARDED, NOISY, REASON_MASK, VALID

# (method, preset): the preview, the fse with its lattice colour differences, the fse with the green-guided ones
SETTINGS = [("preview", "fast"), ("fse", "fast")] + [("fse", p) for p in demosaic.GUIDED_PRESETS]


def _own(out, pattern):
    """Each photosite's own channel of a (3, H, W) image."""
    idx = cfa.channel_index(pattern, out.shape[1], out.shape[2])
    return np.take_along_axis(out, idx[None].astype(np.intp), 0)[0]


def _bilinear(values, known, pattern):
    """A plain per-channel demosaic: each channel the normalised 3 x 3 bilinear convolution of its known
    photosites (the textbook reference)."""
    k = np.array([[0.25, 0.5, 0.25], [0.5, 1.0, 0.5], [0.25, 0.5, 0.25]])
    idx = cfa.channel_index(pattern, *values.shape)
    out = np.empty((3,) + values.shape)
    for ch in range(3):
        m = (idx == ch) & known
        num = np.pad(np.where(m, values, 0.0), 1)
        den = np.pad(m.astype(float), 1)
        h, w = values.shape
        s = sum(k[dy, dx] * num[dy:dy + h, dx:dx + w] for dy in range(3) for dx in range(3))
        n = sum(k[dy, dx] * den[dy:dy + h, dx:dx + w] for dy in range(3) for dx in range(3))
        out[ch] = s / np.maximum(n, 1e-12)
    return out


@pytest.mark.parametrize("method,preset", SETTINGS)
def test_grey_zone_plate_little_false_colour(method, preset):
    """Achromatic rings up to 0.5 cycles/pixel, 30 % of the photosites missing at random: the chroma the
    reconstruction makes of them is at least 2 dB below that of a plain bilinear demosaic of the same
    photosites (the bilinear one gets every photosite: none missing)."""
    rgb, panels = scene.colour_zone_plate(96)
    truth = (1000.0 * rgb[:, :, :96]).astype(np.float32)
    rings = panels["mid"][:, :96]
    m = cfa.mosaic(truth, "rggb")
    st = np.where(np.random.default_rng(2).random(m.shape) < 0.3, DISCARDED, VALID).astype(np.uint8)
    out = demosaic.reconstruct_cfa(m, st, "rggb", method=method, preset=preset)
    ref = _bilinear(m, np.ones(m.shape, bool), "rggb")
    ours = metrics.false_colour_db(truth, out, rings)
    assert ours <= metrics.false_colour_db(truth, ref, rings) - 2.0


@pytest.mark.parametrize("method,preset", SETTINGS)
@pytest.mark.parametrize("pattern", ("rggb", "gbrg"))
def test_colour_edge_kept(method, preset, pattern):
    """Two flat colours meeting at a vertical edge: a median keeps a step, so with every photosite measured
    each pixel two or more columns from the edge has its side's colour (within 0.2 %, the green-guided fse
    0.5 %: its colour-difference model rings slightly);
    with 30 % of them missing (the preview: its colour pass interpolates over the wider gaps) each pixel
    four or more columns from it."""
    h, w = 24, 32
    rgb = np.empty((3, h, w), np.float32)
    rgb[:, :, :16] = np.array([300.0, 150.0, 60.0], np.float32)[:, None, None]
    rgb[:, :, 16:] = np.array([80.0, 160.0, 320.0], np.float32)[:, None, None]
    m = cfa.mosaic(rgb, pattern)
    for missing, gap in ((0.0, 2), (0.3, 4)) if method == "preview" else ((0.0, 2),):
        st = np.where(np.random.default_rng(5).random((h, w)) < missing, DISCARDED, VALID).astype(np.uint8)
        out = demosaic.reconstruct_cfa(m, st, pattern, method=method, preset=preset)
        far = np.r_[0:16 - gap, 16 + gap:w]
        np.testing.assert_allclose(out[:, :, far], rgb[:, :, far],
                                   rtol=5e-3 if preset in demosaic.GUIDED_PRESETS else 2e-3)


@pytest.mark.parametrize("method,preset", SETTINGS)
@pytest.mark.parametrize("pattern", ("rggb", "bggr"))
def test_measured_kept_and_bounds(method, preset, pattern):
    """A random colour mosaic with VALID, NOISY, CLIPPED, DARK and DISCARDED photosites: every VALID one keeps
    its value bit for bit in its own channel, CLIPPED ones' own channel >= their value and DARK ones' <= it,
    and every channel stays within [min(its known values, 0), max(its known values, its clipped values)]."""
    h, w = 40, 44
    rng = np.random.default_rng(7)
    rgb = rng.uniform(20.0, 900.0, (3, h, w)).astype(np.float32)
    m = cfa.mosaic(rgb, pattern)
    reason = rng.choice(np.array([VALID, NOISY, CLIPPED, DARK, DISCARDED], np.uint8), (h, w),
                        p=[0.5, 0.2, 0.1, 0.1, 0.1])
    st = (reason | np.where(rng.random((h, w)) < 0.5, ATTENUATED, 0)).astype(np.uint8)
    st0 = st.copy()
    out = demosaic.reconstruct_cfa(m, st, pattern, method=method, preset=preset,
                                  noise=validity.default_noise())
    assert np.isfinite(out).all()
    idx = cfa.channel_index(pattern, h, w)
    own = _own(out, pattern)
    r = st0 & REASON_MASK
    np.testing.assert_array_equal(own[r == VALID], m[r == VALID])
    assert (own[r == CLIPPED] >= m[r == CLIPPED]).all()
    assert (own[r == DARK] <= m[r == DARK]).all()
    for ch in range(3):
        known = m[(idx == ch) & (r == VALID)]
        top = max(known.max(), m[(idx == ch) & (r == CLIPPED)].max())
        assert out[ch].min() >= min(known.min(), 0.0) and out[ch].max() <= top, ch


@pytest.mark.parametrize("method,preset", SETTINGS)
def test_saturated_region_one_colour_after_median(method, preset):
    """A saturated block (every photosite CLIPPED at one level) inside a coloured field: the median must not
    undo the clipped-neighbour rule; inside the block every channel is the clip level."""
    h, w = 32, 32
    rgb = np.stack([np.full((h, w), 300.0), np.full((h, w), 120.0), np.full((h, w), 40.0)]).astype(np.float32)
    m = cfa.mosaic(rgb, "rggb")
    st = np.zeros((h, w), np.uint8)
    m[10:22, 10:22] = 1000.0
    st[10:22, 10:22] = CLIPPED
    out = demosaic.reconstruct_cfa(m, st, "rggb", method=method, preset=preset)
    np.testing.assert_array_equal(out[:, 11:21, 11:21], 1000.0)


def test_guided_differences_take_green_frequency():
    """A colour difference at 0.35 cycles/photosite (beyond the 0.25 of its lattice, whose samples cannot tell
    it from its alias at 0.15) on 60 % of the lattice's photosites: with a green plane showing that frequency
    the reconstruction is the true difference (rms error below 20 % of the signal's), with a flat green plane
    it is not (the lattice alone: above 50 %); the known photosites keep their value."""
    h, w = 48, 64
    yy, xx = np.mgrid[0:h, 0:w]
    ph = 2 * np.pi * 0.35 * xx
    d = (0.3 * np.cos(ph)).astype(np.float32)
    known = (yy % 2 == 1) & (xx % 2 == 0) & (np.random.default_rng(3).random((h, w)) < 0.6)
    rms = float(np.sqrt(np.mean(d ** 2)))
    err = {}
    for name, g in (("follows", np.log2(200.0 + 100.0 * np.cos(ph))), ("flat", np.full((h, w), 7.0))):
        out = chroma_fse.guided_fse(d, known, g, 1, 0)
        np.testing.assert_array_equal(out[known], d[known])
        err[name] = float(np.sqrt(np.mean((out - d)[~known] ** 2)))
    assert err["follows"] < 0.2 * rms < 0.5 * rms < err["flat"], err


def test_guided_differences_step_without_ringing():
    """A step of the colour difference (2 stops) where green steps too, every lattice photosite known: four or
    more columns from the step each photosite is within 2 % of the step of its side's value (a band-limited
    interpolation of the lattice would ring by a tenth of the step there)."""
    h, w = 24, 32
    yy, xx = np.mgrid[0:h, 0:w]
    d = np.where(xx < 16, 1.0, -1.0).astype(np.float32)
    g = np.log2(np.where(xx < 16, 150.0, 160.0))
    out = chroma_fse.guided_fse(d, (yy % 2 == 0) & (xx % 2 == 0), g, 0, 0)
    far = np.r_[0:12, 20:w]
    assert np.abs(out - d)[:, far].max() < 0.04


def test_guided_differences_bad_lattice():
    with pytest.raises(ValueError, match="parities"):
        chroma_fse.guided_fse(np.zeros((8, 8)), np.ones((8, 8), bool), np.zeros((8, 8)), 2, 0)
    with pytest.raises(ValueError, match="off the lattice"):
        chroma_fse.guided_fse(np.zeros((8, 8)), np.ones((8, 8), bool), np.zeros((8, 8)), 0, 0)


def test_guided_differences_channels_in_one_pass():
    """Two channels on their own lattices in one call (one guide spectrum per area) give what each gives
    alone."""
    h, w = 40, 36
    rng = np.random.default_rng(5)
    yy, xx = np.mgrid[0:h, 0:w]
    g = np.log2(300.0 + 100.0 * np.cos(2 * np.pi * 0.3 * xx + 0.2 * yy))
    d = rng.standard_normal((2, h, w)).astype(np.float32)
    par = ((0, 0), (1, 1))
    known = np.stack([(yy % 2 == py) & (xx % 2 == px) & (rng.random((h, w)) < 0.7) for py, px in par])
    both = chroma_fse.guided_fse(d, known, g, [p[0] for p in par], [p[1] for p in par])
    for i, (py, px) in enumerate(par):
        np.testing.assert_array_equal(both[i], chroma_fse.guided_fse(d[i], known[i], g, py, px))


def test_chromatic_zone_plate_fse_below_grey():
    """Chromatic rings (R and B in antiphase) up to 0.5 cycles/pixel, 30 % of the photosites missing at random:
    the green-guided fse result's false colour is below that of a grey image of the true green (no colour at all: what a
    reconstruction that cannot place colour detail is bounded by) and at least 1.5 dB below a plain bilinear
    demosaic of every photosite."""
    rgb, panels = scene.colour_zone_plate(96)
    truth = (1000.0 * rgb[:, :, 192:]).astype(np.float32)
    rings = panels["colour"][:, 192:]
    m = cfa.mosaic(truth, "rggb")
    st = np.where(np.random.default_rng(2).random(m.shape) < 0.3, DISCARDED, VALID).astype(np.uint8)
    out = demosaic.reconstruct_cfa(m, st, "rggb", method="fse", preset=demosaic.GUIDED_PRESETS[0])
    ours = metrics.false_colour_db(truth, out, rings)
    assert ours < metrics.false_colour_db(truth, np.repeat(truth[1:2], 3, 0), rings)
    assert ours <= metrics.false_colour_db(truth, _bilinear(m, np.ones(m.shape, bool), "rggb"), rings) - 1.5


@pytest.mark.parametrize("case", ["random", "minus_zero", "zeros", "huge", "nan"])
def test_green_range_from_keys_as_by_floats(case):
    """The green plane's range for the median's bounds (`_green_range`): from integer keys, the same floats,
    signs of zero included, as the float comparisons it falls back to (-0, values beyond +-_BIG, NaN)."""
    h, w = 37, 50
    rng = np.random.default_rng(7)
    out = rng.normal(0.0, 100.0, (3, h, w)).astype(np.float32)
    if case == "minus_zero":
        out[1] = np.abs(out[1])
        out[1, 3, 4] = 0.0
        out[1, 20, 7] = -0.0
    elif case == "zeros":
        out[1] = 0.0
    elif case == "huge":
        out[1, 5] = 3.2e38
    elif case == "nan":
        out[1, 9, 9] = np.nan
    sc = demosaic._chroma_scratch(h, w)
    lo, hi = demosaic._green_range(out, np.float32(1.0), sc)
    demosaic._chroma_edges(out, np.float32(1.0), sc["bnd"], sc["gmm"], sc["gk"], False)
    ref = np.array([sc["gmm"][:, 0].min(), sc["gmm"][:, 1].max()], np.float32)
    np.testing.assert_array_equal(np.array([lo, hi], np.float32).view(np.int32), ref.view(np.int32))
