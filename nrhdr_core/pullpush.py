"""Pull-push fill on an image pyramid: the preview reconstruction, and the kernels the fused frame paths
(`reconstruction`, `demosaic`) build on.

A fast stand-in for the paper's FSE reconstruction (sections 2.2, 2.4) where the frame budget is tight. Pull-push
with 0/1 weights (Gortler et al. 1996, "The Lumigraph"): level 1 of the pyramid is pulled from the frame
(`pull_row`), the coarser levels are pulled to 1 x 1 and pushed back down to level 1 (`pull_push_levels`); a
missing pixel then takes the weighted mean of its known 8-neighbours, else its level-1 value (`fill_row`). Every
level's capped weight is 0 or 1, so a push only fills empty cells with their parent's value. `pull_push` (method
"preview" of `reconstruct`) and the fused frame path (`_preview_frame`) share these kernels; the pyramid's levels
1..L live in one flat per-thread plane. The branch-free pixel loops multiply values by their 0/1 weights, so the
level-0 values they read must be finite: `pull_push` reads them from zero-filled planes (any value, NaN too, may
sit under a missing pixel of `reconstruct`'s input), the frame path from a frame it checked to be finite.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from .scratch import planes


def pyramid(h: int, w: int):
    """(pv, pw, hs, ws, off): flat float32 values and weights of levels 1..L (level l at off[l], hs[l] x
    ws[l]; level 0 is the frame), the calling thread's planes for this frame shape."""
    def make():
        levels = int(np.ceil(np.log2(max(h, w, 2))))
        hs = np.empty(levels + 1, np.int64)
        ws = np.empty(levels + 1, np.int64)
        off = np.zeros(levels + 2, np.int64)
        hs[0], ws[0] = h, w
        for lv in range(levels):
            hs[lv + 1] = (hs[lv] + 1) // 2
            ws[lv + 1] = (ws[lv] + 1) // 2
        for lv in range(1, levels + 1):
            off[lv + 1] = off[lv] + hs[lv] * ws[lv]
        n = max(int(off[levels + 1]), 1)
        return np.zeros(n, np.float32), np.zeros(n, np.float32), hs, ws, off
    return planes("pullpush.pyramid", (h, w), make)


@njit(cache=True, nogil=True, inline="always")
def pull_row(values, known, pv, pw, o1, w1, y1):
    """Row y1 of level 1: per cell the sum of its 2 x 2 pixels' values times their 0/1 weights (`known`,
    bool or float; children summed row by row) and of the weights, normalised to weight 1 when above 1."""
    h, w = values.shape
    one = np.float32(1.0)
    zero = np.float32(0.0)
    y = 2 * y1
    base = o1 + y1 * w1
    if y + 1 < h:
        va = values[y]              # row slices: indices from 0 (no wraparound select; the loop vectorises)
        vb = values[y + 1]
        ka = known[y]
        kb = known[y + 1]
        vo = pv[base:base + w1]
        co = pw[base:base + w1]
        for x1 in range(w // 2):
            x = 2 * x1
            k00 = one if ka[x] else zero
            k01 = one if ka[x + 1] else zero
            k10 = one if kb[x] else zero
            k11 = one if kb[x + 1] else zero
            s = zero + va[x] * k00
            s = s + va[x + 1] * k01
            s = s + vb[x] * k10
            s = s + vb[x + 1] * k11
            c = zero + k00
            c = c + k01
            c = c + k10
            c = c + k11
            d = c if c > one else one
            vo[x1] = s / d
            co[x1] = c if c < one else one
        if w % 2:
            x = w - 1
            k00 = one if ka[x] else zero
            k10 = one if kb[x] else zero
            s = zero + va[x] * k00 + vb[x] * k10
            c = zero + k00 + k10
            vo[w // 2] = s / c if c > one else s
            co[w // 2] = c if c < one else one
    else:
        for x1 in range(w1):
            s = zero
            c = zero
            for x in range(2 * x1, min(2 * x1 + 2, w)):
                kk = one if known[y, x] else zero
                s += values[y, x] * kk
                c += kk
            if c > one:
                s = s / c
                c = one
            pv[base + x1] = s
            pw[base + x1] = c


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def pull_level1(values, known, zv, kf, pv, pw, o1, h1, w1):
    """Level 0 as zero-filled values `zv` and 0/1 weights `kf` (whatever `values` holds under missing
    pixels), and level 1 of the pyramid from them (`pull_row`), per pair of rows in parallel."""
    h, w = values.shape
    one = np.float32(1.0)
    zero = np.float32(0.0)
    for y1 in prange(h1):
        for yy in range(2 * y1, min(2 * y1 + 2, h)):
            for x in range(w):
                kk = known[yy, x]
                zv[yy, x] = values[yy, x] if kk else zero
                kf[yy, x] = one if kk else zero
        pull_row(zv, kf, pv, pw, o1, w1, y1)


@njit(cache=True, nogil=True, inline="always")
def pull_at(pv, pw, o0, h0, w0, o1, w1, y1, x1):
    """One coarse pixel of the pull: sum of the 2 x 2 children, normalised once its weight exceeds 1."""
    one = np.float32(1.0)
    s = np.float32(0.0)
    c = np.float32(0.0)
    for y in range(2 * y1, min(2 * y1 + 2, h0)):
        for x in range(2 * x1, min(2 * x1 + 2, w0)):
            s += pv[o0 + y * w0 + x]
            c += pw[o0 + y * w0 + x]
    if c > one:
        s = s / c
        c = one
    pv[o1 + y1 * w1 + x1] = s
    pw[o1 + y1 * w1 + x1] = c


@njit(cache=True, nogil=True, inline="always")
def pull_level_row(pv, pw, o0, h0, w0, o1, w1, y1):
    """Row y1 of a pyramid level (at o1, w1 wide) pulled from the level below it (at o0, h0 x w0):
    `pull_at` of each of its pixels, the same sums in the same order; the full 2 x 2 blocks in a
    branch-free loop over row slices (it vectorises), a last odd row or column by `pull_at`."""
    y = 2 * y1
    if y + 1 >= h0:
        for x1 in range(w1):
            pull_at(pv, pw, o0, h0, w0, o1, w1, y1, x1)
        return
    one = np.float32(1.0)
    zero = np.float32(0.0)
    a0 = o0 + y * w0
    va = pv[a0:a0 + w0]
    vb = pv[a0 + w0:a0 + 2 * w0]
    ca = pw[a0:a0 + w0]
    cb = pw[a0 + w0:a0 + 2 * w0]
    b1 = o1 + y1 * w1
    vo = pv[b1:b1 + w1]
    co = pw[b1:b1 + w1]
    for x1 in range(w0 // 2):
        x = 2 * x1
        s = zero + va[x]
        s = s + va[x + 1]
        s = s + vb[x]
        s = s + vb[x + 1]
        c = zero + ca[x]
        c = c + ca[x + 1]
        c = c + cb[x]
        c = c + cb[x + 1]
        over = c > one
        vo[x1] = s / c if over else s
        co[x1] = one if over else c
    if w0 % 2:
        pull_at(pv, pw, o0, h0, w0, o1, w1, y1, w1 - 1)


@njit(cache=True, nogil=True, inline="always")
def push_row(pv, pw, o0, w0, o1, w1, y):
    """Row y of a level (at o0, w0 wide) pushed from the level above it (at o1, w1 wide): an under-weighted
    pixel takes its parent's normalised value (0 where the parent has no weight), every weight becomes 1;
    branch-free."""
    one = np.float32(1.0)
    zero = np.float32(0.0)
    b0 = o0 + y * w0
    b1 = o1 + (y // 2) * w1
    v0 = pv[b0:b0 + w0]             # row slices: indices from 0 (no wraparound select; the loop vectorises)
    q0 = pw[b0:b0 + w0]
    v1 = pv[b1:b1 + w1]
    q1 = pw[b1:b1 + w1]
    for x in range(w0):
        a = v1[x // 2]
        c = q1[x // 2]
        p = a / c if c > zero else zero
        v0[x] = p if q0[x] < one else v0[x]
        q0[x] = one



@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def pull(pv, pw, o0, h0, w0, o1, h1, w1):
    """A pyramid level (at o1, h1 x w1) pulled from the level below it, rows in parallel (`pull_level_row`)."""
    for y1 in prange(h1):
        pull_level_row(pv, pw, o0, h0, w0, o1, w1, y1)


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def push(pv, pw, o0, h0, w0, o1, w1):
    """A pyramid level (at o0, h0 x w0) pushed from the level above it, rows in parallel (`push_row`)."""
    for y in prange(h0):
        push_row(pv, pw, o0, w0, o1, w1, y)


SERIAL_LEVEL = 1 << 16    # levels smaller than this many pixels are pulled and pushed in one serial call


def pull_push_levels(pv, pw, hs, ws, off, first=1):
    """Pull levels first -> L, then push back to level `first` (level `first` already pulled): big levels
    in parallel regions, the small ones in one serial call (a parallel region per tiny level costs more
    than its work, and much more when the cores are busy)."""
    levels = hs.shape[0] - 1
    small = first
    while small < levels and hs[small] * ws[small] >= SERIAL_LEVEL:
        small += 1
    for lv in range(first, small):
        pull(pv, pw, off[lv], hs[lv], ws[lv], off[lv + 1], hs[lv + 1], ws[lv + 1])
    small_levels(pv, pw, hs, ws, off, small, levels)
    for lv in range(small - 1, first - 1, -1):
        push(pv, pw, off[lv], hs[lv], ws[lv], off[lv + 1], ws[lv + 1])


@njit(cache=True, nogil=True, error_model="numpy")
def small_levels(pv, pw, hs, ws, off, first, levels):
    """Pull from level `first` to the top and push back down to `first`, serially, by rows
    (`pull_level_row`, `push_row`)."""
    for lv in range(first, levels):
        for y1 in range(hs[lv + 1]):
            pull_level_row(pv, pw, off[lv], hs[lv], ws[lv], off[lv + 1], ws[lv + 1], y1)
    for lv in range(levels - 1, first - 1, -1):
        for y in range(hs[lv]):
            push_row(pv, pw, off[lv], ws[lv], off[lv + 1], ws[lv + 1], y)


@njit(cache=True, nogil=True)
def fill_px(values, known, pv, o1, w1, y, x):
    """The fill of pixel (y, x), with bounds checks: the weighted mean of its known 8-neighbours (edges
    weigh 2, corners 1, summed in row-major neighbour order), else its level-1 value."""
    h, w = values.shape
    acc = np.float32(0.0)
    wsum = np.float32(0.0)
    for dy in range(-1, 2):
        yy = y + dy
        if yy < 0 or yy >= h:
            continue
        for dx in range(-1, 2):
            xx = x + dx
            if xx < 0 or xx >= w or (dy == 0 and dx == 0) or not known[yy, xx]:
                continue
            wt = np.float32(1.0) if (dy != 0 and dx != 0) else np.float32(2.0)
            acc += wt * values[yy, xx]
            wsum += wt
    return acc / wsum if wsum > 0 else pv[o1 + (y // 2) * w1 + x // 2]


@njit(cache=True, nogil=True, inline="always")
def fill_row(values, known, pv, o1, w1, y, g, keep):
    """g[x] = `fill_px` of every pixel of row y, or with `keep` its own value where it is known;
    `known`: bool or 0/1 float weights, `values` finite (or zero) where the weight is 0. The interior is
    branch-free (it vectorises): no known neighbour gives 0/0 = NaN there, then replaced by the level-1
    value (so is the NaN of a sum of +inf and -inf, values beyond float32's range)."""
    h, w = values.shape
    zero = np.float32(0.0)
    if y == 0 or y == h - 1 or w < 3:
        for x in range(w):
            own = keep and known[y, x] > 0
            g[x] = values[y, x] if own else fill_px(values, known, pv, o1, w1, y, x)
        return
    two = np.float32(2.0)
    one = np.float32(1.0)
    base = o1 + (y // 2) * w1
    for x in range(1, w - 1):
        k00 = one if known[y - 1, x - 1] else zero
        k01 = one if known[y - 1, x] else zero
        k02 = one if known[y - 1, x + 1] else zero
        k10 = one if known[y, x - 1] else zero
        k12 = one if known[y, x + 1] else zero
        k20 = one if known[y + 1, x - 1] else zero
        k21 = one if known[y + 1, x] else zero
        k22 = one if known[y + 1, x + 1] else zero
        acc = zero + values[y - 1, x - 1] * k00
        acc = acc + two * (values[y - 1, x] * k01)
        acc = acc + values[y - 1, x + 1] * k02
        acc = acc + two * (values[y, x - 1] * k10)
        acc = acc + two * (values[y, x + 1] * k12)
        acc = acc + values[y + 1, x - 1] * k20
        acc = acc + two * (values[y + 1, x] * k21)
        acc = acc + values[y + 1, x + 1] * k22
        ws = zero + k00
        ws = ws + two * k01
        ws = ws + k02
        ws = ws + two * k10
        ws = ws + two * k12
        ws = ws + k20
        ws = ws + two * k21
        ws = ws + k22
        r = acc / ws
        a = values[y, x]
        kc = one if known[y, x] else zero
        g[x] = a if keep & (kc > zero) else r
    for x in range(1, w - 1):
        if g[x] != g[x]:
            g[x] = pv[base + x // 2]
    for x in (0, w - 1):
        own = keep and known[y, x] > 0
        g[x] = values[y, x] if own else fill_px(values, known, pv, o1, w1, y, x)


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def fill(zv, kf, pv, o1, w1, out):
    """out = the level-0 values `zv` where the weight `kf` is 1, the fill (`fill_row`) elsewhere; rows in
    parallel (`out` may be the input values: the fill reads the level-0 planes only)."""
    for y in prange(zv.shape[0]):
        fill_row(zv, kf, pv, o1, w1, y, out[y], True)


def pull_push(vals, k, out=None):
    """Pull-push fill of float32 `vals` (H, W) with bool `known` (the preview method), written into `out`
    (a new array when None; may be `vals` itself)."""
    vals = np.ascontiguousarray(vals, dtype=np.float32)
    k = np.ascontiguousarray(k)
    if out is None:
        out = np.empty_like(vals)
    h, w = vals.shape
    pv, pw, hs, ws, off = pyramid(h, w)
    zv, kf = planes("pullpush.level0", (h, w), lambda: (np.empty((h, w), np.float32),
                                                              np.empty((h, w), np.float32)))
    pull_level1(vals, k, zv, kf, pv, pw, off[1], hs[1], ws[1])
    pull_push_levels(pv, pw, hs, ws, off)
    fill(zv, kf, pv, off[1], ws[1], out)
    return out
