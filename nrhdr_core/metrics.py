"""Measurements: PSNR (linear and log domain), SSIM, flat-field SNR per pixel class (paper Eq. 4-7,
Fig. 3/5/9) and the valid-pixel ratio over flux (Fig. 4 / 8b)."""
from __future__ import annotations

import numpy as np


def psnr(ref: np.ndarray, test: np.ndarray, peak: float | None = None) -> float:
    """PSNR in dB; `peak` defaults to the reference's maximum (255 for 8-bit data should be passed)."""
    ref = np.asarray(ref, np.float64)
    test = np.asarray(test, np.float64)
    peak = float(ref.max()) if peak is None else float(peak)
    mse = float(np.mean((ref - test) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(peak * peak / mse)


def log_psnr(ref: np.ndarray, test: np.ndarray, floor: float | None = None) -> float:
    """PSNR of log2 values (stops) over the reference's log range: the HDR-robust variant
    (hdr-references 'Quality metrics'). `floor` clamps tiny values (default 1e-4 of the max)."""
    ref = np.asarray(ref, np.float64)
    test = np.asarray(test, np.float64)
    floor = float(ref.max()) * 1e-4 if floor is None else floor
    lr = np.log2(np.maximum(ref, floor))
    lt = np.log2(np.maximum(test, floor))
    return psnr(lr - lr.min(), lt - lr.min(), peak=float(lr.max() - lr.min()))


def ssim(ref: np.ndarray, test: np.ndarray, data_range: float | None = None) -> float:
    """Mean SSIM (Wang et al. 2004) with an 11 x 11 Gaussian window, sigma 1.5."""
    from scipy.ndimage import gaussian_filter
    x = np.asarray(ref, np.float64)
    y = np.asarray(test, np.float64)
    L = float(x.max() - x.min()) if data_range is None else float(data_range)
    c1, c2 = (0.01 * L) ** 2, (0.03 * L) ** 2
    f = lambda a: gaussian_filter(a, 1.5, truncate=3.5)
    mx, my = f(x), f(y)
    sxx, syy, sxy = f(x * x) - mx * mx, f(y * y) - my * my, f(x * y) - mx * my
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return float(s.mean())


def snr_db(samples: np.ndarray) -> float:
    """Measured SNR of a flat field, 20 log10(mean / std) (paper Eq. 4)."""
    s = np.asarray(samples, np.float64)
    sd = s.std(ddof=1)
    return float("inf") if sd == 0 else 20.0 * np.log10(s.mean() / sd)


def flat_field_snr(values: np.ndarray, known: np.ndarray, mask: np.ndarray) -> dict:
    """SNR of a flat field (one frame, ND-scaled values) per pixel class over known pixels:
    'regular' (Eq. 4), 'attenuated' (Eq. 5) and 'global' (Eq. 7, all known pixels)."""
    out = {}
    for name, sel in (("regular", known & ~mask), ("attenuated", known & mask), ("global", known)):
        out[name] = snr_db(values[sel]) if sel.sum() > 2 else float("nan")
    return out
