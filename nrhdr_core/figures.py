"""The paper's figures regenerated (`nrhdr figures`, issue 10): Figs. 2-10 as PNG, the numbers behind them
beside the paper's in figures.json and index.md. Plots with matplotlib (Agg)."""
from __future__ import annotations

import numpy as np


# ---- test content ------------------------------------------------------------------------------------

def zone_plate(n: int = 512, fmax: float = 0.45) -> np.ndarray:
    """8-bit-range zone plate (0..255, float32): local frequency rising linearly with the radius to `fmax`
    cycles/pixel at r = n/2, constant beyond (no content above `fmax`)."""
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float64)
    r = np.hypot(yy - (n - 1) / 2, xx - (n - 1) / 2)
    R = n / 2
    phase = np.where(r <= R, fmax * r * r / (2 * R), fmax * (R / 2 + (r - R)))
    return (127.5 + 127.5 * np.cos(2 * np.pi * phase)).astype(np.float32)


def hf_texture(n: int = 256, seed: int = 0) -> np.ndarray:
    """High-frequency texture (0..255): three gratings at 0.38-0.45 cycles/pixel with random phases; sparse
    in Fourier, and every component aliases under the checkerboard."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float64)
    acc = np.zeros((n, n))
    for fy, fx in ((0.05, 0.42), (0.40, -0.12), (0.29, 0.29)):
        acc += np.cos(2 * np.pi * (fy * yy + fx * xx) + rng.uniform(0, 2 * np.pi))
    return (127.5 + 127.5 * acc / 3.0).astype(np.float32)


def load_hdr_scene(path, size: int) -> np.ndarray:
    """Luminance of an HDR scene file, box-downscaled and centre-cropped to size x size (float64 >= 0)."""
    from . import io
    lum = np.maximum(io.read_luminance(path).astype(np.float64), 0.0)
    f = max(1, min(lum.shape[0], lum.shape[1]) // size)
    H, W = lum.shape[0] // f * f, lum.shape[1] // f * f
    lum = lum[:H, :W].reshape(H // f, f, W // f, f).mean(axis=(1, 3))
    if min(lum.shape) < size:
        from scipy.ndimage import zoom
        lum = zoom(lum, size / min(lum.shape) + 1e-3, order=1)
    y0, x0 = (lum.shape[0] - size) // 2, (lum.shape[1] - size) // 2
    return np.maximum(lum[y0:y0 + size, x0:x0 + size], 0.0)
