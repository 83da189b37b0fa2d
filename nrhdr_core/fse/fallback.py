"""FSE fallback for pixels no block could fill (their support area held no usable pixel) and for frames
without a usable model: the value of the Euclidean-nearest source pixel (:func:`nearest_fill`), the bounds
when no pixel is known (:func:`fill_without_data`), the bounds around a constant (:func:`fill_bounded`).

:func:`nearest_fill`: up to NEAREST_RING_MAX pixels a ring search around each (:func:`ring_nearest`: its cost
grows with the pixels left and their distance to a source, not with the frame), the rest (many pixels, or
no source within RING_RADIUS_MAX) the distance transform of a crop around them (:func:`crop_nearest`).
Equidistant sources may resolve differently between the two.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from .params import KNOWN, MISSING, NOISY, RECONSTRUCTED

__all__ = ["nearest_fill", "fill_left", "fill_without_data", "fill_bounded", "ring_nearest", "crop_nearest",
           "NEAREST_RING_MAX", "RING_RADIUS_MAX"]

NEAREST_RING_MAX = 4096     # left pixels up to which the fallback searches rings around each
RING_RADIUS_MAX = 64        # ring radius searched; pixels with no source that near take the cropped transform

# sources by working state: known, reconstructed, noisy measurement; not missing nor skipped
_STATE_SRC = np.zeros(256, np.bool_)
_STATE_SRC[[KNOWN, RECONSTRUCTED, NOISY]] = True
_BOOL_SRC = np.array([False, True] + [True] * 254, np.bool_)


def nearest_fill(work, left, src=None):
    """Pixels ``left`` (bool (H, W)) of ``work`` get the value of the Euclidean-nearest ``src`` pixel (bool
    (H, W); default: every pixel not left), in place; no source anywhere: 0."""
    src = ~left if src is None else src
    ys, xs = np.nonzero(left)
    _fill_at(work, np.ascontiguousarray(src).view(np.uint8), _BOOL_SRC, ys, xs)


def fill_left(work, state):
    """The pixels no block could fill (MISSING) get the value of the nearest known, reconstructed or
    noisy-measurement pixel (:func:`nearest_fill`'s rule) and become RECONSTRUCTED; returns their
    coordinates. One numba scan finds them (no frame-sized numpy temporaries for a handful of pixels)."""
    ys, xs = _left_coords(state)
    _fill_at(work, state, _STATE_SRC, ys, xs)
    state[ys, xs] = RECONSTRUCTED
    return ys, xs


def _fill_at(work, src, is_src, ys, xs):
    """:func:`nearest_fill` of the pixels (ys, xs), sources where ``is_src[src]``; none anywhere: 0."""
    if ys.size == 0:
        return
    todo = np.ones(ys.size, np.bool_)
    if ys.size <= NEAREST_RING_MAX:
        todo = ring_nearest(work, src, is_src, ys, xs, RING_RADIUS_MAX)
    if todo.any():
        crop_nearest(work, src, is_src, ys[todo], xs[todo])


def crop_nearest(work, src, is_src, ys, xs):
    """The distance transform of a crop reaching `m` pixels beyond the bounding box of (ys, xs): a source
    outside it is more than `m` away from every one of them, so the result is exact once each found a
    source within `m` (else `m` grows, up to the whole frame)."""
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
    """(ys, xs) of the MISSING pixels, in row-major order (as np.nonzero)."""
    h, w = state.shape
    n = 0
    for y in range(h):
        for x in range(w):
            n += 1 if state[y, x] == MISSING else 0
    ys = np.empty(n, np.int64)
    xs = np.empty(n, np.int64)
    i = 0
    for y in range(h):
        for x in range(w):
            if state[y, x] == MISSING:
                ys[i] = y
                xs[i] = x
                i += 1
    return ys, xs


@njit(cache=True, nogil=True)
def ring_nearest(work, src, is_src, ys, xs, rcap):
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
                # full rows at the top and bottom, else the two sides
                step = 1 if (dy == -r or dy == r) else 2 * r
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


def fill_without_data(out, miss, lower, upper):
    """No pixel known: the ``miss`` pixels of ``out`` get 0 raised to ``lower`` and lowered to ``upper``
    where those are finite."""
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


def fill_bounded(out, miss, lower, upper):
    """The ``miss`` pixels of ``out`` clamped to ``lower``/``upper`` where those are finite (None: unbounded)."""
    if lower is not None:
        lo = np.broadcast_to(np.asarray(lower, np.float32), out.shape)
        m = miss & np.isfinite(lo)
        out[m] = np.maximum(out[m], lo[m])
    if upper is not None:
        hi = np.broadcast_to(np.asarray(upper, np.float32), out.shape)
        m = miss & np.isfinite(hi)
        out[m] = np.minimum(out[m], hi[m])
    return out
