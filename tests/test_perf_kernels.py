"""The parallel per-frame kernels against independent references (numpy/scipy formulations, serial
loops): same numbers on random and edge inputs (all known, all missing, one known pixel, 1 x N, odd sizes),
in place and out of place, for any thread count. No timing here (benchmarks/stages.py measures speed)."""
import warnings

import numpy as np
import numba
import pytest
from scipy import ndimage

import crosstalk_reference
import tonemap_reference
import validity_reference
import reconstruction_reference as RR
from nrhdr_core import crosstalk, fse, profile as profiles, reconstruction as R, validity as V
import fse_reference  # tests/: numpy expectations of the fse passes

SHAPES = [(1, 1), (1, 9), (9, 1), (2, 2), (3, 5), (17, 33), (40, 63)]
SHARES = [0.0, 0.01, 0.5, 0.99]


def _masks(rng, shape):
    """Known masks: random at several missing shares, all missing, a single known pixel."""
    out = [rng.random(shape) >= p for p in SHARES]
    one = np.zeros(shape, bool)
    one[rng.integers(shape[0]), rng.integers(shape[1])] = True
    out.append(one)
    out.append(np.zeros(shape, bool))
    return out


@pytest.fixture
def threads():
    """Run the body at 1 and at the default thread count; restore afterwards."""
    old = numba.get_num_threads()
    yield [1, old] if old > 1 else [1]
    numba.set_num_threads(old)


# ---- pull-push -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("shape", SHAPES + [(64, 64), (101, 77), (600, 800)])   # 600 x 800: parallel levels
def test_preview_equals_the_pull_push_reference(shape, rng, threads):
    for k in _masks(rng, shape):
        if not k.any():
            continue
        v = (rng.random(shape, dtype=np.float32) * 1000 - 100).astype(np.float32)
        ref = RR.preview(v, k)
        for t in threads:
            numba.set_num_threads(t)
            assert np.array_equal(R.reconstruct(v, k, method="preview"), ref)
            inplace = v.copy()
            assert R.reconstruct(inplace, k, method="preview", out=inplace) is inplace
            assert np.array_equal(inplace, ref)


def test_preview_ignores_nan_at_missing_pixels(rng):
    """Values under missing pixels are never read."""
    v = rng.random((20, 30), dtype=np.float32)
    k = rng.random(v.shape) < 0.5
    a = R.reconstruct(v, k, method="preview")
    v2 = v.copy()
    v2[~k] = np.nan
    assert np.array_equal(R.reconstruct(v2, k, method="preview"), a) and np.isfinite(a).all()


def test_preview_fill_that_overflows_takes_the_nearest_known_value(rng):
    """A 3 x 3 sum beyond float32's range is repaired by the nearest known value: a constant frame near
    float32's maximum stays that constant, through `reconstruct` and `reconstruct_frame`."""
    big = np.float32(3e38)
    v = np.full((20, 30), big, np.float32)
    s = np.where(rng.random(v.shape) < 0.4, V.DISCARDED, V.VALID).astype(np.uint8)
    assert np.array_equal(R.reconstruct(v, s == V.VALID, method="preview"), v)
    vv = np.where(s == V.VALID, big, np.float32(0)).astype(np.float32)
    assert R.reconstruct_frame(vv, s, method="preview") == (s != V.VALID).sum()
    assert np.array_equal(vv, v)


# ---- nearest -----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("shape", SHAPES + [(64, 64), (101, 77)])
def test_nearest_is_an_exact_nearest_known_pixel(shape, rng, threads):
    """Each output is the value of a known pixel at the exact Euclidean distance scipy's EDT reports
    (ties may pick another pixel at the same distance)."""
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w]
    v = (yy * 1000 + xx).astype(np.float32)         # the value encodes the source position
    for k in _masks(rng, shape):
        if not k.any():
            continue
        d_ref = ndimage.distance_transform_edt(~k) ** 2
        for t in threads:
            numba.set_num_threads(t)
            out = R.reconstruct(v, k, method="nearest")
            sy, sx = (out // 1000).astype(int), (out % 1000).astype(int)
            assert k[sy, sx].all()
            assert np.allclose((sy - yy) ** 2 + (sx - xx) ** 2, d_ref)
            assert np.array_equal(out[k], v[k])
            inplace = v.copy()
            R.reconstruct(inplace, k, method="nearest", out=inplace)
            assert np.array_equal(inplace, out)


# ---- dispatcher ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("method", ["preview", "nearest", "linear"])
def test_reconstruct_out_in_place_equals_out_of_place(method, rng):
    v = rng.random((30, 41), dtype=np.float32) * 50
    k = rng.random(v.shape) < 0.5
    lo = np.where(~k & (rng.random(v.shape) < 0.3), 40.0, np.nan).astype(np.float32)
    hi = np.where(~k & (rng.random(v.shape) < 0.3), 5.0, np.nan).astype(np.float32)
    a = R.reconstruct(v, k, method=method, lower=lo, upper=hi)
    buf = np.empty_like(v)
    b = R.reconstruct(v, k, method=method, lower=lo, upper=hi, out=buf)
    c = v.copy()
    R.reconstruct(c, k, method=method, lower=lo, upper=hi, out=c)
    assert b is buf and np.array_equal(a, b) and np.array_equal(a, c)
    if method == "preview":
        assert np.array_equal(a, RR.preview(v, k, lo, hi))
    assert np.array_equal(a[k], v[k])
    with pytest.raises(ValueError, match="out must be"):
        R.reconstruct(v, k, method=method, out=np.empty(v.shape, np.float64))


def test_reconstruct_rejects_non_finite_known_values_and_bounds(rng):
    v = rng.random((6, 7)).astype(np.float64)
    k = np.ones(v.shape, bool)
    k[0, 0] = False
    v[1, 1] = np.inf
    with pytest.raises(ValueError, match="NaN or Inf"):
        R.reconstruct(v, k, method="preview")
    v[1, 1] = 0.5
    v[0, 0] = np.nan                                   # a missing pixel may hold anything
    assert np.isfinite(R.reconstruct(v, k, method="preview")).all()
    lo = np.full(v.shape, np.nan, np.float32)
    lo[2, 2] = -np.inf
    with pytest.raises(ValueError, match="Inf"):
        R.reconstruct(v, k, method="preview", lower=lo)


# ---- validity ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("shape", SHAPES)
def test_prepare_known_bounds_write_back_equal_numpy(shape, rng, threads):
    st = rng.integers(0, 256, shape).astype(np.uint8)
    v = rng.standard_normal(shape).astype(np.float32)
    reason = st & V.REASON_MASK
    miss = (reason != V.VALID) & ((st & V.RECONSTRUCTED) == 0)
    lo_ref = np.where(reason == V.CLIPPED, v, np.nan).astype(np.float32)
    validity_reference.clip_lower_bound(v, st, lo_ref)     # clipped regular pixels amid clipped ND pixels
    hi_ref = np.where(reason == V.DARK, v, np.nan).astype(np.float32)
    res = rng.standard_normal(shape).astype(np.float32)
    for t in threads:
        numba.set_num_threads(t)
        n, k, lo, hi = V.prepare(v, st)
        assert n == miss.sum() and np.array_equal(k, reason == V.VALID)
        assert np.array_equal(lo, lo_ref, equal_nan=True) and np.array_equal(hi, hi_ref, equal_nan=True)
        n2, _, lo2, hi2 = V.prepare(v, st, with_bounds=False)
        assert n2 == n and lo2 is None and hi2 is None
        assert np.array_equal(V.known_mask(st), reason == V.VALID)
        b = V.bounds(v, st)
        assert np.array_equal(b[0], lo_ref, equal_nan=True) and np.array_equal(b[1], hi_ref, equal_nan=True)
        vv, ss = v.copy(), st.copy()
        assert V.write_back(vv, ss, res) == miss.sum()
        assert np.array_equal(vv, np.where(miss, res, v))
        assert np.array_equal(ss, np.where(miss, st | V.RECONSTRUCTED, st))


def test_prepare_fills_given_arrays_and_checks_them(rng):
    st = rng.integers(0, 8, (5, 6)).astype(np.uint8)
    v = rng.random((5, 6), dtype=np.float32)
    k, lo, hi = np.empty((5, 6), bool), np.empty((5, 6), np.float32), np.empty((5, 6), np.float32)
    _, k2, lo2, hi2 = V.prepare(v, st, known=k, lower=lo, upper=hi)
    assert k2 is k and lo2 is lo and hi2 is hi
    with pytest.raises(ValueError, match="lower"):
        V.prepare(v, st, lower=np.empty((5, 6), np.float64))


@pytest.mark.parametrize("method", ["preview", "nearest", "fse"])
@pytest.mark.parametrize("use_bounds", [True, False])
def test_reconstruct_frame_equals_its_contract(method, use_bounds, rng):
    """`reconstruct_frame` against `reconstruct` on the state's known mask and bounds, then written back
    (tests/reconstruction_reference.py `frame`), with and without earlier RECONSTRUCTED pixels."""
    h, w = 24, 37
    v = rng.random((h, w), dtype=np.float32) * 100
    st = rng.choice(np.array([V.VALID, V.CLIPPED, V.DARK, V.DISCARDED], np.uint8), (h, w), p=[.5, .2, .2, .1])
    st |= np.where(rng.random((h, w)) < 0.5, V.ATTENUATED, 0).astype(np.uint8)
    preset = "preview" if method == "fse" else "balanced"
    for already in (False, True):
        s = st.copy()
        if already:   # some pixels reconstructed earlier: kept as they are
            s[(st & V.REASON_MASK != V.VALID) & (rng.random((h, w)) < 0.3)] |= V.RECONSTRUCTED
        n_ref, ref_v, ref_s = RR.frame(v, s, method, use_bounds, preset=preset)
        vv, ss = v.copy(), s.copy()
        n = R.reconstruct_frame(vv, ss, method=method, preset=preset, use_bounds=use_bounds)
        assert n == n_ref == V.missing_mask(s).sum()
        assert np.array_equal(vv, ref_v) and np.array_equal(ss, ref_s)
    full = np.zeros((h, w), np.uint8)
    vv = v.copy()
    assert R.reconstruct_frame(vv, full, method=method) == 0 and np.array_equal(vv, v)


# ---- crosstalk lut ---------------------------------------------------------------------------------------------
def test_crosstalk_lut_equals_the_binary_search_reference(rng, threads):
    h, w, kn = 13, 17, 9
    prof = profiles.default(h, w)
    top = float(prof.clip_code) - float(prof.black_level)
    flux = np.concatenate([[0.0], top * prof.nd * np.geomspace(1e-3, 1.0, kn - 1)])
    s = np.where(prof.mask, prof.nd, 1.0)[:, :, None]
    codes = (flux[None, None, :] / s * (1.0 + 0.05 * rng.standard_normal((h, w)))[:, :, None]).astype(np.float32)
    q, qs, qo = crosstalk.quantize_codes(codes, int(prof.clip_code) + 1)
    n_knots = rng.integers(0, kn + 1, (h, w)).astype(np.int32)
    clip_flux = np.where(rng.random((h, w)) < 0.5, np.nan, 1.3 * top).astype(np.float32)
    calib = crosstalk.CrosstalkCalibration(
        codes_q=q, qscale=qs, qoffset=qo, n_knots=n_knots, knot_flux=flux, clip_flux=clip_flux,
        nd=float(prof.nd), black_level=float(prof.black_level), clip_code=int(prof.clip_code),
        sig_e=np.array([0.0, 1.0], np.float32), sigma=np.zeros((8, 2), np.float32),
        alpha=np.ones((h, w), np.float32))
    px = prof.replace(crosstalk=calib)
    # codes from below the dark level to above the clip level, every state
    scale = np.where(prof.mask, prof.nd, 1.0).astype(np.float32)
    v0 = (rng.uniform(-20, top * 1.2, (h, w)).astype(np.float32) * scale).astype(np.float32)
    st0 = rng.choice(np.array([V.VALID, V.CLIPPED, V.DARK, V.DISCARDED], np.uint8), (h, w), p=[.7, .1, .1, .1])
    st0 |= np.where(prof.mask, V.ATTENUATED, 0).astype(np.uint8)
    v_ref, s_ref = crosstalk_reference.lut_correct(v0, st0, calib, prof.nd)
    for t in threads:
        numba.set_num_threads(t)
        vv, ss = v0.copy(), st0.copy()
        crosstalk.correct(vv, ss, px, mode="lut")
        assert np.array_equal(ss, s_ref)
        assert np.array_equal(vv, v_ref)


# ---- fse wrapper passes -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("shape", SHAPES)
def test_fse_wrapper_passes_equal_numpy(shape, rng, threads):
    for k in _masks(rng, shape):
        v = (rng.random(shape) * 200 - 50).astype(np.float32)
        for t in threads:
            numba.set_num_threads(t)
            nk, kmin, kmax, minpos = fse.domain.stats(v, k)
            assert nk == k.sum()
            if k.any():
                assert kmin == v[k].min() and kmax == v[k].max()
                pos = v[k][v[k] > 0]
                assert minpos == (pos.min() if pos.size else 0.0)
            for logd in (False, True):
                work, state = fse.domain.prep(v, k, logd, np.float32(0.5))
                assert np.array_equal(state, k.astype(np.uint8))
                exp = np.where(k, np.log2(np.maximum(v, np.float32(0.5))) if logd else v, 0).astype(np.float32)
                np.testing.assert_allclose(work, exp, rtol=1e-6)
                out = np.zeros_like(v)
                st2 = state.copy()
                st2[~k] = np.where(rng.random((~k).sum()) < 0.5, 2, 0)
                left = fse.domain.finish(out, work, st2, logd)
                assert left == (st2 == 0).sum()
                rec = st2 == 2
                np.testing.assert_allclose(out[rec], (2.0 ** work[rec]) if logd else work[rec], rtol=1e-6)


def test_fse_result_does_not_depend_on_thread_count(rng, threads):
    v = rng.random((320, 328), dtype=np.float32) * 255   # large enough for the multi-thread path
    k = rng.random(v.shape) < 0.5
    outs = []
    for t in threads:
        numba.set_num_threads(t)
        outs.append(fse.fse_reconstruct(v, k, preset="fast"))
    assert all(np.array_equal(outs[0], o) for o in outs[1:])


# ---- tone mapping ---------------------------------------------------------------------------------------------
def test_fast_log_tonemap_matches_the_libm_kernel(rng):
    from nrhdr_core import tonemap
    v = np.exp(rng.uniform(np.log(1e-4), np.log(5e4), (61, 67))).astype(np.float32)
    v[::7, ::5] = np.nan
    v[::11, ::3] = -2.0
    v[0, :5] = [0.0, 1e-30, 26000.0, 26000.0 * (1 + 1e-7), np.inf]
    for dt in (np.uint8, np.uint16):
        for q in (1000.0, 100.0, 2.0):
            a, b = np.empty(v.shape, dt), np.empty(v.shape, dt)
            tonemap_reference.log_tonemap(v, 26000.0, q, a)
            tonemap.log_tonemap(v, 26000.0, contrast=q, out=b)
            d = np.abs(a.astype(int) - b.astype(int))
            assert d.max() <= (0 if dt == np.uint8 else 1) and (d > 0).mean() < 1e-3


def test_import_sets_passive_openmp_wait_unless_the_user_chose():
    """Spinning OpenMP workers steal one of the two cores between parallel regions (docs/BENCHMARKS.md)."""
    import os
    import subprocess
    import sys
    code = "import os, nrhdr_core; print(os.environ['OMP_WAIT_POLICY'])"
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "PASSIVE"
    env["OMP_WAIT_POLICY"] = "ACTIVE"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "ACTIVE"


def test_crosstalk_lut_on_a_smooth_frame_equals_the_reference(rng, threads):
    """The full LUT on a smooth frame with noise (codes across every knot), every state, odd size."""
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import stages
    h, w = 37, 131
    prof = profiles.default(h, w)
    px = prof.replace(crosstalk=stages.synthetic_calibration(prof, 24, seed=3))
    top = float(prof.clip_code) - float(prof.black_level)
    yy, xx = np.mgrid[0:h, 0:w]
    base = np.exp(np.log(top * 3) * (xx / w)) * (1 + 0.1 * rng.standard_normal((h, w)))
    v0 = np.where(prof.mask, base, base / prof.nd).astype(np.float32) * np.where(prof.mask, prof.nd, 1).astype(np.float32)
    st0 = rng.choice(np.array([V.VALID, V.CLIPPED, V.DARK, V.DISCARDED], np.uint8), (h, w), p=[.7, .1, .1, .1])
    st0 |= np.where(prof.mask, V.ATTENUATED, 0).astype(np.uint8)
    ref_v, ref_s = crosstalk_reference.lut_correct(v0, st0, px.crosstalk, prof.nd)
    for t in threads:
        numba.set_num_threads(t)
        vv, ss = v0.copy(), st0.copy()
        crosstalk.correct(vv, ss, px, mode="lut")
        assert np.array_equal(vv, ref_v) and np.array_equal(ss, ref_s)


# ---- fse driver: fused log-domain wrapper passes -------------------------------------------------
def _hdr_capture(h, w, seed):
    """A sensor capture of the synthetic HDR scene (clipped and dark pixels with their bounds, read and shot
    noise): values, known mask, lower, upper as the element hands them to `reconstruct`."""
    from nrhdr_core import sensor, simulate
    from nrhdr_core.scene import synthetic_hdr_scene
    from nrhdr_core.simulate import Motion
    scene = synthetic_hdr_scene(max(h, 600), max(w, 800))
    prof = profiles.default(h, w)
    flux = simulate.view(scene, h, w, 0.3, Motion()) * np.float32(simulate.exposure_scale(scene, prof, 0.0))
    raw = sensor.capture(flux, prof, np.random.default_rng(seed))
    values, state = V.classify(raw, prof)
    lo, hi = V.bounds(values, state)
    return values, V.known_mask(state), lo, hi, flux


def _hdr_cases(rng):
    v, k, lo, hi, flux = _hdr_capture(96, 136, 3)
    yield v, k, lo, hi                                   # the sensor case: clipped + dark pixels, bounds
    yield v, k, None, None                               # no bounds
    yield v, k, np.full_like(lo, np.nan), hi             # lower all NaN (not used), upper used
    kr = rng.random(v.shape) < 0.25                      # sparse known (sparse_below: 32 x 32 window)
    yield flux.astype(np.float32), kr, None, None
    yield (v * np.float32(1e-3)).astype(np.float32), k, lo * np.float32(1e-3), hi * np.float32(1e-3)  # scale


def test_log_offset_equals_the_numpy_statistics(rng):
    """Same statistics, same subsample: the same offset c, bit for bit (8-bit data, HDR data, big frames)."""
    cases = [(v, k, lo) for v, k, lo, _hi in _hdr_cases(rng)]
    img8 = np.floor(rng.random((50, 70)) * 256).astype(np.float32)
    cases.append((img8, rng.random(img8.shape) < 0.6, None))
    big = (2.0 ** (rng.random((700, 640)) * 14)).astype(np.float32)      # step 1 -> strided rows (step > 1)
    cases.append((big, rng.random(big.shape) < 0.5, None))
    cases.append((big[:, :2].copy(), rng.random((700, 2)) < 0.5, None))  # narrower than a 3-pixel triple
    for v, k, lo in cases:
        assert fse.log_offset(v, k, 2.0, lo) == fse_reference.log_offset_reference(v, k, 2.0, lo)


@pytest.mark.parametrize("preset", ["fast", "preview", "balanced"])
def test_fse_fused_driver_equals_the_reference(preset, rng, threads):
    """The fused driver against the numpy passes it replaces: the same output to float rounding (the log2 of
    the bounds is libm's instead of numpy's SIMD one: <= 1 ulp), known pixels bit-exact, the same PSNR."""
    for v, k, lo, hi in _hdr_cases(rng):
        ref = fse_reference.fse_reconstruct_reference(v, k, lo, hi, preset=preset)
        for t in threads:
            numba.set_num_threads(t)
            out = fse.fse_reconstruct(v, k, lo, hi, preset=preset)
            assert np.array_equal(out[k], v[k])
            np.testing.assert_allclose(out, ref, rtol=1e-5, atol=1e-6 * float(np.abs(v).max()))


def test_fse_local_bound_passes_equal_scipy(rng, threads):
    """`_prep_local` + `_bounds_local` against scipy's min/max filters and `_merge_bounds` (the reference's
    passes), at the frame edges and where no known pixel is near."""
    for shape in [(1, 1), (1, 9), (9, 1), (3, 5), (17, 33), (40, 63)]:
        for k in _masks(rng, shape):
            v = (2.0 ** (rng.random(shape) * 12)).astype(np.float32)
            lo = np.where(rng.random(shape) < 0.1, v * 2, np.nan).astype(np.float32)
            hi = np.where(rng.random(shape) < 0.1, v * 0.5, np.nan).astype(np.float32)
            c, floor = np.float32(3.0), np.float32(3.0)
            for size in (3, 5, 9):
                work_r, state_r = fse.domain.prep(v + c, k, True, floor)
                llo, lhi = fse_reference.local_bounds(work_r, state_r, size, 1.0, True)
                lor = np.log2(np.maximum(np.where(np.isnan(lo), -np.inf, lo) + c, floor)).astype(np.float32)
                hir = np.log2(np.maximum(np.where(np.isnan(hi), np.inf, hi) + c, floor)).astype(np.float32)
                elo, ehi = fse_reference.merge_bounds(lor, hir, True, True, llo, lhi, shape)
                for t in threads:
                    numba.set_num_threads(t)
                    work, state = np.empty(shape, np.float32), np.empty(shape, np.uint8)
                    a, b = np.empty(shape, np.float32), np.empty(shape, np.float32)
                    fse.bounds.prep_local(v, k, (c, floor), size // 2, (work, state, a, b))
                    assert np.array_equal(state, state_r)
                    np.testing.assert_allclose(work, work_r, rtol=1e-6)
                    glo, ghi = np.full(shape, np.nan, np.float32), np.full(shape, np.nan, np.float32)
                    fse.bounds.bounds_local((a, b), size // 2, np.float32(1.0), (lo, hi, True, True), (c, floor),
                                            (glo, ghi), state)
                    # the missing pixels' bounds (the only ones the block kernels read); known ones untouched
                    m = state == 0
                    np.testing.assert_allclose(glo[m], elo[m], rtol=1e-6)
                    np.testing.assert_allclose(ghi[m], ehi[m], rtol=1e-6)
                    assert np.isnan(glo[~m]).all() and np.isnan(ghi[~m]).all()


def test_reconstruct_fse_is_fse_clamped_to_the_data_range(rng, threads):
    """`reconstruct(method="fse")` (FSE in place in its output array, parallel clamp) is `fse_reconstruct`
    clamped to the data range and the bounds (tests/reconstruction_reference.py), bit for bit, any thread
    count."""
    for v, k, lo, hi in _hdr_cases(rng):
        res = fse.fse_reconstruct(v, k, lo, hi, preset="fast")
        assert np.isfinite(res).all()
        exp = RR.apply_bounds(RR.clamp_to_data(res, v, k, lo), k, lo, hi)
        for t in threads:
            numba.set_num_threads(t)
            out = R.reconstruct(v, k, method="fse", preset="fast", lower=lo, upper=hi)
            assert np.array_equal(out, exp)
            inplace = v.copy()
            assert R.reconstruct(inplace, k, method="fse", preset="fast", lower=lo, upper=hi,
                                 out=inplace) is inplace
            assert np.array_equal(inplace, out)


def test_lut_eval_equals_the_binary_search_at_the_knots(rng):
    """`crosstalk.lut_eval` (quantised threshold + count) against the binary search of the reference for codes
    exactly at every knot, one float32 step either side, between knots and outside the range."""
    h, w, kn = 3, 4, 12
    flux = np.concatenate([[0.0], 4094.0 * 6.35 * np.geomspace(1e-3, 1.0, kn - 1)])
    codes = (flux[None, None, :] / 6.35 * (1.0 + 0.05 * rng.standard_normal((h, w)))[:, :, None]).astype(np.float32)
    codes[0, 0, :] = np.arange(kn) * 0.0625 + 3.0          # knots 1 quantisation step apart
    q, qs, qo = crosstalk.quantize_codes(codes, 4095)
    qs, qo = np.float32(qs), np.float32(qo)
    kf = flux.astype(np.float64)
    for y in range(h):
        for x in range(w):
            cq = q[y, x].astype(np.float32) * qs - qo
            for n in (0, 1, 2, 5, kn):
                cs = cq[:max(n, 1)]
                ms = [cs, np.nextafter(cs, np.float32(np.inf)), np.nextafter(cs, np.float32(-np.inf)),
                      (cs[:-1] + cs[1:]) / 2 if n > 1 else cs, np.array([-5.0, 1e5, np.nan], np.float32)]
                for m in np.concatenate(ms).astype(np.float32):
                    for cflux in (np.float32(np.nan), np.float32(2e5)):
                        scale = crosstalk.LutScale(qs, qo, np.float32(4094.0))
                        a = crosstalk.lut_eval(q, kf, scale, y, x, n, cflux, m)
                        b = crosstalk_reference.lut_eval(cq, n, kf, np.float32(4094.0), cflux, m)
                        assert a[1] == b[1] and (a[0] == b[0] or (np.isnan(a[0]) and np.isnan(b[0])))


def _fuse_reference(out, values, known, noisy, noise, texture=1.0, size=5):
    """fuse_noisy written with numpy/scipy window sums (float64), the formula of its docstring."""
    from scipy import ndimage
    kf = known.astype(np.float64)
    a = values.astype(np.float64) * kf
    box = lambda x: ndimage.uniform_filter(x, size, mode="constant", cval=0.0) * size * size  # noqa: E731
    n, t1, t2 = box(kf), box(a), box(a * a)
    g = float(noise.gain)
    floor = g * g * float(noise.read_noise) ** 2 + 1.0 / 12.0
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(n > 0.5, t1 / np.maximum(n, 1), 0.0)
        var = np.where(n > 0.5, t2 / np.maximum(n, 1) - mean * mean, 0.0)
    excess = np.where(n > 0.5, np.maximum(var - (g * np.maximum(mean, 0.0) + floor), 0.0), 0.0)
    gv = out.astype(np.float64)
    gp = np.maximum(gv, 0.0)
    var_g = (g * gp + floor) / 4.0 + texture * excess
    var_m = noise.nd * g * gp + noise.nd ** 2 * floor
    f = gv + var_g / (var_g + var_m) * (values.astype(np.float64) - gv)
    res = out.copy()
    res[noisy] = np.maximum(f, 0.0)[noisy].astype(np.float32)
    return res


@pytest.mark.parametrize("shape", [(1, 1), (3, 40), (37, 29), (64, 80)])
def test_fuse_noisy_equals_the_window_formula(shape, rng, threads):
    from types import SimpleNamespace
    noise = SimpleNamespace(gain=0.55, read_noise=2.0, nd=6.35)
    values = (rng.random(shape) * 3000).astype(np.float32)
    known = rng.random(shape) < 0.5
    noisy = ~known & (rng.random(shape) < 0.6)
    out0 = (values + rng.standard_normal(shape).astype(np.float32) * 50).astype(np.float32)
    ref = _fuse_reference(out0, values, known, noisy, noise)
    for t in threads:
        numba.set_num_threads(t)
        got = R.fuse_noisy(out0.copy(), values, known, noisy, noise, setting="fast")   # the formula above
        np.testing.assert_allclose(got, ref, rtol=2e-6, atol=1e-3)
        assert np.array_equal(got[~noisy], out0[~noisy])


# ---- the fused preview frame path ------------------------------------------------------------------------------
def _noise():
    from types import SimpleNamespace
    return SimpleNamespace(gain=0.55, read_noise=2.0, nd=6.35)


def _both(v, s, use_bounds, noise, method="preview"):
    """(n, values, state) of reconstruct_frame (the fused preview passes) and of its contract."""
    a_v, a_s = v.copy(), s.copy()
    na = R.reconstruct_frame(a_v, a_s, method=method, use_bounds=use_bounds, noise=noise)
    return (na, a_v, a_s), RR.frame(v, s, "preview", use_bounds, noise)


@pytest.mark.parametrize("shape", SHAPES + [(101, 77)])
def test_preview_frame_equals_its_contract(shape, rng, threads):
    """Masks, NOISY fusion, clip bounds (with the clipped-neighbour rule), data-range clamp, earlier
    RECONSTRUCTED pixels kept: the fused passes give `reconstruct`'s bits, any thread count."""
    reasons = np.array([V.VALID, V.CLIPPED, V.DARK, V.DISCARDED, V.NOISY], np.uint8)
    for p in ([.5, .2, .1, .1, .1], [.1, .6, .1, .1, .1], [.02, .9, .03, .03, .02], [0, .5, .5, 0, 0]):
        v = (rng.random(shape, dtype=np.float32) * 100 - 5).astype(np.float32)
        st = rng.choice(reasons, shape, p=p) | np.where(rng.random(shape) < 0.5, V.ATTENUATED, 0).astype(np.uint8)
        for already in (False, True):
            s = st.copy()
            if already:
                s[(st & V.REASON_MASK != V.VALID) & (rng.random(shape) < 0.3)] |= V.RECONSTRUCTED
            for t in threads:
                numba.set_num_threads(t)
                for use_bounds in (True, False):
                    for noise in (_noise(), None):
                        with warnings.catch_warnings():
                            warnings.simplefilter("ignore", R.ReconstructionWarning)
                            (na, av, as_), (nb, bv, bs) = _both(v, s, use_bounds, noise)
                        assert na == nb == V.missing_mask(s).sum()
                        assert np.array_equal(av, bv) and np.array_equal(as_, bs)


def test_preview_frame_on_a_simulated_frame_equals_its_contract(rng):
    """A frame of the sensor model with big clipped areas (bright sky of the synthetic scene, ND pixels
    clipped too) and dark NOISY pixels, as nrvalidity dark-policy=weighted makes it."""
    from nrhdr_core import profile as P, scene, sensor, simulate
    h, w = 270, 480
    prof = P.default(h, w, seed=1)
    sc = scene.synthetic_hdr_scene(400, 600)
    flux = simulate.view(sc, h, w, 0.3, simulate.Motion()) * np.float32(simulate.exposure_scale(sc, prof, 2.0))
    raw = sensor.capture(flux, prof, rng)
    v, s = V.classify(raw, prof, dark_policy="weighted")
    r = s & V.REASON_MASK
    clipped_regular = (s & (V.ATTENUATED | V.REASON_MASK)) == V.CLIPPED
    assert (r == V.NOISY).any() and clipped_regular.sum() > 1000      # the cases this test is for
    for use_bounds in (False, True):
        (na, av, as_), (nb, bv, bs) = _both(v, s, use_bounds, prof)
        assert na == nb > 0 and np.array_equal(av, bv) and np.array_equal(as_, bs)
    calls = []

    def choose(share):
        calls.append(share)
        return "preview", "fast"
    vv, ss = v.copy(), s.copy()
    assert R.reconstruct_frame(vv, ss, method=choose, noise=prof) == nb and len(calls) == 1
    assert np.array_equal(vv, bv) and abs(calls[0] - V.missing_mask(s).mean()) < 1e-12


def test_preview_frame_odd_frames(rng):
    """Non-finite values (`reconstruct`'s error), no known pixel (its warning), a method chosen per frame
    that is not the preview."""
    v = rng.random((20, 30), dtype=np.float32)
    s = np.where(rng.random(v.shape) < 0.4, V.DISCARDED, V.VALID).astype(np.uint8)
    bad = v.copy()
    ky, kx = np.nonzero(s == V.VALID)
    bad[ky[0], kx[0]] = np.nan
    with pytest.raises(ValueError, match="NaN or Inf"):
        R.reconstruct_frame(bad, s.copy(), method="preview")
    with pytest.warns(R.ReconstructionWarning):
        R.reconstruct_frame(v.copy(), np.full(v.shape, V.CLIPPED, np.uint8), method="preview")
    vv, ss = v.copy(), s.copy()
    n = R.reconstruct_frame(vv, ss, method=lambda share: ("nearest", "fast"))
    n_ref, ref_v, ref_s = RR.frame(v, s, "nearest")
    assert n == n_ref and np.array_equal(vv, ref_v) and np.array_equal(ss, ref_s)
