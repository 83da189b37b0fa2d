"""FSE (nrhdr_core/fse.py) against independent expectations: sparse sinusoid sums, constants, scale
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


def test_warmup_runs():
    fse.warmup()


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
