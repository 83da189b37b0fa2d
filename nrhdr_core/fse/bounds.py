"""FSE bounds of the missing pixels in the working domain: the data's own bounds (a clipped pixel is at
least its clip level, a too-dark one at most its threshold) and, in the log domain, the local bound (the
range of the known pixels of a ``local_bound`` neighbourhood widened by ``local_margin`` stops; the data's
bounds win where they conflict). docs/FSE.md "Domain and bounds".

The log domain with the local bound (the HDR case) is three parallel row passes over per-thread planes
(:func:`log_local_prep`): working image and row min/max (:func:`prep_local`), then the column min/max, the
log2 of the data's bounds and the merge at the missing pixels only (:func:`bounds_local`). The block kernels
are compiled with fastmath (no infinities), so unbounded sides are the finite sentinels +-1e38.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from ..scratch import planes
from .params import MISSING

__all__ = ["data_bounds", "log_bounds", "log_local_prep", "prep_local", "bounds_local", "bound_flags"]


def data_bounds(lower, upper, shape, use):
    """(lo, hi, use_lo, use_hi): the data's bounds as float32 (H, W) arrays (NaN: unbounded, as +-inf), and
    whether any is finite ((1, 1) dummies where not); none when ``use`` is False."""
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


def log_bounds(lo_arr, hi_arr, use_lo, use_hi, c, floor):
    """The data's bounds in the log domain: log2(max(b + c, floor))."""
    if use_lo:
        lo_arr = np.log2(np.maximum(lo_arr + np.float32(c), floor)).astype(np.float32)
    if use_hi:
        hi_arr = np.log2(np.maximum(hi_arr + np.float32(c), floor)).astype(np.float32)
    return lo_arr, hi_arr


def _planes(h, w):
    """Per-thread working arrays of the log-domain passes, reused frame after frame (``scratch.planes``):
    work, state, row max, row min, lower, upper. Nothing returned to the caller of ``fse_reconstruct``
    lives in them."""
    return planes("fse.log_local", (h, w), lambda: (
        np.empty((h, w), np.float32), np.empty((h, w), np.uint8), np.empty((h, w), np.float32),
        np.empty((h, w), np.float32), np.empty((h, w), np.float32), np.empty((h, w), np.float32)))


def log_local_prep(v32, k, lower, upper, p, c, floor):
    """Working image, state and merged log-domain bounds (lo, hi) of the log domain log2(max(x + c, floor))
    with the local bound (:func:`prep_local`, :func:`bounds_local`), in per-thread planes."""
    h, w = v32.shape
    use = bool(p["use_bounds"])
    lw = None if (not use or lower is None) else \
        np.ascontiguousarray(np.broadcast_to(np.asarray(lower, np.float32), (h, w)))
    up = None if (not use or upper is None) else \
        np.ascontiguousarray(np.broadcast_to(np.asarray(upper, np.float32), (h, w)))
    dummy = np.zeros((1, 1), np.float32)
    use_lo = use_hi = False
    if lw is not None or up is not None:
        use_lo, use_hi = bound_flags(dummy if lw is None else lw, dummy if up is None else up,
                                      lw is not None, up is not None)
    work, state, hmx, hmn, lo, hi = _planes(h, w)
    r = int(p["local_bound"]) // 2
    cf = np.float32(c)
    ff = np.float32(floor)
    prep_local(v32, k, (cf, ff), r, (work, state, hmx, hmn))
    bounds_local((hmx, hmn), r, np.float32(p["local_margin"]),
                 (dummy if lw is None else lw, dummy if up is None else up, use_lo, use_hi), (cf, ff), (lo, hi),
                 state)
    return work, state, lo, hi


@njit(cache=True, nogil=True, inline="always")
def _row_has_finite(a, y):
    """Whether row y of `a` holds a finite value."""
    for x in range(a.shape[1]):
        v = a[y, x]
        if v - v == 0:
            return True
    return False


@njit(cache=True, nogil=True, parallel=True)
def bound_flags(lower, upper, has_lo, has_hi):
    """(any finite lower, any finite upper): whether the data's bounds are used at all (:func:`data_bounds`)."""
    h = lower.shape[0] if has_lo else upper.shape[0]
    r_lo = np.zeros(h, np.uint8)
    r_hi = np.zeros(h, np.uint8)
    for y in prange(h):
        if has_lo and _row_has_finite(lower, y):
            r_lo[y] = 1
        if has_hi and _row_has_finite(upper, y):
            r_hi[y] = 1
    return bool(r_lo.any()), bool(r_hi.any())


@njit(cache=True, nogil=True, parallel=True)
def prep_local(v, k, lc, r, planes4):
    """``planes4`` = (work, state, hmx, hmn), ``lc`` = (c, floor): work = log2(max(v + c, floor)) at known
    pixels (KNOWN = 1), 0 elsewhere (MISSING = 0); hmx/hmn: max/min of the known work values in the 2r + 1
    wide row window (edges replicated, like scipy's "nearest"), -/+ float32 max where there is none."""
    c, floor = lc
    work, state, hmx, hmn = planes4
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
def bounds_local(rows, r, margin, data, lc, out, state):
    """Log-domain bounds (lo, hi) = ``out`` of the missing pixels (the block kernels read no other pixel's
    bounds, and known ones keep whatever lo/hi held; rows with nothing missing are skipped): the local
    bound (column window over the row max/min ``rows`` = (hmx, hmn) of :func:`prep_local`, widened by
    `margin` stops) narrowed by the data's bounds ``data`` = (lower, upper, use_lo, use_hi) as
    log2(max(b + c, floor)), ``lc`` = (c, floor),
    the data's bound winning where they conflict (a local floor above the data's ceiling yields to the
    ceiling, a local ceiling below the floor to the floor), clipped to +-1e38 (finite sentinels for the
    fastmath block kernels)."""
    hmx, hmn = rows
    lower, upper, use_lo, use_hi = data
    c, floor = lc
    lo, hi = out
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
                nmiss += 1 if state[y, x] == MISSING else 0
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
                    # NaN (no bound) -> -inf -> log2(floor); log2 only where bounded
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
