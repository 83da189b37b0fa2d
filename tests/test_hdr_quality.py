"""Physically valid HDR output (no negative / non-finite value, bounds, no ringing around point
sources), a stable domain (zone plate, noise seed), the noise-aware dark policy, HDR metrics (PU21 by
hand from its published formula), and a saturated frame uniform at its bound."""
import math
import warnings

import numpy as np
import pytest

from conftest import shared_data
from nrhdr_core import metrics, profile, reconstruction, sensor, simulate, io, validity


def chain(raw, prof, **kw):
    v, s = validity.classify(raw, prof, **kw)
    lo, hi = validity.bounds(v, s)
    out = reconstruction.reconstruct(v, validity.known_mask(s), lower=lo, upper=hi,
                                     noisy=validity.noisy_mask(s), noise=prof)
    return out, v, s, lo, hi


# ---- metrics -------------------------------------------------------------------------------------------

def test_pu21_by_hand():
    # V = p7 ((p1 + p2 Y^p4) / (1 + p3 Y^p4))^p5 - p6 p7, 'banding_glare' parameters (gfxdisp/pu21)
    p1, p2, p3, p4, p5, p6, p7 = (0.353487901, 0.3734658629, 8.277049286e-05, 0.9062562627,
                                  0.09150303166, 0.9099517204, 596.3148142)
    for y in (0.005, 1.0, 100.0, 10000.0):
        yp = y ** p4
        v = p7 * (((p1 + p2 * yp) / (1 + p3 * yp)) ** p5 - p6)
        assert metrics.pu21_encode(y) == pytest.approx(v, rel=1e-12)
    # Y = 1: ((p1 + p2) / (1 + p3))^p5 written out
    assert metrics.pu21_encode(1.0) == pytest.approx(596.3148142 * ((0.7269537639 / 1.00008277049286)
                                                                   ** 0.09150303166 - 0.9099517204), rel=1e-9)
    # clamped to the encoder's range, monotonic
    assert metrics.pu21_encode(0.0) == metrics.pu21_encode(0.005)
    assert metrics.pu21_encode(1e6) == metrics.pu21_encode(1e4)
    ys = np.logspace(-2.3, 4, 50)
    assert np.all(np.diff(metrics.pu21_encode(ys)) > 0)


def test_pu21_psnr_and_log2_psnr_match_their_definitions():
    rng = np.random.default_rng(0)
    ref = rng.uniform(1, 1000, (20, 20))
    test = ref * 2.0 ** rng.normal(0, 0.1, ref.shape)
    k = 4000.0 / 1000.0
    a, b = metrics.pu21_encode(ref * k), metrics.pu21_encode(test * k)
    want = 10 * math.log10(256.0 ** 2 / np.mean((a - b) ** 2))
    assert metrics.pu21_psnr(ref, test, white=1000.0) == pytest.approx(want, rel=1e-9)
    d = np.log2(test) - np.log2(ref)
    want = 10 * math.log10(10.0 ** 2 / np.mean(d ** 2))
    assert metrics.log2_psnr(ref, test, floor=1.0, peak_stops=10.0) == pytest.approx(want, rel=1e-9)


def test_regions_and_stops_off():
    truth = np.array([[10.0, 1000.0, 5000.0, 20000.0]])
    test = np.array([[10.0, 2500.0, 5000.0, 1000.0]])
    r = metrics.hdr_report(truth, test, dark_level=635.0, bright_level=4094.0)
    assert (r["dark"]["pixels"], r["mid"]["pixels"], r["bright"]["pixels"]) == (1, 1, 2)
    assert r["all"]["off_1stop"] == 2 and r["all"]["off_3stops"] == 1    # 1.32 stops, 4.32 stops
    assert r["bright"]["off_3stops"] == 1 and r["mid"]["off_1stop"] == 1


# ---- valid output ----------------------------------------------------------------------------------------

def _scene(name, h=192, w=256):
    sc = io.read_luminance(shared_data("hdr", f"{name}.exr"))
    prof = profile.default(h, w)
    k = simulate.exposure_scale(sc, prof, 0.0)
    return simulate.view(sc, h, w, 0.3, simulate.Motion()) * np.float32(k)


@pytest.mark.parametrize("pattern", ["nonregular", "regular"])
def test_kerner_env_no_negative_or_nonfinite_output(pattern):
    t = _scene("KernerEnvLatLong")
    prof = profile.default(*t.shape, pattern=pattern)
    raw = sensor.capture(t, prof, np.random.default_rng(0))
    for policy in ("threshold", "weighted"):
        out, v, s, lo, hi = chain(raw, prof, dark_policy=policy)
        assert np.isfinite(out).all() and (out >= 0).all(), (policy, out.min())
        miss = ~validity.known_mask(s)
        m = miss & ~np.isnan(lo)
        assert (out[m] >= lo[m]).all()
        m = miss & ~np.isnan(hi)
        assert (out[m] <= hi[m]).all()


def test_noise_seed_moves_the_result_by_less_than_half_a_db():
    t = _scene("KernerEnvLatLong")
    prof = profile.default(*t.shape)
    ps = []
    for seed in (1, 2):
        out = chain(sensor.capture(t, prof, np.random.default_rng(seed)), prof)[0]
        ps.append(metrics.log2_psnr(np.minimum(t, prof.white), np.minimum(out, prof.white)))
    assert abs(ps[0] - ps[1]) < 0.5, ps
    # and a mask seed
    out = chain(sensor.capture(t, profile.default(*t.shape, seed=9), np.random.default_rng(1)),
                profile.default(*t.shape, seed=9))[0]
    assert abs(metrics.log2_psnr(np.minimum(t, prof.white), np.minimum(out, prof.white)) - ps[0]) < 0.5


def test_zone_plate_stays_in_its_range():
    n = 256
    yy, xx = np.mgrid[0:n, 0:n]
    r2 = (xx - n / 2) ** 2 + (yy - n / 2) ** 2
    zp = (127.5 + 127.5 * np.cos(np.pi * 0.25 * r2 / (n / 2))).astype(np.float32)  # 0-255, to 0.25 c/px
    known = np.random.default_rng(0).random(zp.shape) < 0.5
    out = reconstruction.reconstruct(zp, known, preset="balanced")
    assert out.min() >= 0.0 and out.max() <= 255.0
    lin = reconstruction.reconstruct(zp, known, preset="balanced", domain="linear")
    assert metrics.psnr(zp, out, 255) > metrics.psnr(zp, lin, 255) - 1.0     # auto ~ linear on 8-bit data
    assert metrics.psnr(zp, out, 255) > 40.0


def test_bright_point_sources_on_dark_background_stay_bounded_without_ringing():
    from scipy.ndimage import gaussian_filter
    h = w = 96
    rng = np.random.default_rng(0)
    t = gaussian_filter(30 + 20 * rng.random((h, w)), 2).astype(np.float32)
    pts = [(20, 20), (40, 70), (70, 30), (75, 80)]
    for y, x in pts:
        t[y, x] = 2e5
        t[y, x + 1] = 5e4
    yy, xx = np.mgrid[0:h, 0:w]
    near = np.zeros(t.shape, bool)
    for y, x in pts:
        near |= (abs(yy - y) <= 4) & (abs(xx - x) <= 4)
    near &= t < 1000
    prof = profile.default(h, w)
    for seed in range(2):
        out, v, s, lo, hi = chain(sensor.capture(t, prof, np.random.default_rng(seed)), prof)
        assert np.isfinite(out).all() and (out >= 0).all()
        m = ~np.isnan(lo)
        assert (out[m] >= lo[m]).all()            # the sources are at least their clip level
        ratio = out[near] / t[near]
        # no ringing: the dark surround stays within a factor 2 of the truth (linear FSE: down to 0)
        assert ratio.max() < 2.0 and np.mean((ratio < 0.5)) < 0.02, (ratio.min(), ratio.max())


def test_saturated_frame_is_uniform_at_the_bound_not_the_mask():
    prof = profile.default(48, 64)
    raw = np.full((48, 64), 4095, np.uint16)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        out = chain(raw, prof)[0]
    assert np.all(out == np.float32(prof.white))       # regular pixels too: their ND neighbours clip
    assert any("bound" in str(r.message) for r in rec)
    assert not any("zeros" in str(r.message) for r in rec)


def test_overexposed_scene_shows_no_mask_pattern():
    """A scene over-exposed by 7 stops: where it saturates both pixel kinds the output is
    one uniform level (regular and ND pixels alike), not the ND mask as a dot pattern."""
    from scipy.ndimage import binary_erosion
    sc = io.read_luminance(shared_data("hdr", "Desk.exr"))
    prof = profile.default(96, 128)
    t = simulate.view(sc, 96, 128, 0.3, simulate.Motion()) * np.float32(simulate.exposure_scale(sc, prof, 7.0))
    out = chain(sensor.capture(t, prof, np.random.default_rng(0)), prof)[0]
    sat = binary_erosion(t > 2 * prof.white, iterations=2)
    assert sat.mean() > 0.2
    assert abs(out[sat & ~prof.mask].mean() - out[sat & prof.mask].mean()) < 1e-3 * prof.white
    assert out[sat].std() < 1e-3 * prof.white


def test_clipped_regular_pixel_takes_its_clipped_nd_neighbours_bound():
    prof = profile.default(32, 32)
    t = np.full((32, 32), 200.0, np.float32)
    t[8:24, 8:24] = 1e6                        # saturates ND pixels too
    raw = sensor.capture(t, prof, np.random.default_rng(0))
    v, s = validity.classify(raw, prof)
    lo, _ = validity.bounds(v, s)
    inner = np.zeros(t.shape, bool)
    inner[10:22, 10:22] = True
    assert np.all(lo[inner] == np.float32(prof.white))


# ---- noise-aware dark policy ------------------------------------------------------------------------------

def test_weighted_policy_keeps_dark_samples_and_improves_dark_regions():
    """Real scene (Tree: large dark areas): the NOISY measurements raise the dark region's log PSNR.
    (On synthetic dark texture of large amplitude the variance-based texture term over-trusts the
    measurement: docs/FSE.md "Noise-aware dark pixels".)"""
    t = _scene("Tree")
    prof = profile.default(*t.shape)
    dark = t < prof.l_min * prof.nd
    res = {}
    for policy in ("threshold", "weighted"):
        out, v, s, lo, hi = chain(sensor.capture(t, prof, np.random.default_rng(3)), prof,
                                  dark_policy=policy)
        res[policy] = metrics.log2_psnr(t[dark], out[dark], peak_stops=float(np.log2(prof.white)))
        if policy == "weighted":
            noisy = (s & validity.REASON_MASK) == validity.NOISY
            assert ((s & validity.ATTENUATED) != 0)[noisy].all()
            assert noisy[dark & prof.mask].mean() > 0.5    # most dark ND pixels are now measurements
    assert res["weighted"] > res["threshold"] + 1.0, res


def test_fusion_weights_follow_the_noise():
    """Flat field: inverse-variance fusion of an estimate with an ND-noisy measurement (Eq. 4-7 noise
    model). "fast": the estimate g (here 100) counts as ~4 regular samples; "accurate": the estimate is
    the mean of the 8 known neighbours of the 3 x 3 window, variance var_r / 8."""
    prof = profile.default(8, 8)
    values = np.full((8, 8), 100.0, np.float32)
    known = np.ones((8, 8), bool)
    known[4, 4] = False
    values[4, 4] = 300.0                       # the noisy measurement
    out = np.full((8, 8), 100.0, np.float32)
    noisy = ~known
    vr = validity.measurement_variance(100.0, prof, regular=True)
    vm = validity.measurement_variance(100.0, prof)
    for setting, vg in (("fast", vr / 4), ("accurate", vr / 8)):
        res = reconstruction.fuse_noisy(out.copy(), values, known, noisy, prof, setting=setting)[4, 4]
        assert res == pytest.approx(100 + vg / (vg + vm) * 200, rel=1e-5), setting
    with pytest.raises(ValueError, match="setting"):
        reconstruction.fuse_noisy(out.copy(), values, known, noisy, prof, setting="best")


@pytest.mark.parametrize("level", [100.0, 400.0])
def test_accurate_fusion_reaches_the_inverse_variance_bound_on_a_flat_dark_field(level):
    """Flat dark field, non-regular mask, dark policy weighted: the accurate setting's error at the NOISY
    pixels approaches the inverse-variance bound of its samples (the pixel's own ND measurement and its
    measured 3 x 3 neighbours, each with the noise model's variance, Eq. 4-7): 1 / (k / var_r + (z + 1) /
    var_m) averaged over the pixels, k / z the known / NOISY neighbour counts; and beats every input."""
    from scipy.ndimage import convolve
    n = 96
    prof = profile.default(n, n)
    t = np.full((n, n), level, np.float32)
    v, s = validity.classify(sensor.capture(t, prof, np.random.default_rng(5)), prof, dark_policy="weighted")
    known, noisy = validity.known_mask(s), validity.noisy_mask(s)
    lo, hi = validity.bounds(v, s)
    interp = reconstruction.reconstruct(v, known, lower=lo, upper=hi)
    fused = {st: reconstruction.fuse_noisy(interp.copy(), v, known, noisy, prof, setting=st)
             for st in ("fast", "accurate")}
    vr = validity.measurement_variance(level, prof, regular=True)
    vm = validity.measurement_variance(level, prof)
    ring = np.ones((3, 3))
    ring[1, 1] = 0
    k8 = convolve(known.astype(float), ring, mode="constant")
    z8 = convolve(noisy.astype(float), ring, mode="constant")
    sel = noisy.copy()
    sel[:2] = sel[-2:] = False
    sel[:, :2] = sel[:, -2:] = False
    assert sel.sum() > 2000
    bound = float(np.mean(1.0 / (k8[sel] / vr + (z8[sel] + 1) / vm)))
    mse = {k: float(np.mean((a[sel] - level) ** 2)) for k, a in
           (("measurement", v), ("interpolation", interp), *fused.items())}
    assert 0.85 * bound < mse["accurate"] < 1.15 * bound, (bound, mse)
    assert mse["accurate"] < 0.5 * min(mse["fast"], mse["interpolation"]), mse
    assert mse["fast"] < min(mse["interpolation"], mse["measurement"]), mse


@pytest.mark.parametrize("setting", ["fast", "accurate"])
def test_fusion_is_never_worse_than_its_inputs_on_a_real_scene(setting):
    """Tree (large dark textured areas): at the dark NOISY pixels the fused value's log2 error (the issue's
    metric) is below both the ND measurement's alone and the reconstruction's alone."""
    t = _scene("Tree")
    prof = profile.default(*t.shape)
    v, s = validity.classify(sensor.capture(t, prof, np.random.default_rng(4)), prof, dark_policy="weighted")
    known, noisy = validity.known_mask(s), validity.noisy_mask(s)
    lo, hi = validity.bounds(v, s)
    interp = reconstruction.reconstruct(v, known, lower=lo, upper=hi)
    fused = reconstruction.fuse_noisy(interp.copy(), v, known, noisy, prof, setting=setting)
    sel = noisy & (t < prof.l_min * prof.nd)
    assert sel.sum() > 1000
    peak = float(np.log2(prof.white))
    psnr = {k: metrics.log2_psnr(t[sel], a[sel], peak_stops=peak)
            for k, a in (("measurement", v), ("interpolation", interp), ("fused", fused))}
    assert psnr["fused"] > max(psnr["measurement"], psnr["interpolation"]) + 0.5, psnr


# ---- elements: the default chain uses the noise-aware policy and matches the core -----------------------

@pytest.mark.gst
def test_element_chain_weighted_default_matches_core(gst, tiny_clip):
    from conftest import raw_buffer, run_appsrc
    d, prof, raws = tiny_clip
    dur = 200_000_000
    caps = f"video/x-raw,format=GRAY16_LE,width={prof.width},height={prof.height},framerate=5/1"
    bufs = [raw_buffer(r, pts=i * dur, duration=dur) for i, r in enumerate(raws)]
    r = run_appsrc(f"nrvalidity profile={d / 'camera.json'} ! nrreconstruct method=preview", caps, bufs)
    assert r.error is None, r.error_text
    assert len(r.samples) == len(raws)
    for i, smp in enumerate(r.samples):
        vals, st = smp[3]
        v, s = validity.classify(raws[i], prof, dark_policy="weighted")
        noisy = (s & validity.REASON_MASK) == validity.NOISY
        assert noisy.any()
        np.testing.assert_array_equal(st[noisy], s[noisy] | validity.RECONSTRUCTED)
        lo, hi = validity.bounds(v, s)
        want = reconstruction.reconstruct(v, validity.known_mask(s), method="preview", lower=lo, upper=hi,
                                          noisy=noisy, noise=prof)
        np.testing.assert_allclose(vals, want, rtol=1e-5, atol=1e-3)
        assert np.isfinite(vals).all() and (vals >= 0).all()


def test_noisy_without_noise_model_is_a_clear_error():
    v = np.ones((8, 8), np.float32)
    k = np.ones((8, 8), bool)
    k[3, 3] = False
    with pytest.raises(ValueError, match="noise model"):
        reconstruction.reconstruct(v, k, noisy=~k)
    with pytest.raises(ValueError, match="shape"):
        reconstruction.reconstruct(v, k, noisy=np.zeros((4, 4), bool), noise=validity.default_noise())


def test_noisy_weights_are_the_noise_ratio_of_eq_4_7():
    """Joint FSE sample weights: factor x var_regular / var_ND at the measured level
    (Eq. 4-7): factor / ND^2 at black (read noise), towards factor / ND when shot noise dominates;
    0 at pixels that are not NOISY; at most 1 (a known pixel's weight)."""
    prof = profile.default(8, 8)
    m = np.array([[0.0, 50.0, 1e7, 300.0]], np.float32)
    noisy = np.array([[True, True, True, False]])
    w = reconstruction.noisy_weights(m, noisy, prof, 2.0)
    ratio = validity.measurement_variance(m, prof, regular=True) / validity.measurement_variance(m, prof)
    assert w[0, :3] == pytest.approx(2.0 * ratio[0, :3], rel=1e-5)
    assert w[0, 0] == pytest.approx(2.0 / prof.nd ** 2, rel=1e-5)
    assert w[0, 2] == pytest.approx(2.0 / prof.nd, rel=1e-3)
    assert w[0, 3] == 0.0
    assert reconstruction.noisy_weights(m, noisy, prof, 1e3).max() == 1.0


def test_reconstruct_noisy_joint_opt_in_keeps_measured_pixels():
    """reconstruct(noisy_joint=) on a real dark scene: measured pixels bit-exact, output finite and
    >= 0; a frame whose NOISY mask is empty gives the default's bits."""
    scene = io.read_luminance(shared_data("hdr", "Desk.exr"))
    prof = profile.default(96, 128, seed=3)
    t = simulate.view(scene, 96, 128, 0.3, simulate.Motion())
    t = t * np.float32(simulate.exposure_scale(scene, prof, 0))
    raw = sensor.capture(t, prof, np.random.default_rng(5))
    v, s = validity.classify(raw, prof, dark_policy="weighted")
    k, nz = validity.known_mask(s), validity.noisy_mask(s)
    lo, hi = validity.bounds(v, s)
    assert nz.any()
    out = reconstruction.reconstruct(v, k, lower=lo, upper=hi, noisy=nz, noise=prof, noisy_joint=2.0)
    assert np.array_equal(out[k], v[k])
    assert np.all(np.isfinite(out)) and out.min() >= 0.0
    none = np.zeros_like(nz)
    a = reconstruction.reconstruct(v, k, lower=lo, upper=hi, noisy=none, noise=prof, noisy_joint=2.0)
    assert np.array_equal(a, reconstruction.reconstruct(v, k, lower=lo, upper=hi))
