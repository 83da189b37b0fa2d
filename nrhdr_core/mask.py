"""ND filter masks (paper Fig. 1a, section 2.1) and reduced-randomness non-regular designs.

A mask is a bool array (H, W): True where the pixel sits behind the ND filter. On disk it is an 8-bit PNG,
255 = attenuated, 0 = regular (see `io.write_mask` / `io.read_mask`).

Patterns (`PATTERNS`, `make_mask`); every one has exactly round(H*W/2) attenuated pixels and is seeded:
- ``nonregular`` (alias ``random``): the paper's iid-uniform positions (section 2).
- ``regular``: the 2 x 2 checkerboard after Nayar and Mitsunaga (ref. 5).
- ``cell2``: exactly two attenuated pixels per 2 x 2 cell, one of the 6 arrangements at random per cell
  (reduced randomness after Jonscher, Seiler, Kaup et al., "Reducing randomness of non-regular sampling
  masks": no 2 x 2 cell is fully known or fully unknown).
- ``bluenoise``: error diffusion (Floyd-Steinberg, serpentine) of a flat 50 % grey with a randomised
  threshold (Ulichney's blue noise): no spectral peak besides DC, little low-frequency energy.
  ``jitter`` tunes it: 0 gives the checkerboard, larger values more randomness.
- ``cell2diag``: per 2 x 2 cell one of the two diagonal arrangements at random (a checkerboard whose phase
  flips at random per cell).
- ``voidcluster``: Ulichney's void-and-cluster blue noise (initial binary pattern: swap the tightest cluster
  into the largest void under a Gaussian filter of width ``sigma`` until stable) on a 128 x 128 toroidal tile,
  tiled with a seeded offset. A narrow filter (sigma 0.8) matches the checkerboard on natural images while
  keeping most of the non-regular advantage on high frequencies (docs/PAPER.md).

ND layouts over a Bayer CFA (`ND_LAYOUTS`, `cfa_mask`; docs/COLOUR.md, docs/SIMULATOR.md):
- ``independent``: the chosen pattern over the whole sensor as is, ignoring the CFA.
- ``balanced`` (the default, `DEFAULT_ND_LAYOUT`): the chosen pattern drawn on each of the four 2 x 2 CFA
  sub-lattices (R, the two greens, B) separately, so every colour plane has exactly half its photosites
  attenuated, placed as the pattern places them (non-regular within each plane for ``nonregular``).
- ``regular``: the Assorted-Pixels / spatially-varying-exposure layout (spatially varying exposure, Nayar and
  Mitsunaga, CVPR 2000, over the colour mosaic as in Assorted Pixels, Narasimhan and Nayar, TPAMI 2005): whole 2 x 2 Bayer blocks alternate
  clear / ND in a checkerboard of blocks, so every colour plane is a regular checkerboard (the pattern is
  not used).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from . import cfa as cfas
from .cfa import DEFAULT_ND_LAYOUT, ND_LAYOUTS, NO_ND  # noqa: F401  (named here too: the layouts' module)

PATTERNS = ("nonregular", "random", "regular", "cell2", "cell2diag", "bluenoise", "voidcluster")
VOIDCLUSTER_SIGMA = 0.8  # Gaussian width of `voidcluster` (benchmarks/masks.py: matches the checkerboard on Kodak)
VOIDCLUSTER_TILE = 128
BLUENOISE_JITTER = 0.4   # threshold randomisation of `bluenoise` (benchmarks/masks.py: the measured trade-off)


def make_mask(pattern: str, height: int, width: int, seed: int = 0, **kw) -> np.ndarray:
    """The mask of the named pattern (`PATTERNS`), exactly half attenuated, deterministic per seed."""
    if pattern in ("nonregular", "random"):
        return nonregular_mask(height, width, seed=seed)
    if pattern == "regular":
        return regular_mask(height, width)
    if pattern == "cell2":
        return cell2_mask(height, width, seed=seed)
    if pattern == "cell2diag":
        return cell2_mask(height, width, seed=seed, diagonal_only=True)
    if pattern == "bluenoise":
        return bluenoise_mask(height, width, seed=seed, **kw)
    if pattern == "voidcluster":
        return voidcluster_mask(height, width, seed=seed, **kw)
    raise ValueError(f"mask pattern must be one of {PATTERNS}, got {pattern!r}")


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


_CELL2 = np.array([[[1, 1], [0, 0]], [[0, 0], [1, 1]], [[1, 0], [1, 0]], [[0, 1], [0, 1]],
                   [[1, 0], [0, 1]], [[0, 1], [1, 0]]], dtype=bool)     # last two: the diagonals


def cell2_mask(height: int, width: int, seed: int = 0, diagonal_only: bool = False) -> np.ndarray:
    """Exactly two attenuated pixels in every 2 x 2 cell, the arrangement drawn per cell (all 6, or only
    the 2 diagonal ones), after Jonscher, Seiler, Kaup et al. (reduced randomness). Odd edges: cropped,
    then the count is made exactly half by flipping random pixels of the last row/column."""
    _check_size(height, width)
    rng = np.random.default_rng(seed)
    ch, cw = (height + 1) // 2, (width + 1) // 2
    choices = _CELL2[4:] if diagonal_only else _CELL2
    pick = rng.integers(0, len(choices), size=(ch, cw))
    m = choices[pick].transpose(0, 2, 1, 3).reshape(2 * ch, 2 * cw)[:height, :width]
    return _exact_half(m, rng)


@njit(cache=True, nogil=True)
def _error_diffuse(h, w, level, thr_noise):
    """Floyd-Steinberg error diffusion of a flat image `level`, serpentine scan, threshold 0.5 + noise."""
    err = np.zeros((h + 1, w + 2), np.float64)
    out = np.zeros((h, w), np.bool_)
    for y in range(h):
        rev = (y % 2) == 1
        for i in range(w):
            x = w - 1 - i if rev else i
            v = level + err[y, x + 1]
            o = 1.0 if v >= 0.5 + thr_noise[y, x] else 0.0
            out[y, x] = o > 0.5
            e = v - o
            d = -1 if rev else 1
            err[y, x + 1 + d] += e * 7.0 / 16.0
            err[y + 1, x + 1 - d] += e * 3.0 / 16.0
            err[y + 1, x + 1] += e * 5.0 / 16.0
            err[y + 1, x + 1 + d] += e * 1.0 / 16.0
    return out


def bluenoise_mask(height: int, width: int, seed: int = 0, jitter: float = BLUENOISE_JITTER) -> np.ndarray:
    """Blue-noise mask: error diffusion of a flat 50 % grey with the threshold randomised uniformly in
    0.5 +- jitter/2 (Ulichney, "Digital Halftoning"; Jonscher et al.). jitter = 0 gives the checkerboard;
    the count is made exactly half by flipping a few random pixels."""
    _check_size(height, width)
    if not (np.isfinite(jitter) and 0.0 <= jitter <= 2.0):
        raise ValueError(f"bluenoise jitter must be in [0, 2], got {jitter}")
    rng = np.random.default_rng(seed)
    noise = (rng.random((height, width)) - 0.5) * float(jitter)
    m = _error_diffuse(height, width, 0.5, noise)
    return _exact_half(np.asarray(m, bool), rng)


@njit(cache=True, nogil=True)
def _void_and_cluster(b, sigma, max_iter):
    """Initial binary pattern of void-and-cluster (Ulichney 1993) on a torus, in place: move the 1 with the
    largest Gaussian-filtered density (tightest cluster) to the 0 with the smallest (largest void) until the
    move would put it back. Returns the number of swaps."""
    n, m = b.shape
    r = int(np.ceil(3.0 * sigma))
    k = np.empty((2 * r + 1, 2 * r + 1))
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            k[dy + r, dx + r] = np.exp(-(dy * dy + dx * dx) / (2.0 * sigma * sigma))
    f = np.zeros((n, m))
    for y in range(n):
        for x in range(m):
            if b[y, x]:
                for dy in range(-r, r + 1):
                    for dx in range(-r, r + 1):
                        f[(y + dy) % n, (x + dx) % m] += k[dy + r, dx + r]
    for it in range(max_iter):
        bi, bv = 0, -1e300
        for i in range(n * m):
            if b[i // m, i % m] and f[i // m, i % m] > bv:
                bv, bi = f[i // m, i % m], i
        y, x = bi // m, bi % m
        b[y, x] = False
        for dy in range(-r, r + 1):
            for dx in range(-r, r + 1):
                f[(y + dy) % n, (x + dx) % m] -= k[dy + r, dx + r]
        vi, vv = 0, 1e300
        for i in range(n * m):
            if not b[i // m, i % m] and f[i // m, i % m] < vv:
                vv, vi = f[i // m, i % m], i
        y2, x2 = vi // m, vi % m
        b[y2, x2] = True
        for dy in range(-r, r + 1):
            for dx in range(-r, r + 1):
                f[(y2 + dy) % n, (x2 + dx) % m] += k[dy + r, dx + r]
        if vi == bi:
            return it
    return max_iter


def voidcluster_mask(height: int, width: int, seed: int = 0, sigma: float = VOIDCLUSTER_SIGMA,
                     tile: int = VOIDCLUSTER_TILE) -> np.ndarray:
    """Void-and-cluster blue-noise mask (Ulichney, "The void-and-cluster method for dither array
    generation", 1993): a seeded random half of a `tile` x `tile` torus relaxed by `_void_and_cluster`, tiled
    over the sensor from a seeded offset; the count is then made exactly half."""
    _check_size(height, width)
    if not (np.isfinite(sigma) and 0.3 <= sigma <= 4.0):
        raise ValueError(f"voidcluster sigma must be in [0.3, 4], got {sigma}")
    if not 8 <= int(tile) <= 512:
        raise ValueError(f"voidcluster tile must be in 8..512, got {tile}")
    tile = int(tile)
    rng = np.random.default_rng(seed)
    b = (rng.permutation(tile * tile) < tile * tile // 2).reshape(tile, tile)
    _void_and_cluster(b, float(sigma), 50 * tile * tile)
    oy, ox = rng.integers(0, tile, 2)
    reps = (-(-(height + oy) // tile), -(-(width + ox) // tile))
    m = np.tile(b, reps)[oy:oy + height, ox:ox + width]
    return _exact_half(m, rng)


def _exact_half(m: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Flip random pixels of the majority kind until exactly round(H*W/2) are attenuated."""
    m = np.array(m, dtype=bool, copy=True)
    k = int(round(m.size / 2))
    d = int(m.sum()) - k
    if d != 0:
        idx = np.flatnonzero(m if d > 0 else ~m)
        m.flat[rng.choice(idx, size=abs(d), replace=False)] = d < 0
    return m


def mask_spectrum(mask: np.ndarray) -> np.ndarray:
    """Magnitude of the 2-D DFT of the zero-mean sampling pattern of the *regular* (known) pixels,
    normalised so that the DC peak is 1 (paper Fig. 2, right column)."""
    s = (~mask).astype(np.float64)
    spec = np.abs(np.fft.fftshift(np.fft.fft2(s)))
    return spec / max(spec.max(), 1e-12)


def spectrum_stats(mask: np.ndarray, low: float = 0.125) -> dict:
    """Numbers behind Fig. 2: the largest non-DC spectral peak relative to DC (1 = the checkerboard's
    ambiguity) and the share of the non-DC power below `low` cycles/pixel (radial; white noise ~ the
    area share, blue noise far less)."""
    h, w = mask.shape
    s = (~mask).astype(np.float64)
    P = np.abs(np.fft.fft2(s - s.mean())) ** 2
    dc = float(s.sum()) ** 2
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.fftfreq(w)[None, :]
    r = np.hypot(fy, fx)
    tot = float(P.sum())
    return {"peak_ratio": float(np.sqrt(P.max() / dc)) if dc > 0 else float("nan"),
            "low_freq_power_share": float(P[r < low].sum() / tot) if tot > 0 else 0.0,
            "low_freq_area_share": float(np.mean(r < low))}


def check_nd_layout(layout, what: str = "nd_layout") -> str:
    """`layout` if it is one of ND_LAYOUTS; ValueError naming `what` otherwise."""
    if layout not in ND_LAYOUTS:
        raise ValueError(f"{what}: must be one of {', '.join(ND_LAYOUTS)}, got {layout!r}")
    return layout


SUBLATTICES = ((0, 0), (0, 1), (1, 0), (1, 1))   # the four 2 x 2 CFA sub-lattices: (row, column) offsets


def block_checkerboard(height: int, width: int) -> np.ndarray:
    """The `regular` ND layout over a CFA (SVE, Nayar and Mitsunaga 2000; Assorted Pixels, Narasimhan and Nayar 2005): 2 x 2 blocks
    attenuated where (block row + block column) is odd, the top-left block clear; every colour plane is a
    regular checkerboard."""
    _check_size(height, width)
    yy, xx = np.mgrid[0:height, 0:width]
    return ((yy // 2 + xx // 2) % 2) == 1


def cfa_mask(pattern: str, height: int, width: int, layout: str = DEFAULT_ND_LAYOUT, seed: int = 0,
             **kw) -> np.ndarray:
    """The ND mask of a Bayer sensor (even `height` and `width`) in ND layout `layout` (ND_LAYOUTS, see the
    module docstring): `independent` is `make_mask(pattern, ...)`; `balanced` draws `make_mask(pattern, ...)`
    on each 2 x 2 sub-lattice with its own seed (`seed`, k), k = 0..3 in row-major order of the block, so each
    holds round(n / 2) attenuated photosites of its n; `regular` is `block_checkerboard` (`pattern` unused).
    Deterministic per seed."""
    check_nd_layout(layout)
    _check_size(height, width)
    if height % 2 or width % 2:
        raise ValueError(f"a Bayer sensor has an even width and height (whole 2 x 2 blocks), got {width} x "
                         f"{height}")
    if layout == "independent":
        return make_mask(pattern, height, width, seed=seed, **kw)
    if layout == "regular":
        return block_checkerboard(height, width)
    m = np.empty((height, width), bool)
    for k, (dy, dx) in enumerate(SUBLATTICES):
        m[dy::2, dx::2] = make_mask(pattern, height // 2, width // 2, seed=[int(seed), k], **kw)
    return m


def nd_layout_of(mask: np.ndarray, cfa_name: str) -> str:
    """The ND layout a mask has over a Bayer CFA: NO_ND without attenuated photosites, `regular` for
    `block_checkerboard` or its complement, `balanced` when each 2 x 2 sub-lattice holds half its photosites
    attenuated (round(n / 2) or, n odd, the other rounding), else `independent`; a monochrome sensor
    (`cfa_name` none) is `independent` whenever it has ND pixels."""
    m = np.asarray(mask, bool)
    if not m.any():
        return NO_ND
    if not cfas.is_colour(cfa_name) or m.shape[0] % 2 or m.shape[1] % 2:
        return "independent"
    reg = block_checkerboard(*m.shape)
    if np.array_equal(m, reg) or np.array_equal(m, ~reg):
        return "regular"
    half = all(abs(2 * int(m[dy::2, dx::2].sum()) - m[dy::2, dx::2].size) <= 1
               for dy, dx in SUBLATTICES)
    return "balanced" if half else "independent"


def _check_size(height: int, width: int) -> None:
    if height < 1 or width < 1:
        raise ValueError(f"mask size must be positive, got {height} x {width}")
