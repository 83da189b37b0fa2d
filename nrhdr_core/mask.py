"""ND filter masks (paper Fig. 1a, section 2.1).

A mask is a bool array (H, W): True where the pixel sits behind the ND filter. On disk it is an 8-bit PNG,
255 = attenuated, 0 = regular (see `io.write_mask` / `io.read_mask`).
"""
from __future__ import annotations

import numpy as np


def nonregular_mask(height: int, width: int, seed: int = 0, fraction: float = 0.5) -> np.ndarray:
    """The paper's non-regular pattern (section 2): exactly round(fraction*H*W) attenuated pixels at
    uniformly random, seeded positions. Its spectrum has a single dominant peak at DC (Fig. 2b)."""
    _check_size(height, width)
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"mask fraction must be in [0, 1], got {fraction}")
    n = height * width
    k = int(round(fraction * n))
    rng = np.random.default_rng(seed)
    flat = np.zeros(n, dtype=bool)
    flat[rng.permutation(n)[:k]] = True
    return flat.reshape(height, width)


def regular_mask(height: int, width: int) -> np.ndarray:
    """Regular 2 x 2 pattern after Nayar and Mitsunaga (ref. 5) with two attenuation levels: the
    diagonal of each 2 x 2 cell is attenuated (a checkerboard). Its spectrum has two equal peaks (Fig. 2a),
    the aliasing ambiguity the non-regular pattern avoids."""
    _check_size(height, width)
    yy, xx = np.mgrid[0:height, 0:width]
    return ((yy + xx) % 2) == 1


def mask_spectrum(mask: np.ndarray) -> np.ndarray:
    """Magnitude of the 2-D DFT of the zero-mean sampling pattern of the *regular* (known) pixels,
    normalised so that the DC peak is 1 (paper Fig. 2, right column)."""
    s = (~mask).astype(np.float64)
    spec = np.abs(np.fft.fftshift(np.fft.fft2(s)))
    return spec / max(spec.max(), 1e-12)


def _check_size(height: int, width: int) -> None:
    if height < 1 or width < 1:
        raise ValueError(f"mask size must be positive, got {height} x {width}")
