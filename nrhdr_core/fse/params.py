"""FSE parameters: the presets, their validation, the density switch and the tables the block kernels read.

Every preset is a complete, explicit parameter set; ``**params`` override single entries:

- ``window``: FFT window = support area (N x N); ``max_block``/``min_block``: quadtree block sizes;
  ``split_sigma``: area sigma below which a block of that size is not split further (Genser et al.);
- ``rho``: isotropic weight decay per block size; ``delta``: weight of already reconstructed pixels;
  ``gamma``: orthogonality-deficiency compensation (Seiler & Kaup, SPL 2010);
- iterations n = clip(round(``iter_c`` * sigma), ``iter_min``, ``iter_max``) (a conjugate pair counts 2;
  Genser et al., IWSSIP 2017); ``prior``: spectral prior on/off (Genser et al., IWSSIP 2018);
- ``domain``: "auto" | "linear" | "log"; ``log_offset``: None (the rule of :func:`domain.log_offset`) or
  c >= 0, the log domain is log2(x + c); ``offset_noise_k``: noise floor factor of that rule;
  ``log_scale_stops``: cap of the log domain's data scale; ``use_bounds``: clamp to lower/upper;
- ``local_bound``: 0 (off) or the size (3/5/7/9) of the known neighbourhood whose range, widened by
  ``local_margin`` stops, bounds a missing pixel in the log domain (the data's own bounds win);
- ``edge_penalty``, ``order_levels``, ``order_slack``: processing order (Genser et al., PCS 2018);
- ``sparse_below``/``sparse``: overrides applied below that share of known pixels.

docs/FSE.md "Presets" gives the measured trade of each preset.
"""
from __future__ import annotations

import math
from collections import namedtuple

import numpy as np

__all__ = ["FSE_PRESETS", "resolve_params", "density_params", "tables", "Tables"]

# Working states of the FSE frame (the ``state`` plane of the block kernels; not the pixel states of
# nrhdr_core.states): missing, known, reconstructed (weight delta for later blocks), noisy measurement
# (joint estimation, weighted), skipped (missing but left to the caller: weight 0, never counted nor written).
MISSING = 0
KNOWN = 1
RECONSTRUCTED = 2
NOISY = 3
SKIP = 4

_BASE = dict(
    window=32,
    max_block=16,
    min_block=4,
    split_sigma={16: 0.014, 8: 0.030, 4: 0.090},
    rho={16: 0.80, 8: 0.60, 4: 0.55, 2: 0.50},
    delta=0.5,
    gamma=0.5,
    iter_c=1000.0,
    iter_min=20,
    iter_max=100,
    prior=True,
    domain="auto",
    log_scale_stops=3.0,
    use_bounds=True,
    log_offset=None,
    offset_noise_k=2.0,
    local_bound=5,
    local_margin=1.0,
    edge_penalty=1.0,
    order_levels=4,
    order_slack=1,
    sparse_below=0.0,
    sparse={},
)

# published rho (fse-reference.md): slower decay, better when few pixels are known
_RHO_PUBLISHED = {16: 0.80, 8: 0.70, 4: 0.66, 2: 0.64}

FSE_PRESETS: dict[str, dict] = {
    # live preview: fixed 8 x 8 blocks in a 16 x 16 window, 16 iterations (8 conjugate pairs)
    "preview": dict(_BASE, window=16, max_block=8, min_block=8, iter_c=0.0, iter_min=16, iter_max=16,
                    gamma=0.7),
    # fast: 8 x 8 blocks, few iterations; the 32 x 32 window only below 30 % known
    "fast": dict(_BASE, window=16, max_block=8, min_block=8, iter_c=1000.0, iter_min=10, iter_max=60,
                 sparse_below=0.3, sparse=dict(window=32)),
    # balanced: quadtree 8/4 in a 16 x 16 window
    "balanced": dict(_BASE, window=16, max_block=8, min_block=4, iter_c=1500.0, iter_min=20,
                     iter_max=150, sparse_below=0.4, sparse=dict(window=32, rho=_RHO_PUBLISHED)),
    # best: quadtree 16/8/4 in a 32 x 32 window, up to 200 iterations
    "best": dict(_BASE, window=32, max_block=16, min_block=4, gamma=0.5, iter_c=2000.0, iter_min=40,
                 iter_max=200, sparse_below=0.4, sparse=dict(rho=_RHO_PUBLISHED)),
}


def resolve_params(preset: str = "balanced", **params) -> dict:
    """Preset merged with overrides; an unknown preset raises ``ValueError``, unknown keys ``TypeError``,
    invalid values ``ValueError``."""
    if preset not in FSE_PRESETS:
        raise ValueError(f"unknown FSE preset {preset!r}; choose one of {sorted(FSE_PRESETS)}")
    p = dict(FSE_PRESETS[preset])
    for k, v in params.items():
        if k not in p:
            raise TypeError(f"unknown FSE parameter {k!r}; known: {sorted(p)}")
        p[k] = v
    for k in p["sparse"]:
        if k not in p or k in ("sparse", "sparse_below"):
            raise TypeError(f"unknown FSE parameter {k!r} in 'sparse'")
    _check(p)
    return p


def _check(p):
    n = int(p["window"])
    if n not in (8, 16, 32, 64, 128):
        raise ValueError("FSE window must be a power of two in 8..128")
    for key in ("max_block", "min_block"):
        b = int(p[key])
        if b not in (1, 2, 4, 8, 16, 32) or b > n:
            raise ValueError(f"FSE {key} must be a power of two <= window")
    if p["min_block"] > p["max_block"]:
        raise ValueError("FSE min_block must be <= max_block")
    if p["domain"] not in ("auto", "linear", "log"):
        raise ValueError("FSE domain must be one of auto, linear, log")
    if int(p["local_bound"]) not in (0, 3, 5, 7, 9):
        raise ValueError("FSE local_bound must be 0 (off) or 3, 5, 7, 9")
    if not float(p["local_margin"]) >= 0.0:
        raise ValueError("FSE local_margin must be >= 0")
    if p["log_offset"] is not None and not float(p["log_offset"]) >= 0.0:
        raise ValueError("FSE log_offset must be None or >= 0")


def density_params(p: dict, known_share: float) -> dict:
    """``p`` with its ``sparse`` overrides applied when fewer than ``sparse_below`` of the pixels are known
    (a 32 x 32 window and slower weight decay win at 10-25 % known, lose at 50 %; docs/FSE.md "Presets")."""
    if known_share < float(p["sparse_below"]) and p["sparse"]:
        q = dict(p)
        q.update(p["sparse"])
        _check(q)
        return q
    return p


# sizes: block size per quadtree level; split: split_sigma per level; rho_tab: rho^r per level (r = distance
# to the window centre); prior2: squared spectral prior on the half spectrum [v, u]; tw_c/tw_s: twiddles
# cos/sin(2 pi t / N); bitrev: the FFT's bit-reversed order; phs: synthesis phases [lvl, cos/sin, k, m]
Tables = namedtuple("Tables", "sizes split rho_tab prior2 tw_c tw_s bitrev phs")

_TABLE_CACHE: dict = {}


def tables(p: dict) -> Tables:
    """The block kernels' read-only tables for the parameter set ``p`` (cached by the entries they use)."""
    key = (int(p["window"]), int(p["max_block"]), int(p["min_block"]), bool(p["prior"]),
           tuple(sorted((int(a), float(b)) for a, b in p["rho"].items())),
           tuple(sorted((int(a), float(b)) for a, b in p["split_sigma"].items())))
    t = _TABLE_CACHE.get(key)
    if t is None:
        t = _make_tables(p)
        if len(_TABLE_CACHE) > 32:
            _TABLE_CACHE.clear()
        _TABLE_CACHE[key] = t
    return t


def _make_tables(p):
    n = int(p["window"])
    h = n // 2 + 1
    nn = np.arange(n)
    tw_c = np.cos(2.0 * np.pi * nn / n).astype(np.float32)   # e^{-i 2 pi t/N} = (c, -s)
    tw_s = np.sin(2.0 * np.pi * nn / n).astype(np.float32)
    bits = int(round(math.log2(n)))
    bitrev = np.array([int(format(i, f"0{bits}b")[::-1], 2) for i in range(n)], dtype=np.int64)
    # spectral prior on the half spectrum, squared (selection works on energies; Genser et al. 2018)
    fu = np.minimum(nn, n - nn).astype(np.float64)[:, None]
    fv = np.arange(h, dtype=np.float64)[None, :]
    if p["prior"]:
        pr = np.clip(1.0 - math.sqrt(2.0) * np.sqrt(fu ** 2 + fv ** 2) / n, 0.0, 1.0)
    else:
        pr = np.ones((n, h))
    prior2 = np.ascontiguousarray((pr ** 2).T).astype(np.float32)   # (h, n): [v, u]
    # isotropic weight decay rho^r per block size level
    sizes = []
    b = int(p["max_block"])
    while b >= int(p["min_block"]):
        sizes.append(b)
        b //= 2
    c = (n - 1) / 2.0
    r = np.sqrt((nn[:, None] - c) ** 2 + (nn[None, :] - c) ** 2)
    rho_tab = np.empty((len(sizes), n, n), np.float32)
    split = np.zeros(len(sizes), np.float64)
    for i, s in enumerate(sizes):
        rho = float(p["rho"].get(s, min(p["rho"].values()) if s < min(p["rho"]) else max(p["rho"].values())))
        rho_tab[i] = (rho ** r).astype(np.float32)
        split[i] = float(p["split_sigma"].get(s, 0.0))
    sizes = np.array(sizes, np.int64)
    return Tables(sizes, split, rho_tab, prior2, tw_c, tw_s, bitrev, _phase_table(n, sizes, tw_c, tw_s))


def _phase_table(n, sizes, tw_c, tw_s):
    """The synthesis phases of every block size: [lvl, 0 / 1, k, m] = cos / sin(2 pi k (o + m) / N),
    o = (N - b) / 2 the block's offset in its window (entries of the twiddle tables)."""
    bmax = int(max(1, sizes.max()))
    ph = np.zeros((sizes.shape[0], 2, n, bmax), np.float32)
    k = np.arange(n)[:, None]
    for lv, b in enumerate(sizes):
        o = (n - int(b)) // 2
        t = (k * (o + np.arange(int(b))[None, :])) & (n - 1)
        ph[lv, 0, :, :b] = tw_c[t]
        ph[lv, 1, :, :b] = tw_s[t]
    return ph
