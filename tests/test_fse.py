"""FSE (nrhdr_core/fse/) against independent expectations: sparse sinusoid sums, constants, scale
invariance, bounds, presets, determinism, and real images against Delaunay-linear / OpenCV FSR_FAST.
Small images and the fast presets only; no timing assertions (speed is the benchmark's job)."""
from __future__ import annotations


import numpy as np
import pytest

from conftest import shared_data
from nrhdr_core import reconstruct
from nrhdr_core import fse

def psnr(ref, test, peak):
    mse = np.mean((np.asarray(ref, np.float64) - np.asarray(test, np.float64)) ** 2)
    return float("inf") if mse == 0 else 10 * np.log10(peak * peak / mse)


def sinusoids(h=64, w=80):
    """A sum of three 2-D sinusoids: sparse in the Fourier domain."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    img = (100.0 + 40.0 * np.cos(2 * np.pi * (xx / 16.0 + yy / 32.0))
           + 25.0 * np.sin(2 * np.pi * (xx / 40.0 - yy / 11.0) + 0.3)
           + 15.0 * np.cos(2 * np.pi * yy / 8.0))
    return img.astype(np.float32)


@pytest.fixture
def mask50():
    return np.random.default_rng(7).random((64, 80)) < 0.5


@pytest.mark.parametrize("preset", ["fast", "balanced"])
def test_sparse_sinusoids_reconstruct_well(preset, mask50):
    img = sinusoids()
    out = reconstruct(img, mask50, method="fse", preset=preset)
    lin = reconstruct(img, mask50, method="linear")
    p_fse = psnr(img, out, 255.0)
    p_lin = psnr(img, lin, 255.0)
    assert p_fse > 38.0, p_fse
    assert p_fse > p_lin + 3.0, (p_fse, p_lin)


def test_known_pixels_bit_exact_and_dtype(mask50):
    rng = np.random.default_rng(1)
    img = (sinusoids() + rng.normal(0, 3, (64, 80))).astype(np.float64)
    out = reconstruct(img, mask50, method="fse", preset="fast")
    assert out.dtype == np.float32 and out.shape == img.shape
    assert np.array_equal(out[mask50], img.astype(np.float32)[mask50])
    assert np.isfinite(out).all()


@pytest.mark.parametrize("preset", list(fse.FSE_PRESETS))
def test_constant_image_is_exact(preset, mask50):
    img = np.full((64, 80), 37.125, np.float32)
    out = reconstruct(img, mask50, method="fse", preset=preset)
    assert np.array_equal(out, img)


@pytest.mark.parametrize("k", [2.0 ** -12, 1000.0, 3.7e5])
def test_scale_invariance(k, mask50):
    img = sinusoids()
    a = reconstruct(img, mask50, method="fse", preset="fast")
    b = reconstruct(img * np.float32(k), mask50, method="fse", preset="fast")
    err = np.abs(b.astype(np.float64) / k - a)
    assert err.max() < 1e-3 * (img.max() - img.min()), err.max()


def test_bounds_are_respected_and_help(mask50):
    img = sinusoids()
    lower = np.full(img.shape, np.nan, np.float32)
    upper = np.full(img.shape, np.nan, np.float32)
    hi_px = (~mask50) & (img > 140)
    lo_px = (~mask50) & (img < 70)
    lower[hi_px] = 140.0
    upper[lo_px] = 70.0
    out = reconstruct(img, mask50, method="fse", preset="fast", lower=lower, upper=upper)
    assert (out[hi_px] >= 140.0).all() and (out[lo_px] <= 70.0).all()
    free = reconstruct(img, mask50, method="fse", preset="fast")
    assert psnr(img, out, 255) >= psnr(img, free, 255) - 1e-6


def test_presets_are_explicit_and_overridable(mask50):
    for name, p in fse.FSE_PRESETS.items():
        for key in ("window", "min_block", "max_block", "gamma", "delta", "rho", "iter_c", "iter_min",
                    "iter_max", "prior", "domain", "use_bounds"):
            assert key in p, (name, key)
    assert fse.resolve_params("fast", gamma=0.3)["gamma"] == 0.3
    with pytest.raises(TypeError):
        fse.resolve_params("fast", no_such_parameter=1)
    with pytest.raises(ValueError):
        fse.resolve_params("nonexistent")
    img = sinusoids()
    a = reconstruct(img, mask50, method="fse", preset="fast", iter_max=4, iter_min=4)
    b = reconstruct(img, mask50, method="fse", preset="fast")
    assert not np.array_equal(a, b)


def test_deterministic_across_runs_and_threads():
    numba = pytest.importorskip("numba")
    rng = np.random.default_rng(3)
    # large enough (thousands of 4 x 4 leaves) for the parallel path to be taken with > 1 thread
    img = (sinusoids(320, 288) + rng.normal(0, 5, (320, 288))).astype(np.float32)
    known = rng.random(img.shape) < 0.4
    old = numba.get_num_threads()
    try:
        outs = []
        for nt in sorted({1, old}):
            numba.set_num_threads(nt)
            outs.append(reconstruct(img, known, method="fse", preset="balanced"))
            outs.append(reconstruct(img, known, method="fse", preset="balanced"))
    finally:
        numba.set_num_threads(old)
    for o in outs[1:]:
        assert np.array_equal(o, outs[0])


def test_structured_hole_is_filled_from_the_border():
    """A large clipped-like hole (no known pixel inside the support of its centre blocks) is filled
    by the processing order from its border inwards; a smooth gradient stays smooth."""
    yy, xx = np.mgrid[0:96, 0:96].astype(np.float32)
    img = 50.0 + xx + 0.5 * yy
    known = np.ones(img.shape, bool)
    known[20:76, 20:76] = False
    out = reconstruct(img, known, method="fse", preset="fast")
    assert np.isfinite(out).all()
    assert out.min() >= img.min() - 1.0 and out.max() <= img.max() + 1.0
    pull_push = reconstruct(img, known, method="preview")
    assert psnr(img, out, 255) > 30.0
    assert psnr(img, out, 255) > psnr(img, pull_push, 255) + 3.0


def test_chain_warmup_runs_fse():
    """The one warm-up entry point compiles FSE's kernels (presets, log domain, skipped pixels, fallback)."""
    from nrhdr_core import chain
    chain.warmup(chain.ChainSettings(method="fse"), stages=("reconstruction",))


def _gray(path):
    import OpenImageIO as oiio
    a = oiio.ImageBuf(str(path)).get_pixels(oiio.FLOAT)
    if a.ndim == 3 and a.shape[2] >= 3:
        a = a[..., :3] @ np.array([0.299, 0.587, 0.114])
    elif a.ndim == 3:
        a = a[..., 0]
    return np.round(a * 255.0).astype(np.float32)


def test_kodak_crop_beats_linear_and_opencv_fsr_fast():
    img = _gray(shared_data("kodak", "kodim03.png"))[100:228, 200:328]
    known = np.random.default_rng(11).random(img.shape) < 0.5
    out = reconstruct(img, known, method="fse", preset="balanced")
    lin = reconstruct(img, known, method="linear")
    p_fse, p_lin = psnr(img, out, 255), psnr(img, lin, 255)
    assert p_fse > p_lin + 0.5, (p_fse, p_lin)
    cv2 = pytest.importorskip("cv2")
    if not hasattr(cv2, "xphoto"):
        pytest.skip("opencv-contrib (xphoto) not installed")
    src = img.astype(np.uint8)
    src[~known] = 0
    dst = np.zeros_like(src)
    cv2.xphoto.inpaint(src, known.astype(np.uint8) * 255, dst, cv2.xphoto.INPAINT_FSR_FAST)
    p_cv = psnr(img, dst, 255)
    assert p_fse > p_cv, (p_fse, p_cv)


# ---- the block kernel: the n = 16 / 32 specialisations, the generic kernel and an independent numpy FSE
# ---- of one block (np.fft, complex128, residual by explicit FFT of the update)
def _numpy_fse_block(img, known, by, bx, b, n, rho, gamma, nit):
    """Seiler & Kaup's FSE of one block, written from fse-reference.md with np.fft: weights w = known *
    rho^r, mean removed, c = gamma R(k) / W(0) at the largest |R(k)| prior(k) of the half spectrum,
    conjugate pair added, R(j) -= c W(j - k) + conj(c) W(j + k); g = mean + Re(IDFT(G))."""
    o = (n - b) // 2
    f = img[by - o:by - o + n, bx - o:bx - o + n].astype(np.float64)
    yy, xx = np.mgrid[0:n, 0:n]
    r = np.hypot(yy - (n - 1) / 2, xx - (n - 1) / 2)
    w = known[by - o:by - o + n, bx - o:bx - o + n] * rho ** r
    mean = np.sum(w * f) / np.sum(w)
    W = np.fft.fft2(w)
    R = np.fft.fft2(w * (f - mean))
    fu = np.minimum(np.arange(n), n - np.arange(n))
    prior = np.clip(1 - np.sqrt(2) * np.hypot(fu[:, None], fu[None, :]) / n, 0, 1)
    G = np.zeros((n, n), complex)
    it = 0
    while it < nit:
        e = (np.abs(R) ** 2 * prior ** 2)[:, :n // 2 + 1].T    # [v, u], v-major like the kernel
        kv, ku = np.unravel_index(np.argmax(e), e.shape)
        c = gamma * R[ku, kv] / W[0, 0]
        if ku in (0, n // 2) and kv in (0, n // 2):
            c = c.real
            G[ku, kv] += c
            R = R - c * np.roll(W, (ku, kv), (0, 1))
            it += 1
        else:
            G[ku, kv] += c
            G[-ku, -kv] += np.conj(c)
            R = R - c * np.roll(W, (ku, kv), (0, 1)) - np.conj(c) * np.roll(W, (-ku, -kv), (0, 1))
            it += 2
    g = mean + np.real(np.fft.ifft2(G)) * n * n
    return g[o:o + b, o:o + b]


def _run_block_kernel(block_kernel, img, state, by, bx, b, n, rho, gamma, nit):
    """One leaf (by, bx) of size b through `block_kernel` (fse.kernel), its tile in round 0."""
    p = fse.resolve_params("balanced", window=n, max_block=b, min_block=b, rho={b: rho}, gamma=gamma)
    tab = fse.params.tables(p)
    img = img.copy()
    state = state.copy()
    tshift = int(np.log2(b))
    tw_tiles = -(-img.shape[1] // b)
    tile_round = np.zeros(-(-img.shape[0] // b) * tw_tiles, np.int64)
    t = (by >> tshift) * tw_tiles + (bx >> tshift)
    one = lambda a: np.array([a], np.int64)  # noqa: E731
    plan = fse.plan.Plan(tile_round, tshift, tw_tiles, np.array([0, 1]), one(t), np.zeros(len(tile_round) + 1,
                         np.int64), one(by), one(bx), one(0))
    dummy = np.zeros((1, 1), np.float32)
    K = fse.kernel
    ctx = K.Context(K.Frame(img, state, dummy, dummy), plan, tab, K.Params(0.5, gamma, 0.0, nit, nit, 1.0, False,
                                                                         False))
    assert block_kernel(ctx, (dummy, dummy), 0, K.make_scratch(n, nit + 2))
    return img, state


@pytest.mark.parametrize("n, b", [(16, 8), (16, 4), (32, 8), (8, 4)])
def test_block_kernel_matches_numpy_fse_and_specialisation_matches_generic(n, b):
    """The block kernel (one source) against an independent numpy FSE of the same block; for
    n = 16 and 32 the specialised kernel (compile-time n) gives the generic kernel's result to float rounding."""
    rng = np.random.default_rng(n + b)
    img = (sinusoids(48, 48) + rng.normal(0, 3, (48, 48))).astype(np.float32)
    known = rng.random(img.shape) < 0.5
    state = known.astype(np.uint8)
    work = np.where(known, img, 0).astype(np.float32)
    by = bx = 24   # a block inside the image, on the block grid
    nit, rho, gamma = 12, 0.7, 0.5
    out, st = _run_block_kernel(fse.kernel.block_generic, work, state, by, bx, b, n, rho, gamma, nit)
    ref = _numpy_fse_block(work, known, by, bx, b, n, rho, gamma, nit)
    blk = (slice(by, by + b), slice(bx, bx + b))
    miss = ~known[blk]
    assert miss.any() and np.all(st[blk][miss] == 2) and np.all(st[blk][~miss] == 1)
    np.testing.assert_array_equal(out[blk][~miss], work[blk][~miss])      # known pixels untouched
    np.testing.assert_allclose(out[blk][miss], ref[miss], rtol=0, atol=1e-3 * np.ptp(img))
    outside = np.ones(img.shape, bool)
    outside[blk] = False
    np.testing.assert_array_equal(out[outside], work[outside])            # nothing outside the block
    if n in (16, 32):
        spec = fse.kernel.block16 if n == 16 else fse.kernel.block32
        out16, st16 = _run_block_kernel(spec, work, state, by, bx, b, n, rho, gamma, nit)
        np.testing.assert_array_equal(st16, st)
        np.testing.assert_allclose(out16, out, rtol=1e-6, atol=1e-5)


# ---- joint estimation: noisy measurements as weighted samples --------------------------------------------
def _joint_case(seed=4):
    """A dark HDR field with fine random texture (not sparse: 50 % samples do not determine it, as on
    real dark scene regions) and a bright corner (log-domain FSE): truth, masks."""
    from scipy.ndimage import gaussian_filter
    rng = np.random.default_rng(seed)
    h, w = 64, 80
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    tex = gaussian_filter(rng.standard_normal((h, w)), 0.8)
    tex /= tex.std()
    t = (60.0 * 2.0 ** (0.5 * tex + 0.5 * np.sin(2 * np.pi * (xx / 3.1 + yy / 4.3)))).astype(np.float32)
    t[:4, :4] = 6.0e4
    u = rng.random(t.shape)
    known = u < 0.5
    noisy = (u >= 0.5) & (u < 0.85)          # measured but noisy; the rest is missing
    known[:4, :4] = True
    noisy[:4, :4] = False
    return t, known, noisy, rng


def test_joint_weights_without_a_noisy_pixel_give_the_same_bits():
    """No pixel that is both unknown and weighted: the plain path (same bits as weights=None)."""
    t, known, noisy, _ = _joint_case()
    ref = fse.fse_reconstruct(t, known, preset="balanced")
    for wts in (np.zeros_like(t), np.where(known, np.float32(0.5), np.float32(0.0))):
        out = fse.fse_reconstruct(t, known, preset="balanced", weights=wts)
        assert np.array_equal(out, ref)
    with pytest.raises(ValueError, match="weights shape"):
        fse.fse_reconstruct(t, known, weights=np.zeros((3, 3), np.float32))


def test_joint_estimate_uses_the_noisy_samples():
    """Known truth (dark fine texture): with the noisy measurements as weighted samples, the error at
    those pixels is below FSE's with them missing (the interpolation of 50 % samples) and below the
    measurement's; noise-free with weight 1, the noisy pixels are nearly reproduced and the remaining
    missing ones improve too."""
    t, known, noisy, rng = _joint_case()
    meas = np.where(noisy, t * (1.0 + 0.2 * rng.standard_normal(t.shape)), t).astype(np.float32)
    miss = ~known & ~noisy
    rms = lambda o, m: float(np.sqrt(np.mean((np.log2(np.maximum(o[m], 1e-3)) - np.log2(t[m])) ** 2)))
    interp = fse.fse_reconstruct(meas, known, preset="balanced")
    joint = fse.fse_reconstruct(meas, known, preset="balanced", weights=np.where(noisy, 0.3, 0.0))
    assert np.array_equal(joint[known], meas[known])            # known pixels bit-exact
    assert np.all(np.isfinite(joint))
    # below both of its inputs at the noisy pixels: the interpolation and the measurement
    assert rms(joint, noisy) < 0.8 * min(rms(interp, noisy), rms(meas, noisy))
    clean = fse.fse_reconstruct(t, known, preset="balanced", weights=np.where(noisy, 1.0, 0.0))
    plain = fse.fse_reconstruct(t, known, preset="balanced")
    assert rms(clean, noisy) < 0.5 * rms(plain, noisy)
    assert rms(clean, miss) < rms(plain, miss)


# ---- FSE skips NOISY pixels before the accurate noise fusion ----------------------------------------------
def _prof():
    from types import SimpleNamespace
    return SimpleNamespace(gain=0.55, read_noise=2.0, nd=6.35)


def test_skipped_pixels_are_neither_read_nor_written():
    """Skipped pixels: FSE writes no skipped pixel (they keep their input bits), and the other missing
    pixels do not depend on the skipped pixels' values (weight 0: garbage there gives the same bits);
    with every missing pixel skipped nothing is reconstructed at all."""
    t, known, noisy, rng = _joint_case()
    skip = noisy & ~known
    a = fse.fse_reconstruct(t, known, preset="fast", skip=skip)
    assert np.array_equal(a[skip], t[skip]) and np.array_equal(a[known], t[known])
    garbage = t.copy()
    garbage[skip] = rng.random(int(skip.sum())).astype(np.float32) * 1e6
    b = fse.fse_reconstruct(garbage, known, preset="fast", skip=skip)
    miss = ~known & ~skip
    assert np.array_equal(a[miss], b[miss])
    assert np.array_equal(b[skip], garbage[skip])
    # the plain path would read them (delta-weighted reconstructions) and write them
    c = fse.fse_reconstruct(t, known, preset="fast")
    assert not np.array_equal(c[skip], t[skip])
    # nothing but skipped pixels missing: the input comes back unchanged
    d = fse.fse_reconstruct(t, known | miss, preset="fast", skip=skip)
    assert np.array_equal(d, t)


def test_noisy_skip_without_a_noisy_pixel_gives_the_same_bits():
    """No NOISY pixel (an empty mask, or NOISY only at known pixels): the same bits as without a mask."""
    t, known, _, _ = _joint_case()
    ref = reconstruct(t, known, preset="fast")
    for nz in (np.zeros_like(known), known.copy()):
        out = reconstruct(t, known, preset="fast", noisy=nz, noise=_prof(), noisy_skip=True)
        assert np.array_equal(out, ref)


def _fusion_numpy(g, m, known, noisy, prof, texture=1.0, r=2):
    """`fuse_noisy` accurate written out in numpy/float64 from its docstring: e = inverse-variance
    mean of the measured 3 x 3 neighbours (known: 1 / var_r, other NOISY: 1 / var_m), var_e = 1 / sum of
    weights + texture x excess variance of the known pixels of the 5 x 5 window; e = g, var_e = var_r / 4
    + excess when no neighbour is measured; f = max(e + var_e / (var_e + var_m) (m - e), 0)."""
    floor = prof.gain ** 2 * prof.read_noise ** 2 + 1.0 / 12.0
    out = g.astype(np.float64).copy()
    h, w = g.shape
    m = m.astype(np.float64)
    for y, x in zip(*np.nonzero(noisy)):
        gp = max(float(g[y, x]), 0.0)
        var_r = prof.gain * gp + floor
        var_m = prof.nd * prof.gain * gp + prof.nd ** 2 * floor
        win = (slice(max(y - r, 0), y + r + 1), slice(max(x - r, 0), x + r + 1))
        kv = m[win][known[win]]
        excess = 0.0
        if kv.size:
            excess = max(kv.var() - (prof.gain * max(kv.mean(), 0.0) + floor), 0.0)
        w3 = (slice(max(y - 1, 0), y + 2), slice(max(x - 1, 0), x + 2))
        kn3 = m[w3][known[w3]]
        nz3 = noisy[w3] & ~known[w3]
        nz3[y - w3[0].start, x - w3[1].start] = False
        zv = m[w3][nz3]
        sw = kn3.size / var_r + zv.size / var_m
        e, var_e = float(g[y, x]), var_r / 4.0 + texture * excess
        if sw > 0.5 / var_m:
            e = (kn3.sum() / var_r + zv.sum() / var_m) / sw
            var_e = 1.0 / sw + texture * excess
        f = e + var_e / (var_e + var_m) * (m[y, x] - e)
        out[y, x] = max(f, 0.0)
    return out


def test_noisy_skip_fused_result_matches_numpy():
    """The default path of `reconstruct(fse, noisy, accurate)`: FSE with the NOISY pixels skipped, their
    level the mean of the non-NOISY 3 x 3 neighbours (numpy here), clamped to the data range, then the
    fusion formula (numpy above), against the dispatcher; known pixels bit-exact; FSE's model at the other
    missing pixels the same as the skipped FSE run's."""
    t, known, noisy, rng = _joint_case(seed=5)
    t = t[:32, :40].copy()
    known, noisy = known[:32, :40].copy(), noisy[:32, :40] & ~known[:32, :40]
    meas = np.where(noisy, t * (1.0 + 0.3 * rng.standard_normal(t.shape)), t).astype(np.float32)
    out = reconstruct(meas, known, preset="fast", noisy=noisy, noise=_prof())
    g = fse.fse_reconstruct(meas, known, preset="fast", skip=noisy).astype(np.float64)
    lvl = g.copy()
    for y, x in zip(*np.nonzero(noisy)):
        win = (slice(max(y - 1, 0), y + 2), slice(max(x - 1, 0), x + 2))
        src = ~noisy[win]
        lvl[y, x] = g[win][src].mean() if src.any() else max(g[y, x], 0.0)
    lvl = np.where(known, lvl, np.clip(lvl, min(meas[known].min(), 0.0), meas[known].max()))
    want = _fusion_numpy(lvl.astype(np.float32), meas, known, noisy, _prof())
    assert np.array_equal(out[known], meas[known])
    miss = ~known & ~noisy
    np.testing.assert_allclose(out[miss], lvl[miss], rtol=1e-6)
    np.testing.assert_allclose(out[noisy], want[noisy], rtol=2e-5, atol=1e-4)
    # the switch: noisy_skip=False keeps FSE's value at the NOISY pixels, a different result
    old = reconstruct(meas, known, preset="fast", noisy=noisy, noise=_prof(), noisy_skip=False)
    assert not np.array_equal(old, out)
    # the fast fusion and the joint estimation keep FSE at the NOISY pixels (the skip is for accurate only)
    assert np.array_equal(reconstruct(meas, known, preset="fast", noisy=noisy, noise=_prof(), fusion="fast"),
                          reconstruct(meas, known, preset="fast", noisy=noisy, noise=_prof(), fusion="fast",
                                      noisy_skip=False))


# ---- the fallback fill of blocks without data ------------------------------------------------------------
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_nearest_fill_crop_gives_a_nearest_source(seed):
    """`fill.nearest_fill` (ring search around each left pixel; a crop's distance transform where no source
    is within RING_RADIUS_MAX, seed 2): every left pixel gets the value of a source pixel at the minimal
    Euclidean distance (the whole-frame distance transform); FSE's `fill_left` gives the same values."""
    from scipy import ndimage

    from nrhdr_core import fill
    rng = np.random.default_rng(seed)
    h, w = 120, 200
    src = rng.random((h, w)) < (0.02 if seed else 0.5)
    left = np.zeros((h, w), bool)
    left[40:70, 90:150] = rng.random((30, 60)) < 0.7     # a hole region, sources far away for seed > 0
    src &= ~left
    if seed == 2:
        src[:] = False
        src[0, 0] = True                                  # one source in a corner: the crop must grow
    work = np.arange(h * w, dtype=np.float64).reshape(h, w).astype(np.float32)   # value = source id
    ref = work.copy()
    fill.nearest_fill(work, left, src)
    dist = ndimage.distance_transform_edt(~src)
    ys, xs = np.nonzero(left)
    sid = work[ys, xs].astype(np.int64)
    sy, sx = sid // w, sid % w
    assert np.all(src[sy, sx])                                                    # sources only
    np.testing.assert_allclose(np.hypot(sy - ys, sx - xs), dist[ys, xs], rtol=0, atol=1e-9)  # nearest
    np.testing.assert_array_equal(work[~left], ref[~left])                        # nothing else touched
    # the driver's form: left = MISSING, sources = KNOWN (skipped pixels are not)
    P = fse.params
    state = np.where(left, P.MISSING, np.where(src, P.KNOWN, P.SKIP)).astype(np.uint8)
    work2 = ref.copy()
    ys2, xs2 = fse.fallback.fill_left(work2, state)
    np.testing.assert_array_equal(ys2, ys)
    np.testing.assert_array_equal(xs2, xs)
    np.testing.assert_array_equal(work2, work)
