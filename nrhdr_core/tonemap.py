"""Logarithmic tone mapping for display (paper section 5, Fig. 10 g/h; hdr-references 'Tone mapping').

y = log(1 + q x) / log(1 + q), x = clip(L 2^e / white, 0, 1): the standard logarithmic operator
(HDR Toolbox LogarithmicTMO) with contrast q and exposure e in stops. The normaliser `white` is fixed
(the sensor's largest scaled value, (clip - black) * ND) or smoothed over time (`WhiteTracker`), never a
per-frame min/max: video must not flicker.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

DEFAULT_CONTRAST = 1000.0


@njit(cache=True, nogil=True, parallel=True)
def _log_kernel(values, scale, q, inv_den, out_max, out):
    h, w = values.shape
    for y in prange(h):
        for x in range(w):
            v = values[y, x] * scale
            if not (v > 0.0):  # also maps NaN to black
                v = np.float32(0.0)
            elif v > 1.0:
                v = np.float32(1.0)
            t = math.log1p(q * v) * inv_den
            out[y, x] = np.uint16(t * out_max + np.float32(0.5)) if out_max > 255 else np.uint8(
                t * out_max + np.float32(0.5))


# ---- vectorisable log1p (perf, issue 7 item 3): math.log1p is a scalar libm call per pixel (~37 ms per
# 1080p frame on one core); this evaluates log via exponent/mantissa split (integer view of a row buffer)
# and the Cephes logf polynomial (~1 ulp), with log1p(a) = log(u) * a / (u - 1), u = 1 + a (Kahan's
# correction of the rounding of 1 + a). Same codes as the libm path except for values within ~1e-6 of a
# rounding boundary (tests/test_perf_kernels.py).
@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _log_kernel_fast(values, scale, q, inv_den, out_max, out):
    h, w = values.shape
    nch = min(h, 64)
    for c in prange(nch):
        ubuf = np.empty(w, np.float32)
        mbuf = np.empty(w, np.float32)
        ebuf = np.empty(w, np.float32)
        ubits = ubuf.view(np.int32)
        mbits = mbuf.view(np.int32)
        for y in range((c * h) // nch, ((c + 1) * h) // nch):
            for x in range(w):
                v = values[y, x] * scale
                v = v if v > np.float32(0.0) else np.float32(0.0)     # also maps NaN to black
                v = v if v < np.float32(1.0) else np.float32(1.0)
                ubuf[x] = np.float32(1.0) + q * v
            for x in range(w):
                b = ubits[x]
                ebuf[x] = np.float32((b >> 23) - 127)
                mbits[x] = (b & 0x7FFFFF) | 0x3F800000
            for x in range(w):
                m = mbuf[x]
                e = ebuf[x]
                big = m > np.float32(1.4142135)
                m = m * np.float32(0.5) if big else m
                e = e + np.float32(1.0) if big else e
                z = m - np.float32(1.0)
                zz = z * z
                p = np.float32(7.0376836292e-2)
                p = p * z - np.float32(1.1514610310e-1)
                p = p * z + np.float32(1.1676998740e-1)
                p = p * z - np.float32(1.2420140846e-1)
                p = p * z + np.float32(1.4249322787e-1)
                p = p * z - np.float32(1.6668057665e-1)
                p = p * z + np.float32(2.0000714765e-1)
                p = p * z - np.float32(2.4999993993e-1)
                p = p * z + np.float32(3.3333331174e-1)
                r = p * z * zz
                r = r - np.float32(2.12194440e-4) * e
                r = r - np.float32(0.5) * zz
                lg = z + r + np.float32(0.693359375) * e
                u = ubuf[x]
                a = u - np.float32(1.0)
                a0 = (values[y, x] * scale)
                a0 = a0 if a0 > np.float32(0.0) else np.float32(0.0)
                a0 = q * (a0 if a0 < np.float32(1.0) else np.float32(1.0))
                l1p = lg * (a0 / a) if a > np.float32(0.0) else a0
                out[y, x] = l1p * inv_den * out_max + np.float32(0.5)


def log_tonemap(values: np.ndarray, white: float, exposure_stops: float = 0.0,
                contrast: float = DEFAULT_CONTRAST, out: np.ndarray | None = None,
                dtype=np.uint8) -> np.ndarray:
    """Map linear values (H, W) to uint8 or uint16 display codes; `out` (filled in place) fixes the type."""
    if not (white > 0 and math.isfinite(white)):
        raise ValueError(f"tone mapping white must be a finite number > 0, got {white}")
    if not (contrast > 0 and math.isfinite(contrast)):
        raise ValueError(f"tone mapping contrast must be > 0, got {contrast}")
    v = np.asarray(values, dtype=np.float32)
    if out is None:
        out = np.empty(v.shape, dtype=dtype)
    if out.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"tone mapping output must be uint8 or uint16, got {out.dtype}")
    out_max = 255.0 if out.dtype == np.uint8 else 65535.0
    scale = np.float32(2.0 ** exposure_stops / white)
    q = np.float32(contrast)
    _log_kernel_fast(v, scale, q, np.float32(1.0 / math.log1p(contrast)), np.float32(out_max), out)
    return out


def robust_peak(values: np.ndarray, percentile: float = 99.9, stride: int = 4) -> float:
    """A flicker-robust frame statistic: the given percentile of a subsampled frame (not the maximum)."""
    sub = np.asarray(values)[::stride, ::stride]
    sub = sub[np.isfinite(sub)]
    return float(np.percentile(sub, percentile)) if sub.size else 0.0


class WhiteTracker:
    """Temporally smoothed normaliser, libcamera style: white_t = speed * peak_t + (1 - speed) * white_t-1,
    peak_t a high percentile of the frame; the first frame initialises it."""

    def __init__(self, speed: float = 0.1, percentile: float = 99.9):
        if not 0.0 < speed <= 1.0:
            raise ValueError(f"smoothing speed must be in (0, 1], got {speed}")
        self.speed, self.percentile, self.white = speed, percentile, None

    def update(self, values: np.ndarray) -> float:
        peak = max(robust_peak(values, self.percentile), 1e-6)
        self.white = peak if self.white is None else self.speed * peak + (1 - self.speed) * self.white
        return self.white

    def reset(self) -> None:
        self.white = None


def warmup() -> None:
    log_tonemap(np.ones((2, 2), np.float32), 1.0)
    log_tonemap(np.ones((2, 2), np.float32), 1.0, dtype=np.uint16)
