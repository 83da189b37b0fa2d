"""The logarithmic tone map (paper section 5; `tonemap.log_tonemap`) with the C library's log1p per pixel,
for the tests to check the vectorised kernel against."""
from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit
def _log_kernel(values, scale, q, inv_den, out_max, out):
    h, w = values.shape
    for y in range(h):
        for x in range(w):
            v = values[y, x] * scale
            if not (v > 0.0):  # also maps NaN to black
                v = np.float32(0.0)
            elif v > 1.0:
                v = np.float32(1.0)
            t = math.log1p(q * v) * inv_den
            out[y, x] = t * out_max + np.float32(0.5)


def log_tonemap(values, white, contrast, out):
    """y = log(1 + q x) / log(1 + q), x = clip(values / white, 0, 1), rounded to `out`'s integer codes, in
    float32 like `tonemap.log_tonemap`."""
    out_max = 255.0 if out.dtype == np.uint8 else 65535.0
    _log_kernel(np.asarray(values, np.float32), np.float32(1.0 / white), np.float32(contrast),
                np.float32(1.0 / math.log1p(contrast)), np.float32(out_max), out)
    return out
