"""The simulator's ideal model against the paper's Eq. 1-7 on flat fields (section 2.3)."""
import math

import numpy as np
import pytest

from nrhdr_core import metrics, profile, sensor, validity


def ideal_profile(nd=6.35, size=256):
    # gain 1 DN/e-, 16-bit ADC, no read noise: shot noise dominates (quantisation adds 1/12 DN^2)
    return profile.default(size, size, seed=5, nd=nd, bit_depth=16, clip_code=65534, gain=1.0,
                           full_well=70000.0, read_noise=0.0, l_min=5.0)


@pytest.mark.parametrize("mu", [400.0, 2500.0])
def test_snr_regular_and_attenuated_match_eq4_eq5(mu, rng):
    p = ideal_profile()
    raw = sensor.capture(np.full(p.mask.shape, mu), p, rng)
    v, s = validity.classify(raw, p, "all")
    assert validity.known_mask(s).all()
    snr_reg = metrics.snr_db(v[~p.mask])
    snr_att = metrics.snr_db(v[p.mask])
    # Eq. 4: sigma^2 = mu; Eq. 5: attenuated pixel scaled by ND has sqrt(ND) more relative noise
    eq4 = 20 * math.log10(mu / math.sqrt(mu))
    eq5 = 20 * math.log10(mu / (math.sqrt(p.nd) * math.sqrt(mu)))
    assert snr_reg == pytest.approx(eq4, abs=0.15)
    assert snr_att == pytest.approx(eq5, abs=0.2)
    assert float(sensor.snr_regular_db(mu)) == pytest.approx(eq4)
    assert float(sensor.snr_attenuated_db(mu, p.nd)) == pytest.approx(eq5)


def test_scaled_attenuated_mean_equals_regular_mean_eq3(rng):
    p = ideal_profile()
    raw = sensor.capture(np.full(p.mask.shape, 1500.0), p, rng)
    v, _ = validity.classify(raw, p, "all")
    # Eq. 3: mu_d1,scaled = ND * mu_d1 = mu_d0 (rounding of the attenuated codes is unbiased)
    assert v[p.mask].mean() == pytest.approx(v[~p.mask].mean(), rel=3e-3)


@pytest.mark.parametrize("nd", [4.0, 6.35, 16.0])
def test_global_snr_matches_eq6_eq7(nd, rng):
    p = ideal_profile(nd=nd)
    mu = 2000.0
    raw = sensor.capture(np.full(p.mask.shape, mu), p, rng)
    v, s = validity.classify(raw, p, "all")
    var_meas = v.astype(np.float64).var()
    eq6 = (1 + nd) / 2 * mu                     # sigma_global^2 = (1 + ND) / 2 sigma_d0^2, sigma_d0^2 = mu
    assert var_meas == pytest.approx(eq6, rel=0.03)
    eq7 = 20 * math.log10(math.sqrt(2 / (1 + nd)) * mu / math.sqrt(mu))
    assert metrics.snr_db(v) == pytest.approx(eq7, abs=0.15)
    assert float(sensor.snr_global_db(mu, nd)) == pytest.approx(eq7)


def test_known_ratio_per_selection_mode_fig4(rng):
    p = ideal_profile()
    raw = sensor.capture(np.full(p.mask.shape, 3000.0), p, rng)
    ratios = {m: validity.valid_ratio(validity.classify(raw, p, m)[1]) for m in validity.MODES}
    assert ratios["all"] == 1.0
    assert ratios["threshold"] == 1.0
    # best pixel only: every attenuated pixel has a valid regular neighbour almost surely at 50 %
    assert ratios["best"] == pytest.approx(1 - p.mask.mean(), abs=0.005)


def test_clipping_at_full_well():
    p = profile.default(32, 32, seed=1)
    raw = sensor.capture(np.full(p.mask.shape, 3 * p.regular_white), p, np.random.default_rng(0))
    assert (raw[~p.mask] >= p.clip_code).all()          # regular pixels saturate
    assert (raw[p.mask] < p.clip_code).all()            # 3x is within the ND range (6.35)
    assert raw.max() <= p.max_code


def test_attenuated_pixels_clip_beyond_nd(rng):
    p = profile.default(32, 32, seed=1)
    raw_in = sensor.capture(np.full(p.mask.shape, 0.8 * p.nd * p.regular_white), p, rng)
    raw_out = sensor.capture(np.full(p.mask.shape, 1.3 * p.nd * p.regular_white), p, rng)
    assert (raw_in[p.mask] < p.clip_code).all()
    assert (raw_out[p.mask] >= p.clip_code).all()


def test_capture_is_deterministic_and_validates():
    p = profile.default(16, 16, seed=2)
    f = np.full(p.mask.shape, 500.0)
    a = sensor.capture(f, p, np.random.default_rng(7))
    b = sensor.capture(f, p, np.random.default_rng(7))
    assert np.array_equal(a, b)
    with pytest.raises(ValueError, match="mask"):
        sensor.capture(np.zeros((8, 8)), p, np.random.default_rng(0))
    with pytest.raises(ValueError, match="finite"):
        sensor.capture(np.full(p.mask.shape, np.nan), p, np.random.default_rng(0))


def test_read_noise_and_black_level(rng):
    p = profile.default(128, 128, seed=4, read_noise=5.0, black_level=64.0, gain=1.0, full_well=5000.0)
    raw = sensor.capture(np.zeros(p.mask.shape), p, rng)
    assert raw.astype(float).mean() == pytest.approx(64.0, abs=0.1)
    assert raw.astype(float).std() == pytest.approx(math.sqrt(25 + 1 / 12), rel=0.03)


def test_zero_db_signal():
    p = profile.default(4, 4, gain=1.0, read_noise=0.0, full_well=5000.0)
    s = sensor.zero_db_signal_dn(p)
    # SNR = 0 dB where s^2 = g s + 1/12
    assert s * s == pytest.approx(s + 1 / 12)
