"""Crosstalk sensor model, correction kernels and calibration storage (nrhdr_core/crosstalk.py)."""
from __future__ import annotations

import numpy as np
import pytest

from nrhdr_core import crosstalk, profile, validity


def _prof(h=16, w=16, **kw):
    return profile.default(h, w, seed=1, **kw)


# ---- sensor model -----------------------------------------------------------------------------------

def test_zero_kernel_is_identity():
    p = _prof()
    m = crosstalk.SensorModel(kernel=np.zeros((3, 3)))
    e = np.random.default_rng(0).uniform(0, 5000, p.mask.shape)
    np.testing.assert_allclose(m.apply(e, p), e)


def test_linear_kernel_matches_hand_computed_spill():
    """One bright source pixel: every neighbour receives exactly kernel * source, the source loses it all."""
    p = _prof(7, 7)
    k = crosstalk.make_kernel(0.01, 0.02, 0.003)
    m = crosstalk.SensorModel(kernel=k)
    e = np.zeros((7, 7))
    e[3, 3] = 1000.0
    out = m.apply(e, p)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy or dx:
                # target (3 - dy, 3 - dx) sees the source at offset (dy, dx)
                assert out[3 - dy, 3 - dx] == pytest.approx(1000.0 * k[1 + dy, 1 + dx])
    assert out[3, 3] == pytest.approx(1000.0 * (1 - k.sum()))
    assert out.sum() == pytest.approx(1000.0)          # charge conserved (centre = 1 - outgoing)
    # anisotropy: column neighbours (edge_v) get twice the row neighbours (edge_h)
    assert out[2, 3] == pytest.approx(2 * out[3, 2])


def test_flat_field_is_unchanged_in_the_interior():
    p = _prof(9, 9)
    m = crosstalk.SensorModel(kernel=crosstalk.make_kernel(0.01, 0.01, 0.0025))
    out = m.apply(np.full((9, 9), 1234.0), p)
    np.testing.assert_allclose(out[1:-1, 1:-1], 1234.0)


def test_nonlinear_near_saturation():
    """Blooming: the spill per source electron grows once the source approaches full well."""
    p = _prof(5, 5)
    m = crosstalk.SensorModel(kernel=crosstalk.make_kernel(0.01, 0.01, 0.0), gamma=0.0,
                              bloom=crosstalk.make_kernel(0.02, 0.02, 0.0), knee=0.9, knee_width=0.2)

    def spill(level):
        e = np.zeros((5, 5))
        e[2, 2] = level
        return m.apply(e, p)[2, 1] / level

    fw = p.full_well
    assert spill(0.3 * fw) == pytest.approx(0.01)
    assert spill(0.6 * fw) == pytest.approx(0.01)
    assert spill(2.0 * fw) > 1.5 * spill(0.6 * fw)


def test_signal_dependent_coupling():
    p = _prof(5, 5)
    m = crosstalk.SensorModel(kernel=crosstalk.make_kernel(0.01, 0.01, 0.0), gamma=0.7)
    e = np.zeros((5, 5))
    e[2, 2] = 0.1 * p.full_well
    lo = m.apply(e, p)[2, 1] / e[2, 2]
    e[2, 2] = 0.9 * p.full_well
    hi = m.apply(e, p)[2, 1] / e[2, 2]
    assert lo == pytest.approx(0.01 * (1 + 0.7 * (0.1 - 0.5)))
    assert hi == pytest.approx(0.01 * (1 + 0.7 * (0.9 - 0.5)))


def test_presets():
    assert crosstalk.sensor_model_preset("none", 8, 8) is None
    a = crosstalk.sensor_model_preset("prototype", 8, 10, seed=4)
    b = crosstalk.sensor_model_preset("prototype", 8, 10, seed=4)
    c = crosstalk.sensor_model_preset("prototype", 8, 10, seed=5)
    assert a.spread.shape == (8, 10)
    np.testing.assert_array_equal(a.spread, b.spread)
    assert not np.array_equal(a.spread, c.spread)
    k = a.kernel
    assert k[1, 0] == pytest.approx(0.01) and k[0, 1] > k[1, 0]          # ~1 %, column anisotropy
    with pytest.raises(ValueError, match="preset"):
        crosstalk.sensor_model_preset("bogus", 8, 8)


def test_prototype_amplified_crosstalk():
    """Paper 3.1: a 1 % spill from bright unattenuated neighbours is amplified by the ND factor: an
    attenuated pixel with regular neighbours reads several % to tens of % too high."""
    from nrhdr_core import sensor
    p = _prof(32, 32)
    m = crosstalk.sensor_model_preset("linear", 32, 32)
    flux = np.full((32, 32), 1000.0)
    raw = sensor.capture(flux, p, np.random.default_rng(0), sensor_model=m, shot_noise=False)
    v, s = validity.classify(raw, p.replace(read_noise=0.0))
    rel = v[p.mask][5:] / 1000.0 - 1.0
    assert np.median(rel) > 0.05


# ---- correction ---------------------------------------------------------------------------------------

def test_modes_and_identity_without_calibration():
    p = _prof()
    v = np.full(p.mask.shape, 100.0, np.float32)
    s = np.zeros(p.mask.shape, np.uint8)
    v2, s2 = crosstalk.correct(v, s, p, mode="lut")
    assert v2 is v and np.all(v == 100.0)
    with pytest.raises(ValueError, match="mode"):
        crosstalk.correct(v, s, p, mode="fancy")
    assert crosstalk.MODES == ("lut", "kernel", "off")


def _frame(p, flux, seed=0):
    from nrhdr_core import sensor
    raw = sensor.capture(np.asarray(flux, float), p.replace(read_noise=0.0), np.random.default_rng(seed),
                         shot_noise=False)
    return validity.classify(raw, p)


@pytest.mark.parametrize("mode", ["lut", "kernel", "off"])
def test_identity_calibration_is_identity(mode):
    p = _prof(24, 24)
    p = p.replace(crosstalk=crosstalk.identity_calibration(p.mask, nd=p.nd, clip_code=p.clip_code))
    yy, xx = np.mgrid[0:24, 0:24]
    flux = 10 ** (1 + 4 * xx / 24.0)
    v, s = _frame(p, flux)
    v0, s0 = v.copy(), s.copy()
    crosstalk.correct(v, s, p, mode=mode)
    np.testing.assert_array_equal(s, s0)
    np.testing.assert_allclose(v, v0, rtol=5e-4, atol=0.05)   # 1/16 DN knot quantisation


def _hand_calibration(mask):
    """Every pixel: codes [0, 100, 300] at fluxes [0, 500, 1000]; clips (code 400) at flux 1200."""
    h, w = mask.shape
    codes = np.zeros((h, w, 3), np.float32)
    codes[:, :, 1] = 100.0
    codes[:, :, 2] = 300.0
    q, qs, qo = crosstalk.quantize_codes(codes, 4095)
    return crosstalk.CrosstalkCalibration(
        codes_q=q, qscale=qs, qoffset=qo, n_knots=np.full((h, w), 3, np.int32),
        knot_flux=np.array([0.0, 500.0, 1000.0]), clip_flux=np.full((h, w), 1200.0, np.float32),
        nd=1.0, black_level=0.0, clip_code=400, sig_e=np.array([0.0, 1.0], np.float32),
        sigma=np.zeros((8, 2), np.float32), alpha=np.ones((h, w), np.float32))


def test_lut_interpolates_and_marks_out_of_range():
    mask = np.zeros((4, 4), bool)
    p = profile.make(mask, nd=1.0, clip_code=400, l_min=10.0, full_well=1e5)
    p = p.replace(crosstalk=_hand_calibration(mask))
    v = np.array([[50, 200, 350, 399]] * 4, np.float32)
    s = np.zeros((4, 4), np.uint8)
    s[3, :] = validity.CLIPPED
    v[3, :] = 400.0
    s[2, 0] = validity.DARK
    crosstalk.correct(v, s, p, mode="lut")
    assert v[0, 0] == pytest.approx(250.0, abs=0.5)        # 50 in [0, 100] -> [0, 500]
    assert v[0, 1] == pytest.approx(750.0, abs=0.5)        # 200 in [100, 300] -> [500, 1000]
    # 350, 399 lie between the last knot and the measured clipping point: interpolated to 1200
    assert v[0, 2] == pytest.approx(1000 + 50 / 100 * 200, abs=0.5)
    assert s[0, 2] == validity.VALID
    # clipped pixels keep their state; their lower bound is the calibrated clipping flux
    assert np.all(s[3] == validity.CLIPPED) and np.all(v[3] == pytest.approx(400.0))
    # without a measured clipping point, codes above the last knot are UNCALIBRATED, not extrapolated
    cal = _hand_calibration(mask)
    cal.clip_flux[:] = np.nan
    p2 = p.replace(crosstalk=cal)
    v = np.full((4, 4), 350.0, np.float32)
    s = np.full((4, 4), validity.ATTENUATED * 0, np.uint8)
    crosstalk.correct(v, s, p2, mode="lut")
    assert np.all((s & validity.REASON_MASK) == validity.UNCALIBRATED)
    assert np.all(v == 350.0)


def test_clipped_bound_lowered_to_calibrated_clip_flux():
    mask = np.zeros((4, 4), bool)
    p = profile.make(mask, nd=1.0, clip_code=400, l_min=10.0, full_well=1e5)
    cal = _hand_calibration(mask)
    cal.clip_flux[:] = 380.0
    p = p.replace(crosstalk=cal)
    v = np.full((4, 4), 400.0, np.float32)
    s = np.full((4, 4), validity.CLIPPED, np.uint8)
    crosstalk.correct(v, s, p)
    assert np.all(s == validity.CLIPPED) and np.allclose(v, 380.0)


def test_kernel_mode_equals_lut_on_flat_field():
    """With neighbours as bright as the pixel the kernel mode's neighbour term vanishes (the paper's
    assumption holds): both modes agree."""
    p = _prof(20, 20)
    cal = crosstalk.identity_calibration(p.mask, nd=p.nd, clip_code=p.clip_code)
    cal.sig_e = np.array([0.0, 10000.0], np.float32)
    cal.sigma = np.full((8, 2), 0.0, np.float32)
    cal.sigma[:, 1] = 100.0                                   # 1 % spill per neighbour
    p = p.replace(crosstalk=cal)
    v, s = _frame(p, np.full((20, 20), 2000.0))
    a, sa = v.copy(), s.copy()
    b, sb = v.copy(), s.copy()
    crosstalk.correct(a, sa, p, mode="lut")
    crosstalk.correct(b, sb, p, mode="kernel")
    np.testing.assert_allclose(a, b, rtol=5e-4)     # code rounding differs between neighbours


def _linear_spill_profile(h, w, k):
    """Hand-made calibration, all regular pixels, ND 1: a flat field at flux F reads F (conserving
    kernel), so the LUT is the identity; spill sigma(e) = k * e per neighbour."""
    mask = np.zeros((h, w), bool)
    p = profile.make(mask, nd=1.0, clip_code=4094, l_min=10.0, full_well=1e6, gain=4094 / 1e5)
    cal = crosstalk.identity_calibration(mask, nd=1.0, clip_code=4094)
    cal.sig_e = np.array([0.0, 1e5], np.float32)
    cal.sigma = np.zeros((8, 2), np.float32)
    cal.sigma[:, 1] = k * 1e5
    return p.replace(crosstalk=cal)


def test_kernel_mode_removes_spill_from_a_bright_neighbour():
    """Known truth: a hand-made calibration with spill sigma(e) = 1 % e per neighbour and an exact LUT for a
    flat field; a pixel whose right neighbour is 10x brighter must get the extra spill removed."""
    h, w, k = 5, 5, 0.01
    p = _linear_spill_profile(h, w, k)
    truth = np.full((h, w), 200.0)
    truth[:, 3:] = 2000.0
    model = crosstalk.SensorModel(kernel=crosstalk.make_kernel(k, k, k))
    from nrhdr_core import sensor
    raw = sensor.capture(truth, p.replace(read_noise=0.0), np.random.default_rng(0), sensor_model=model,
                         shot_noise=False)
    v, s = validity.classify(raw, p)
    err_before = abs(v[2, 2] / 200.0 - 1)
    crosstalk.correct(v, s, p, mode="kernel")
    assert err_before > 0.2                                  # 3 neighbours x 1 % x 1800 = 54 DN on 200
    assert abs(v[2, 2] / 200.0 - 1) < 0.02


# ---- storage -------------------------------------------------------------------------------------------

def test_save_load_roundtrip(tmp_path):
    p = _prof(12, 14)
    cal = crosstalk.identity_calibration(p.mask, nd=p.nd, clip_code=p.clip_code)
    cal.alpha[:] = 1.25
    p = p.replace(crosstalk=cal)
    path = profile.save(p, tmp_path / "cam.json")
    q = profile.load(path)
    assert q.crosstalk is not None and q.crosstalk_file == "cam_crosstalk.npz"
    np.testing.assert_array_equal(q.crosstalk.codes_q, cal.codes_q)
    np.testing.assert_allclose(q.crosstalk.alpha, 1.25)
    assert q.crosstalk.nd == pytest.approx(p.nd)


def test_load_rejects_corrupt_and_mismatched(tmp_path):
    p = _prof(12, 14)
    p = p.replace(crosstalk=crosstalk.identity_calibration(p.mask, nd=p.nd, clip_code=p.clip_code))
    path = profile.save(p, tmp_path / "cam.json")
    import json
    entry = json.loads(path.read_text())["crosstalk"]
    assert entry["file"] == "cam_crosstalk.npz"
    with pytest.raises(ValueError, match="expected uint16"):
        crosstalk.load_calibration(entry, tmp_path, (10, 14))
    (tmp_path / "cam_crosstalk.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="not a readable"):
        crosstalk.load_calibration(entry, tmp_path, (12, 14))
    with pytest.raises(profile.ProfileError, match="crosstalk"):
        profile.load(path)
    with pytest.raises(ValueError, match="not found"):
        crosstalk.load_calibration(dict(entry, file="missing.npz"), tmp_path, (12, 14))
    with pytest.raises(ValueError, match="format"):
        crosstalk.load_calibration({"file": "x"}, tmp_path, (12, 14))


def test_chain_warmup_compiles_what_the_elements_run():
    """After `chain.warmup` of the validity and crosstalk stages with the elements' array types, the calls the
    elements make compile nothing: classify of a read-only raw frame with padded rows (GStreamer pads GRAY16
    rows to 4 bytes), correct in every mode and LUT form."""
    from nrhdr_core import chain
    from nrhdr_core.realtime import JitWatch
    pairs = [(x, lut) for x in crosstalk.MODES for lut in crosstalk.LUT_FORMS]
    chain.warmup([chain.ChainSettings(crosstalk=x, crosstalk_lut=lut) for x, lut in pairs],
                 stages=("validity", "crosstalk"), elements=True)
    p = profile.default(20, 31, seed=1)
    p = p.replace(crosstalk=crosstalk.identity_calibration(p.mask, nd=p.nd, clip_code=p.clip_code))
    buf = np.random.default_rng(0).integers(0, 4096, (20, 32)).astype(np.uint16)
    raw = buf[:, :31]
    raw.setflags(write=False)
    snap = JitWatch.snapshot()
    v, s = validity.classify(raw, p, dark_policy="weighted")
    for x, lut in pairs:
        crosstalk.correct(v.copy(), s.copy(), p, x, lut=lut)
    assert JitWatch.since(snap)[0] == 0
    with pytest.raises(ValueError, match="stage"):
        chain.warmup(stages=("crosstalks",))
    with pytest.raises(ValueError, match="transfer"):
        chain.warmup(stages=("tonemap",), transfers=("gamma",))


def test_kernel_mode_drops_pixels_dominated_by_clipped_neighbours():
    """A dark pixel next to clipped bright pixels: their flux is only known as a lower bound, and when their
    estimated spill exceeds the pixel's own signal the pixel becomes UNCALIBRATED (missing) instead of
    carrying a guess; with clip_share=None it is kept (and corrected with the bound)."""
    h, w, k = 5, 5, 0.01
    p = _linear_spill_profile(h, w, k)
    truth = np.full((h, w), 20.0)
    truth[:, 3:] = 4600.0                                   # just above clipping
    model = crosstalk.SensorModel(kernel=crosstalk.make_kernel(k, k, k))
    from nrhdr_core import sensor
    raw = sensor.capture(truth, p.replace(read_noise=0.0), np.random.default_rng(0), sensor_model=model,
                         shot_noise=False)
    v, s = validity.classify(raw, p)
    assert s[2, 3] & validity.REASON_MASK == validity.CLIPPED and s[2, 2] == validity.VALID
    v1, s1 = v.copy(), s.copy()
    crosstalk.correct(v1, s1, p, mode="kernel")
    assert s1[2, 2] & validity.REASON_MASK == validity.UNCALIBRATED
    assert s1[2, 0] == validity.VALID                         # far from the clipped pixels: kept
    v2, s2 = v.copy(), s.copy()
    crosstalk.correct(v2, s2, p, mode="kernel", clip_share=None)
    assert s2[2, 2] == validity.VALID and abs(v2[2, 2] - 20.0) < abs(v[2, 2] - 20.0)


@pytest.mark.parametrize("mode", ["lut", "lut-compact", "kernel"])
@pytest.mark.parametrize("f0", [0.0, 40.0])
def test_codes_below_the_first_knot_are_never_negative(mode, f0):
    """Codes inside the dark noise, below a pixel's first (dark) knot, map into [0, first knot's flux],
    monotone in the code: the first segment of an attenuated pixel spans ~1 DN of code for a large flux
    step, and extrapolating it sent such codes to -24000 DN. Analytic: between (black, 0) and the first
    knot (c0, f0)."""
    mask = np.ones((8, 8), bool)
    nd = 6.35
    p = profile.make(mask, nd=nd, clip_code=4094, l_min=10.0, full_well=1e5)
    codes = np.zeros((8, 8, 3), np.float32)
    codes[:, :, 0] = 3.0                   # dark level 3 DN above black
    codes[:, :, 1] = 4.0                   # first segment: 1 DN of code ...
    codes[:, :, 2] = 600.0
    q, qs, qo = crosstalk.quantize_codes(codes, 4095)
    cal = crosstalk.CrosstalkCalibration(
        codes_q=q, qscale=qs, qoffset=qo, n_knots=np.full((8, 8), 3, np.int32),
        knot_flux=np.array([f0, 5000.0, 30000.0], np.float64),   # ... for 5000 DN of flux
        clip_flux=np.full((8, 8), np.nan, np.float32), nd=nd, black_level=0.0, clip_code=4094,
        sig_e=np.array([0.0, 1.0], np.float32), sigma=np.zeros((8, 2), np.float32),
        alpha=np.ones((8, 8), np.float32))
    p = p.replace(crosstalk=cal)
    m = np.linspace(-20.0, 2.99, 64).reshape(8, 8).astype(np.float32)   # codes above black, all <= c0
    v = m * np.float32(nd)                                               # attenuated: values scaled by ND
    s = np.full((8, 8), validity.VALID | validity.ATTENUATED, np.uint8)
    mode, lut = ("lut", "compact") if mode == "lut-compact" else (mode, "full")
    crosstalk.correct(v, s, p, mode=mode, lut=lut)
    assert np.all((s & validity.REASON_MASK) == validity.VALID)
    assert np.all(v >= 0.0) and np.all(v <= f0 + 1e-3)
    flat = v.ravel()
    assert np.all(np.diff(flat) >= 0.0)                                  # monotone in the code
    c0 = float(cal.codes()[0, 0, 0])                                    # 3 DN as stored (quantised)
    np.testing.assert_allclose(flat, f0 * np.clip(m.ravel(), 0, None) / c0, rtol=1e-5, atol=1e-3)
    # DARK pixels (an upper bound) below the first knot: never negative either
    v2 = m * np.float32(nd)
    s2 = np.full((8, 8), validity.DARK | validity.ATTENUATED, np.uint8)
    crosstalk.correct(v2, s2, p, mode=mode, lut=lut)
    assert np.all(v2 >= np.minimum(m * np.float32(nd), 0.0))   # kept (f <= 0) or replaced by f > 0
    assert np.all(v2[v2 != m * np.float32(nd)] > 0.0)
