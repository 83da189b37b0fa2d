"""Nearest fill: each target pixel takes the value of its Euclidean-nearest source pixel. The one
implementation behind ``reconstruct(method="nearest")``, the linear method outside the convex hull, the
repair of non-finite values, and FSE's fallback for pixels no block could fill.

Tie rule (equidistant sources): the source with the smallest column, then the smallest row. Every strategy
follows it, so the result does not depend on the strategy :func:`nearest_at` picks:

- up to NEAREST_RING_MAX targets: a ring search around each (:func:`_ring`; its cost grows with the targets
  and their distance to a source, not with the frame), exact within RING_RADIUS_MAX;
- the rest: the exact Euclidean distance transform with argmin tracking (Felzenszwalb & Huttenlocher,
  Theory of Computing 2012: nearest source row per column, then the lower envelope of parabolas per row)
  on a crop reaching `m` pixels beyond the targets' bounding box (the whole frame once the crop would
  cover half of it). A source outside the crop is more than `m` away from every target, so the result is
  exact once each target found a source within `m`; else `m` becomes the largest distance found (then
  exact), or grows 4-fold while the crop holds no source.

Sources and targets are given as code arrays with lookup tables (a pixel is a source where
``is_src[src[y, x]]``, a target where ``is_tgt[tgt[y, x]]``): a bool mask viewed as uint8, or a state plane.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from .scratch import planes

__all__ = ["nearest", "nearest_fill", "nearest_at", "coords", "NEAREST_RING_MAX", "RING_RADIUS_MAX",
           "TRUE_CODES", "FALSE_CODES"]

NEAREST_RING_MAX = 4096     # targets up to which a ring search around each is tried first
RING_RADIUS_MAX = 64        # ring radius searched; targets with no source that near take the transform
_NONE = np.int64(2 ** 62)   # squared distance of a target whose crop holds no source

TRUE_CODES = np.zeros(256, np.bool_)    # a bool mask viewed as uint8: its True pixels
TRUE_CODES[1:] = True
FALSE_CODES = ~TRUE_CODES               # its False pixels


def nearest(values, known, out=None):
    """Every pixel not ``known`` gets the value of the nearest known pixel (the tie rule of the module),
    written into ``out`` (may be ``values``: known pixels are only read) or a new float32 array."""
    vals = np.ascontiguousarray(values, dtype=np.float32)
    codes = np.ascontiguousarray(known, dtype=np.bool_).view(np.uint8)
    if out is None:
        out = vals.copy()
    nearest_at(vals, out, codes, TRUE_CODES, codes, FALSE_CODES)
    return out


def nearest_fill(work, left, src=None):
    """Pixels ``left`` (bool (H, W)) of ``work`` get the value of the nearest ``src`` pixel (bool (H, W);
    default: every pixel not left), in place; no source anywhere: 0."""
    left = np.ascontiguousarray(left, dtype=np.bool_).view(np.uint8)
    if src is None:
        nearest_at(work, work, left, FALSE_CODES, left, TRUE_CODES)
    else:
        nearest_at(work, work, np.ascontiguousarray(src, dtype=np.bool_).view(np.uint8), TRUE_CODES, left,
                   TRUE_CODES)


def nearest_at(vals, dst, src, is_src, tgt, is_tgt, ys=None, xs=None):
    """``dst`` at each target pixel = ``vals`` at its nearest source (module docstring: tie rule,
    strategies); no source anywhere: 0. ``vals`` and ``dst`` float32 (H, W), may be one array; ``ys``,
    ``xs``: the targets' coordinates when the caller has them (exactly the target pixels)."""
    h, w = src.shape
    if not (vals.shape == dst.shape == tgt.shape == (h, w)) or vals.ndim != 2:
        raise ValueError(f"nearest fill: values {vals.shape}, output {dst.shape}, sources {src.shape} and "
                         f"targets {tgt.shape} must be one (H, W) shape")
    if ys is None:
        n, y0, y1, x0, x1 = _target_box(tgt, is_tgt)
        if n == 0:
            return
        if n <= NEAREST_RING_MAX:
            ys, xs = _target_coords(tgt, is_tgt, n)
    else:
        n = ys.size
        if n == 0:
            return
        y0, y1, x0, x1 = int(ys.min()), int(ys.max()) + 1, int(xs.min()), int(xs.max()) + 1
    if n <= NEAREST_RING_MAX:
        todo = _ring(vals, dst, src, is_src, ys, xs, RING_RADIUS_MAX)
        if not todo.any():
            return
        ty, tx = ys[todo], xs[todo]
        y0, y1, x0, x1 = int(ty.min()), int(ty.max()) + 1, int(tx.min()), int(tx.max()) + 1
    m = 16
    while True:
        cy0, cy1, cx0, cx1 = max(0, y0 - m), min(h, y1 + m), max(0, x0 - m), min(w, x1 + m)
        if 2 * (cy1 - cy0) * (cx1 - cx0) >= h * w:     # most of the frame: the whole one (no second pass)
            cy0, cy1, cx0, cx1 = 0, h, 0, w
        whole = (cy0, cy1, cx0, cx1) == (0, h, 0, w)
        flat = planes("fill.rows", (h, w), lambda: np.empty(h * w, np.int32))
        row = flat[:(cy1 - cy0) * (cx1 - cx0)].reshape(cy1 - cy0, cx1 - cx0)
        _columns(src, is_src, cy0, cy1, cx0, cx1, row)
        d2 = _rows(vals, dst, tgt, is_tgt, cy0, cx0, y0, y1, x0, x1, row)
        if whole or d2 <= m * m:
            return
        # a source within the largest distance found is within that margin: the next crop is exact
        m = 4 * m if d2 >= _NONE else math.isqrt(int(d2) - 1) + 1


def coords(codes, table):
    """(ys, xs) int64 of the pixels where ``table[codes]``, in row-major order (as np.nonzero), without
    frame-sized temporaries."""
    return _target_coords(codes, table, _target_box(codes, table)[0])


@njit(cache=True, nogil=True)
def _target_box(tgt, is_tgt):
    """(count, y0, y1, x0, x1): the number of target pixels and their bounding box (half-open)."""
    h, w = tgt.shape
    n = 0
    y0, y1, x0, x1 = h, 0, w, 0
    for y in range(h):
        c = 0
        for x in range(w):
            c += 1 if is_tgt[tgt[y, x]] else 0
        if c:
            n += c
            y0 = min(y0, y)
            y1 = y + 1
            for x in range(w):
                if is_tgt[tgt[y, x]]:
                    x0 = min(x0, x)
                    break
            for x in range(w - 1, -1, -1):
                if is_tgt[tgt[y, x]]:
                    x1 = max(x1, x + 1)
                    break
    return n, y0, y1, x0, x1


@njit(cache=True, nogil=True)
def _target_coords(tgt, is_tgt, n):
    """(ys, xs) of the ``n`` target pixels, in row-major order."""
    h, w = tgt.shape
    ys = np.empty(n, np.int64)
    xs = np.empty(n, np.int64)
    i = 0
    for y in range(h):
        for x in range(w):
            if is_tgt[tgt[y, x]]:
                ys[i] = y
                xs[i] = x
                i += 1
    return ys, xs


@njit(cache=True, nogil=True)
def _ring(vals, dst, src, is_src, ys, xs, rcap):
    """For each (ys[i], xs[i]): the value of the nearest source pixel (the module's tie rule), searched in
    square rings of growing Chebyshev radius r while r^2 does not exceed the best squared distance found
    (a pixel of ring r is at least r away, so an equidistant one may still come), r <= rcap. Values are
    read first, then written. Returns which pixels are left to do (no source proven nearest within rcap;
    their value is not written)."""
    h, w = src.shape
    vals_out = np.empty(ys.size, np.float32)
    todo = np.zeros(ys.size, np.bool_)
    rmax = min(max(h, w), rcap)
    for i in range(ys.size):
        y0 = ys[i]
        x0 = xs[i]
        if is_src[src[y0, x0]]:
            vals_out[i] = vals[y0, x0]
            continue
        best = -1
        by = 0
        bx = 0
        r = 1
        while r <= rmax and (best < 0 or r * r <= best):
            for dy in range(-r, r + 1):
                y = y0 + dy
                if y < 0 or y >= h:
                    continue
                # full rows at the top and bottom, else the two sides
                step = 1 if (dy == -r or dy == r) else 2 * r
                for dx in range(-r, r + 1, step):
                    x = x0 + dx
                    if x < 0 or x >= w or not is_src[src[y, x]]:
                        continue
                    d = dy * dy + dx * dx
                    if best < 0 or d < best or (d == best and (x < bx or (x == bx and y < by))):
                        best = d
                        by = y
                        bx = x
            r += 1
        vals_out[i] = vals[by, bx] if best >= 0 else np.float32(0.0)
        # not done: no source within the cap, or one beyond a ring not yet searched
        todo[i] = (best < 0 or r * r <= best) and r <= max(h, w)
    for i in range(ys.size):
        if not todo[i]:
            dst[ys[i], xs[i]] = vals_out[i]
    return todo


@njit(cache=True, nogil=True, parallel=True)
def _columns(src, is_src, cy0, cy1, cx0, cx1, row):
    """row[y - cy0, x - cx0] = the row of the nearest source in column x within rows cy0..cy1-1 (ties:
    the upper one; -1: none); column blocks of 64 in parallel, rows in memory order."""
    ch = cy1 - cy0
    cw = cx1 - cx0
    nb = (cw + 63) // 64
    for b in prange(nb):
        c0 = b * 64
        c1 = min(cw, c0 + 64)
        below = np.empty(c1 - c0, np.int32)
        for c in range(c0, c1):
            row[0, c] = cy0 if is_src[src[cy0, cx0 + c]] else -1
        for i in range(1, ch):
            for c in range(c0, c1):
                row[i, c] = cy0 + i if is_src[src[cy0 + i, cx0 + c]] else row[i - 1, c]
        for c in range(c0, c1):
            below[c - c0] = -1
        for i in range(ch - 1, -1, -1):
            y = cy0 + i
            for c in range(c0, c1):
                if is_src[src[y, cx0 + c]]:
                    below[c - c0] = y
                bl = below[c - c0]
                up = row[i, c]
                if bl >= 0 and (up < 0 or bl - y < y - up):
                    row[i, c] = bl


@njit(cache=True, nogil=True, parallel=True)
def _rows(vals, dst, tgt, is_tgt, cy0, cx0, y0, y1, x0, x1, row):
    """Rows y0..y1-1: the lower envelope of the parabolas (x - q)^2 + (y - row[y, q])^2 over the crop's
    columns q that have a source (ties: the smaller column); each target in columns x0..x1-1 takes the
    value at its minimiser. Returns the largest squared distance written (_NONE: the crop has no source;
    its targets get 0)."""
    cw = row.shape[1]
    nr = y1 - y0
    nch = min(nr, 64)
    dmax = np.zeros(nch, np.int64)
    for c in prange(nch):
        v = np.empty(cw, np.int64)
        z = np.empty(cw + 1, np.float64)
        f = np.empty(cw, np.float64)
        dm = np.int64(0)
        for y in range(y0 + (c * nr) // nch, y0 + ((c + 1) * nr) // nch):
            ri = y - cy0
            kk = -1
            for q in range(cw):
                r = row[ri, q]
                if r < 0:
                    continue
                f[q] = np.float64((y - r) * (y - r))
                if kk < 0:
                    kk = 0
                    v[0] = q
                    z[0] = -np.inf
                    z[1] = np.inf
                    continue
                fq = f[q] + np.float64(q * q)
                p = v[kk]
                s = (fq - (f[p] + np.float64(p * p))) / np.float64(2 * (q - p))
                while s <= z[kk]:
                    kk -= 1
                    p = v[kk]
                    s = (fq - (f[p] + np.float64(p * p))) / np.float64(2 * (q - p))
                kk += 1
                v[kk] = q
                z[kk] = s
                z[kk + 1] = np.inf
            if kk < 0:
                for x in range(x0, x1):
                    if is_tgt[tgt[y, x]]:
                        dst[y, x] = np.float32(0.0)
                        dm = _NONE
                continue
            j = 0
            for x in range(x0, x1):
                q = x - cx0
                while z[j + 1] < q:
                    j += 1
                if is_tgt[tgt[y, x]]:
                    p = v[j]
                    sy = row[ri, p]
                    dst[y, x] = vals[sy, p + cx0]
                    d = np.int64((y - sy) * (y - sy) + (q - p) * (q - p))
                    dm = max(dm, d)
        dmax[c] = dm
    return dmax.max()
