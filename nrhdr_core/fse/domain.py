"""FSE working domain: the data statistics, the log domain's offset, the working image (prep) and the
way back (finish).

The block model is fitted in a working domain chosen per frame (docs/FSE.md "Domain and bounds"): linear,
or log2(x + c) with the offset c of :func:`log_offset` ("auto"). The statistics passes are branch-free over
order-preserving integer keys of the float32 values (:func:`f32_key`).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from .params import KNOWN, MISSING, RECONSTRUCTED

__all__ = ["log_offset", "working_domain", "stats", "prep", "finish", "finish_c", "finish_at", "finite_max",
           "f32_key", "f32_unkey"]


def working_domain(p, v32, k, lower, kmin, kmax):
    """("linear" | "log", c): the domain of the block model for parameters ``p`` and the known values'
    range [kmin, kmax]; "auto" is log2(x + c) with c from :func:`log_offset` (``log_offset`` None) or the
    given c, exactly linear where c >= 64 x the data range (log2(x + c) is linear to < 1 % there)."""
    domain = p["domain"]
    c = 0.0
    if domain == "auto":
        domain = "log"
        if p["log_offset"] is None:
            c = log_offset(v32, k, float(p["offset_noise_k"]), lower if p["use_bounds"] else None)
        else:
            c = float(p["log_offset"])
        if c >= 64.0 * (float(kmax) - min(float(kmin), 0.0)):
            domain, c = "linear", 0.0
    elif domain == "log" and p["log_offset"] is not None:
        c = float(p["log_offset"])
    return domain, c


def log_scale(p, c, kmin, kmax, floor):
    """The data scale of sigma in the log domain: the known values' log range, at most ``log_scale_stops``
    (an almost linear low-dynamic-range domain then behaves like the linear one)."""
    wr = math.log2(max(kmax, 0.0) + c) - math.log2(max(max(kmin, 0.0) + c, floor))
    return float(p["log_scale_stops"]) if not wr > 0 else min(float(p["log_scale_stops"]), wr)


def log_floor(c, minpos):
    """The floor of the log domain: the offset c, or half the smallest positive known value without one."""
    if c > 0.0:
        return c
    return 0.5 * minpos if minpos > 0 else 1e-30


def log_offset(v: np.ndarray, k: np.ndarray, noise_k: float = 2.0, lower=None) -> float:
    """The offset c of the ``auto`` domain log2(x + c) (docs/FSE.md "Domain and bounds"), from robust
    statistics of the known values only, so that it moves little with the noise or mask seed:

    c = max(p50 * 2^(12 - 5 r), noise_k * sigma_dark), r = log2(top / p50) (stops of highlights above
    the median), top = max(p99.9 of the known values, largest lower bound: a clipped pixel implies at
    least its clip level, so a scene whose highlights all clip is still HDR). The family log2(x + c)
    is continuous in c and tends to the linear domain as c grows: low-dynamic-range data (8-bit
    images, r <= 1.5) get c >= 8 x their maximum, i.e. linear (the
    caller switches to exactly linear above 64 x the range, where the two agree); HDR data (r >= 4) a
    log domain down to the noise floor sigma_dark, a MAD estimate from second differences of three
    horizontally adjacent known pixels among the darkest tenth (~0 for noise-free data).
    Scales with the data (k * values -> k * c). The statistics of a row-strided subsample, gathered by
    numba kernels without full-frame temporaries."""
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
            found, mx = finite_max(np.ascontiguousarray(lw).reshape(1, -1) if lw.ndim != 2
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
def f32_key(i):
    """Order-preserving int32 key of float32 bits (an involution; integer min/max vectorise where float
    ones do not, and branches on a random mask mispredict): same order as the floats (-0 below +0)."""
    return i ^ ((i >> 31) & 0x7FFFFFFF)


@njit(cache=True, nogil=True, inline="always")
def f32_unkey(key):
    """float32 of a :func:`f32_key` key, as float64."""
    return np.float64(np.array([key ^ ((key >> 31) & 0x7FFFFFFF)], np.int32).view(np.float32)[0])


@njit(cache=True, nogil=True, parallel=True)
def finite_max(b):
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
            m = max(m, f32_key(bi[y, x]) if fin else kmin)
            f |= np.int64(fin)
        r_max[y] = m
        r_any[y] = f
    m = kmin
    f = False
    for y in range(h):
        if r_any[y]:
            f = True
            m = max(m, r_max[y])
    return f, (f32_unkey(m) if f else -np.inf)


@njit(cache=True, nogil=True, parallel=True)
def stats(v, k):
    """(known count, min, max, smallest positive known value) in one parallel pass (per-row partials,
    reduced in row order: the result does not depend on the thread count; branch-free over the integer
    keys of the float32 values, :func:`f32_key`)."""
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
            key = f32_key(vi[y, x])
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
    kmin = np.inf if nk == 0 else f32_unkey(lo)
    kmax = -np.inf if nk == 0 else f32_unkey(hi)
    minpos = 0.0 if pos == kmax_ else f32_unkey(pos)
    return nk, kmin, kmax, minpos


@njit(cache=True, nogil=True, parallel=True)
def prep(v, k, logd, floor):
    """Working image and state: known pixels (KNOWN) hold v, or log2(max(v, floor)) in the log domain
    (``logd``); the others are MISSING and hold 0."""
    h, w = v.shape
    work = np.empty((h, w), np.float32)
    state = np.empty((h, w), np.uint8)
    for y in prange(h):
        for x in range(w):
            if k[y, x]:
                state[y, x] = KNOWN
                if logd:
                    work[y, x] = np.float32(math.log2(max(v[y, x], floor)))
                else:
                    work[y, x] = v[y, x]
            else:
                state[y, x] = MISSING
                work[y, x] = 0.0
    return work, state


@njit(cache=True, nogil=True, parallel=True)
def finish(out, work, state, logd):
    """Write the reconstructed pixels of the working image into out (2^work in the log domain, ``logd``);
    returns the count of pixels left missing."""
    h, w = out.shape
    left = 0
    for y in prange(h):
        c = 0
        for x in range(w):
            s = state[y, x]
            if s == RECONSTRUCTED:
                if logd:
                    out[y, x] = np.float32(2.0 ** np.float64(work[y, x]))
                else:
                    out[y, x] = work[y, x]
            elif s == MISSING:
                c += 1
        left += c
    return left


@njit(cache=True, nogil=True, parallel=True)
def finish_c(out, work, state, c):
    """The log domain with the offset c: out = 2^work - c at the reconstructed pixels; returns the count of
    pixels left missing."""
    h, w = out.shape
    left = 0
    for y in prange(h):
        n = 0
        idx = np.empty(w, np.int64)
        m = 0
        for x in range(w):              # branch-free: count left, compact the reconstructed pixels
            s = state[y, x]
            n += np.int64(s == MISSING)
            idx[m] = x
            m += np.int64(s == RECONSTRUCTED)
        for q in range(m):
            x = idx[q]
            out[y, x] = np.float32(2.0 ** np.float64(work[y, x])) - c
        left += n
    return left


@njit(cache=True, nogil=True)
def finish_at(out, work, ys, xs, c, with_c, logd):
    """`finish_c` (`with_c`) or `finish` at the pixels (ys, xs) only: the fallback's few pixels."""
    for i in range(ys.size):
        y = ys[i]
        x = xs[i]
        if with_c:
            out[y, x] = np.float32(2.0 ** np.float64(work[y, x])) - c
        elif logd:
            out[y, x] = np.float32(2.0 ** np.float64(work[y, x]))
        else:
            out[y, x] = work[y, x]
