"""Independent numpy/scipy expectations of FSE's domain and bounds passes, for the tests: the log domain
offset (`log_offset_reference`), the local bound (`local_bounds`, scipy's min/max filters), its merge with
the data's bounds (`merge_bounds`) and a whole `fse_reconstruct` whose passes around the block kernels are
these numpy ones (`fse_reconstruct_reference`; the block plan and kernels are the package's)."""
from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from nrhdr_core import fse
from nrhdr_core.fse import fallback, kernel, params, reconstruct
from nrhdr_core.fse.params import KNOWN, MISSING, RECONSTRUCTED


def log_offset_reference(v: np.ndarray, k: np.ndarray, noise_k: float = 2.0, lower=None) -> float:
    """`fse.log_offset` in numpy (its docstring gives the rule): percentiles and the MAD of the dark
    second differences on the same row-strided subsample."""
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


def local_bounds(work, state, size, margin, logd):
    """Range of the known pixels (KNOWN) in each pixel's size x size neighbourhood, widened by
    `margin` (stops in the log domain; share of the local range in the linear one); +-inf where no
    known pixel is near."""
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


def merge_bounds(lo_arr, hi_arr, use_lo, use_hi, llo, lhi, shape):
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


def fse_reconstruct_reference(values, known, lower=None, upper=None, preset="balanced", **overrides):
    """`fse.fse_reconstruct` (no weights, no skip) with numpy passes around the block kernels: statistics,
    offset (`log_offset_reference`), log2 of the data and of the bounds, the local bound (`local_bounds`,
    `merge_bounds`), 2^work - c back. The same output to float rounding (the log2 of the data and of the
    bounds in float64 rounded to float32, where the fused driver takes libm's float32 log2f: the same but for
    rare halfway cases)."""
    p = fse.resolve_params(preset, **overrides)
    v32 = np.ascontiguousarray(values, np.float32)
    k = np.asarray(known, bool)
    out = v32.copy()
    kv = v32[k]
    if kv.size == v32.size or kv.size == 0:
        raise ValueError("reference: needs known and missing pixels")
    p = params.density_params(p, kv.size / v32.size)
    kmin, kmax = float(kv.min()), float(kv.max())
    pos = kv[kv > 0]
    minpos = float(pos.min()) if pos.size else 0.0
    if kmin == kmax:
        raise ValueError("reference: constant data")
    use = p["use_bounds"]
    shape = v32.shape
    lo = np.full(shape, -np.inf, np.float32) if not (use and lower is not None) else \
        np.where(np.isnan(lower), -np.inf, lower).astype(np.float32)
    hi = np.full(shape, np.inf, np.float32) if not (use and upper is not None) else \
        np.where(np.isnan(upper), np.inf, upper).astype(np.float32)
    use_lo, use_hi = bool(np.isfinite(lo).any()), bool(np.isfinite(hi).any())
    domain, c = p["domain"], 0.0
    if domain == "auto":
        domain = "log"
        c = log_offset_reference(v32, k, float(p["offset_noise_k"]), lower if use else None) \
            if p["log_offset"] is None else float(p["log_offset"])
        if c >= 64.0 * (kmax - min(kmin, 0.0)):
            domain, c = "linear", 0.0
    elif domain == "log" and p["log_offset"] is not None:
        c = float(p["log_offset"])
    logd = domain == "log"
    state = np.where(k, KNOWN, MISSING).astype(np.uint8)
    if logd:
        floor = c if c > 0.0 else (0.5 * minpos if minpos > 0 else 1e-30)
        # log2 in float64, rounded to float32: within libm's log2f's 0.502 ulp (numpy's float32 SIMD log2 is not)
        work = np.where(k, np.log2(np.maximum(v32 + np.float32(c), np.float32(floor)).astype(np.float64)),
                        0).astype(np.float32)
        lo = np.log2(np.maximum(lo + np.float32(c), floor)).astype(np.float32)
        hi = np.log2(np.maximum(hi + np.float32(c), floor)).astype(np.float32)
        wr = math.log2(max(kmax, 0.0) + c) - math.log2(max(max(kmin, 0.0) + c, floor))
        scale = float(p["log_scale_stops"]) if not wr > 0 else min(float(p["log_scale_stops"]), wr)
        if int(p["local_bound"]):
            llo, lhi = local_bounds(work, state, int(p["local_bound"]), float(p["local_margin"]), True)
            lo, hi = merge_bounds(lo, hi, use_lo, use_hi, llo, lhi, shape)
            use_lo = use_hi = True
    else:
        work = np.where(k, v32, 0).astype(np.float32)
        scale = kmax - kmin
    big = np.float32(1e38)
    lo = np.ascontiguousarray(np.clip(lo, -big, big), np.float32)
    hi = np.ascontiguousarray(np.clip(hi, -big, big), np.float32)
    reconstruct.extrapolate_frame(kernel.Frame(work, state, lo, hi), p, scale, use_lo, use_hi)
    if (state == MISSING).any():
        fallback.fill_left(work, state)
    rec = state == RECONSTRUCTED
    out[rec] = (2.0 ** work[rec].astype(np.float64)).astype(np.float32) if logd else work[rec]
    if logd and c > 0:
        out[~k] -= np.float32(c)
    return out
