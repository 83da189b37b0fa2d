"""The compact LUT (nrcrosstalk mode=lut lut=compact, docs/CROSSTALK.md "Compact LUT"): derived from the full
table at load time, it must reproduce the full table's corrections (the paper's per-pixel LUT, section 3.2)
within the resampling error and handle every pixel state exactly as the full table does."""
from __future__ import annotations

import numpy as np
import pytest

import crosstalk_reference
from nrhdr_core import crosstalk, profile, validity


def _smooth_calibration(mask, nd, seed=0, knots=40, clip_code=4094):
    """Per-pixel curves like calibration.py's: knots at geometric fluxes, code = F / s * g * (1 - a F / top)
    with a per-pixel gain g (PRNU) and a per-pixel crosstalk-like compression a; dark level c0 ~ 1 DN; the
    pixel clips at clip_code (clip flux from the same formula)."""
    rng = np.random.default_rng(seed)
    h, w = mask.shape
    top = float(clip_code)
    s = np.where(mask, nd, 1.0)[:, :, None]
    flux_top = top * nd * 1.6
    kf = np.concatenate([[0.0], np.geomspace(5.0, flux_top, knots - 1)])
    g = 1.0 + 0.01 * rng.standard_normal((h, w, 1))
    a = np.where(mask, 0.15, 0.02)[:, :, None] * rng.uniform(0.5, 1.5, (h, w, 1))
    c0 = rng.uniform(0.0, 2.0, (h, w, 1))
    codes = c0 + kf[None, None, :] / s * g * (1.0 - a * kf[None, None, :] / (top * s * 2.0))
    n = np.sum(codes < top, axis=2)
    # flux at the clip code: invert the (monotone) formula by bisection on the dense fluxes
    fine = np.linspace(0.0, flux_top, 20001)
    clip = np.empty((h, w), np.float32)
    for y in range(h):
        for x in range(w):
            cf = c0[y, x, 0] + fine / s[y, x, 0] * g[y, x, 0] * (1 - a[y, x, 0] * fine / (top * s[y, x, 0] * 2))
            clip[y, x] = fine[np.searchsorted(cf, top)] if cf[-1] >= top else np.nan
    codes = np.where(np.arange(knots)[None, None, :] < n[:, :, None], codes, 0.0)
    q, qs, qo = crosstalk.quantize_codes(codes.astype(np.float32), clip_code + 1)
    return crosstalk.CrosstalkCalibration(
        codes_q=np.ascontiguousarray(q), qscale=qs, qoffset=qo, n_knots=n.astype(np.int32),
        knot_flux=kf, clip_flux=clip, nd=nd, black_level=0.0, clip_code=clip_code,
        sig_e=np.array([0.0, 1.0], np.float32), sigma=np.zeros((8, 2), np.float32),
        alpha=np.ones((h, w), np.float32))


@pytest.fixture(scope="module")
def smooth():
    p = profile.default(24, 32, seed=3)
    return p.replace(crosstalk=_smooth_calibration(p.mask, p.nd))


def test_compact_reproduces_the_full_table_on_smooth_curves(smooth):
    p = smooth
    err = crosstalk_reference.compact_error(p, codes_per_pixel=8)
    assert err["state_differs_pct"] == 0.0
    # a smooth curve resampled at 14 codes: the lerp error is far below the calibration's own noise
    assert err["rel_pct_median"] < 0.05 and err["rel_pct_p99"] < 0.5, err
    assert err["psnr_db"] > 60, err


def test_compact_is_exact_on_linear_curves():
    """The identity calibration (F = code * s) has zero correction: the compact form is the identity too."""
    p = profile.default(16, 16, seed=1)
    p = p.replace(crosstalk=crosstalk.identity_calibration(p.mask, nd=p.nd, clip_code=p.clip_code))
    m = np.random.default_rng(0).uniform(0, p.clip_code - 1, p.mask.shape).astype(np.float32)
    s = np.where(p.mask, np.uint8(validity.ATTENUATED), np.uint8(0))
    v = m * np.where(p.mask, np.float32(p.nd), np.float32(1.0))
    v2, s2 = v.copy(), s.copy()
    crosstalk.correct(v2, s2, p, mode="lut", lut="compact")
    np.testing.assert_array_equal(s2, s)
    np.testing.assert_allclose(v2, v, rtol=5e-5, atol=0.05)   # the knots are stored at 1/16 DN


def test_compact_handles_every_state_as_the_full_table(smooth):
    """Mixed frame: VALID (in range, above the range of pixels without clipping point, below the dark knot),
    CLIPPED (bound lowered to the calibrated clip flux), DARK (bound mapped through the LUT), NOISY and
    DISCARDED (untouched): same states as the full table, values within the resampling error."""
    p = smooth
    cal = p.crosstalk
    cal2 = crosstalk.CrosstalkCalibration(**{f: getattr(cal, f) for f in (
        "codes_q", "qscale", "qoffset", "n_knots", "knot_flux", "clip_flux", "nd", "black_level", "clip_code",
        "sig_e", "sigma", "alpha")})
    cal2.clip_flux = cal.clip_flux.copy()
    cal2.clip_flux[:, ::3] = np.nan             # these pixels' range ends at their last knot
    p = p.replace(crosstalk=cal2)
    rng = np.random.default_rng(5)
    h, w = p.mask.shape
    m = rng.uniform(-3.0, p.clip_code - 1, (h, w)).astype(np.float32)
    reasons = rng.choice([validity.VALID] * 4 + [validity.CLIPPED, validity.DARK, validity.NOISY,
                                                  validity.DISCARDED], size=(h, w)).astype(np.uint8)
    s = reasons | np.where(p.mask, np.uint8(validity.ATTENUATED), np.uint8(0))
    v = m * np.where(p.mask, np.float32(p.nd), np.float32(1.0))
    vf, sf = v.copy(), s.copy()
    vc, sc = v.copy(), s.copy()
    crosstalk.correct(vf, sf, p, mode="lut", lut="full")
    crosstalk.correct(vc, sc, p, mode="lut", lut="compact")
    np.testing.assert_array_equal(sc, sf)
    assert np.any((sf & validity.REASON_MASK) == validity.UNCALIBRATED)       # some codes above a range without clip point
    untouched = np.isin(s & validity.REASON_MASK, [validity.NOISY, validity.DISCARDED]) | ((sf & validity.REASON_MASK) == validity.UNCALIBRATED)
    np.testing.assert_array_equal(vc[untouched], v[untouched])
    clipped = (s & validity.REASON_MASK) == validity.CLIPPED
    np.testing.assert_array_equal(vc[clipped], vf[clipped])
    rest = ~untouched & ~clipped
    np.testing.assert_allclose(vc[rest], vf[rest], rtol=5e-3, atol=0.5)
    assert np.all(vc[rest] >= 0.0)


def test_compact_is_cached_per_profile_and_rejects_bad_forms(smooth):
    a = crosstalk.compact_for(smooth)
    assert crosstalk.compact_for(smooth) is a
    v = np.zeros(smooth.mask.shape, np.float32)
    s = np.zeros(smooth.mask.shape, np.uint8)
    with pytest.raises(ValueError, match="lut form"):
        crosstalk.correct(v, s, smooth, mode="lut", lut="tiny")


def test_compact_form_is_not_pickled_with_the_calibration(smooth):
    """Batch workers receive the profile pickled: the derived compact form (66 MB at 1080p) stays behind."""
    import pickle
    crosstalk.compact_for(smooth)
    cal = pickle.loads(pickle.dumps(smooth.crosstalk))
    assert "_compact" not in cal.__dict__
    np.testing.assert_array_equal(cal.codes_q, smooth.crosstalk.codes_q)
