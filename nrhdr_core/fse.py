"""Frequency Selective Extrapolation (FSE) in numba.

Block-wise sparse Fourier model fitted to the known pixels of a support area around each block
(Seiler & Kaup, SPL 2010; Seiler et al., TIP 2015, "FSR"), with the refinements of Genser et al.
(IWSSIP 2017/2018, PCS 2018): adaptive iteration count, spectral prior, processing order by neighbour
availability. Facts: ``/work/shared/docs/fse-reference.md``; design and measured choices: ``docs/FSE.md``.

Public entry points: :func:`fse_reconstruct`, :data:`FSE_PRESETS`, :func:`warmup`.
Nothing is compiled at import time; kernels compile on first call (``cache=True``).
"""
from __future__ import annotations

import math
import warnings

import numpy as np
from numba import njit, prange, get_num_threads, set_num_threads
from numba.core import cgutils, types
from numba.extending import intrinsic
from llvmlite import ir as llvm_ir

from .scratch import ThreadScratch  # scratch per OS thread (issue 7)

__all__ = ["FSE_PRESETS", "fse_reconstruct", "warmup", "resolve_params"]

# --------------------------------------------------------------------------------------------------
# Presets. Every preset is a complete, explicit parameter set; ``**params`` override single entries.
# ``window``: FFT window = support area (N x N); ``max_block``/``min_block``: quadtree sizes;
# ``split_sigma``: area sigma below which a block of that size is not split further;
# ``rho``: isotropic weight decay per block size; ``delta``: weight of already reconstructed pixels;
# ``gamma``: orthogonality-deficiency compensation; iterations n = clip(round(iter_c * sigma),
# iter_min, iter_max) (a conjugate pair counts 2); ``prior``: spectral prior on/off;
# ``domain``: "auto" | "linear" | "log" | "local" (see docs/FSE.md); ``use_bounds``: clamp to lower/upper;
# ``log_offset``: None (the data-driven rule of :func:`log_offset`) or c >= 0, the log domain is log2(x + c);
# ``local_bound``: 0 (off) or the size (3/5/7/9) of the known neighbourhood whose range, widened by
# ``local_margin`` stops, bounds a missing pixel in the log domain (issue 8: overshoot around point
# sources; not used in the linear domain, where it was measured to cut true peaks of fine detail); the
# data's own bounds (clip, l_min) always win.
# --------------------------------------------------------------------------------------------------
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
    pair_exact=False,
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
    # fast: 8 x 8 blocks, few iterations; the 32 x 32 window only below 30 % known (session 4: HDR frames
    # at ~40 % known equal or +0.1 dB at 16 x 16 and 2x faster; Kodak at 35-38 % known -0.05..-0.25 dB)
    "fast": dict(_BASE, window=16, max_block=8, min_block=8, iter_c=1000.0, iter_min=10, iter_max=60,
                 sparse_below=0.3, sparse=dict(window=32)),
    # balanced: quadtree 8/4 in a 16 x 16 window (measured as good as 32 x 32 on Kodak, 3x cheaper)
    "balanced": dict(_BASE, window=16, max_block=8, min_block=4, iter_c=1500.0, iter_min=20,
                     iter_max=150, sparse_below=0.4, sparse=dict(window=32, rho=_RHO_PUBLISHED)),
    # best: quadtree 16/8/4 in a 32 x 32 window, up to 200 iterations
    "best": dict(_BASE, window=32, max_block=16, min_block=4, gamma=0.5, iter_c=2000.0, iter_min=40,
                 iter_max=200, sparse_below=0.4, sparse=dict(rho=_RHO_PUBLISHED)),
}


def resolve_params(preset: str = "balanced", **params) -> dict:
    """Preset merged with overrides; unknown keys raise ``TypeError``."""
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
        raise ValueError("window must be a power of two in 8..128")
    for key in ("max_block", "min_block"):
        b = int(p[key])
        if b not in (1, 2, 4, 8, 16, 32) or b > n:
            raise ValueError(f"{key} must be a power of two <= window")
    if p["min_block"] > p["max_block"]:
        raise ValueError("min_block must be <= max_block")
    if p["domain"] not in ("auto", "linear", "log", "local"):
        raise ValueError("domain must be one of auto, linear, log, local")
    if int(p["local_bound"]) not in (0, 3, 5, 7, 9):
        raise ValueError("local_bound must be 0 (off) or 3, 5, 7, 9")
    if not float(p["local_margin"]) >= 0.0:
        raise ValueError("local_margin must be >= 0")
    if p["log_offset"] is not None and not float(p["log_offset"]) >= 0.0:
        raise ValueError("log_offset must be None or >= 0")


def _density_params(p, known_share):
    """Apply ``sparse`` overrides when fewer than ``sparse_below`` of the pixels are known (measured:
    a 32 x 32 window and slower weight decay win at 10-25 % known, lose at 50 %; docs/FSE.md)."""
    if known_share < float(p["sparse_below"]) and p["sparse"]:
        q = dict(p)
        q.update(p["sparse"])
        _check(q)
        return q
    return p


# --------------------------------------------------------------------------------------------------
# Tables
# --------------------------------------------------------------------------------------------------
def _tables(p):
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


_TABLE_CACHE: dict = {}


def _make_tables(p):
    n = int(p["window"])
    h = n // 2 + 1
    nn = np.arange(n)
    ang = 2.0 * np.pi * (np.outer(nn, nn) % n) / n
    cos_t = np.cos(ang).astype(np.float32)          # (n, n), symmetric: cos(2 pi j v / N)
    sin_t = np.sin(ang).astype(np.float32)
    tw_c = np.cos(2.0 * np.pi * nn / n).astype(np.float32)   # e^{-i 2 pi t/N} = (c, -s)
    tw_s = np.sin(2.0 * np.pi * nn / n).astype(np.float32)
    bits = int(round(math.log2(n)))
    bitrev = np.array([int(format(i, f"0{bits}b")[::-1], 2) for i in range(n)], dtype=np.int64)
    # spectral prior on the half spectrum, squared (selection works on energies)
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
    return cos_t, sin_t, tw_c, tw_s, bitrev, prior2, rho_tab, split, np.array(sizes, np.int64)


# --------------------------------------------------------------------------------------------------
# Scheduling: quadtree leaves and rounds of independent tiles
# --------------------------------------------------------------------------------------------------
@njit(cache=True, nogil=True)
def _integral(img, state):
    h, w = img.shape
    c = np.zeros((h + 1, w + 1), np.float64)
    s1 = np.zeros((h + 1, w + 1), np.float64)
    s2 = np.zeros((h + 1, w + 1), np.float64)
    for y in range(h):
        rc = 0.0
        r1 = 0.0
        r2 = 0.0
        for x in range(w):
            if state[y, x] == 1:
                v = np.float64(img[y, x])
                rc += 1.0
                r1 += v
                r2 += v * v
            c[y + 1, x + 1] = c[y, x + 1] + rc
            s1[y + 1, x + 1] = s1[y, x + 1] + r1
            s2[y + 1, x + 1] = s2[y, x + 1] + r2
    return c, s1, s2


@njit(cache=True, nogil=True, inline="always")
def _box(a, y0, x0, y1, x1):
    return a[y1, x1] - a[y0, x1] - a[y1, x0] + a[y0, x0]


@njit(cache=True, nogil=True)
def _area_sigma(c, s1, s2, y, x, b, n, h, w, scale, local):
    o = (n - b) // 2
    y0 = max(y - o, 0)
    x0 = max(x - o, 0)
    y1 = min(y - o + n, h)
    x1 = min(x - o + n, w)
    if y1 <= y0 or x1 <= x0:
        return 0.0
    cnt = _box(c, y0, x0, y1, x1)
    if cnt < 2.0:
        return 0.0
    m = _box(s1, y0, x0, y1, x1) / cnt
    var = _box(s2, y0, x0, y1, x1) / cnt - m * m
    if var < 0.0:
        var = 0.0
    sc = scale
    if local:
        sc = abs(m) * scale
        if sc <= 0.0:
            return 0.0
    return math.sqrt(var) / sc


@njit(cache=True, nogil=True)
def _missing_per_tile(state, tile):
    """Pixels needing the model (state 0 missing, 3 noisy measurement) of every tile, row-major tiles."""
    h, w = state.shape
    tw = (w + tile - 1) // tile
    miss = np.zeros(((h + tile - 1) // tile) * tw, np.int64)
    for y in range(h):
        base = (y // tile) * tw
        for tx in range(tw):
            c = 0
            for x in range(tx * tile, min(tx * tile + tile, w)):
                st = state[y, x]
                c += 1 if (st == 0 or st == 3) else 0
            miss[base + tx] += c
    return miss


@njit(cache=True, nogil=True)
def _any_missing(state, y, x, b):
    h, w = state.shape
    for yy in range(y, min(y + b, h)):
        for xx in range(x, min(x + b, w)):
            st = state[yy, xx]
            if st == 0 or st == 3:
                return True
    return False


@njit(cache=True, nogil=True)
def _quadtree_leaves(img, state, tile, n, sizes, split, scale, local, miss):
    """Quadtree leaves of every tile, depth-first in z-order (Genser et al.: a block of size b is a leaf
    when the sigma of its support area is below split[b], else it is split down to the smallest size);
    only blocks with a missing pixel are kept: blocks with nothing missing cost nothing.
    Returns (leaf_ptr, leaf_y, leaf_x, leaf_lvl)."""
    h, w = state.shape
    tw = (w + tile - 1) // tile
    nt = miss.shape[0]
    need_sigma = False
    for i in range(sizes.shape[0] - 1):
        if split[i] > 0.0:
            need_sigma = True
    if need_sigma:
        c, s1, s2 = _integral(img, state)
    else:
        c = np.zeros((1, 1))
        s1 = c
        s2 = c
    cap = 16
    for t in range(nt):
        if miss[t] > 0:
            cap += (tile // sizes[sizes.shape[0] - 1]) ** 2
    leaf_y = np.empty(cap, np.int64)
    leaf_x = np.empty(cap, np.int64)
    leaf_l = np.empty(cap, np.int64)
    leaf_ptr = np.zeros(nt + 1, np.int64)
    sy = np.empty(4 * 64, np.int64)
    sx = np.empty(4 * 64, np.int64)
    sl = np.empty(4 * 64, np.int64)
    nl = 0
    for t in range(nt):
        leaf_ptr[t] = nl
        if miss[t] == 0:
            continue
        sy[0] = (t // tw) * tile
        sx[0] = (t % tw) * tile
        sl[0] = 0
        sp = 1
        while sp > 0:
            sp -= 1
            y = sy[sp]
            x = sx[sp]
            lv = sl[sp]
            b = sizes[lv]
            if y >= h or x >= w or not _any_missing(state, y, x, b):
                continue
            leaf = lv == sizes.shape[0] - 1
            if not leaf and split[lv] > 0.0:
                leaf = _area_sigma(c, s1, s2, y, x, b, n, h, w, scale, local) < split[lv]
            if leaf:
                leaf_y[nl] = y
                leaf_x[nl] = x
                leaf_l[nl] = lv
                nl += 1
            else:
                hb = b // 2
                # push in reverse so that the top-left child is processed first
                sy[sp] = y + hb
                sx[sp] = x + hb
                sy[sp + 1] = y + hb
                sx[sp + 1] = x
                sy[sp + 2] = y
                sx[sp + 2] = x + hb
                sy[sp + 3] = y
                sx[sp + 3] = x
                for q in range(4):
                    sl[sp + q] = lv + 1
                sp += 4
    leaf_ptr[nt] = nl
    return leaf_ptr, leaf_y[:nl], leaf_x[:nl], leaf_l[:nl]


@njit(cache=True, nogil=True)
def _rounds(miss, h, w, tile, edge_penalty, levels, slack):
    """Processing order by neighbour availability (Genser et al., PCS 2018): a tile's priority is the
    missing share of its 3 x 3 tile neighbourhood (not yet reconstructed; out-of-image neighbours count
    ``edge_penalty``), quantised to ``levels``; a round is a greedy set of mutually non-adjacent tiles
    with level <= lowest + ``slack``, so its tiles are independent. Returns (tile_round, round_ptr,
    round_tiles, n_rounds)."""
    th = (h + tile - 1) // tile
    tw = (w + tile - 1) // tile
    nt = th * tw
    tile_round = np.full(nt, -1, np.int64)
    rem = 0
    for t in range(nt):
        if miss[t] > 0:
            tile_round[t] = -2
            rem += 1
    cur = np.zeros(nt, np.float64)
    for t in range(nt):
        ty = t // tw
        tx = t % tw
        area = min(tile, h - ty * tile) * min(tile, w - tx * tile)
        cur[t] = miss[t] / area
    lvl = np.zeros(nt, np.int64)
    in_round = np.zeros(nt, np.bool_)
    round_tiles = np.empty(max(rem, 1), np.int64)
    round_ptr = np.zeros(rem + 2, np.int64)
    r = 0
    k = 0
    while rem > 0:
        lmin = 1 << 60
        for t in range(nt):
            if tile_round[t] != -2:
                continue
            ty = t // tw
            tx = t % tw
            p = 0.0
            for dy in range(-1, 2):
                for dx in range(-1, 2):
                    yy = ty + dy
                    xx = tx + dx
                    if yy < 0 or yy >= th or xx < 0 or xx >= tw:
                        p += edge_penalty
                    else:
                        p += cur[yy * tw + xx]
            lv = int(p / 9.0 * levels)
            lvl[t] = lv
            if lv < lmin:
                lmin = lv
        round_ptr[r] = k
        for t in range(nt):
            if tile_round[t] != -2 or lvl[t] > lmin + slack:
                continue
            ty = t // tw
            tx = t % tw
            ok = True
            for dy in range(-1, 2):
                for dx in range(-1, 2):
                    yy = ty + dy
                    xx = tx + dx
                    if 0 <= yy < th and 0 <= xx < tw and in_round[yy * tw + xx]:
                        ok = False
            if ok:
                in_round[t] = True
                round_tiles[k] = t
                k += 1
        for i in range(round_ptr[r], k):
            t = round_tiles[i]
            in_round[t] = False
            tile_round[t] = r
            cur[t] = 0.0
            rem -= 1
        r += 1
    round_ptr[r] = k
    return tile_round, round_ptr[: r + 1], round_tiles[:k], r


@njit(cache=True, nogil=True)
def _plan(img, state, tile, n, sizes, split, scale, local, edge_penalty, levels, slack):
    """Quadtree leaves per tile (only leaves with missing pixels) and the round of every tile.

    Returns (tile_round, round_ptr, round_tiles, leaf_ptr, leaf_y, leaf_x, leaf_lvl, n_rounds)."""
    h, w = state.shape
    miss = _missing_per_tile(state, tile)
    leaf_ptr, leaf_y, leaf_x, leaf_l = _quadtree_leaves(img, state, tile, n, sizes, split, scale, local, miss)
    tile_round, round_ptr, round_tiles, r = _rounds(miss, h, w, tile, edge_penalty, levels, slack)
    return tile_round, round_ptr, round_tiles, leaf_ptr, leaf_y, leaf_x, leaf_l, r


# --------------------------------------------------------------------------------------------------
# One block: the FSE of Seiler & Kaup (SPL 2010), one step per helper
# --------------------------------------------------------------------------------------------------
# The helpers take the window size ``n`` as an argument and are inlined (numba IR, ``inline="always"``)
# into the block kernel that :func:`_make_block_kernel` builds: in the kernel for the 16 x 16 window
# ``n`` is the compile-time constant of the factory's closure, so the short loops get fixed trip counts
# that LLVM unrolls and vectorises (measured ~4x on the gather against a runtime ``n``); the generic
# kernel gets ``n`` at run time. One source, two specialisations, both cached by numba (its cache keys
# a closure by the values it closes over).
_INL = dict(cache=True, nogil=True, fastmath=True, inline="always")


@njit(**_INL)
def _gather(img, state, tile_round, tshift, tw_tiles, t_self, r_cur, ay, ax, lvl, n, rho_tab, delta,
            wbuf, xbuf, joint, wp):
    """Step 1, spatial weights w = s * rho^r and values f of the N x N support area whose top-left corner
    is (ay, ax), into wbuf / xbuf: s = 1 for known pixels, ``delta`` for reconstructed ones of this tile
    or of a tile of an earlier round (same-round tiles are never read), 0 for missing ones and outside;
    `joint` (a compile-time constant of the kernel): ``wp[y, x]`` for noisy measurements (state 3)."""
    h, w = img.shape
    for i in range(n):
        y = ay + i
        # (direct 2-D indexing, no row views: a view costs an atomic reference-count update on the
        # array shared by all threads)
        if y < 0 or y >= h:
            for j in range(n):
                wbuf[i, j] = 0.0
                xbuf[i, j] = 0.0
            continue
        j0 = max(0, -ax)
        j1 = min(n, w - ax)
        for j in range(j0):
            wbuf[i, j] = 0.0
            xbuf[i, j] = 0.0
        for j in range(j1, n):
            wbuf[i, j] = 0.0
            xbuf[i, j] = 0.0
        tbase = (y >> tshift) * tw_tiles
        tsz = 1 << tshift
        tc0 = (ax + j0) >> tshift
        if ((ax + j1 - 1) >> tshift) - tc0 <= 2:
            # common case (window spans <= 3 tile columns): the same-round rule of the three columns
            # as selects, one branch-free pass over the row that vectorises
            d0 = np.float32(0.0)
            d1 = np.float32(0.0)
            d2 = np.float32(0.0)
            tt = tbase + tc0
            if tt == t_self or tile_round[tt] < r_cur:
                d0 = np.float32(delta)
            if tc0 + 1 < tw_tiles and (tt + 1 == t_self or tile_round[tt + 1] < r_cur):
                d1 = np.float32(delta)
            if tc0 + 2 < tw_tiles and (tt + 2 == t_self or tile_round[tt + 2] < r_cur):
                d2 = np.float32(delta)
            e0 = ((tc0 + 1) << tshift) - ax
            e1 = e0 + (1 << tshift)
            for jj in range(j0, j1):
                xx = ax + jj
                dwt = d0 if jj < e0 else (d1 if jj < e1 else d2)
                st = state[y, xx]
                fs = np.float32(1.0) if st == 1 else (dwt if st == 2 else np.float32(0.0))
                if joint:
                    fs = wp[y, xx] if st == 3 else fs
                wv = fs * rho_tab[lvl, i, jj]
                wbuf[i, jj] = wv
                xbuf[i, jj] = img[y, xx] if wv > 0.0 else np.float32(0.0)
            continue
        j = j0
        while j < j1:
            # one segment per tile column: the same-round rule is decided once per segment
            x = ax + j
            tt = tbase + (x >> tshift)
            allowed = tt == t_self or tile_round[tt] < r_cur
            dwt = np.float32(delta) if allowed else np.float32(0.0)
            je = min(j1, j + tsz - (x & (tsz - 1)))
            # branch-free (random masks make the state unpredictable): selects instead of branches
            for jj in range(j, je):
                xx = ax + jj
                st = state[y, xx]
                fs = np.float32(1.0) if st == 1 else (dwt if st == 2 else np.float32(0.0))
                if joint:
                    fs = wp[y, xx] if st == 3 else fs
                wv = fs * rho_tab[lvl, i, jj]
                wbuf[i, jj] = wv
                xbuf[i, jj] = img[y, xx] if wv > 0.0 else np.float32(0.0)
            j = je


@njit(**_INL)
def _moments(wbuf, xbuf, n):
    """(sum w, sum w f, count, sum f, sum f^2) over the usable pixels of the area: a pure reduction
    pass (no stores), which vectorises."""
    sw = 0.0
    swf = 0.0
    cnt = 0.0
    s1 = 0.0
    s2 = 0.0
    for i in range(n):
        for j in range(n):
            wv = wbuf[i, j]
            fv = xbuf[i, j]
            sw += wv
            swf += wv * fv
            cnt += 1.0 if wv > 0.0 else 0.0
            s1 += fv
            s2 += fv * fv
    return sw, swf, cnt, s1, s2


@njit(**_INL)
def _iteration_count(cnt, s1, s2, scale, local, iter_c, iter_min, iter_max):
    """Texture-adaptive iteration count (Genser et al. 2017): clip(round(iter_c * sigma), iter_min,
    iter_max), sigma = (unweighted) std of the usable pixels relative to the data scale."""
    m1 = s1 / cnt
    var = s2 / cnt - m1 * m1
    if var < 0.0:
        var = 0.0
    sc = scale
    if local:
        sc = abs(m1) * scale
    sigma = 0.0
    if sc > 0.0:
        sigma = math.sqrt(var) / sc
    nit = int(round(iter_c * sigma))
    if nit < iter_min:
        nit = iter_min
    if nit > iter_max:
        nit = iter_max
    return nit


@njit(**_INL)
def _fft_pass(zb, off_r, off_i, n, tw_c, tw_s):
    """One 1-D radix-2 decimation-in-frequency FFT (Gentleman-Sande, in place, output in bit-reversed
    order) along the first index of the complex n x n block zb[off_r + p n + l] + i zb[off_i + p n + l],
    batched over the n lanes l: every butterfly is a contiguous, vectorised loop over the lanes. One
    flat buffer with compile-time offsets (n = 16) lets LLVM prove that the rows do not alias."""
    half = n // 2
    step = 1
    while half >= 1:
        for start in range(0, n, 2 * half):
            for k in range(half):
                p = (start + k) * n
                q = p + half * n
                c = tw_c[k * step]      # e^{-i 2 pi k step / n} = c - i s
                s = tw_s[k * step]
                for l in range(n):
                    ar = zb[off_r + p + l]
                    ai = zb[off_i + p + l]
                    br = zb[off_r + q + l]
                    bi = zb[off_i + q + l]
                    zb[off_r + p + l] = ar + br
                    zb[off_i + p + l] = ai + bi
                    dr = ar - br
                    di = ai - bi
                    zb[off_r + q + l] = dr * c + di * s
                    zb[off_i + q + l] = di * c - dr * s
        half //= 2
        step *= 2


@njit(**_INL)
def _pack_scale(cnt, s1, s2):
    """(2^-e, 2^e) with 2^e ~ the std of the usable values (from ``_moments``; 1 when they are
    constant): w (f - mean) 2^-e is of the magnitude of w, exactly (a power of two), so a k-fold
    scaled input (k a power of two) gives the same packed FFT, and any k the same up to rounding."""
    m1 = s1 / cnt
    var = s2 / cnt - m1 * m1
    e = 0
    if var > 0.0:
        e = math.frexp(math.sqrt(var))[1]
    return np.float32(math.ldexp(1.0, -e)), np.float32(math.ldexp(1.0, e))


@njit(**_INL)
def _split_bin(zb, n, ia, ib, v, u, hx, prior2, wr, wi, rr, ri, en):
    """One bin of the split of Z = DFT(w + i x) (zb[2n^2 + .] real, zb[3n^2 + .] imaginary, ia: k,
    ib: -k): W = (Z(k) + conj Z(-k)) / 2 into its copies on the doubled periodic grid (rows v and, for
    v < n/2 + 1, v + n; columns u and u + n); for v < n/2 + 1 also R = (Z(k) - conj Z(-k)) / 2i
    (times 2 hx = the packing's inverse scale) and its selection energy |R|^2 prior^2."""
    nn = n * n
    ar = zb[2 * nn + ia]
    ai = zb[3 * nn + ia]
    br = zb[2 * nn + ib]
    bi = zb[3 * nn + ib]
    wre = np.float32(0.5) * (ar + br)
    wim = np.float32(0.5) * (ai - bi)
    wr[v, u] = wre
    wi[v, u] = wim
    wr[v, u + n] = wre
    wi[v, u + n] = wim
    if 2 * v <= n:
        wr[v + n, u] = wre
        wi[v + n, u] = wim
        wr[v + n, u + n] = wre
        wi[v + n, u + n] = wim
        rre = hx * (ai + bi)
        rim = hx * (br - ar)
        rr[v, u] = rre
        ri[v, u] = rim
        en[v, u] = (rre * rre + rim * rim) * prior2[v, u]


@njit(**_INL)
def _forward_dft(n, tw_c, tw_s, bitrev, zb, xi, prior2, wr, wi, rr, ri, en, rm):
    """Step 2, W = DFT(w) and R = DFT(w (f - mean)) from zb[0:n^2] = w and zb[n^2:2n^2] = w (f - mean) / xi
    (row-major [i, j]; xi a power of two, see ``_pack_scale``) straight into the layout of the
    iterations: R[v, u] (v = half-spectrum index, u full, contiguous) with its selection energies |R|^2 prior^2 and their per-row maxima; W on a
    doubled periodic grid W[v', u'] so that W(j - k) and W(j + k) are contiguous slices without modulo
    (rows >= n + n/2 + 1 are never read and not written). Both signals are real: one complex 2-D FFT
    of z = w + i w (f - mean), split by conjugate symmetry, W(k) = (Z(k) + conj Z(-k)) / 2,
    R(k) = (Z(k) - conj Z(-k)) / 2i. The FFT is batched radix-2 over the rows (lanes: the columns), a
    transpose that also undoes the bit reversal of the row frequencies, then over the columns (lanes:
    the row frequencies u, natural order). Issue 7 session 4 (docs/FSE.md): replaces the separable
    dot-product DFT and the separate layout step."""
    nn = n * n
    hx = np.float32(0.5) * xi
    _fft_pass(zb, 0, nn, n, tw_c, tw_s)              # along i: row p holds u = bitrev[p]
    for p in range(n):
        bp = bitrev[p]
        for j in range(n):
            zb[2 * nn + j * n + bp] = zb[p * n + j]
            zb[3 * nn + j * n + bp] = zb[nn + p * n + j]
    _fft_pass(zb, 2 * nn, 3 * nn, n, tw_c, tw_s)     # along j: Z(u, v) at [bitrev[v], u]
    for v in range(n):
        ra = bitrev[v] * n
        rb = bitrev[(n - v) & (n - 1)] * n
        _split_bin(zb, n, ra, rb, v, 0, hx, prior2, wr, wi, rr, ri, en)
        for u in range(1, n):
            _split_bin(zb, n, ra + u, rb + n - u, v, u, hx, prior2, wr, wi, rr, ri, en)
    _row_maxima(n, en, rm)


@njit(**_INL)
def _row_maxima(n, en, rm):
    """rm[v] = max_u en[v, u] with four independent running maxima (n is a multiple of 4): a single
    chain of scalar max operations was latency-bound and kept the update loop from vectorising
    (measured 209 -> 116 ns per pair update at n = 16). The maximum is exact; the energies, now computed
    by vectorised code, may differ from the scalar ones by float rounding (FMA contraction), which can
    flip a near-tie bin choice: outputs within float rounding, PSNR within 0.001 dB (docs/BENCHMARKS.md)."""
    hh = n // 2 + 1
    for v in range(hh):
        m0 = en[v, 0]
        m1 = en[v, 1]
        m2 = en[v, 2]
        m3 = en[v, 3]
        for u in range(4, n, 4):
            m0 = max(m0, en[v, u])
            m1 = max(m1, en[v, u + 1])
            m2 = max(m2, en[v, u + 2])
            m3 = max(m3, en[v, u + 3])
        rm[v] = max(max(m0, m1), max(m2, m3))


@njit(**_INL)
def _select_bin(n, en, rm):
    """Step 3a, basis choice: the half-spectrum bin (kv, ku) of the largest weighted residual energy
    |R(k)|^2 prior(k)^2 (per-row maxima first, then the row); best = that energy."""
    hh = n // 2 + 1
    kv = 0
    best = rm[0]
    for v in range(1, hh):
        if rm[v] > best:
            best = rm[v]
            kv = v
    ku = 0
    for u in range(n):
        if en[kv, u] == best:
            ku = u
            break
    return kv, ku, best


@njit(**_INL)
def _pair_projection(kv, ku, w0, gamma, wr, wi, rr, ri, cr, ci):
    """``pair_exact``: the weighted least-squares projection onto the real pair {phi_k, phi_-k},
    R = c W(0) + conj(c) W(2k), instead of c = gamma R(k) / W(0); (cr, ci) unchanged when ill-posed."""
    w2r = wr[2 * kv, 2 * ku]
    w2i = wi[2 * kv, 2 * ku]
    den = w0 * w0 - (w2r * w2r + w2i * w2i)
    if den > 1e-3 * w0 * w0:
        r0 = rr[kv, ku]
        i0 = ri[kv, ku]
        gg = np.float32(gamma) / den
        cr = (r0 * w0 - (r0 * w2r + i0 * w2i)) * gg
        ci = (i0 * w0 - (r0 * w2i - i0 * w2r)) * gg
    return cr, ci


@njit(**_INL)
def _update_self(n, kv, ku, cr, prior2, wr, wi, rr, ri, en, rm):
    """Step 3c for a self-conjugate bin (DC, Nyquist): R(j) -= c W(j - k), c real; energies refreshed."""
    hh = n // 2 + 1
    u1 = n - ku
    for v in range(hh):
        v1 = v - kv + n
        for u in range(n):
            nr = rr[v, u] - cr * wr[v1, u1 + u]
            ni = ri[v, u] - cr * wi[v1, u1 + u]
            rr[v, u] = nr
            ri[v, u] = ni
            en[v, u] = (nr * nr + ni * ni) * prior2[v, u]
    _row_maxima(n, en, rm)


@njit(**_INL)
def _update_pair(n, kv, ku, cr, ci, prior2, wr, wi, rr, ri, en, rm):
    """Step 3c for a conjugate pair, in the frequency domain without an inverse FFT:
    R(j) -= c W(j - k) + conj(c) W(j + k) (= DFT(w (f - g)) exactly); energies refreshed."""
    hh = n // 2 + 1
    u1 = n - ku
    for v in range(hh):
        v1 = v - kv + n
        v2 = v + kv
        for u in range(n):
            a = wr[v1, u1 + u]
            bq = wi[v1, u1 + u]
            a2 = wr[v2, ku + u]
            b2 = wi[v2, ku + u]
            nr = rr[v, u] - (cr * (a + a2) + ci * (b2 - bq))
            ni = ri[v, u] - (cr * (bq + b2) + ci * (a - a2))
            rr[v, u] = nr
            ri[v, u] = ni
            en[v, u] = (nr * nr + ni * ni) * prior2[v, u]
    _row_maxima(n, en, rm)


@njit(**_INL)
def _extrapolate(n, nit, gamma, pair_exact, prior2, wr, wi, rr, ri, en, rm, sel_u, sel_v, sel_r, sel_i):
    """Step 3, the iterations: choose the basis function (bin) of largest weighted residual energy,
    its coefficient c = gamma R(k) / W(0) (gamma: orthogonality-deficiency compensation), add c at k
    and conj(c) at -k to the model (a pair counts 2 iterations, DC / Nyquist 1), update the residual
    spectrum. The model's coefficients go to sel_*; returns their count."""
    w0 = wr[0, 0]
    g = np.float32(gamma) / w0
    it = 0
    ns = 0
    while it < nit:
        kv, ku, best = _select_bin(n, en, rm)
        if best <= 0.0:
            break
        cr = rr[kv, ku] * g
        ci = ri[kv, ku] * g
        selfm = ((ku == 0) or (2 * ku == n)) and ((kv == 0) or (2 * kv == n))
        if pair_exact and not selfm:
            cr, ci = _pair_projection(kv, ku, w0, gamma, wr, wi, rr, ri, cr, ci)
        if selfm:
            ci = np.float32(0.0)
            _update_self(n, kv, ku, cr, prior2, wr, wi, rr, ri, en, rm)
            it += 1
        else:
            _update_pair(n, kv, ku, cr, ci, prior2, wr, wi, rr, ri, en, rm)
            it += 2
        sel_u[ns] = ku
        sel_v[ns] = kv
        sel_r[ns] = cr if selfm else 2.0 * cr
        sel_i[ns] = ci if selfm else 2.0 * ci
        ns += 1
    return ns


@njit(cache=True, nogil=True)
def _bit_reversal(n):
    """bitrev[i]: i with its log2(n) bits reversed (the output order of ``_fft_pass``)."""
    bits = 0
    while (1 << bits) < n:
        bits += 1
    br = np.zeros(n, np.int64)
    for i in range(n):
        for bb in range(bits):
            br[i] |= ((i >> bb) & 1) << (bits - 1 - bb)
    return br


@njit(cache=True, nogil=True)
def _phase_table(n, sizes, tw_c, tw_s):
    """The synthesis phases of every block size: [lvl, 0 / 1, k, m] = cos / sin(2 pi k (o + m) / N),
    o = (N - b) / 2 the block's offset in its window (the same table entries the per-block lookups
    gave, so the synthesis is unchanged bit for bit)."""
    nl = sizes.shape[0]
    bmax = 1
    for lv in range(nl):
        bmax = max(bmax, sizes[lv])
    ph = np.zeros((nl, 2, n, bmax), np.float32)
    for lv in range(nl):
        b = sizes[lv]
        o = (n - b) // 2
        for k in range(n):
            for m in range(b):
                t = (k * (o + m)) & (n - 1)
                ph[lv, 0, k, m] = tw_c[t]
                ph[lv, 1, k, m] = tw_s[t]
    return ph


@njit(**_INL)
def _synthesize(b, lvl, ns, sel_u, sel_v, sel_r, sel_i, phs, xbuf):
    """Step 4, the model on the block only: g(m) - mean = sum Re(c e^{+i 2 pi k m / N}) into xbuf[:b, :b]
    (no inverse FFT). Separable phases: Re(c e^{i(a + b)}) = cos b (c_r cos a - c_i sin a) - sin b
    (c_r sin a + c_i cos a), a = 2 pi u (o + i) / N per row, b = 2 pi v (o + j) / N per column, read
    from the block size's phase table (``_phase_table``), vectorised over the block row."""
    for i in range(b):
        for j in range(b):
            xbuf[i, j] = 0.0
    for q in range(ns):
        cq = sel_r[q]
        sq = sel_i[q]
        uq = sel_u[q]
        vq = sel_v[q]
        for i in range(b):
            ca = phs[lvl, 0, uq, i]
            sa = phs[lvl, 1, uq, i]
            pp = cq * ca - sq * sa
            qq = cq * sa + sq * ca
            for j in range(b):
                xbuf[i, j] += pp * phs[lvl, 0, vq, j] - qq * phs[lvl, 1, vq, j]


@njit(**_INL)
def _write_block(img, state, lo, hi, use_lo, use_hi, by, bx, b, mean, xbuf, joint, mest):
    """Step 5, the block's missing pixels only: mean + model, clamped to [lo, hi] where bounded, become
    "reconstructed" (state 2, weight delta) for later blocks; known pixels stay bit-exact. `joint`: the
    model at noisy measurements (state 3, which stay measurements for later blocks) goes to ``mest``.
    A block inside the image is written branch-free (random masks make ``state`` unpredictable: the
    branchy loop measured ~1.3 us per 8 x 8 block): every pixel is stored, a known or skipped one with
    its own value and state (no other thread writes this block)."""
    h, w = img.shape
    if not joint and by + b <= h and bx + b <= w:
        for i in range(b):
            y = by + i
            for j in range(b):
                x = bx + j
                st = state[y, x]
                val = np.float32(mean + xbuf[i, j])
                if use_lo:
                    val = max(val, lo[y, x])
                if use_hi:
                    val = min(val, hi[y, x])
                miss = st == 0
                img[y, x] = val if miss else img[y, x]
                state[y, x] = np.uint8(2) if miss else st
        return
    for i in range(b):
        y = by + i
        if y >= h:
            break
        for j in range(b):
            x = bx + j
            if x >= w:
                break
            st = state[y, x]
            if st != 0:
                if joint and st == 3:
                    val = np.float32(mean + xbuf[i, j])
                    if use_lo and val < lo[y, x]:
                        val = lo[y, x]
                    if use_hi and val > hi[y, x]:
                        val = hi[y, x]
                    mest[y, x] = val
                continue
            val = np.float32(mean + xbuf[i, j])
            if use_lo and val < lo[y, x]:
                val = lo[y, x]
            if use_hi and val > hi[y, x]:
                val = hi[y, x]
            img[y, x] = val
            state[y, x] = 2


def _make_block_kernel(n_fixed, joint=False):
    """The block kernel, FSE of one quadtree leaf; ``n_fixed`` > 0: specialised for that window size (a
    compile-time constant), 0: the window size is the ``n`` argument. ``joint`` (compile-time): noisy
    measurements (state 3) enter the fit with the weights ``wp`` and the model there is written to
    ``mest`` (joint estimation, docs/FSE.md); without it ``wp``/``mest`` are never read."""

    @njit(cache=True, nogil=True, fastmath=True)
    def block_kernel(img, state, lo, hi, use_lo, use_hi, tile_round, tshift, tw_tiles, t_self, r_cur,
                     by, bx, b, lvl, n, rho_tab, bitrev, tw_c, tw_s, prior2, phs,
                     delta, gamma, iter_c, iter_min, iter_max, scale, local, pair_exact,
                     wbuf, xbuf, zb, wr, wi, rr, ri, en, rm, sel_u, sel_v, sel_r, sel_i,
                     wp, mest):
        """Reconstruct the missing pixels of block (by, bx, b) in place (Seiler & Kaup, SPL 2010: weighted
        projection of the support area onto DFT basis functions, one chosen per iteration, residual
        updated in the frequency domain). Returns False if its support area has no usable pixel (left
        for the fallback)."""
        if n_fixed > 0:
            n = n_fixed
        o = (n - b) // 2
        _gather(img, state, tile_round, tshift, tw_tiles, t_self, r_cur, by - o, bx - o, lvl, n, rho_tab,
                delta, wbuf, xbuf, joint, wp)
        sw, swf, cnt, s1, s2 = _moments(wbuf, xbuf, n)
        if sw <= 0.0:
            return False
        mean = swf / sw     # weighted mean removed (ours: translation invariance, float32 conditioning)
        nit = _iteration_count(cnt, s1, s2, scale, local, iter_c, iter_min, iter_max)
        fm = np.float32(mean)
        # w and w (f - mean) share one complex FFT (_forward_dft): the second is brought to the first's
        # magnitude by a power of two 2^-e ~ 1 / std(f) (exact, undone in the split), so that the
        # rounding of one does not swamp the other whatever the data scale (scale invariance)
        xs, xi = _pack_scale(cnt, s1, s2)
        nn = n * n
        for i in range(n):
            for j in range(n):
                wv = wbuf[i, j]
                zb[i * n + j] = wv
                zb[nn + i * n + j] = wv * (xbuf[i, j] - fm) * xs
        _forward_dft(n, tw_c, tw_s, bitrev, zb, xi, prior2, wr, wi, rr, ri, en, rm)
        ns = _extrapolate(n, nit, gamma, pair_exact, prior2, wr, wi, rr, ri, en, rm,
                          sel_u, sel_v, sel_r, sel_i)
        _synthesize(b, lvl, ns, sel_u, sel_v, sel_r, sel_i, phs, xbuf)
        _write_block(img, state, lo, hi, use_lo, use_hi, by, bx, b, mean, xbuf, joint, mest)
        return True

    return block_kernel


# the common 16 x 16 window (preview, fast, balanced) and any other window
_block16 = _make_block_kernel(16)
_block32 = _make_block_kernel(32)   # `best`, and `fast` / `balanced` below 40 % known
_block = _make_block_kernel(0)
# joint estimation with noisy measurements (state 3): separate specialisations, the plain ones unchanged
_block16j = _make_block_kernel(16, True)
_blockj = _make_block_kernel(0, True)

@intrinsic
def _fetch_add(typingctx, counter, i):
    """counter[i] += 1 as one atomic operation; returns the value before (dynamic scheduling)."""
    sig = types.int64(counter, i)

    def codegen(context, builder, signature, args):
        aryty, ity = signature.args
        ary = context.make_array(aryty)(context, builder, args[0])
        idx = context.cast(builder, args[1], ity, types.intp)
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [idx])
        return builder.atomic_rmw("add", ptr, context.get_constant(types.int64, 1), "monotonic")

    return sig, codegen


@intrinsic
def _prefetch(typingctx, arr, y, x):
    """Hint the cache line of arr[y, x] into the cache (llvm.prefetch, read, high locality); y, x must
    be inside the array."""
    sig = types.void(arr, y, x)

    def codegen(context, builder, signature, args):
        aryty, yty, xty = signature.args
        ary = context.make_array(aryty)(context, builder, args[0])
        iy = context.cast(builder, args[1], yty, types.intp)
        ix = context.cast(builder, args[2], xty, types.intp)
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [iy, ix])
        i32 = llvm_ir.IntType(32)
        p8 = builder.bitcast(ptr, llvm_ir.IntType(8).as_pointer())
        fnty = llvm_ir.FunctionType(llvm_ir.VoidType(), [p8.type, i32, i32, i32])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch.p0")
        builder.call(fn, [p8, i32(0), i32(3), i32(1)])
        return context.get_dummy_value()

    return sig, codegen


@njit(cache=True, nogil=True, inline="always")
def _prefetch_window(img, state, ay, ax, n):
    """Prefetch the n x n support area at (ay, ax) of img and state (first and last column of each row),
    issued one tile ahead: the gather of a block otherwise waits for its rows (measured ~0.9 us of its
    ~1.8 us per 8 x 8 block at 1080p, where the rounds sweep the whole frame)."""
    h, w = img.shape
    x0 = min(max(ax, 0), w - 1)
    x1 = min(max(ax + n - 1, 0), w - 1)
    for y in range(max(ay, 0), min(ay + n, h)):
        _prefetch(img, y, x0)
        _prefetch(img, y, x1)
        _prefetch(state, y, x0)
        _prefetch(state, y, x1)


@njit(cache=True, nogil=True)
def _worker(img, state, lo, hi, use_lo, use_hi, tile_round, tshift, tw_tiles, r, r0, cntr, counter,
            round_tiles, leaf_ptr, leaf_y, leaf_x, leaf_l, sizes, n, rho_tab, cos_t, sin_t, tw_c, tw_s,
            prior2, delta, gamma, iter_c, iter_min, iter_max, scale, local, pair_exact, wp, mest):
    """The tiles of round r on one thread: each thread takes the next unprocessed tile of the round
    (``counter[r]``, atomic), so both threads stay busy whatever the tiles cost and however the OS
    schedules them (a static split waits for the slower thread). The scratch is owned by this call (a
    few kB): no views of arrays shared with the other threads in the per-block calls. ``wp``/``mest``
    None: the plain kernels (numba prunes the joint branch for that signature, so the joint kernels
    are compiled only when used); arrays: the joint kernels."""
    hh = n // 2 + 1
    nsel = iter_max + 2
    wbuf = np.zeros((n, n), np.float32)
    xbuf = np.zeros((n, n), np.float32)
    zb = np.zeros(4 * n * n, np.float32)           # the forward FFT's work area (_forward_dft)
    wr = np.zeros((2 * n, 2 * n), np.float32)
    wi = np.zeros((2 * n, 2 * n), np.float32)
    rr = np.zeros((hh, n), np.float32)
    ri = np.zeros((hh, n), np.float32)
    en = np.zeros((hh, n), np.float32)
    rm = np.zeros(hh, np.float32)
    sel_u = np.zeros(nsel, np.int64)
    sel_v = np.zeros(nsel, np.int64)
    sel_r = np.zeros(nsel, np.float32)
    sel_i = np.zeros(nsel, np.float32)
    dummy = np.zeros((1, 1), np.float32)
    bitrev = _bit_reversal(n)
    phs = _phase_table(n, sizes, tw_c, tw_s)
    while True:
        q = _fetch_add(counter, r)
        if q >= cntr:
            return
        t = round_tiles[r0 + q]
        # the support areas of the next two tiles of the round (the likely next one of this thread)
        for qq in range(q + 1, min(q + 3, cntr)):
            l2 = leaf_ptr[round_tiles[r0 + qq]]
            o2 = (n - sizes[leaf_l[l2]]) // 2
            _prefetch_window(img, state, leaf_y[l2] - o2, leaf_x[l2] - o2, n)
        for li in range(leaf_ptr[t], leaf_ptr[t + 1]):
            lv = leaf_l[li]
            if wp is not None:
                if n == 16:     # the common window: the kernel specialised for n = 16
                    _block16j(img, state, lo, hi, use_lo, use_hi, tile_round, tshift, tw_tiles, t, r,
                                leaf_y[li], leaf_x[li], sizes[lv], lv, 16, rho_tab, bitrev, tw_c,
                               tw_s, prior2, phs, delta, gamma, iter_c, iter_min, iter_max, scale,
                               local, pair_exact, wbuf, xbuf, zb, wr, wi, rr, ri, en, rm,
                               sel_u, sel_v, sel_r, sel_i, wp, mest)
                else:
                    _blockj(img, state, lo, hi, use_lo, use_hi, tile_round, tshift, tw_tiles, t, r,
                            leaf_y[li], leaf_x[li], sizes[lv], lv, n, rho_tab, bitrev, tw_c,
                            tw_s, prior2, phs, delta, gamma, iter_c, iter_min, iter_max, scale,
                            local, pair_exact, wbuf, xbuf, zb, wr, wi, rr, ri, en, rm,
                            sel_u, sel_v, sel_r, sel_i, wp, mest)
            elif n == 16:     # the common window: the kernel specialised for n = 16
                _block16(img, state, lo, hi, use_lo, use_hi, tile_round, tshift, tw_tiles, t, r,
                         leaf_y[li], leaf_x[li], sizes[lv], lv, 16, rho_tab, bitrev, tw_c,
                         tw_s, prior2, phs, delta, gamma, iter_c, iter_min, iter_max, scale,
                         local, pair_exact, wbuf, xbuf, zb, wr, wi, rr, ri, en, rm,
                         sel_u, sel_v, sel_r, sel_i, dummy, dummy)
            elif n == 32:
                _block32(img, state, lo, hi, use_lo, use_hi, tile_round, tshift, tw_tiles, t, r,
                         leaf_y[li], leaf_x[li], sizes[lv], lv, 32, rho_tab, bitrev, tw_c,
                         tw_s, prior2, phs, delta, gamma, iter_c, iter_min, iter_max, scale,
                         local, pair_exact, wbuf, xbuf, zb, wr, wi, rr, ri, en, rm,
                         sel_u, sel_v, sel_r, sel_i, dummy, dummy)
            else:
                _block(img, state, lo, hi, use_lo, use_hi, tile_round, tshift, tw_tiles, t, r,
                       leaf_y[li], leaf_x[li], sizes[lv], lv, n, rho_tab, bitrev, tw_c,
                       tw_s, prior2, phs, delta, gamma, iter_c, iter_min, iter_max, scale,
                       local, pair_exact, wbuf, xbuf, zb, wr, wi, rr, ri, en, rm,
                       sel_u, sel_v, sel_r, sel_i, dummy, dummy)


@njit(cache=True, nogil=True, parallel=True)
def _run(img, state, lo, hi, use_lo, use_hi, tile, n, tile_round, round_ptr, round_tiles,
         leaf_ptr, leaf_y, leaf_x, leaf_l, sizes, rho_tab, cos_t, sin_t, tw_c, tw_s, prior2,
         delta, gamma, iter_c, iter_min, iter_max, scale, local, pair_exact, nthreads, wp, mest):
    """The rounds one after the other; the tiles of a round on ``nthreads`` threads."""
    h, w = img.shape
    tw_tiles = (w + tile - 1) // tile
    tshift = 0
    while (1 << tshift) < tile:
        tshift += 1
    nround = round_ptr.shape[0] - 1
    counter = np.zeros(max(nround, 1), np.int64)
    for r in range(nround):
        r0 = round_ptr[r]
        cntr = round_ptr[r + 1] - r0
        if nthreads == 1:
            _worker(img, state, lo, hi, use_lo, use_hi, tile_round, tshift, tw_tiles, r, r0, cntr, counter,
                    round_tiles, leaf_ptr, leaf_y, leaf_x, leaf_l, sizes, n, rho_tab, cos_t, sin_t,
                    tw_c, tw_s, prior2, delta, gamma, iter_c, iter_min, iter_max, scale, local,
                    pair_exact, wp, mest)
            continue
        for th in prange(nthreads):
            _worker(img, state, lo, hi, use_lo, use_hi, tile_round, tshift, tw_tiles, r, r0, cntr, counter,
                    round_tiles, leaf_ptr, leaf_y, leaf_x, leaf_l, sizes, n, rho_tab, cos_t, sin_t,
                    tw_c, tw_s, prior2, delta, gamma, iter_c, iter_min, iter_max, scale, local,
                    pair_exact, wp, mest)


# --------------------------------------------------------------------------------------------------
# Python wrapper
# --------------------------------------------------------------------------------------------------
def log_offset(v: np.ndarray, k: np.ndarray, noise_k: float = 2.0, lower=None) -> float:
    """The offset c of the ``auto`` domain log2(x + c) (issue 8; docs/FSE.md "Domain"), from robust
    statistics of the known values only, so that it moves little with the noise or mask seed:

    c = max(p50 * 2^(12 - 5 r), noise_k * sigma_dark), r = log2(top / p50) (stops of highlights above
    the median), top = max(p99.9 of the known values, largest lower bound: a clipped pixel implies at
    least its clip level, so a scene whose highlights all clip is still HDR). The family log2(x + c)
    is continuous in c and tends to the linear domain as c grows: low-dynamic-range data (8-bit
    images, r <= 1.5) get c >= 8 x their maximum, i.e. linear (the
    caller switches to exactly linear above 64 x the range, where the two agree); HDR data (r >= 4) a
    log domain down to the noise floor sigma_dark, a MAD estimate from second differences of three
    horizontally adjacent known pixels among the darkest tenth (~0 for noise-free data).
    Scales with the data (k * values -> k * c).
    The same statistics on the same row-strided subsample as the numpy version
    (:func:`_log_offset_reference`), gathered by numba kernels without full-frame temporaries (issue 7
    item 3): the same c."""
    v = np.asarray(v)
    k = np.asarray(k, dtype=bool)
    h, w = v.shape
    step = max(1, (h * w) // 400_000)        # a row-strided subsample is plenty for percentiles
    v32 = np.ascontiguousarray(v, np.float32) if v.dtype != np.float64 else np.ascontiguousarray(v)
    k = np.ascontiguousarray(k)
    nrows = (h + step - 1) // step
    buf = np.empty(nrows * w, np.float64)
    n = _lo_gather(v32, k, step, buf)
    if n < 2:
        return 0.0
    kv = buf[:n]
    lo10, p50, p999 = np.percentile(kv, [10.0, 50.0, 99.9])
    if not p50 > 0.0:
        p50 = float(np.mean(np.abs(kv)))
        if not p50 > 0.0:
            return 0.0
    top = float(p999)
    if lower is not None:
        lw = np.asarray(lower, np.float32)
        if lw.size > 1:
            found, mx = _finite_max(np.ascontiguousarray(lw).reshape(1, -1) if lw.ndim != 2
                                    else np.ascontiguousarray(lw))
            if found:
                top = max(top, float(mx))
    r = math.log2(max(top, p50) / p50)
    c = p50 * 2.0 ** min(12.0 - 5.0 * r, 60.0)
    if w >= 3:
        nd = _lo_dark(v32, k, step, float(lo10), buf)
        if nd >= 16:
            sd = 1.4826 * float(np.median(buf[:nd])) / math.sqrt(6.0)
            c = max(c, noise_k * sd)
    return float(c)


@njit(cache=True, nogil=True)
def _lo_gather(v, k, step, buf):
    """Known values of every `step`-th row, as float64, into buf; their count."""
    h, w = v.shape
    n = 0
    for y in range(0, h, step):
        for x in range(w):
            if k[y, x]:
                buf[n] = np.float64(v[y, x])
                n += 1
    return n


@njit(cache=True, nogil=True)
def _lo_dark(v, k, step, lo10, buf):
    """|a - 2 m + b| of three horizontally adjacent known pixels (every `step`-th row) whose middle m is
    <= lo10, into buf; their count."""
    h, w = v.shape
    n = 0
    for y in range(0, h, step):
        for x in range(1, w - 1):
            if k[y, x - 1] and k[y, x] and k[y, x + 1]:
                m = np.float64(v[y, x])
                if m <= lo10:
                    buf[n] = abs(np.float64(v[y, x - 1]) - 2.0 * m + np.float64(v[y, x + 1]))
                    n += 1
    return n


@njit(cache=True, nogil=True, inline="always")
def _key(i):
    """Order-preserving int32 key of float32 bits (an involution; integer min/max vectorise where float
    ones do not, and branches on a random mask mispredict): same order as the floats (-0 below +0). Also
    `reconstruction`'s `_f32_key`."""
    return i ^ ((i >> 31) & 0x7FFFFFFF)


@njit(cache=True, nogil=True, inline="always")
def _unkey(key):
    """float32 of a `_key` key, as float64."""
    return np.float64(np.array([key ^ ((key >> 31) & 0x7FFFFFFF)], np.int32).view(np.float32)[0])


@njit(cache=True, nogil=True, parallel=True)
def _finite_max(b):
    """(any finite value, largest finite value) of a 2-D float32 array (per-row partials; branch-free
    over integer keys)."""
    h, w = b.shape
    bi = b.view(np.int32)
    kmin = np.int32(-0x7FFFFFFF - 1)
    r_max = np.empty(h, np.int32)
    r_any = np.zeros(h, np.uint8)
    for y in prange(h):
        m = kmin
        f = 0
        for x in range(w):
            a = b[y, x]
            fin = a - a == np.float32(0.0)
            m = max(m, _key(bi[y, x]) if fin else kmin)
            f |= np.int64(fin)
        r_max[y] = m
        r_any[y] = f
    m = kmin
    f = False
    for y in range(h):
        if r_any[y]:
            f = True
            m = max(m, r_max[y])
    return f, (_unkey(m) if f else -np.inf)


def _log_offset_reference(v: np.ndarray, k: np.ndarray, noise_k: float = 2.0, lower=None) -> float:
    """The numpy version of :func:`log_offset` (before issue 7 item 3; tests compare). The offset c of the ``auto`` domain log2(x + c) (issue 8; docs/FSE.md "Domain"), from robust
    statistics of the known values only, so that it moves little with the noise or mask seed:

    c = max(p50 * 2^(12 - 5 r), noise_k * sigma_dark), r = log2(top / p50) (stops of highlights above
    the median), top = max(p99.9 of the known values, largest lower bound: a clipped pixel implies at
    least its clip level, so a scene whose highlights all clip is still HDR). The family log2(x + c)
    is continuous in c and tends to the linear domain as c grows: low-dynamic-range data (8-bit
    images, r <= 1.5) get c >= 8 x their maximum, i.e. linear (the
    caller switches to exactly linear above 64 x the range, where the two agree); HDR data (r >= 4) a
    log domain down to the noise floor sigma_dark, a MAD estimate from second differences of three
    horizontally adjacent known pixels among the darkest tenth (~0 for noise-free data).
    Scales with the data (k * values -> k * c)."""
    h, w = v.shape
    step = max(1, (h * w) // 400_000)        # a row-strided subsample is plenty for percentiles
    vs = np.asarray(v[::step], np.float64)
    ks = k[::step]
    kv = vs[ks]
    if kv.size < 2:
        return 0.0
    lo10, p50, p999 = np.percentile(kv, [10.0, 50.0, 99.9])
    if not p50 > 0.0:
        p50 = float(np.mean(np.abs(kv)))
        if not p50 > 0.0:
            return 0.0
    top = float(p999)
    if lower is not None:
        lw = np.asarray(lower, np.float32)
        if lw.size > 1:
            fin = lw[np.isfinite(lw)]
            if fin.size:
                top = max(top, float(fin.max()))
    r = math.log2(max(top, p50) / p50)
    c = p50 * 2.0 ** min(12.0 - 5.0 * r, 60.0)
    if vs.shape[1] >= 3:
        tri = ks[:, 2:] & ks[:, 1:-1] & ks[:, :-2]
        a = vs[:, :-2][tri]
        m = vs[:, 1:-1][tri]
        b = vs[:, 2:][tri]
        dark = m <= lo10
        if dark.sum() >= 16:
            sd = 1.4826 * float(np.median(np.abs(a[dark] - 2.0 * m[dark] + b[dark]))) / math.sqrt(6.0)
            c = max(c, noise_k * sd)
    return float(c)


def _local_bounds(work, state, size, margin, logd):
    """Range of the known pixels (state 1) in each pixel's size x size neighbourhood, widened by
    `margin` (stops in the log domain; share of the local range in the linear one); +-inf where no
    known pixel is near."""
    from scipy import ndimage
    kn = state == 1
    big = np.float32(np.finfo(np.float32).max)
    mx = ndimage.maximum_filter(np.where(kn, work, -big), size=size, mode="nearest")
    mn = ndimage.minimum_filter(np.where(kn, work, big), size=size, mode="nearest")
    none = mx < mn
    if logd:
        lo = mn - np.float32(margin)
        hi = mx + np.float32(margin)
    else:
        d = (mx - mn) * np.float32(margin)
        lo = mn - d
        hi = mx + d
    lo[none] = -np.inf
    hi[none] = np.inf
    return lo.astype(np.float32), hi.astype(np.float32)


def _merge_bounds(lo_arr, hi_arr, use_lo, use_hi, llo, lhi, shape):
    """Local bounds narrowed by the data's bounds; where they conflict the data's bound wins (a clipped
    pixel is at least its clip level however dark its neighbours)."""
    dlo = lo_arr if use_lo else np.full(shape, -np.inf, np.float32)
    dhi = hi_arr if use_hi else np.full(shape, np.inf, np.float32)
    lo = np.maximum(dlo, llo)
    hi = np.minimum(dhi, lhi)
    lo = np.minimum(lo, dhi)          # a local floor above the data's ceiling yields to the ceiling
    hi = np.maximum(hi, lo)           # a local ceiling below the (data) floor yields to the floor
    # finite sentinels: the block kernels are compiled with fastmath (no-infs), where comparisons
    # with +-inf are not reliable
    big = np.float32(1e38)
    return (np.ascontiguousarray(np.clip(lo, -big, big), np.float32),
            np.ascontiguousarray(np.clip(hi, -big, big), np.float32))


def fse_reconstruct(values, known, lower=None, upper=None, preset: str = "balanced", weights=None, **params):
    """Reconstruct the pixels where ``known`` is False with FSE; returns float32 (H, W).

    ``values``: finite float (H, W), any scale; ``known``: bool (H, W); known pixels are returned
    bit-exact. ``lower``/``upper``: optional float arrays (NaN = no bound): a missing pixel's
    reconstruction is clamped to ``[lower, upper]`` (clipped pixels: >= clip level; dark pixels:
    <= threshold). ``preset`` selects one of :data:`FSE_PRESETS`, ``**params`` override entries.
    The output does not depend on the number of threads (each round's blocks read only pixels
    finalised in earlier rounds). ``weights``: optional float (H, W); where a pixel is not known and
    its weight is > 0 its value is a noisy measurement that enters the model's fit with that weight
    (known pixels weigh 1; joint estimation, docs/FSE.md "Noisy samples") and is replaced by the
    model there; None (default) or no such pixel: the plain path, same bits. See docs/FSE.md.
    """
    return _fse(values, known, lower, upper, preset, False, params, weights=weights)


def _fse(values, known, lower, upper, preset, inplace, params, fused=True, weights=None, skip=None):
    """`fse_reconstruct`; `inplace`: write the missing pixels into `values` itself when it is a
    C-contiguous float32 array (the dispatcher's output array) and return it. `skip`: optional bool
    (H, W) of missing pixels FSE leaves alone (state SKIP: weight 0 in `_gather`, not counted as
    missing by the plan, never written by `_write_block` nor `_finish`; their value in the result is
    whatever `values` held there; issue 7: the NOISY pixels that `fuse_noisy` accurate re-estimates
    from their measured neighbours anyway, docs/FSE.md "Skipping NOISY pixels"). `fused=False`: the driver
    before its wrapper passes were fused (issue 7 item 3: numpy offset statistics, numpy log2 of the
    bounds, scipy local bound, serial finish), kept as `_fse_reconstruct_reference` for the tests."""
    p = resolve_params(preset, **params)
    v = np.asarray(values)
    k = np.asarray(known, dtype=bool)
    if v.ndim != 2 or k.shape != v.shape:
        raise ValueError("values and known must be 2-D arrays of the same shape")
    v32 = np.ascontiguousarray(v, dtype=np.float32)
    k = np.ascontiguousarray(k)
    out = v32 if (inplace and v32 is v) else v32.copy()
    noisy = None
    if weights is not None:
        wts = np.asarray(weights, np.float32)
        if wts.shape != v.shape:
            raise ValueError(f"weights shape {wts.shape} differs from values shape {v.shape}")
        noisy = (wts > 0) & ~k
        if not noisy.any():
            noisy = None
    nk, kmin, kmax, minpos = _stats(v32, k)
    if nk == v32.size:
        return out
    if nk == 0:
        warnings.warn("fse_reconstruct: no known pixel; output is filled from the bounds or 0",
                      RuntimeWarning, stacklevel=2)
        return _fill_without_data(out, ~k, lower, upper)
    p = _density_params(p, nk / v32.size)
    if kmin == kmax:
        # constant known data: the constant is the only model (exact), within the bounds
        out[~k] = np.float32(kmin)
        return _fill_bounded(out, ~k, lower if p["use_bounds"] else None, upper if p["use_bounds"] else None)
    domain = p["domain"]
    c = 0.0
    if domain == "auto":
        domain = "log"
        if p["log_offset"] is None:
            c = (log_offset if fused else _log_offset_reference)(
                v32, k, float(p["offset_noise_k"]), lower if p["use_bounds"] else None)
        else:
            c = float(p["log_offset"])
        if c >= 64.0 * (float(kmax) - min(float(kmin), 0.0)):
            domain, c = "linear", 0.0     # log2(x + c) is linear to < 1 % there: use it exactly
    elif domain == "log" and p["log_offset"] is not None:
        c = float(p["log_offset"])
    floor = 0.0
    if fused and domain == "log" and int(p["local_bound"]):
        # the common HDR case, fused (issue 7 item 3): log2 of data and bounds, the local bound and the
        # merge in three parallel passes; same bounds as the numpy passes of the reference to float rounding
        work, state, lo_arr, hi_arr, scale = _log_local_passes(v32, k, lower, upper, p, c, kmin, kmax, minpos)
        floor = c if c > 0.0 else (0.5 * minpos if minpos > 0 else 1e-30)
        use_lo = use_hi = True
        local = False
    else:
        lo_arr, hi_arr, use_lo, use_hi = _bounds(lower, upper, v.shape, p["use_bounds"])
        floor = 0.0
        local = False
        src = v32
        if domain == "log":
            if c > 0.0:
                # log2(max(x, 0) + c): well conditioned down to the offset (no blow-up at black pixels)
                src = v32 + np.float32(c)
                floor = c
            else:
                floor = 0.5 * minpos if minpos > 0 else 1e-30
            if use_lo:
                lo_arr = np.log2(np.maximum(lo_arr + np.float32(c), floor)).astype(np.float32)
            if use_hi:
                hi_arr = np.log2(np.maximum(hi_arr + np.float32(c), floor)).astype(np.float32)
            # sigma relative to the known values' log range, at most log_scale_stops (an almost linear
            # low-dynamic-range domain then behaves like the linear one)
            wr = math.log2(max(kmax, 0.0) + c) - math.log2(max(max(kmin, 0.0) + c, floor))
            scale = float(p["log_scale_stops"]) if not wr > 0 else min(float(p["log_scale_stops"]), wr)
        elif domain == "local":
            scale = 1.0 / 0.4   # std relative to 2.5x the local mean ~ std/255 for mid-grey 8-bit data
            local = True
        else:
            rng = float(kmax - kmin)
            scale = rng if rng > 0 else 1.0
        work, state = _prep(src, k, domain == "log", np.float32(floor))
        if int(p["local_bound"]) and domain == "log":
            llo, lhi = _local_bounds(work, state, int(p["local_bound"]), float(p["local_margin"]),
                                     domain == "log")
            lo_arr, hi_arr = _merge_bounds(lo_arr, hi_arr, use_lo, use_hi, llo, lhi, v.shape)
            use_lo = use_hi = True
    if skip is not None:
        _mark_skip(state, skip)
    joint = noisy is not None
    if joint:
        # noisy measurements: state 3, their value in the working domain, their weight (`_gather`)
        state[noisy] = 3
        mv = v32[noisy]
        if domain == "log":
            mv = np.log2(np.maximum(mv + np.float32(c), np.float32(floor)))
        work[noisy] = mv
        wp = np.where(noisy, np.minimum(wts, np.float32(1.0)), np.float32(0.0)).astype(np.float32)
        mest = np.zeros_like(work)
    else:
        wp = mest = None
    tables = _tables(p)
    cos_t, sin_t, tw_c, tw_s, bitrev, prior2, rho_tab, split, sizes = tables
    n = int(p["window"])
    tile = int(p["max_block"])
    plan = _plan(work, state, tile, n, sizes, split, scale, local, float(p["edge_penalty"]),
                 int(p["order_levels"]), int(p["order_slack"]))
    tile_round, round_ptr, round_tiles, leaf_ptr, leaf_y, leaf_x, leaf_l, _nr = plan
    nthreads = int(get_num_threads())
    # small jobs run on the calling thread only: fork/join per round would cost more than it gains
    # (the result is the same for any thread count)
    if leaf_y.shape[0] * n * n < 400_000:
        nthreads = 1
    old = get_num_threads()
    set_num_threads(nthreads)
    try:
        _run(work, state, lo_arr, hi_arr, use_lo, use_hi, tile, n, tile_round, round_ptr, round_tiles,
             leaf_ptr, leaf_y, leaf_x, leaf_l, sizes, rho_tab, cos_t, sin_t, tw_c, tw_s, prior2,
             float(p["delta"]), float(p["gamma"]), float(p["iter_c"]), int(p["iter_min"]),
             int(p["iter_max"]), scale, local, bool(p["pair_exact"]), nthreads, wp, mest)
    finally:
        set_num_threads(old)
    logd = domain == "log"
    cf = np.float32(c if logd else 0.0)
    fused_c = fused and cf > 0
    nleft = _finish_c(out, work, state, cf) if fused_c else _finish(out, work, state, logd)
    if nleft:
        # blocks whose support held no usable pixel: nearest reconstructed/known value
        # (from known, reconstructed and noisy-measurement pixels: skipped ones hold no value in `work`)
        ys, xs = _fill_left(work, state)
        # only these pixels are new: finish them, not the frame again (same values as `_finish(_c)`)
        _finish_at(out, work, ys, xs, cf if fused_c else np.float32(0.0), fused_c, logd)
    if joint:
        # the model at the noisy measurements
        me = mest[noisy]
        if logd:
            me = (2.0 ** me.astype(np.float64)).astype(np.float32)
            if fused_c:
                me -= cf
        out[noisy] = me
    if cf > 0 and not fused:
        out[~k] -= cf
    return out


# FSE pixel states: 0 missing, 1 known, 2 reconstructed (weight delta), 3 noisy measurement (joint
# estimation, weighted), SKIP: missing but left to the caller (weight 0, never counted nor written)
SKIP = 4


@njit(cache=True, nogil=True, parallel=True)
def _mark_skip(state, skip):
    """state = SKIP at the `skip` pixels that are not known (`_fse`'s skip argument)."""
    h, w = state.shape
    for y in prange(h):
        for x in range(w):
            if skip[y, x] and state[y, x] != 1:
                state[y, x] = SKIP


_SCRATCH = ThreadScratch()


def _scratch(h, w):
    """Per-thread working arrays of the fused passes, reused frame after frame (no per-frame allocation
    and page faults; issue 7 item 3): work, state, row max/min, lower, upper. Nothing returned to the
    caller lives in them."""
    s = getattr(_SCRATCH, "s", None)
    if s is None or s[0].shape != (h, w):
        s = _SCRATCH.s = (np.empty((h, w), np.float32), np.empty((h, w), np.uint8),
                          np.empty((h, w), np.float32), np.empty((h, w), np.float32),
                          np.empty((h, w), np.float32), np.empty((h, w), np.float32))
    return s


def _log_local_passes(v32, k, lower, upper, p, c, kmin, kmax, minpos):
    """Working image, state and merged log-domain bounds for the log domain with the local bound
    (`_prep_local`, `_bounds_local`); the log-range scale of the block kernels."""
    h, w = v32.shape
    if c > 0.0:
        floor = c
    else:
        floor = 0.5 * minpos if minpos > 0 else 1e-30
    use = bool(p["use_bounds"])
    lw = None if (not use or lower is None) else \
        np.ascontiguousarray(np.broadcast_to(np.asarray(lower, np.float32), (h, w)))
    up = None if (not use or upper is None) else \
        np.ascontiguousarray(np.broadcast_to(np.asarray(upper, np.float32), (h, w)))
    dummy = np.zeros((1, 1), np.float32)
    use_lo = use_hi = False
    if lw is not None or up is not None:
        use_lo, use_hi = _bound_flags(dummy if lw is None else lw, dummy if up is None else up,
                                      lw is not None, up is not None)
    work, state, hmx, hmn, lo, hi = _scratch(h, w)
    r = int(p["local_bound"]) // 2
    cf = np.float32(c)
    ff = np.float32(floor)
    _prep_local(v32, k, cf, ff, r, work, state, hmx, hmn)
    _bounds_local(hmx, hmn, r, np.float32(p["local_margin"]), dummy if lw is None else lw,
                  dummy if up is None else up, use_lo, use_hi, cf, ff, lo, hi, state)
    wr = math.log2(max(kmax, 0.0) + c) - math.log2(max(max(kmin, 0.0) + c, floor))
    scale = float(p["log_scale_stops"]) if not wr > 0 else min(float(p["log_scale_stops"]), wr)
    return work, state, lo, hi, scale


def _fse_reconstruct_reference(values, known, lower=None, upper=None, preset: str = "balanced", **params):
    """`fse_reconstruct` with the driver before its wrapper passes were fused (issue 7 item 3); the
    tests compare the two."""
    return _fse(values, known, lower, upper, preset, False, params, fused=False)


def _fill_bounded(out, miss, lower, upper):
    if lower is not None:
        lo = np.broadcast_to(np.asarray(lower, np.float32), out.shape)
        m = miss & np.isfinite(lo)
        out[m] = np.maximum(out[m], lo[m])
    if upper is not None:
        hi = np.broadcast_to(np.asarray(upper, np.float32), out.shape)
        m = miss & np.isfinite(hi)
        out[m] = np.minimum(out[m], hi[m])
    return out


@njit(cache=True, nogil=True, parallel=True)
def _stats(v, k):
    """(known count, min, max, smallest positive known value) in one parallel pass (per-row partials,
    reduced in row order: the result does not depend on the thread count; branch-free over the integer
    keys of the float32 values, `_key`)."""
    h, w = v.shape
    vi = v.view(np.int32)
    kmax_ = np.int32(0x7FFFFFFF)
    kmin_ = np.int32(-0x7FFFFFFF - 1)
    r_n = np.zeros(h, np.int64)
    r_min = np.empty(h, np.int32)
    r_max = np.empty(h, np.int32)
    r_pos = np.empty(h, np.int32)
    for y in prange(h):
        nk = 0
        lo = kmax_
        hi = kmin_
        pos = kmax_
        for x in range(w):
            kk = k[y, x]
            key = _key(vi[y, x])
            nk += np.int64(kk)
            lo = min(lo, key if kk else kmax_)
            hi = max(hi, key if kk else kmin_)
            pos = min(pos, key if kk & (v[y, x] > np.float32(0.0)) else kmax_)
        r_n[y] = nk
        r_min[y] = lo
        r_max[y] = hi
        r_pos[y] = pos
    nk = 0
    lo = kmax_
    hi = kmin_
    pos = kmax_
    for y in range(h):
        nk += r_n[y]
        lo = min(lo, r_min[y])
        hi = max(hi, r_max[y])
        pos = min(pos, r_pos[y])
    kmin = np.inf if nk == 0 else _unkey(lo)
    kmax = -np.inf if nk == 0 else _unkey(hi)
    minpos = 0.0 if pos == kmax_ else _unkey(pos)
    return nk, kmin, kmax, minpos


@njit(cache=True, nogil=True, parallel=True)
def _prep(v, k, logd, floor):
    h, w = v.shape
    work = np.empty((h, w), np.float32)
    state = np.empty((h, w), np.uint8)
    for y in prange(h):
        for x in range(w):
            if k[y, x]:
                state[y, x] = 1
                if logd:
                    work[y, x] = np.float32(math.log2(max(v[y, x], floor)))
                else:
                    work[y, x] = v[y, x]
            else:
                state[y, x] = 0
                work[y, x] = 0.0
    return work, state


@njit(cache=True, nogil=True, parallel=True)
def _finish(out, work, state, logd):
    """Write reconstructed pixels (state 2) of the working image into out; count pixels left."""
    h, w = out.shape
    left = 0
    for y in prange(h):
        c = 0
        for x in range(w):
            s = state[y, x]
            if s == 2:
                if logd:
                    out[y, x] = np.float32(2.0 ** np.float64(work[y, x]))
                else:
                    out[y, x] = work[y, x]
            elif s == 0:
                c += 1
        left += c
    return left


def _bounds(lower, upper, shape, use):
    use_lo = use_hi = False
    lo_arr = np.zeros((1, 1), np.float32)
    hi_arr = np.zeros((1, 1), np.float32)
    if use and lower is not None:
        lo_arr = np.ascontiguousarray(np.broadcast_to(np.asarray(lower, np.float32), shape)).copy()
        lo_arr[np.isnan(lo_arr)] = -np.inf
        use_lo = bool(np.isfinite(lo_arr).any())
        if not use_lo:
            lo_arr = np.zeros((1, 1), np.float32)
    if use and upper is not None:
        hi_arr = np.ascontiguousarray(np.broadcast_to(np.asarray(upper, np.float32), shape)).copy()
        hi_arr[np.isnan(hi_arr)] = np.inf
        use_hi = bool(np.isfinite(hi_arr).any())
        if not use_hi:
            hi_arr = np.zeros((1, 1), np.float32)
    return lo_arr, hi_arr, use_lo, use_hi


NEAREST_RING_MAX = 4096     # left pixels up to which the fallback searches rings around each
RING_RADIUS_MAX = 64        # ring radius searched; pixels with no source that near take the cropped transform

# sources by FSE state: known (1), reconstructed (2), noisy measurement (3); not missing (0) nor skipped (4)
_STATE_SRC = np.zeros(256, np.bool_)
_STATE_SRC[[1, 2, 3]] = True
_BOOL_SRC = np.array([False, True] + [True] * 254, np.bool_)


def _nearest_fill(work, left, src=None):
    """Pixels `left` get the value of the nearest `src` pixel (default: every pixel not left), Euclidean
    (issue 7: a whole-frame distance transform cost 50-90 ms per 1080p frame for a few hundred pixels):
    up to NEAREST_RING_MAX pixels a ring search around each (`_ring_nearest`, cost grows with the
    pixels left and their distance to a source, not with the frame), the rest (many pixels, or no
    source within RING_RADIUS_MAX) the distance transform of a crop around them (`_crop_nearest`).
    Equidistant sources may resolve differently between the two."""
    src = ~left if src is None else src
    ys, xs = np.nonzero(left)
    _fill_at(work, np.ascontiguousarray(src).view(np.uint8), _BOOL_SRC, ys, xs)


def _fill_left(work, state):
    """The pixels no block could fill (state 0) get the value of the nearest known, reconstructed or
    noisy-measurement pixel (`_nearest_fill`'s rule) and state 2; returns their coordinates. One numba
    scan finds them (no frame-sized numpy temporaries for a handful of pixels)."""
    ys, xs = _left_coords(state)
    _fill_at(work, state, _STATE_SRC, ys, xs)
    state[ys, xs] = 2
    return ys, xs


def _fill_at(work, src, is_src, ys, xs):
    """`_nearest_fill` of the pixels (ys, xs), sources where ``is_src[src]``; none anywhere: 0."""
    if ys.size == 0:
        return
    todo = np.ones(ys.size, np.bool_)
    if ys.size <= NEAREST_RING_MAX:
        todo = _ring_nearest(work, src, is_src, ys, xs, RING_RADIUS_MAX)
    if todo.any():
        _crop_nearest(work, src, is_src, ys[todo], xs[todo])


def _crop_nearest(work, src, is_src, ys, xs):
    """The distance transform of a crop reaching `m` pixels beyond the bounding box of (ys, xs) (helper
    fse2): a source outside it is more than `m` away from every one of them, so the result is exact once
    each found a source within `m` (else `m` grows, up to the whole frame)."""
    from scipy import ndimage
    h, w = work.shape
    y0, y1, x0, x1 = int(ys.min()), int(ys.max()) + 1, int(xs.min()), int(xs.max()) + 1
    m = 16
    while True:
        cy0, cy1, cx0, cx1 = max(0, y0 - m), min(h, y1 + m), max(0, x0 - m), min(w, x1 + m)
        whole = (cy0, cy1, cx0, cx1) == (0, h, 0, w)
        sub = is_src[src[cy0:cy1, cx0:cx1]]
        if sub.any():
            d, idx = ndimage.distance_transform_edt(~sub, return_distances=True, return_indices=True)
            ly, lx = ys - cy0, xs - cx0
            if whole or float(d[ly, lx].max()) <= m:
                work[ys, xs] = work[idx[0][ly, lx] + cy0, idx[1][ly, lx] + cx0]
                return
        elif whole:      # no source at all
            work[ys, xs] = 0.0
            return
        m *= 4


@njit(cache=True, nogil=True)
def _left_coords(state):
    """(ys, xs) of the state-0 pixels, in row-major order (as np.nonzero)."""
    h, w = state.shape
    n = 0
    for y in range(h):
        for x in range(w):
            n += 1 if state[y, x] == 0 else 0
    ys = np.empty(n, np.int64)
    xs = np.empty(n, np.int64)
    i = 0
    for y in range(h):
        for x in range(w):
            if state[y, x] == 0:
                ys[i] = y
                xs[i] = x
                i += 1
    return ys, xs


@njit(cache=True, nogil=True)
def _ring_nearest(work, src, is_src, ys, xs, rcap):
    """For each (ys[i], xs[i]): the value of the Euclidean-nearest source pixel (``is_src[src[y, x]]``),
    searched in square rings of growing Chebyshev radius r until r^2 exceeds the best squared distance
    found (a pixel of ring r is at least r away), r <= rcap. Values are read first, then written (a
    filled pixel is never a source). Returns which pixels are left to do (no source proven nearest
    within rcap; their value is not written)."""
    h, w = src.shape
    vals = np.empty(ys.size, np.float32)
    todo = np.zeros(ys.size, np.bool_)
    for i in range(ys.size):
        y0 = ys[i]
        x0 = xs[i]
        best = -1
        bv = np.float32(0.0)
        r = 1
        rmax = min(max(h, w), rcap)
        while r <= rmax and (best < 0 or r * r <= best):
            for dy in range(-r, r + 1):
                y = y0 + dy
                if y < 0 or y >= h:
                    continue
                step = 1 if (dy == -r or dy == r) else 2 * r   # full rows at the top and bottom, else the two sides
                for dx in range(-r, r + 1, step):
                    x = x0 + dx
                    if x < 0 or x >= w or not is_src[src[y, x]]:
                        continue
                    d = dy * dy + dx * dx
                    if best < 0 or d < best:
                        best = d
                        bv = work[y, x]
            r += 1
        vals[i] = bv
        # not done: no source within the cap, or one beyond a ring not yet searched
        todo[i] = (best < 0 or r * r <= best) and r <= max(h, w)
    for i in range(ys.size):
        if not todo[i]:
            work[ys[i], xs[i]] = vals[i]
    return todo


def _fill_without_data(out, miss, lower, upper):
    fill = np.zeros(out.shape, np.float32)
    if lower is not None:
        lo = np.broadcast_to(np.asarray(lower, np.float32), out.shape)
        m = np.isfinite(lo)
        fill[m] = np.maximum(fill[m], lo[m])
    if upper is not None:
        hi = np.broadcast_to(np.asarray(upper, np.float32), out.shape)
        m = np.isfinite(hi)
        fill[m] = np.minimum(fill[m], hi[m])
    out[miss] = fill[miss]
    return out


# ---- fused wrapper passes of the log domain with the local bound (issue 7 item 3) -----------------------
# The numpy passes of `_fse_reconstruct_reference` (offset add, log2 of the data and of both bounds, the
# masked 5 x 5 min/max filters, the merge and the clip to finite sentinels, exp2 and the offset after the
# blocks) in three parallel row loops. Min/max are exact; the log2 of the bounds is libm's (numpy's SIMD
# log2 differs from it by at most 1 ulp on ~1 % of the values): the same bounds to float rounding.

@njit(cache=True, nogil=True, parallel=True)
def _bound_flags(lower, upper, has_lo, has_hi):
    """(any finite lower, any finite upper): whether the data's bounds are used at all (`_bounds`)."""
    h, w = lower.shape if has_lo else upper.shape
    r_lo = np.zeros(h, np.uint8)
    r_hi = np.zeros(h, np.uint8)
    for y in prange(h):
        if has_lo:
            for x in range(w):
                a = lower[y, x]
                if a - a == 0:
                    r_lo[y] = 1
                    break
        if has_hi:
            for x in range(w):
                a = upper[y, x]
                if a - a == 0:
                    r_hi[y] = 1
                    break
    return bool(r_lo.any()), bool(r_hi.any())


@njit(cache=True, nogil=True, parallel=True)
def _prep_local(v, k, c, floor, r, work, state, hmx, hmn):
    """work = log2(max(v + c, floor)) at known pixels (state 1), 0 elsewhere (state 0); hmx/hmn: max/min
    of the known work values in the 2r + 1 wide row window (edges replicated, like scipy's "nearest"),
    -/+ float32 max where there is none."""
    h, w = v.shape
    big = np.float32(3.4028234663852886e38)
    nch = min(h, 64)
    for ch in prange(nch):
        mrow = np.empty(w + 2 * r, np.float32)     # masked row, edges replicated (one per chunk)
        nrow = np.empty(w + 2 * r, np.float32)
        idx = np.empty(w, np.int64)
        for y in range(ch * h // nch, (ch + 1) * h // nch):
            nk = 0
            for x in range(w):          # branch-free: state, zeros, the known pixels compacted
                kk = k[y, x]
                state[y, x] = np.uint8(kk)
                work[y, x] = np.float32(0.0)
                idx[nk] = x
                nk += np.int64(kk)
            for q in range(nk):         # libm log2 only where known (a branch here mispredicts at random)
                x = idx[q]
                work[y, x] = np.float32(math.log2(max(v[y, x] + c, floor)))
            for x in range(w):
                kk = k[y, x]
                a = work[y, x]
                mrow[x + r] = a if kk else -big
                nrow[x + r] = a if kk else big
            for i in range(r):
                mrow[i] = mrow[r]
                nrow[i] = nrow[r]
                mrow[w + r + i] = mrow[w + r - 1]
                nrow[w + r + i] = nrow[w + r - 1]
            for x in range(w):
                hmx[y, x] = mrow[x]
                hmn[y, x] = nrow[x]
            for d in range(1, 2 * r + 1):
                for x in range(w):
                    hmx[y, x] = max(hmx[y, x], mrow[x + d])
                    hmn[y, x] = min(hmn[y, x], nrow[x + d])


@njit(cache=True, nogil=True, parallel=True)
def _bounds_local(hmx, hmn, r, margin, lower, upper, use_lo, use_hi, c, floor, lo, hi, state):
    """Log-domain bounds of the missing pixels (state 0; the block kernels read no other pixel's bounds,
    and known ones keep whatever `lo`/`hi` held: issue 7, two libm log2 per pixel were the cost of this
    pass, and rows with nothing missing are skipped): the local bound (column window over hmx/hmn,
    widened by `margin` stops, `_local_bounds`) narrowed by the data's bounds log2(max(b + c, floor))
    with the data's bound winning (`_merge_bounds`), clipped to +-1e38 (finite sentinels for the
    fastmath block kernels)."""
    h, w = hmx.shape
    sent = np.float32(1e38)
    inf = np.float32(np.inf)
    lfl = np.float32(math.log2(floor))
    nch = min(h, 64)
    for ch in prange(nch):
        cmx = np.empty(w, np.float32)      # column-window max/min of one row (one per chunk)
        cmn = np.empty(w, np.float32)
        idx = np.empty(w, np.int64)
        for y in range(ch * h // nch, (ch + 1) * h // nch):
            nmiss = 0
            for x in range(w):          # the row's missing pixels, compacted without branches
                idx[nmiss] = x
                nmiss += 1 if state[y, x] == 0 else 0
            if nmiss == 0:
                continue
            y0 = max(y - r, 0)
            for x in range(w):
                cmx[x] = hmx[y0, x]
                cmn[x] = hmn[y0, x]
            for dy in range(-r + 1, r + 1):
                yy = min(max(y + dy, 0), h - 1)
                for x in range(w):
                    cmx[x] = max(cmx[x], hmx[yy, x])
                    cmn[x] = min(cmn[x], hmn[yy, x])
            for q in range(nmiss):
                x = idx[q]
                mx = cmx[x]
                mn = cmn[x]
                none = mx < mn
                llo = -inf if none else mn - margin
                lhi = inf if none else mx + margin
                dlo = -inf
                if use_lo:
                    a = lower[y, x]
                    # NaN (no bound) -> -inf -> log2(floor), as in the reference; log2 only where bounded
                    dlo = lfl if a != a else np.float32(math.log2(max(a + c, floor)))
                dhi = inf
                if use_hi:
                    b = upper[y, x]
                    if b == b:
                        dhi = np.float32(math.log2(max(b + c, floor)))
                a = max(dlo, llo)
                b = min(dhi, lhi)
                a = min(a, dhi)
                b = max(b, a)
                lo[y, x] = min(max(a, -sent), sent)
                hi[y, x] = min(max(b, -sent), sent)


@njit(cache=True, nogil=True)
def _finish_at(out, work, ys, xs, c, with_c, logd):
    """`_finish_c` (`with_c`) or `_finish` at the pixels (ys, xs) only: the fallback's few pixels."""
    for i in range(ys.size):
        y = ys[i]
        x = xs[i]
        if with_c:
            out[y, x] = np.float32(2.0 ** np.float64(work[y, x])) - c
        elif logd:
            out[y, x] = np.float32(2.0 ** np.float64(work[y, x]))
        else:
            out[y, x] = work[y, x]


@njit(cache=True, nogil=True, parallel=True)
def _finish_c(out, work, state, c):
    """`_finish` in the log domain with the offset: out = 2^work - c at reconstructed pixels."""
    h, w = out.shape
    left = 0
    for y in prange(h):
        n = 0
        idx = np.empty(w, np.int64)
        m = 0
        for x in range(w):              # branch-free: count left, compact the reconstructed pixels
            s = state[y, x]
            n += np.int64(s == 0)
            idx[m] = x
            m += np.int64(s == 2)
        for q in range(m):
            x = idx[q]
            out[y, x] = np.float32(2.0 ** np.float64(work[y, x])) - c
        left += n
    return left


def warmup() -> None:
    """Compile the kernels on a tiny image (call from an element's ``do_start``)."""
    rng = np.random.default_rng(0)
    v = rng.random((24, 24)).astype(np.float32)
    k = rng.random((24, 24)) < 0.5
    for preset in ("preview", "balanced"):
        fse_reconstruct(v, k, lower=np.full_like(v, np.nan), upper=np.full_like(v, np.nan),
                        preset=preset)
    # HDR data (12 stops, a clipped and a dark bound): the log domain's fused passes (issue 7 item 3)
    hv = (2.0 ** (12.0 * v)).astype(np.float32)
    lo = np.full_like(v, np.nan)
    hi = np.full_like(v, np.nan)
    lo[0, 0] = hv.max()
    hi[1, 1] = hv.min()
    fse_reconstruct(hv, k, lower=lo, upper=hi, preset="preview")
    # NOISY pixels skipped (the default before reconstruct's accurate noise fusion, issue 7)
    _fse(v, k, None, None, "preview", False, {}, skip=~k & (rng.random((24, 24)) < 0.5))
    # the fallback for pixels no block could fill (ring search)
    _nearest_fill(v.copy(), ~k, k)
    ys, xs = _fill_left(v.copy(), np.where(k, 1, 0).astype(np.uint8))
    for with_c, logd in ((True, True), (False, True), (False, False)):
        _finish_at(v.copy(), v, ys, xs, np.float32(1.0), with_c, logd)
    # (the joint estimation with `weights=` is opt-in: its kernels compile on first use, not here)
