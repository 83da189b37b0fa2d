"""Logarithmic tone mapping for display (paper section 5, Fig. 10 g/h; hdr-references 'Tone mapping').

y = log(1 + q x) / log(1 + q), x = clip(L 2^e / white, 0, 1): the standard logarithmic operator
(HDR Toolbox LogarithmicTMO) with contrast q and exposure e in stops. The normaliser `white` is fixed
(the sensor's largest scaled value, (clip - black) * ND) or smoothed over time (`WhiteTracker`), never a
per-frame min/max: video must not flicker. `LocalTonemap` is the local operator (base / detail on log
luminance, Durand and Dorsey 2002, with a guided filter), `auto_white` / `AutoWhite` the white of inputs
without a sensor profile (docs/TONEMAP.md).

HDR display output (beyond the paper): the SMPTE ST 2084 (PQ) inverse EOTF and the ARIB STD-B67 / ITU-R
BT.2100 HLG OETF, named and written as in colour-science (colour/models/rgb/transfer_functions/st_2084.py,
arib_std_b67.py), and `hdr_encode`, which maps linear frames to 10-bit BT.2100 codes (narrow range 64..940,
ITU-R BT.2100 Table 9) in uint16 words, MSB-aligned (code << 6) as GRAY16_LE wants them.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

DEFAULT_CONTRAST = 1000.0


# ---- vectorisable log1p: math.log1p is a scalar libm call per pixel (~37 ms per
# 1080p frame on one core); this evaluates log via exponent/mantissa split (integer view of a row buffer)
# and the Cephes logf polynomial (~1 ulp), with log1p(a) = log(u) * a / (u - 1), u = 1 + a (Kahan's
# correction of the rounding of 1 + a). Same codes as math.log1p except for values within ~1e-6 of a
# rounding boundary (tests/tonemap_reference.py, tests/test_perf_kernels.py).
@njit(cache=True, nogil=True, inline="always")
def _split(bits, mbits, ebuf):
    """Exponent (into `ebuf`, as float32) and mantissa in [1, 2) (into `mbits`) of the float32 row `bits`
    (its int32 view)."""
    for x in range(bits.shape[0]):
        b = bits[x]
        ebuf[x] = np.float32((b >> 23) - 127)
        mbits[x] = (b & 0x7FFFFF) | 0x3F800000


@njit(cache=True, nogil=True, inline="always")
def _log_level(m, e, u, a0, q):
    """log1p(q min(max(a0, 0), 1)) from the mantissa m and exponent e of u = 1 + q min(max(a0, 0), 1) (Cephes
    logf polynomial, Kahan's correction, module notes)."""
    big = m > np.float32(1.4142135)
    m = m * np.float32(0.5) if big else m
    e = e + np.float32(1.0) if big else e
    z = m - np.float32(1.0)
    zz = z * z
    p = np.float32(7.0376836292e-2)
    p = p * z - np.float32(1.1514610310e-1)
    p = p * z + np.float32(1.1676998740e-1)
    p = p * z - np.float32(1.2420140846e-1)
    p = p * z + np.float32(1.4249322787e-1)
    p = p * z - np.float32(1.6668057665e-1)
    p = p * z + np.float32(2.0000714765e-1)
    p = p * z - np.float32(2.4999993993e-1)
    p = p * z + np.float32(3.3333331174e-1)
    r = p * z * zz
    r = r - np.float32(2.12194440e-4) * e
    r = r - np.float32(0.5) * zz
    lg = z + r + np.float32(0.693359375) * e
    a = u - np.float32(1.0)
    a0 = a0 if a0 > np.float32(0.0) else np.float32(0.0)
    a0 = q * (a0 if a0 < np.float32(1.0) else np.float32(1.0))
    return lg * (a0 / a) if a > np.float32(0.0) else a0


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _log_kernel(values, scale, q, inv_den, out_max, out):
    h, w = values.shape
    nch = min(h, 64)
    for c in prange(nch):
        ubuf = np.empty(w, np.float32)
        mbuf = np.empty(w, np.float32)
        ebuf = np.empty(w, np.float32)
        ubits = ubuf.view(np.int32)
        mbits = mbuf.view(np.int32)
        for y in range((c * h) // nch, ((c + 1) * h) // nch):
            for x in range(w):
                v = values[y, x] * scale
                v = v if v > np.float32(0.0) else np.float32(0.0)     # also maps NaN to black
                v = v if v < np.float32(1.0) else np.float32(1.0)
                ubuf[x] = np.float32(1.0) + q * v
            _split(ubits, mbits, ebuf)
            for x in range(w):
                out[y, x] = _log_level(mbuf[x], ebuf[x], ubuf[x], values[y, x] * scale, q) * inv_den * out_max \
                    + np.float32(0.5)


def _check_tone(white, contrast) -> None:
    if not (white > 0 and math.isfinite(white)):
        raise ValueError(f"tone mapping white must be a finite number > 0, got {white}")
    if not (contrast > 0 and math.isfinite(contrast)):
        raise ValueError(f"tone mapping contrast must be > 0, got {contrast}")


def log_tonemap(values: np.ndarray, white: float, exposure_stops: float = 0.0,
                contrast: float = DEFAULT_CONTRAST, out: np.ndarray | None = None,
                dtype=np.uint8) -> np.ndarray:
    """Map linear values (H, W) to uint8 or uint16 display codes; `out` (filled in place) fixes the type."""
    _check_tone(white, contrast)
    v = np.asarray(values, dtype=np.float32)
    if out is None:
        out = np.empty(v.shape, dtype=dtype)
    if out.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"tone mapping output must be uint8 or uint16, got {out.dtype}")
    out_max = 255.0 if out.dtype == np.uint8 else 65535.0
    scale = np.float32(2.0 ** exposure_stops / white)
    q = np.float32(contrast)
    _log_kernel(v, scale, q, np.float32(1.0 / math.log1p(contrast)), np.float32(out_max), out)
    return out


def robust_peak(values: np.ndarray, percentile: float = 99.9, stride: int = 4) -> float:
    """A flicker-robust frame statistic: the given percentile of a subsampled frame (not the maximum)."""
    sub = np.asarray(values)[::stride, ::stride]
    sub = sub[np.isfinite(sub)]
    return float(np.percentile(sub, percentile)) if sub.size else 0.0


class WhiteTracker:
    """Temporally smoothed normaliser, libcamera style: white_t = speed * peak_t + (1 - speed) * white_t-1,
    peak_t a high percentile of the frame; the first frame initialises it."""

    def __init__(self, speed: float = 0.1, percentile: float = 99.9):
        if not 0.0 < speed <= 1.0:
            raise ValueError(f"smoothing speed must be in (0, 1], got {speed}")
        self.speed, self.percentile, self.white = speed, percentile, None

    def update(self, values: np.ndarray) -> float:
        peak = max(robust_peak(values, self.percentile), 1e-6)
        self.white = peak if self.white is None else self.speed * peak + (1 - self.speed) * self.white
        return self.white

    def reset(self) -> None:
        self.white = None


AUTO_MEAN_LEVEL = 115.94 / 255   # display level of the log-average: TMQI's natural mean (Yeganeh and Wang Eq. 9)


def auto_white(values: np.ndarray, contrast: float = DEFAULT_CONTRAST, stride: int = 8) -> float | None:
    """The white of inputs without a sensor profile: the log-average (geometric mean) of the lit, finite
    pixels of a subsampled frame (Reinhard et al. 2002's key) shown by the log curve at AUTO_MEAN_LEVEL:
    white = key * q / (exp(AUTO_MEAN_LEVEL log(1 + q)) - 1). None when no pixel is lit."""
    sub = np.asarray(values, np.float32)[::stride, ::stride]
    sub = sub[np.isfinite(sub) & (sub > 0)]
    if not sub.size:
        return None
    key = float(np.exp(np.mean(np.log(sub), dtype=np.float64)))
    return key * contrast / math.expm1(AUTO_MEAN_LEVEL * math.log1p(contrast))


class AutoWhite:
    """`auto_white` smoothed over time in the log domain (exposure changes are symmetric):
    log white_t = speed log w_t + (1 - speed) log white_t-1; the first lit frame initialises it, frames
    without a lit pixel keep it (1.0 until then)."""

    def __init__(self, speed: float = 0.1, contrast: float = DEFAULT_CONTRAST):
        if not 0.0 < speed <= 1.0:
            raise ValueError(f"smoothing speed must be in (0, 1], got {speed}")
        self.speed, self.contrast, self.white = speed, contrast, None

    def update(self, values: np.ndarray) -> float:
        w = auto_white(values, self.contrast)
        if w is not None:
            w = min(max(w, 1e-30), 1e30)
            self.white = w if self.white is None else math.exp(
                self.speed * math.log(w) + (1 - self.speed) * math.log(self.white))
        return 1.0 if self.white is None else self.white

    def reset(self) -> None:
        self.white = None


# ---- local operator: base / detail on log luminance (Durand and Dorsey 2002) ------------------------------
#
# l = log2(x + 1/q), x = L 2^e / white (the log curve's toe: below white / q shadows compress linearly, so
# the noise floor is not amplified); base = a guided filter of l (He, Sun and Tang 2013, the fast variant of
# He and Sun 2015: coefficients on CELL x CELL means, bilinearly upsampled), detail = l - base;
# o = c (base - m) + g detail + s shown through y = log(1 + Q 2^min(o, 0)) / log(1 + Q).
# c compresses the base's robust range (0.5 .. 99.5th percentile of BLOCK-pixel block means) to at most
# LOCAL_RANGE stops; s puts the mean display level at LOCAL_MEAN and g (in [1, LOCAL_GAIN_MAX]) gives a mean
# 11 x 11-scale contrast of LOCAL_CONTRAST: the brightness and contrast of natural images (the mode of TMQI's
# naturalness model, Yeganeh and Wang 2013 Eq. 9-10). The statistics are smoothed over time like WhiteTracker.

LOCAL_CELL = 4              # pixels per coarse cell (guided-filter subsampling)
LOCAL_BLOCK = 3             # coarse cells per statistics block (12 x 12 pixels)
LOCAL_RADIUS = 0.02         # guided-filter radius, fraction of the larger frame side (Durand: 2 %)
LOCAL_EPS = 0.5             # guided-filter regulariser, stops^2: edges above ~0.7 stop stay in the base
LOCAL_RANGE = 7.0           # stops of base range shown
LOCAL_MEAN = 115.94 / 255   # target mean display level
LOCAL_CONTRAST = 17.5 / 255  # target mean block std (64.29 x the Beta mode 3.4/12.5 of TMQI)
LOCAL_GAIN_MAX = 5.0
LOCAL_Q = 300.0             # display curve contrast
LOCAL_TOE_LEVEL = 0.25      # highest display level of the toe (x = white / q)
_LUT_LO, _LUT_STEPS = -40.0, 64     # LUT domain o in [-40, 0] stops, 64 entries per stop
_LOG2_MAX = 100.0                    # x is capped at 2^100 (1e30 and +inf stay finite)


@njit(cache=True, nogil=True, inline="always")
def _log2_values(lrow, mrow):
    """lrow (x + toe per pixel) -> log2 in place by exponent / mantissa split (`mrow` the mantissas), ln m =
    2 atanh(z), z = (m-1)/(m+1) (|error| < 1e-6 stops)."""
    w = lrow.shape[0]
    k2 = np.float32(2.0 / math.log(2.0))
    _split(lrow.view(np.int32), mrow.view(np.int32), lrow)
    for x in range(w):
        m = mrow[x]
        big = m > np.float32(1.4142135)
        m = m * np.float32(0.5) if big else m
        e = lrow[x] + np.float32(1.0) if big else lrow[x]
        z = (m - np.float32(1.0)) / (m + np.float32(1.0))
        zz = z * z
        p = np.float32(1.0 / 9.0)
        p = p * zz + np.float32(1.0 / 7.0)
        p = p * zz + np.float32(1.0 / 5.0)
        p = p * zz + np.float32(1.0 / 3.0)
        p = p * zz + np.float32(1.0)
        lrow[x] = e + k2 * z * p


@njit(cache=True, nogil=True, inline="always")
def _cell_sums(lrow, cy, cm, cm2):
    """The sums of the row's l and l^2 per cell added to row cy of `cm`, `cm2`, left to right; the
    full cells in a loop of their own whose inner loop has a fixed count (LOCAL_CELL): it unrolls and the loop
    over cells vectorises."""
    w = lrow.shape[0]
    cell = LOCAL_CELL
    full = w // cell
    for cx in range(full):
        s1 = 0.0
        s2 = 0.0
        for j in range(cell):
            t = lrow[cx * cell + j]
            s1 += t
            s2 += t * t
        cm[cy, cx] += s1
        cm2[cy, cx] += s2
    for cx in range(full, cm.shape[1]):       # the partial last cell
        s1 = 0.0
        s2 = 0.0
        for x in range(cx * cell, w):
            t = lrow[x]
            s1 += t
            s2 += t * t
        cm[cy, cx] += s1
        cm2[cy, cx] += s2


@njit(cache=True, nogil=True, inline="always")
def _cell_means(cy, h, w, cm, cm2):
    """Sums of row cy of `cm`, `cm2` -> means over the cells' pixels."""
    cell = LOCAL_CELL
    ny = min(h, (cy + 1) * cell) - cy * cell
    for cx in range(cm.shape[1]):
        n = ny * (min(w, (cx + 1) * cell) - cx * cell)
        cm[cy, cx] /= n
        cm2[cy, cx] /= n


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _local_log(values, scale, toe, l, cm, cm2, mbuf):
    """l = log2(min(max(v scale, 0), 2^100) + toe) (NaN -> log2(toe)) per pixel into `l` (`_log2_values`); `cm`,
    `cm2`: means of l and l^2 per LOCAL_CELL^2 cell; rows in chunks, `mbuf` (chunks, w) the chunks' mantissa
    rows."""
    h, w = values.shape
    hc = cm.shape[0]
    nch = mbuf.shape[0]
    cell = LOCAL_CELL
    xmax = np.float32(2.0 ** _LOG2_MAX)
    for c in prange(nch):
        for cy in range((c * hc) // nch, ((c + 1) * hc) // nch):
            cm[cy, :] = 0.0
            cm2[cy, :] = 0.0
            for y in range(cy * cell, min(h, (cy + 1) * cell)):
                lrow = l[y]
                for x in range(w):
                    v = values[y, x] * scale
                    v = v if v > np.float32(0.0) else np.float32(0.0)     # also NaN
                    v = v if v < xmax else xmax
                    lrow[x] = v + toe
                _log2_values(lrow, mbuf[c])
                _cell_sums(lrow, cy, cm, cm2)
            _cell_means(cy, h, w, cm, cm2)


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _rgb_local_log(rgb, k, scale, toe, l, cm, cm2, mbuf):
    """`_local_log` of the luminance of the colour frame `rgb` (3, H, W) by `k` (`_luminance`)."""
    h, w = l.shape
    hc = cm.shape[0]
    nch = mbuf.shape[0]
    cell = LOCAL_CELL
    xmax = np.float32(2.0 ** _LOG2_MAX)
    k0, k1, k2, kr, kb = k[0], k[1], k[2], k[3], k[4]
    for c in prange(nch):
        for cy in range((c * hc) // nch, ((c + 1) * hc) // nch):
            cm[cy, :] = 0.0
            cm2[cy, :] = 0.0
            for y in range(cy * cell, min(h, (cy + 1) * cell)):
                lrow = l[y]
                for x in range(w):
                    v = _luminance(rgb, y, x, k0, k1, k2, kr, kb) * scale
                    v = v if v > np.float32(0.0) else np.float32(0.0)
                    v = v if v < xmax else xmax
                    lrow[x] = v + toe
                _log2_values(lrow, mbuf[c])
                _cell_sums(lrow, cy, cm, cm2)
            _cell_means(cy, h, w, cm, cm2)


@njit(cache=True, nogil=True, error_model="numpy")
def _box(src, r, tmp, acc, dst):
    """Mean over the (2r+1)^2 window clipped to the frame (running sums: along rows, four rows at a time as
    independent chains (the last group repeats the last row), each row then divided by the window widths held
    in `acc`; then down the columns with the row vector `acc`)."""
    h, w = src.shape
    for x in range(w):
        acc[x] = min(x + r, w - 1) - max(x - r, 0) + 1
    for y in range(0, h, 4):
        y1, y2, y3 = min(y + 1, h - 1), min(y + 2, h - 1), min(y + 3, h - 1)
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        s3 = 0.0
        for x in range(min(r, w - 1) + 1):
            s0 += src[y, x]
            s1 += src[y1, x]
            s2 += src[y2, x]
            s3 += src[y3, x]
        for x in range(w):
            lo, hi = x - r, x + r
            tmp[y, x] = s0
            tmp[y1, x] = s1
            tmp[y2, x] = s2
            tmp[y3, x] = s3
            if hi + 1 < w:
                s0 += src[y, hi + 1]
                s1 += src[y1, hi + 1]
                s2 += src[y2, hi + 1]
                s3 += src[y3, hi + 1]
            if lo >= 0:
                s0 -= src[y, lo]
                s1 -= src[y1, lo]
                s2 -= src[y2, lo]
                s3 -= src[y3, lo]
        for yy in range(y, min(y + 4, h)):
            for x in range(w):
                tmp[yy, x] = tmp[yy, x] / acc[x]
    for x in range(w):
        acc[x] = 0.0
    for y in range(min(r, h - 1) + 1):
        for x in range(w):
            acc[x] += tmp[y, x]
    for y in range(h):
        lo, hi = y - r, y + r
        inv = 1.0 / (min(hi, h - 1) - max(lo, 0) + 1)
        for x in range(w):
            dst[y, x] = acc[x] * inv
        if hi + 1 < h:
            for x in range(w):
                acc[x] += tmp[hi + 1, x]
        if lo >= 0:
            for x in range(w):
                acc[x] -= tmp[lo, x]


@njit(cache=True, nogil=True, error_model="numpy")
def _guided_coefficients(cm, cm2, r, eps, ca, cb, t1, t2, t3, acc):
    """Guided filter of the coarse log image by itself (He et al. 2013, Alg. 1): a = var / (var + eps),
    b = mean (1 - a), each box-averaged into `ca`, `cb`."""
    _box(cm, r, t1, acc, t2)            # mean
    _box(cm2, r, t1, acc, t3)           # mean of squares
    h, w = cm.shape
    for y in range(h):
        for x in range(w):
            mu = t2[y, x]
            var = t3[y, x] - mu * mu
            var = var if var > 0.0 else 0.0
            a = var / (var + eps)
            t2[y, x] = a
            t3[y, x] = mu - a * mu
    _box(t2, r, t1, acc, ca)
    _box(t3, r, t1, acc, cb)


@njit(cache=True, nogil=True)
def _block_stats(cm, cm2, ca, cb, stats):
    """Per LOCAL_BLOCK^2-cell block: cells, and the sums of the cells' means of base, base^2, detail, detail^2,
    base detail and of the coefficient a, from each cell's l moments with its coefficients (base = a l + b, detail = (1 - a) l - b)."""
    hc, wc = cm.shape
    stats[:] = 0.0
    for y in range(hc):
        by = y // LOCAL_BLOCK
        for x in range(wc):
            bx = x // LOCAL_BLOCK
            a, b, m1, m2 = ca[y, x], cb[y, x], cm[y, x], cm2[y, x]
            u = 1.0 - a
            stats[by, bx, 0] += 1.0
            stats[by, bx, 1] += a * m1 + b
            stats[by, bx, 2] += a * a * m2 + 2.0 * a * b * m1 + b * b
            stats[by, bx, 3] += u * m1 - b
            stats[by, bx, 4] += u * u * m2 - 2.0 * u * b * m1 + b * b
            stats[by, bx, 5] += a * u * m2 + (b * u - a * b) * m1 - b * b
            stats[by, bx, 6] += a


@njit(cache=True, nogil=True, inline="always")
def _lut_at(lut, o):
    t = (o - _LUT_LO) * _LUT_STEPS
    t = t if t > 0.0 else 0.0
    t = t if t < lut.shape[0] - 1 else lut.shape[0] - 1.0
    i = min(int(t), lut.shape[0] - 2)
    return lut[i] + (t - i) * (lut[i + 1] - lut[i])


@njit(cache=True, nogil=True)
def _mean_level(rel, wgt, s, lut):
    acc = 0.0
    for i in range(rel.shape[0]):
        acc += wgt[i] * _lut_at(lut, rel[i] + s)
    return acc


_LEVEL_BINS = 256                   # weight bins of `_level_bounds`
_LEVEL_MARGIN = 1e-9                # relative: far above the rounding of the sums (n u, n = 14400 at 1080p)


@njit(cache=True, nogil=True)
def _level_bins(rel, wgt, lo, width, wb):
    """The weights `wgt` summed into `wb` by the bin of rel (bins of `width` from `lo`, the last one closed)."""
    nb = wb.shape[0]
    wb[:] = 0.0
    for i in range(rel.shape[0]):
        wb[min(max(int((rel[i] - lo) / width), 0), nb - 1)] += wgt[i]


@njit(cache=True, nogil=True)
def _level_bounds(wb, lo, width, s, lut):
    """Lower and upper bounds of `_mean_level` at s from the binned weights: each term's level lies between
    the display levels of its bin's edges (widened by 1e-6 stop; the LUT curve is non-decreasing)."""
    lb = 0.0
    ub = 0.0
    for b in range(wb.shape[0]):
        if wb[b] > 0.0:
            lb += wb[b] * _lut_at(lut, lo + b * width - 1e-6 + s)
            ub += wb[b] * _lut_at(lut, lo + (b + 1) * width + 1e-6 + s)
    return lb, ub


def _mean_level_for_bisect(rel, wgt, lut, target):
    """s -> `_mean_level(rel, wgt, s, lut)` as `_bisect` uses it, compared with `target` only: where the bounds
    of `_level_bounds` put the level on one side of the target by more than _LEVEL_MARGIN, the bound stands in
    for it (the same comparisons, so the same s) and the full sum is skipped."""
    lo, hi = float(np.min(rel)), float(np.max(rel))
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return lambda s: _mean_level(rel, wgt, s, lut)
    width = max(hi - lo, 1e-6) / _LEVEL_BINS
    wb = np.empty(_LEVEL_BINS)
    _level_bins(rel, wgt, lo, width, wb)

    def level(s):
        lb, ub = _level_bounds(wb, lo, width, s, lut)
        if ub * (1.0 + _LEVEL_MARGIN) < target:
            return ub * (1.0 + _LEVEL_MARGIN)
        if lb * (1.0 - _LEVEL_MARGIN) > target:
            return lb * (1.0 - _LEVEL_MARGIN)
        return _mean_level(rel, wgt, s, lut)
    return level


@njit(cache=True, nogil=True)
def _mean_contrast(slope, wgt, vb, vd, cov, free, c, g):
    acc = 0.0
    for i in range(slope.shape[0]):
        gi = 1.0 + (g - 1.0) * free[i]
        v = c * c * vb[i] + gi * gi * vd[i] + 2.0 * c * gi * cov[i]
        acc += wgt[i] * slope[i] * math.sqrt(v if v > 0.0 else 0.0)
    return acc


@njit(cache=True, nogil=True, inline="always")
def _local_position(rows, c, lv, cx, j, c0, g1, k0, lo, steps):
    """LUT position of pixel j (0..3) of cell cx: a, b interpolated along the row (`rows[c, 0]`, `rows[c, 1]`,
    edge-extended by one cell), o = c base + (1 + (g - 1)(1 - a)) detail + k0."""
    i0 = cx + (j >> 1)
    fx = np.float32(0.625 + 0.25 * j - (j >> 1))
    av = rows[c, 0, i0] + fx * (rows[c, 0, i0 + 1] - rows[c, 0, i0])
    bv = rows[c, 1, i0] + fx * (rows[c, 1, i0 + 1] - rows[c, 1, i0])
    base = av * lv + bv
    gain = np.float32(1.0) + g1 * (np.float32(1.0) - av)
    return ((c0 * base + gain * (lv - base) + k0) - lo) * steps


@njit(cache=True, nogil=True)
def _local_levels(l, ca, cb, y, rows, t, ib, c, c0, g1, k0, n):
    """Row y's display-curve LUT positions (`_local_position`): indices into `ib[c]`, fractions into `t[c]`,
    for a LUT of n entries (NaN positions: entry 0). `rows[c]` (2, wc + 2) the coarse a, b interpolated down the
    column (edge-extended by one cell). The positions and the clamp / index split have loops of their own (both
    vectorise)."""
    w = l.shape[1]
    hc, wc = ca.shape
    steps = np.float32(_LUT_STEPS)
    lo = np.float32(_LUT_LO)
    top = np.float32(n - 1)
    cell = LOCAL_CELL
    ra = rows[c, 0]
    rb = rows[c, 1]
    tr = t[c]
    ir = ib[c]
    f = max((y + 0.5) / cell - 0.5, 0.0)
    y0 = min(int(f), hc - 1)
    y1 = min(y0 + 1, hc - 1)
    fy = f - y0
    for cx in range(wc):
        ra[cx + 1] = np.float32(ca[y0, cx] + fy * (ca[y1, cx] - ca[y0, cx]))
        rb[cx + 1] = np.float32(cb[y0, cx] + fy * (cb[y1, cx] - cb[y0, cx]))
    ra[0], rb[0] = ra[1], rb[1]
    ra[wc + 1], rb[wc + 1] = ra[wc], rb[wc]
    lrow = l[y]
    # pixel j of cell cx sits at cx + (j - 1.5) / 4: between cells cx-1|cx (j < 2) or cx|cx+1
    full = w // cell
    for cx in range(full):
        for j in range(cell):
            x = cx * cell + j
            tr[x] = _local_position(rows, c, lrow[x], cx, j, c0, g1, k0, lo, steps)
    for x in range(full * cell, w):
        tr[x] = _local_position(rows, c, lrow[x], full, x - full * cell, c0, g1, k0, lo, steps)
    last = np.int32(n - 2)
    for x in range(w):
        tv = min(max(np.float32(0.0), tr[x]), top)        # max(0, NaN) is 0 (`_unit`)
        i = min(np.int32(tv), last)
        ir[x] = i
        tr[x] = tv - np.float32(i)


@njit(cache=True, nogil=True, inline="always")
def _display_light(lut, dlut, dec, i, t):
    """The sRGB EOTF (table `dec`) of `_local_apply`'s 16-bit level (code + 0.5) at LUT index i (uint32) and
    fraction t (`dlut` the LUT's steps lut[i + 1] - lut[i])."""
    return dec[np.uint32((lut[i] + t * dlut[i]) * np.float32(65535.0) + np.float32(0.5))]


@njit(cache=True, nogil=True)
def _local_display(l, ca, cb, y, rows, t, ib, c, c0, g1, k0, lut, dlut, dec):
    """Row y's display light (`_display_light`) of the `_local_levels` positions into `t[c]`, as
    `_rgb_channels` takes it; `ib[c]` the row's LUT indices: the first row of a `_rgb_local_apply` chunk (the
    kernel looks the next rows' display light up beside the codes of the row before)."""
    w = l.shape[1]
    _local_levels(l, ca, cb, y, rows, t, ib, c, c0, g1, k0, lut.shape[0])
    tr = t[c]
    ir = ib[c]
    for x in range(w):
        tr[x] = _display_light(lut, dlut, dec, np.uint32(ir[x]), tr[x])


@njit(cache=True, nogil=True, parallel=True)
def _local_apply(l, ca, cb, c0, g1, k0, lut, dlut, out_max, rows, tbuf, ibuf, out):
    """o = c base + (1 + (g - 1)(1 - a)) detail + k0 (g1 = g - 1), base = a l + b with a, b bilinear from the
    coarse grid (cell centres): the gain fades to 1 where the base follows the image (a -> 1, strong edges,
    where a detail is the filter's residual, not texture); display code by the LUT (linear interpolation, `dlut`
    its steps lut[i + 1] - lut[i]). Rows in chunks (`_local_levels`): `rows` (chunks, 2, wc + 2) the coarse a, b
    of a row, `tbuf` (chunks, w) the LUT fractions, `ibuf` (chunks, w) the LUT indices."""
    h, w = l.shape
    n = lut.shape[0]
    nch = tbuf.shape[0]
    for c in prange(nch):
        tr = tbuf[c]
        ir = ibuf[c]
        for y in range((c * h) // nch, ((c + 1) * h) // nch):
            _local_levels(l, ca, cb, y, rows, tbuf, ibuf, c, c0, g1, k0, n)
            for x in range(w):
                i = np.uint32(ir[x])
                out[y, x] = (lut[i] + tr[x] * dlut[i]) * out_max + np.float32(0.5)


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _rgb_local_apply(rgb, k, l, ca, cb, c0, g1, k0, lut, dlut, rows, tbuf, ibuf, dec, code, sat, fbuf, fbits, out):
    """`_local_apply` on the luminance of the colour frame `rgb` by `k`, shown in colour into sRGB `out`
    (H, W, 3); `ibuf` (chunks, w) the LUT indices, `fbuf` (chunks, 3, w) the rows' channels. A chunk's rows in
    turn: row y's channels (`_rgb_channels` of its display light), then row y + 1's LUT positions
    (`_local_levels`) and one loop of the two scalar table look-ups, row y + 1's display light
    (`_display_light`) beside row y's codes (`_rgb_codes`)."""
    h, w = l.shape
    n = lut.shape[0]
    nch = tbuf.shape[0]
    for c in prange(nch):
        y0, y1 = (c * h) // nch, ((c + 1) * h) // nch
        tr = tbuf[c]
        ir = ibuf[c]
        if y0 < y1:
            _local_display(l, ca, cb, y0, rows, tbuf, ibuf, c, c0, g1, k0, lut, dlut, dec)
        for y in range(y0, y1):
            _rgb_channels(rgb, y, k, tbuf, c, sat, fbuf)
            if y + 1 < y1:
                _local_levels(l, ca, cb, y + 1, rows, tbuf, ibuf, c, c0, g1, k0, n)
                for x in range(w):
                    tr[x] = _display_light(lut, dlut, dec, np.uint32(ir[x]), tr[x])
                    _rgb_codes(fbits, c, x, code, out, y)
            else:
                for x in range(w):
                    _rgb_codes(fbits, c, x, code, out, y)


def _display(o):
    """The local operator's display curve: y = log(1 + Q 2^min(o, 0)) / log(1 + Q)."""
    return np.log1p(LOCAL_Q * np.exp2(np.minimum(o, 0.0))) / math.log1p(LOCAL_Q)


def _display_slope(o):
    """dy/do of `_display` (per stop), 0 where the curve is at full scale."""
    x = LOCAL_Q * np.exp2(np.minimum(o, 0.0))
    return np.where(o < 0.0, math.log(2.0) * x / (1.0 + x) / math.log1p(LOCAL_Q), 0.0)


_LUT = []


def _lut() -> np.ndarray:
    return _luts()[0]


def _luts() -> tuple[np.ndarray, np.ndarray]:
    """(the display curve's LUT, its steps lut[i + 1] - lut[i] in float32, 0 after the last entry)."""
    if not _LUT:
        o = _LUT_LO + np.arange(int(-_LUT_LO * _LUT_STEPS) + 1) / _LUT_STEPS
        lut = _display(o).astype(np.float32)
        _LUT.append((lut, np.append(lut[1:] - lut[:-1], np.float32(0.0))))
    return _LUT[0]


def _bisect(f, lo: float, hi: float, target: float, tol: float) -> float:
    """x in [lo, hi] where the increasing f(x) reaches target (lo or hi when it never does)."""
    if f(lo) >= target:
        return lo
    if f(hi) <= target:
        return hi
    while hi - lo > tol:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if f(mid) < target else (lo, mid)
    return 0.5 * (lo + hi)


def local_parameters(stats: np.ndarray, toe: float = 1.0 / DEFAULT_CONTRAST) -> tuple[float, float, float]:
    """(c, g, s - c m) from the block sums of `_block_stats`: base compression, detail gain and offset that
    give the target mean level and contrast (module notes). The offset never shows the toe (x = toe,
    l = log2(2 toe)) above LOCAL_TOE_LEVEL: a black frame stays dark instead of being lifted to the mean."""
    st = stats.reshape(-1, 7)
    n = st[:, 0]
    n = np.where(n > 0, n, 1.0)
    mu, mu_d = st[:, 1] / n, st[:, 3] / n
    var_b = np.maximum(st[:, 2] / n - mu * mu, 0.0)
    var_d = np.maximum(st[:, 4] / n - mu_d * mu_d, 0.0)
    cov = st[:, 5] / n - mu * mu_d
    free = 1.0 - st[:, 6] / n           # 1 - a: the detail's share that gets the extra gain
    wgt = st[:, 0] / st[:, 0].sum()
    m = float(np.sum(wgt * mu))
    lo, hi = np.percentile(mu, [0.5, 99.5])
    c = min(1.0, LOCAL_RANGE / max(float(hi - lo), 1e-6))
    rel = c * (mu - m)
    lut = _lut()
    s = _bisect(_mean_level_for_bisect(rel, wgt, lut, LOCAL_MEAN), -60.0, 60.0, LOCAL_MEAN, 1e-3)
    slope = _display_slope(rel + s)
    g = _bisect(lambda g: _mean_contrast(slope, wgt, var_b, var_d, cov, free, c, g), 1.0, LOCAL_GAIN_MAX,
                LOCAL_CONTRAST, 1e-3)
    o_toe = math.log2(math.expm1(LOCAL_TOE_LEVEL * math.log1p(LOCAL_Q)) / LOCAL_Q)     # inverse of _display
    return c, g, min(s - c * m, o_toe - c * math.log2(2.0 * toe))


class LocalTonemap:
    """The local operator (module notes) with its statistics (c, g, offset) smoothed over time:
    p_t = speed * frame + (1 - speed) * p_t-1, the first frame initialises them (`reset` restarts)."""

    def __init__(self, speed: float = 1.0):
        if not 0.0 < speed <= 1.0:
            raise ValueError(f"smoothing speed must be in (0, 1], got {speed}")
        self.speed = speed
        self.params = None

    def reset(self) -> None:
        self.params = None

    def __call__(self, values: np.ndarray, white: float, exposure_stops: float = 0.0,
                 contrast: float = DEFAULT_CONTRAST, out: np.ndarray | None = None, dtype=np.uint8) -> np.ndarray:
        """Linear values (H, W) to uint8 / uint16 display codes; `white` / `contrast` set the toe (white / q),
        `exposure_stops` shifts the automatic brightness."""
        _check_tone(white, contrast)
        v = np.asarray(values, dtype=np.float32)
        if v.ndim != 2 or min(v.shape) < 1:
            raise ValueError(f"tone mapping needs a 2-D frame, got shape {v.shape}")
        if out is None:
            out = np.empty(v.shape, dtype=dtype)
        if out.dtype not in (np.uint8, np.uint16):
            raise ValueError(f"tone mapping output must be uint8 or uint16, got {out.dtype}")
        out_max = 255.0 if out.dtype == np.uint8 else 65535.0
        return self._run(v, None, white, exposure_stops, contrast, out_max, None, out)

    def _run(self, v, k, white, exposure_stops, contrast, out_max, colour, out):
        """The operator on the grey `v` (H, W), or on the luminance of the colour `v` (3, H, W) by `k` with
        `colour` the colour display's tables and rows (`_rgb_local_apply`: sRGB tables, saturation, channel
        rows)."""
        from .scratch import planes
        h, w = v.shape[-2:]
        cell = LOCAL_CELL
        hc, wc = -(-h // cell), -(-w // cell)

        def make():
            coarse = [np.empty((hc, wc)) for _ in range(7)]
            return (np.empty((h, w), np.float32), np.empty((min(hc, 64), w), np.float32),
                    np.empty((min(h, 64), 2, wc + 2), np.float32), np.empty((min(h, 64), w), np.float32),
                    np.empty((min(h, 64), w), np.int32), np.empty(wc),
                    np.empty((-(-hc // LOCAL_BLOCK), -(-wc // LOCAL_BLOCK), 7)), *coarse)
        l, mbuf, rows, tbuf, ibuf, acc, stats, cm, cm2, ca, cb, t1, t2, t3 = planes("tonemap.local", (h, w), make)
        scale, toe = np.float32(1.0 / white), np.float32(1.0 / contrast)
        if colour is None:
            _local_log(v, scale, toe, l, cm, cm2, mbuf)
        else:
            _rgb_local_log(v, k, scale, toe, l, cm, cm2, mbuf)
        r = max(1, int(round(LOCAL_RADIUS * max(h, w) / cell)))
        _guided_coefficients(cm, cm2, r, LOCAL_EPS, ca, cb, t1, t2, t3, acc)
        _block_stats(cm, cm2, ca, cb, stats)
        p = np.array(local_parameters(stats, 1.0 / contrast))
        self.params = p if self.params is None else self.speed * p + (1 - self.speed) * self.params
        c, g, k0 = (float(t) for t in self.params)
        c, g1, k0 = np.float32(c), np.float32(g - 1.0), np.float32(k0 + exposure_stops)
        if colour is None:
            _local_apply(l, ca, cb, c, g1, k0, *_luts(), np.float32(out_max), rows, tbuf, ibuf, out)
        else:
            _rgb_local_apply(v, k, l, ca, cb, c, g1, k0, *_luts(), rows, tbuf, ibuf, *colour, out)
        return out

    def rgb(self, rgb: np.ndarray, white: float, exposure_stops: float = 0.0, contrast: float = DEFAULT_CONTRAST,
            white_balance=(1.0, 1.0, 1.0), saturation: float = 1.0, out: np.ndarray | None = None) -> np.ndarray:
        """Colour frames (3, H, W) -> sRGB uint8 (H, W, 3): `tonemap_rgb` with these statistics (the
        luminance's, smoothed over the frames as for grey)."""
        return tonemap_rgb(rgb, white, "local", white_balance, exposure_stops, contrast, saturation, out, local=self)


def local_tonemap(values: np.ndarray, white: float, exposure_stops: float = 0.0,
                  contrast: float = DEFAULT_CONTRAST, out: np.ndarray | None = None, dtype=np.uint8) -> np.ndarray:
    """One frame through a fresh `LocalTonemap` (stills; video keeps one `LocalTonemap`)."""
    return LocalTonemap()(values, white, exposure_stops, contrast, out, dtype)


SDR_OPERATORS = ("log", "local")


def warmup_local(elements: bool = False) -> None:
    """Compile (or load) the local operator's kernels on a tiny frame; `elements`: also a read-only input and
    padded uint8 / uint16 output rows (nrtonemap's mapped buffers)."""
    h, w = 12, 16
    v = np.geomspace(1.0, 1e4, h * w).astype(np.float32).reshape(h, w)
    inputs = [v]
    outs = [np.empty((h, w), np.uint8)]
    if elements:
        ro = v.copy()
        ro.setflags(write=False)
        inputs.append(ro)
        outs += [np.empty((h, w), np.uint16)] + [np.zeros((h, w + 4), dt)[:, :w] for dt in (np.uint8, np.uint16)]
    for x in inputs:
        for out in outs:
            LocalTonemap()(x, 1e4, out=out)


# ---- HDR transfer functions (ITU-R BT.2100) --------------------------------------------------------------

# SMPTE ST 2084:2014, section 5 (as published: exact rationals)
M_1 = 2610 / 4096 / 4          # 0.1593017578125
M_2 = 2523 / 4096 * 128        # 78.84375
C_1 = 3424 / 4096              # 0.8359375 = C_3 - C_2 + 1
C_2 = 2413 / 4096 * 32         # 18.8515625
C_3 = 2392 / 4096 * 32         # 18.6875
L_P = 10000.0                  # cd/m^2 of PQ's full signal

# ARIB STD-B67 / ITU-R BT.2100 Table 5 (HLG)
HLG_A = 0.17883277
HLG_B = 1 - 4 * HLG_A          # 0.28466892
HLG_C = 0.5 - HLG_A * math.log(4 * HLG_A)   # 0.55991073

# ITU-R BT.2408: diffuse (graphics) white of HDR programmes
REFERENCE_WHITE_NITS = 203.0
HLG_NOMINAL_PEAK = 1000.0      # cd/m^2 of the HLG reference display (BT.2100 Note 5f: system gamma 1.2)
HLG_SYSTEM_GAMMA = 1.2


def eotf_inverse_ST2084(C, L_p: float = L_P):
    """SMPTE ST 2084 inverse EOTF: display luminance C (cd/m^2) -> non-linear signal N in [0, 1].
    N = ((c1 + c2 Y^m1) / (1 + c3 Y^m1))^m2, Y = C / L_p (colour-science `eotf_inverse_ST2084`)."""
    Y = np.clip(np.asarray(C, dtype=np.float64) / L_p, 0.0, 1.0)
    Y_m1 = Y ** M_1
    return ((C_1 + C_2 * Y_m1) / (C_3 * Y_m1 + 1)) ** M_2


def eotf_ST2084(N, L_p: float = L_P):
    """SMPTE ST 2084 EOTF: signal N in [0, 1] -> luminance in cd/m^2 (inverse of eotf_inverse_ST2084)."""
    V_p = np.clip(np.asarray(N, dtype=np.float64), 0.0, 1.0) ** (1 / M_2)
    n = np.maximum(V_p - C_1, 0.0)
    return L_p * (n / (C_2 - C_3 * V_p)) ** (1 / M_1)


def oetf_HLG(E):
    """ARIB STD-B67 / BT.2100 HLG OETF: scene linear E in [0, 1] -> signal E' in [0, 1].
    E' = sqrt(3 E) for E <= 1/12, else a ln(12 E - b) + c (colour-science `oetf_ARIB_STD_B67` form)."""
    E = np.clip(np.asarray(E, dtype=np.float64), 0.0, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(E <= 1 / 12, np.sqrt(3 * E), HLG_A * np.log(np.maximum(12 * E - HLG_B, 1e-12)) + HLG_C)


def oetf_inverse_HLG(E_p):
    """Inverse HLG OETF: signal E' in [0, 1] -> scene linear E in [0, 1]."""
    E_p = np.clip(np.asarray(E_p, dtype=np.float64), 0.0, 1.0)
    return np.where(E_p <= 0.5, E_p ** 2 / 3, (np.exp((E_p - HLG_C) / HLG_A) + HLG_B) / 12)


def hlg_reference_E(reference_white: float = REFERENCE_WHITE_NITS) -> float:
    """Scene light E that the BT.2100 HLG reference OOTF (gray: L = L_W E^gamma, L_W = 1000 cd/m^2,
    gamma 1.2) shows at `reference_white` cd/m^2: E = (L / L_W)^(1/gamma); 203 cd/m^2 -> E' = 0.75 (BT.2408)."""
    return float((reference_white / HLG_NOMINAL_PEAK) ** (1 / HLG_SYSTEM_GAMMA))


def display_luminance(values, diffuse_white: float, reference_white: float = REFERENCE_WHITE_NITS,
                      exposure_stops: float = 0.0):
    """The chain's linear values -> display light in cd/m^2: L = v / diffuse_white * 2^exposure *
    reference_white. The regular pixels' white (`diffuse_white`, the caps' diffuse-white) is the scene's
    diffuse white and is shown at `reference_white` (ITU-R BT.2408: 203 cd/m^2); brighter values keep their
    ratio (scene-referred, no OOTF). Negative and non-finite values give 0."""
    v = np.nan_to_num(np.asarray(values, dtype=np.float64), nan=0.0, posinf=np.inf, neginf=0.0)
    return np.maximum(v, 0.0) * (2.0 ** exposure_stops / diffuse_white * reference_white)


def eetf_BT2390(L, source_peak: float, target_peak: float):
    """ITU-R BT.2390 (section 5.4) EETF in the PQ domain, source and target black 0: luminance L (cd/m^2)
    of a source graded up to `source_peak` -> luminance on a display of `target_peak`. With E1 = PQ(L) /
    PQ(source_peak), maxLum = PQ(target_peak) / PQ(source_peak), KS = 1.5 maxLum - 0.5: E1 below KS is kept,
    above it the Hermite spline P(E1) rolls off to maxLum at the source peak (beyond: maxLum). A source peak
    at or below the target's is returned unchanged (clipped to the target peak)."""
    L = np.asarray(L, dtype=np.float64)
    if source_peak <= target_peak:
        return np.minimum(np.maximum(L, 0.0), target_peak)
    src = float(eotf_inverse_ST2084(source_peak))
    max_lum = float(eotf_inverse_ST2084(target_peak)) / src
    ks = max(1.5 * max_lum - 0.5, 0.0)
    e1 = np.minimum(eotf_inverse_ST2084(L) / src, 1.0)
    t = (e1 - ks) / (1.0 - ks)
    p = (2 * t ** 3 - 3 * t ** 2 + 1) * ks + (t ** 3 - 2 * t ** 2 + t) * (1 - ks) + (-2 * t ** 3 + 3 * t ** 2) * max_lum
    return eotf_ST2084(np.where(e1 > ks, p, e1) * src)


def _eetf_params(source_peak: float, target_peak: float):
    """(PQ(source_peak), KS, maxLum) of eetf_BT2390 for the kernel; PQ(source) = 0 switches the EETF off."""
    if not (target_peak > 0) or source_peak <= target_peak:
        return 0.0, 1.0, 1.0
    src = float(eotf_inverse_ST2084(source_peak))
    max_lum = float(eotf_inverse_ST2084(target_peak)) / src
    return src, max(1.5 * max_lum - 0.5, 0.0), max_lum


@njit(cache=True, nogil=True, inline="always")
def _hdr_signal(v, transfer):
    """Non-linear signal of v in [0, 1] (NaN and negatives: black): PQ (0, v = cd/m^2 / L_p) or HLG (1, v = E)."""
    if not (v > 0.0):
        v = 0.0
    elif v > 1.0:
        v = 1.0
    if transfer == 0:
        ym = v ** M_1
        return ((C_1 + C_2 * ym) / (C_3 * ym + 1.0)) ** M_2
    if v <= 1.0 / 12.0:
        return math.sqrt(3.0 * v)
    return HLG_A * math.log(12.0 * v - HLG_B) + HLG_C


@njit(cache=True, nogil=True, inline="always")
def _rolled_off(v, transfer, src_pq, ks, max_lum):
    """PQ signal of the display light of v (transfer 0: v = cd/m^2 / L_p; 1: v = HLG's E, light of the
    1000 cd/m^2 reference display E^1.2) after the BT.2390 EETF (PQ of the source peak src_pq, knee ks,
    target maxLum), and whether the EETF changed it (False below the knee); NaN and negatives are black."""
    if not (v > 0.0):
        v = 0.0
    if transfer == 1:
        v = v ** HLG_SYSTEM_GAMMA * (HLG_NOMINAL_PEAK / L_P)
    if v > 1.0:
        v = 1.0
    ym = v ** M_1
    e1 = ((C_1 + C_2 * ym) / (C_3 * ym + 1.0)) ** M_2 / src_pq
    rolled = e1 > ks
    if e1 >= 1.0:
        e1 = max_lum
    elif rolled:
        t = (e1 - ks) / (1.0 - ks)
        t2 = t * t
        t3 = t2 * t
        e1 = ((2.0 * t3 - 3.0 * t2 + 1.0) * ks + (t3 - 2.0 * t2 + t) * (1.0 - ks)
              + (-2.0 * t3 + 3.0 * t2) * max_lum)
    return e1 * src_pq, rolled


@njit(cache=True, nogil=True, inline="always")
def _pq_light(e):
    """ST 2084 EOTF of the signal e, in units of L_p."""
    vp = e ** (1.0 / M_2)
    n = vp - C_1
    if n < 0.0:
        n = 0.0
    return (n / (C_2 - C_3 * vp)) ** (1.0 / M_1)


@njit(cache=True, nogil=True, inline="always")
def _hlg_from_pq(e):
    """HLG scene light E (at most 1) whose reference-display light E^1.2 has the PQ signal e."""
    v = (_pq_light(e) * (L_P / HLG_NOMINAL_PEAK)) ** (1.0 / HLG_SYSTEM_GAMMA)
    return v if v <= 1.0 else 1.0


@njit(cache=True, nogil=True, parallel=True)
def _hdr_kernel(values, scale, transfer, src_pq, ks, max_lum, code_max, out):
    """values * scale -> PQ (transfer 0: scale gives cd/m^2 / L_p) or HLG (1: scale gives E) -> 10-bit
    narrow-range code << 6. Same formulas as eotf_inverse_ST2084 / oetf_HLG / eetf_BT2390, in float64.
    src_pq > 0: display light (HLG: of the 1000 cd/m^2 reference display, L = E^1.2) goes through the BT.2390
    EETF (PQ of the source peak src_pq, knee ks, target maxLum) and HLG's E is taken back from it. Codes
    are capped at code_max (940, or the last code at or below the target peak)."""
    h, w = values.shape
    for y in prange(h):
        for x in range(w):
            v = values[y, x] * scale
            if src_pq > 0.0:
                e, _ = _rolled_off(v, transfer, src_pq, ks, max_lum)
                if transfer == 1:
                    v = _hlg_from_pq(e)
                    if v <= 1.0 / 12.0:
                        e = math.sqrt(3.0 * v)
                    else:
                        e = HLG_A * math.log(12.0 * v - HLG_B) + HLG_C
            else:
                e = _hdr_signal(v, transfer)
            code = int(64.0 + 876.0 * e + 0.5)
            if code > code_max:
                code = code_max
            out[y, x] = np.uint16(code << 6)


TRANSFERS = ("pq", "hlg")


def peak_luminance(white: float, diffuse_white: float, transfer: str = "pq",
                   reference_white: float = REFERENCE_WHITE_NITS, exposure_stops: float = 0.0) -> float:
    """Display light (cd/m^2) at which `hdr_encode` shows the linear value `white` (the sensor's largest,
    the caps' white) before any roll-off: the source peak of the EETF. pq: the display_luminance mapping
    (capped at 10000); hlg: the 1000 cd/m^2 reference display's L_W E^1.2."""
    r = 2.0 ** exposure_stops * white / diffuse_white
    if transfer == "pq":
        return float(min(r * reference_white, L_P))
    return float(HLG_NOMINAL_PEAK * (r * hlg_reference_E(reference_white)) ** HLG_SYSTEM_GAMMA)


def hdr_encode(values: np.ndarray, diffuse_white: float, transfer: str = "pq",
               reference_white: float = REFERENCE_WHITE_NITS, exposure_stops: float = 0.0,
               out: np.ndarray | None = None, peak: float = 0.0, source_peak: float = 0.0) -> np.ndarray:
    """Linear frame (H, W) -> BT.2100 10-bit narrow-range codes (64..940) << 6 in uint16.

    The linear value `diffuse_white` (x 2^-exposure) is shown at `reference_white` cd/m^2 (BT.2408 diffuse
    white, 203 by default); brighter values keep their ratio up to PQ's 10000 cd/m^2 or HLG's E = 1.
    pq: C = v / diffuse_white * 2^exposure * reference_white, code of eotf_inverse_ST2084(C).
    hlg: E = v / diffuse_white * 2^exposure * hlg_reference_E(reference_white), code of oetf_HLG(E).
    `peak` > 0 (cd/m^2, the mastering display's): display light from `source_peak` (`peak_luminance` of the
    frame's white) down is rolled off to `peak` by the BT.2390 EETF (`eetf_BT2390`; HLG: on the 1000 cd/m^2
    reference display's light) instead of being clipped, and no code exceeds the last one at or below `peak`."""
    args = _hdr_arguments(transfer, diffuse_white, reference_white, exposure_stops, peak, source_peak)
    v = np.asarray(values, dtype=np.float32)
    if out is None:
        out = np.empty(v.shape, np.uint16)
    if out.dtype != np.uint16:
        raise ValueError(f"HDR output must be uint16, got {out.dtype}")
    _hdr_kernel(v, *args, out)
    return out


def _hdr_arguments(transfer, diffuse_white, reference_white, exposure_stops, peak, source_peak) -> tuple:
    """The settings of `hdr_encode` / `hdr_encode_rgb` checked, as the kernels take them: (scale, transfer
    0 = pq / 1 = hlg, PQ of the source peak, knee, maxLum, highest code)."""
    if transfer not in TRANSFERS:
        raise ValueError(f"HDR transfer must be one of {', '.join(TRANSFERS)}, got {transfer!r}")
    if not (diffuse_white > 0 and math.isfinite(diffuse_white)):
        raise ValueError(f"HDR diffuse white must be a finite number > 0, got {diffuse_white}")
    if not (reference_white > 0 and math.isfinite(reference_white)):
        raise ValueError(f"reference white must be > 0 cd/m^2, got {reference_white}")
    if not (0.0 <= peak <= L_P and 0.0 <= source_peak and math.isfinite(source_peak)):
        raise ValueError(f"HDR peak must be in 0..{L_P:g} cd/m^2 and the source peak >= 0, got {peak}, "
                         f"{source_peak}")
    gain = 2.0 ** exposure_stops / diffuse_white
    src_pq, ks, max_lum = _eetf_params(min(source_peak, L_P), peak)
    code_max = 940
    if peak > 0:
        top = (eotf_inverse_ST2084(peak) if transfer == "pq"
               else oetf_HLG((min(peak, HLG_NOMINAL_PEAK) / HLG_NOMINAL_PEAK) ** (1 / HLG_SYSTEM_GAMMA)))
        code_max = min(int(math.floor(64.0 + 876.0 * float(top) + 1e-4)), 940)
    if transfer == "pq":
        return gain * reference_white / L_P, 0, src_pq, ks, max_lum, code_max
    return gain * hlg_reference_E(reference_white), 1, src_pq, ks, max_lum, code_max


# ---- colour (docs/COLOUR.md "Colour output") ---------------------------------------------------------------
#
# Camera RGB is linear light in BT.709 / sRGB primaries (the simulator's and the reconstruction's units,
# planar float32 (3, H, W)). SDR: white balance, then the luminance L (BT.709 weights) goes through the grey
# operators (log or local) to a display level; each channel becomes (c / L)^s Y' in linear display light
# (Y' = the sRGB EOTF of that level, s the saturation: 1 keeps hue and saturation; Schlick 1994, Mantiuk et
# al. 2009), so the displayed luminance is the grey tone map's. Out of gamut (a channel above full scale) the
# colour is mixed with its own grey Y' until the largest channel is at full scale: luminance and hue kept,
# saturation lowered, never a per-channel clip. HDR: BT.709 -> BT.2020 (ITU-R BT.2087), then PQ or HLG per
# channel; the BT.2390 roll-off works on max(R, G, B) and scales the three channels alike (hue kept).

LUMA_BT709 = (0.2126, 0.0722)         # (Kr, Kb) of BT.709: luminance of linear BT.709 / sRGB RGB
LUMA_BT2020 = (0.2627, 0.0593)        # (Kr, Kb) of BT.2020 non-constant luminance (ITU-R BT.2020 Table 4)
# CIE 1931 xy of the R, G, B primaries (ITU-R BT.709 Table 1 item 1.3, BT.2020 Table 3) and the D65 white
RGB_PRIMARIES = {
    "bt709": ((0.640, 0.330), (0.300, 0.600), (0.150, 0.060)),
    "bt2020": ((0.708, 0.292), (0.170, 0.797), (0.131, 0.046)),
}
WHITE_D65 = (0.3127, 0.3290)
WHITE_BALANCE = ("profile", "grey-world", "none")
_CHANNEL_CAP = 1e30                    # linear channel values are capped here (+inf stays finite)


def rgb_to_xyz_matrix(primaries: str) -> np.ndarray:
    """3 x 3 matrix from linear RGB of `primaries` (RGB_PRIMARIES) to CIE XYZ, white D65 at Y = 1 (SMPTE RP
    177: columns = the primaries' XYZ scaled so that RGB = (1, 1, 1) is the white)."""
    if primaries not in RGB_PRIMARIES:
        raise ValueError(f"primaries must be one of {', '.join(RGB_PRIMARIES)}, got {primaries!r}")

    def xyz(x, y):
        return np.array([x / y, 1.0, (1.0 - x - y) / y])
    p = np.stack([xyz(*c) for c in RGB_PRIMARIES[primaries]], axis=1)
    return p * np.linalg.solve(p, xyz(*WHITE_D65))


def primaries_matrix(source: str = "bt709", target: str = "bt2020") -> np.ndarray:
    """Linear RGB of `source` primaries -> linear RGB of `target` primaries (same D65 white): ITU-R BT.2087
    for bt709 -> bt2020 (rows 0.6274 0.3293 0.0433 / 0.0691 0.9195 0.0114 / 0.0164 0.0880 0.8956)."""
    return np.linalg.solve(rgb_to_xyz_matrix(target), rgb_to_xyz_matrix(source))


def _gains(white_balance, what: str = "white balance") -> np.ndarray:
    g = np.asarray(white_balance, dtype=np.float64).reshape(-1)
    if g.shape != (3,) or not (np.isfinite(g).all() and (g > 0).all()):
        raise ValueError(f"{what} must be three finite gains > 0 (R, G, B), got {white_balance!r}")
    return g


def _rgb_input(rgb, what: str = "colour image") -> np.ndarray:
    v = np.asarray(rgb, dtype=np.float32)
    if v.ndim != 3 or v.shape[0] != 3 or min(v.shape[1:]) < 1:
        raise ValueError(f"{what} must be planar RGB (3, H, W), got shape {v.shape}")
    return v


def grey_world(rgb: np.ndarray, white: float | None = None, stride: int = 4,
               dark: float = 2.0 ** -10) -> tuple[float, float, float]:
    """Grey-world white balance gains (R, G, B), G = 1: the means of R, G and B over the usable pixels are made
    equal (Buchsbaum 1980). Usable: finite, every channel > 0, the largest channel below 0.98 `white` (the
    sensor's largest value: clipped pixels have lost their colour; without `white`, below the 99th percentile
    of the largest channel) and the luminance above `dark` times that level (near black: noise). Every
    `stride`-th pixel in both directions. (1, 1, 1) when no pixel is usable; gains are kept within 1/64..64."""
    v = _rgb_input(rgb)[:, ::stride, ::stride].reshape(3, -1).astype(np.float64)
    ok = np.isfinite(v).all(axis=0) & (v > 0).all(axis=0)
    v = v[:, ok]
    if not v.shape[1]:
        return (1.0, 1.0, 1.0)
    m = v.max(axis=0)
    top = 0.98 * float(white) if white else float(np.percentile(m, 99.0))
    lum = v[1] + LUMA_BT709[0] * (v[0] - v[1]) + LUMA_BT709[1] * (v[2] - v[1])
    keep = (m < top) & (lum > dark * top)
    if not keep.any():
        return (1.0, 1.0, 1.0)
    means = v[:, keep].mean(axis=1)
    g = np.clip(means[1] / means, 1 / 64, 64)
    return (float(g[0]), 1.0, float(g[2]))


class GreyWorld:
    """`grey_world` gains smoothed over time in the log domain (as `AutoWhite`): log g_t = speed log g(frame)
    + (1 - speed) log g_t-1; the first frame initialises them."""

    def __init__(self, speed: float = 0.1, white: float | None = None):
        if not 0.0 < speed <= 1.0:
            raise ValueError(f"smoothing speed must be in (0, 1], got {speed}")
        self.speed, self.white, self.gains = speed, white, None

    def update(self, rgb: np.ndarray) -> tuple[float, float, float]:
        g = np.log(grey_world(rgb, self.white))
        self.gains = g if self.gains is None else self.speed * g + (1 - self.speed) * self.gains
        return tuple(float(x) for x in np.exp(self.gains))

    def reset(self) -> None:
        self.gains = None


@njit(cache=True, nogil=True, inline="always")
def _channel(v, g):
    """The white-balanced channel min(max(v g, 0), cap) (NaN -> 0)."""
    c = v * g
    return min(c if c > np.float32(0.0) else np.float32(0.0), np.float32(_CHANNEL_CAP))


@njit(cache=True, nogil=True, inline="always")
def _luminance(rgb, y, x, k0, k1, k2, kr, kb):
    """L = G + Kr (R - G) + Kb (B - G) of the white-balanced channels (`_channel`, gains k0, k1, k2): exactly G
    for a grey pixel."""
    r = _channel(rgb[0, y, x], k0)
    g = _channel(rgb[1, y, x], k1)
    b = _channel(rgb[2, y, x], k2)
    return g + kr * (r - g) + kb * (b - g)


@njit(cache=True, nogil=True, inline="always")
def _unit(v):
    """v clamped to [+0, 1]; NaN gives 0 (builtin max(a, b) is b > a ? b : a: selects, never branches)."""
    return min(max(np.float32(0.0), v), np.float32(1.0))


@njit(cache=True, nogil=True, inline="always")
def _into_gamut(t0, t1, t2, yd, tb, c, x):
    """Mix (t0, t1, t2) with its grey yd until the largest is at most 1; into tb[c, :, x], clamped (`_unit`)."""
    one = np.float32(1.0)
    mx = max(t0, max(t1, t2))
    f = (one - yd) / (mx - yd) if mx > one else one
    tb[c, 0, x] = _unit(yd + (t0 - yd) * f)
    tb[c, 1, x] = _unit(yd + (t1 - yd) * f)
    tb[c, 2, x] = _unit(yd + (t2 - yd) * f)


@njit(cache=True, nogil=True, inline="always")
def _srgb_code(b, code):
    """The sRGB 8-bit code of the linear light t in [+0, 1] with float32 bit pattern b (uint32): the number of
    code thresholds at or below t, from the `_srgb_tables` entry of b's top 16 bits ((n << 16) + 2^16 - o: n
    thresholds below the entry's range, o the low 16 bits of the one threshold in its range, 2^16 where none;
    adding b's low 16 bits carries into bit 16 exactly where they are at or above o)."""
    return np.uint8((code[b >> np.uint32(16)] + (b & np.uint32(0xFFFF))) >> np.uint32(16))


@njit(cache=True, nogil=True, inline="always")
def _rgb_channels(rgb, y, k, lev, c, sat, fb):
    """Row y's channels in linear display light into `fb[c]` (3, w) from the display light Y' of the grey
    operator's 16-bit level of its luminance (`lev[c]`, the sRGB EOTF of the code): channel t = (c / L)^sat Y'
    (Y' where L = 0); above full scale mixed with Y' until max(t) = 1. Every array indexed in full (no slices);
    the loop vectorises."""
    npx = lev.shape[1]
    zero = np.float32(0.0)
    one = np.float32(1.0)
    wr, wg, wb, kr, kb = k[0], k[1], k[2], k[3], k[4]
    if sat != one:
        for x in range(npx):
            L = _luminance(rgb, y, x, wr, wg, wb, kr, kb)
            yd = lev[c, x]
            if L > zero:
                _into_gamut((_channel(rgb[0, y, x], wr) / L) ** sat * yd,
                            (_channel(rgb[1, y, x], wg) / L) ** sat * yd,
                            (_channel(rgb[2, y, x], wb) / L) ** sat * yd, yd, fb, c, x)
            else:
                _into_gamut(yd, yd, yd, yd, fb, c, x)
    else:
        for x in range(npx):
            r = _channel(rgb[0, y, x], wr)
            g = _channel(rgb[1, y, x], wg)
            b = _channel(rgb[2, y, x], wb)
            L = g + kr * (r - g) + kb * (b - g)
            yd = lev[c, x]
            lit = L > zero
            kf = yd / (L if lit else one)
            t0 = r * kf if lit else yd
            t1 = g * kf if lit else yd
            t2 = b * kf if lit else yd
            mx = max(t0, max(t1, t2))
            over = mx > one
            mix = (one - yd) / (mx - yd if over else one)
            mix = mix if over else one
            fb[c, 0, x] = _unit(yd + (t0 - yd) * mix)
            fb[c, 1, x] = _unit(yd + (t1 - yd) * mix)
            fb[c, 2, x] = _unit(yd + (t2 - yd) * mix)


@njit(cache=True, nogil=True, inline="always")
def _rgb_codes(fbits, c, x, code, out, y):
    """The sRGB 8-bit codes (`_srgb_code`) of pixel x's channels, bits `fbits[c, :, x]` (the uint32 view of
    `_rgb_channels`' `fb`), into out[y, x] (table indices unsigned: no negative-index wrap)."""
    for ch in range(3):
        out[y, x, ch] = _srgb_code(fbits[c, ch, x], code)


@njit(cache=True, nogil=True, inline="always")
def _rgb_row(rgb, y, k, lev, c, code, sat, fb, fbits, out):
    """Row y of the colour display codes (H, W, 3): the channels (`_rgb_channels`), then their codes
    (`_rgb_codes`) in a loop of their own."""
    _rgb_channels(rgb, y, k, lev, c, sat, fb)
    for x in range(lev.shape[1]):
        _rgb_codes(fbits, c, x, code, out, y)


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _rgb_log_kernel(rgb, k, scale, q, inv_den, lev, dec, code, sat, fbuf, fbits, out):
    """`_log_kernel` on the luminance of the colour frame `rgb` (3, H, W) by `k` (`_luminance`, 16-bit levels
    into `lev` (chunks, w), then their display light by the sRGB EOTF table `dec`), shown in colour (`_rgb_row`)
    into sRGB `out` (H, W, 3); `fbuf` (chunks, 3, w) its rows, before them the log curve's 1 + q v, mantissas and
    exponents."""
    h, w = out.shape[0], out.shape[1]
    nch = fbuf.shape[0]
    k0, k1, k2, kr, kb = k[0], k[1], k[2], k[3], k[4]
    lmax = np.float32(65535.0)
    for c in prange(nch):
        ubuf = fbuf[c, 0]
        mbuf = fbuf[c, 1]
        ebuf = fbuf[c, 2]
        ubits = ubuf.view(np.int32)
        mbits = mbuf.view(np.int32)
        for y in range((c * h) // nch, ((c + 1) * h) // nch):
            for x in range(w):
                a = _luminance(rgb, y, x, k0, k1, k2, kr, kb) * scale
                lev[c, x] = a
                v = a if a > np.float32(0.0) else np.float32(0.0)
                v = v if v < np.float32(1.0) else np.float32(1.0)
                ubuf[x] = np.float32(1.0) + q * v
            _split(ubits, mbits, ebuf)
            for x in range(w):
                lev[c, x] = _log_level(mbuf[x], ebuf[x], ubuf[x], lev[c, x], q) * inv_den * lmax + np.float32(0.5)
            for x in range(w):
                lev[c, x] = dec[np.uint32(lev[c, x])]     # the look-up on its own: the loops beside vectorise
            _rgb_row(rgb, y, k, lev, c, code, sat, fbuf, fbits, out)


def srgb_eotf(v):
    """IEC 61966-2-1 sRGB EOTF: signal in [0, 1] -> linear display light in [0, 1]."""
    v = np.clip(np.asarray(v, dtype=np.float64), 0.0, 1.0)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


_SRGB = []


def _srgb_tables():
    """(decode: float32 sRGB EOTF of each 16-bit level; code: `_srgb_code`'s uint32 entry for each top 16 bits
    of a float32 in [+0, 1]). Code k + 1 starts at the float32 threshold srgb_eotf((k + 0.5) / 255) (rounding
    in the encoded domain); an entry's range (2^16 bit patterns, less than 0.79 % of its values) holds at most
    one threshold (those are 0.89 % or more apart)."""
    if not _SRGB:
        dec = srgb_eotf(np.arange(65536) / 65535.0).astype(np.float32)
        tb = srgb_eotf((np.arange(255) + 0.5) / 255.0).astype(np.float32).view(np.uint32).astype(np.int64)
        top = np.arange((0x3F800000 >> 16) + 1, dtype=np.int64)
        below = np.searchsorted(tb, top << 16, side="left")
        inside = np.searchsorted(tb, (top + 1) << 16, side="left") - below
        if inside.max() > 1:
            raise AssertionError("sRGB code tables: two thresholds in one entry's range")
        low = np.where(inside == 1, tb[np.minimum(below, tb.size - 1)] & 0xFFFF, 0x10000)
        _SRGB.append((dec, ((below << 16) + 0x10000 - low).astype(np.uint32)))
    return _SRGB[0]


def tonemap_rgb(rgb: np.ndarray, white: float, operator: str = "local", white_balance=(1.0, 1.0, 1.0),
                exposure_stops: float = 0.0, contrast: float = DEFAULT_CONTRAST, saturation: float = 1.0,
                out: np.ndarray | None = None, local: "LocalTonemap | None" = None) -> np.ndarray:
    """Linear camera RGB (3, H, W) -> 8-bit sRGB display codes (H, W, 3).

    Channels times `white_balance`, then the luminance L (BT.709 weights) through `operator` ("log": the
    paper's curve, section 5; "local": `local`, a `LocalTonemap` whose statistics are smoothed over the
    frames, or a fresh one) with `white`, `exposure_stops`, `contrast` as for grey frames; each channel in
    linear display light is (c / L)^saturation Y', Y' the display light of L's level (module notes: hue and
    saturation kept, out-of-gamut colours mixed with their grey, a grey pixel gives R = G = B)."""
    from .scratch import planes
    if operator not in SDR_OPERATORS:
        raise ValueError(f"tone mapping operator must be one of {', '.join(SDR_OPERATORS)}, got {operator!r}")
    if not (saturation > 0 and math.isfinite(saturation)):
        raise ValueError(f"saturation must be a finite number > 0, got {saturation}")
    v = _rgb_input(rgb)
    gains = _gains(white_balance)
    _, h, w = v.shape
    if out is None:
        out = np.empty((h, w, 3), np.uint8)
    if out.dtype != np.uint8 or out.shape != (h, w, 3):
        raise ValueError(f"colour tone mapping output must be uint8 ({h}, {w}, 3), got {out.dtype} {out.shape}")
    _check_tone(white, contrast)
    k = np.array([*gains, *LUMA_BT709], np.float32)
    lev, fbuf = planes("tonemap.rgb", (h, w), lambda: (np.empty((min(h, 64), w), np.float32),
                                                       np.empty((min(h, 64), 3, w), np.float32)))
    colour = (*_srgb_tables(), np.float32(saturation), fbuf, fbuf.view(np.uint32))
    if operator == "local":
        (LocalTonemap() if local is None else local)._run(v, k, white, exposure_stops, contrast, 65535.0,
                                                          colour, out)
    else:
        _rgb_log_kernel(v, k, np.float32(2.0 ** exposure_stops / white), np.float32(contrast),
                        np.float32(1.0 / math.log1p(contrast)), lev, *colour, out)
    return out


def warmup_rgb(elements: bool = False, operators=SDR_OPERATORS) -> None:
    """Compile (or load) the colour tone map's kernels on a tiny frame; `elements`: also a read-only input
    and padded output rows (nrtonemap's mapped buffers)."""
    h, w = 12, 16
    v = np.geomspace(1.0, 1e4, 3 * h * w).astype(np.float32).reshape(3, h, w)
    inputs = [v]
    outs = [np.empty((h, w, 3), np.uint8)]
    if elements:
        ro = v.copy()
        ro.setflags(write=False)
        inputs.append(ro)
        outs.append(np.zeros((h, w * 3 + 4), np.uint8)[:, :w * 3].reshape(h, w, 3))
    for op in operators:
        for x in inputs:
            for o in outs:
                tonemap_rgb(x, 1e4, op, out=o)


@njit(cache=True, nogil=True, inline="always")
def _hdr_code(e, code_max):
    code = int(64.0 + 876.0 * e + 0.5)
    return np.uint16((code if code < code_max else code_max) << 6)


# Colour HDR codes by threshold tables: a channel's code is a non-decreasing function f(v) of its linear value,
# so code(v) = f(0) + #{c : thr[c] <= v} with thr[c] the smallest float64 v where f reaches c, found by bisection
# on the bit patterns with the very formulas of `_hdr_kernel` (the same codes, not an approximation). Bins of
# 2^_TAB_BITS per octave (on the float64 bit pattern) give the code at each bin's start; the thresholds inside
# a bin are stepped over.
_TAB_BITS = 8
_TAB_SHIFT = 52 - _TAB_BITS
_TAB_VMAX = 16.0               # above every clamp of the transfers (HLG's roll-off: E^1.2 / 10 <= 1)
_TAB_VMIN = 2.0 ** -80
_TABLES: dict = {}


@njit(cache=True, nogil=True)
def _code_at(v, kind, transfer, src_pq, ks, max_lum, code_max):
    """The 10-bit code of `_hdr_rgb_kernel` for a channel value v: kind 0 a channel's own (PQ / HLG, no
    roll-off), 1 the largest channel's through the roll-off; kind 2: 1 if the roll-off changes v, else 0."""
    if kind == 0:
        e = _hdr_signal(v, transfer)
    else:
        e, rolled = _rolled_off(v, transfer, src_pq, ks, max_lum)
        if kind == 2:
            return 1 if rolled else 0
        if transfer == 1:
            e = _hdr_signal(_hlg_from_pq(e), 1)
    code = int(64.0 + 876.0 * e + 0.5)
    return code if code < code_max else code_max


@njit(cache=True, nogil=True)
def _thresholds(kind, transfer, src_pq, ks, max_lum, code_max, thr):
    """thr[c] = the smallest float64 v in [0, _TAB_VMAX] with `_code_at` >= c (inf where none); returns
    (f(0), f(_TAB_VMAX))."""
    bits = np.empty(1, np.int64)
    val = bits.view(np.float64)
    val[0] = _TAB_VMAX
    top_bits = bits[0]
    lo_code = _code_at(0.0, kind, transfer, src_pq, ks, max_lum, code_max)
    hi_code = _code_at(_TAB_VMAX, kind, transfer, src_pq, ks, max_lum, code_max)
    thr[:] = np.inf
    for c in range(lo_code + 1, hi_code + 1):
        lo, hi = 0, top_bits              # f(lo) < c <= f(hi)
        while hi - lo > 1:
            mid = (lo + hi) // 2
            bits[0] = mid
            if _code_at(val[0], kind, transfer, src_pq, ks, max_lum, code_max) >= c:
                hi = mid
            else:
                lo = mid
        bits[0] = hi
        thr[c] = val[0]
    return lo_code, hi_code


def _code_table(kind, transfer, src_pq, ks, max_lum, code_max):
    """(base bit pattern >> _TAB_SHIFT, codes at the bins' starts (int32), thresholds (float64, by code), top
    code) for `_table_code`, kept per setting."""
    key = (kind, transfer, src_pq, ks, max_lum, code_max)
    if key not in _TABLES:
        thr = np.empty(1026, np.float64)
        lo_code, hi_code = _thresholds(kind, transfer, src_pq, ks, max_lum, code_max, thr)
        finite = thr[np.isfinite(thr)]
        vmin = max(float(finite.min()) if finite.size else _TAB_VMAX, _TAB_VMIN)
        base = int(np.array(vmin).view(np.int64)) >> _TAB_SHIFT
        top = int(np.array(_TAB_VMAX).view(np.int64)) >> _TAB_SHIFT
        starts = (np.arange(base, top + 1, dtype=np.int64) << _TAB_SHIFT).view(np.float64).copy()
        starts[0] = 0.0
        bins = (lo_code + np.searchsorted(np.sort(finite), starts, side="right")).astype(np.int32)
        if len(_TABLES) > 32:
            _TABLES.clear()
        _TABLES[key] = (np.int64(base), bins, thr, np.int64(hi_code))
    return _TABLES[key]


@njit(cache=True, nogil=True, inline="always")
def _table_code(v, vbits, base, bins, thr, top):
    """`_code_at` of v (its float64 bit pattern `vbits`) from a `_code_table`."""
    if not (v > 0.0):
        return bins[0]
    if v >= _TAB_VMAX:
        return top
    i = (vbits >> _TAB_SHIFT) - base
    code = bins[i if i > 0 else 0]
    while code < top and v >= thr[code + 1]:
        code += 1
    return code


@njit(cache=True, nogil=True, parallel=True)
def _hdr_rgb_kernel(rgb, gains, d, scale, transfer, src_pq, ks, max_lum, code_max, knee, tab, tabm, out):
    """Colour `_hdr_kernel`: channels times `gains`, primaries converted as c + d[k, 0] (R - B) + d[k, 1]
    (G - B) (M - I with rows summing to 0: exact for grey), times `scale`, then PQ / HLG per channel (codes
    from the table `tab`). With src_pq > 0 the BT.2390 EETF maps m = max(R, G, B) (display light; HLG: of the
    reference display; its code from `tabm`) and the channels are scaled by m' / m; below the knee of PQ's
    roll-off (m < `knee`) m' = m."""
    h, w = rgb.shape[1:]
    cap = _CHANNEL_CAP
    b0, b1, bt, t0 = tab
    m0, m1, mt, tm = tabm
    nch = min(h, 64)
    for c in prange(nch):
        vb = np.empty(4, np.float64)
        ib = vb.view(np.int64)
        for y in range((c * h) // nch, ((c + 1) * h) // nch):
            for x in range(w):
                r = rgb[0, y, x] * gains[0]
                g = rgb[1, y, x] * gains[1]
                b = rgb[2, y, x] * gains[2]
                r = min(r if r > 0.0 else 0.0, cap)
                g = min(g if g > 0.0 else 0.0, cap)
                b = min(b if b > 0.0 else 0.0, cap)
                vb[0] = (r + d[0, 0] * (r - b) + d[0, 1] * (g - b)) * scale
                vb[1] = (g + d[1, 0] * (r - b) + d[1, 1] * (g - b)) * scale
                vb[2] = (b + d[2, 0] * (r - b) + d[2, 1] * (g - b)) * scale
                if src_pq > 0.0:
                    m = max(vb[0], max(vb[1], vb[2]))
                    if not (m > 0.0):
                        m = 0.0
                    vb[3] = m
                    cm = _table_code(m, ib[3], m0, m1, mt, tm)
                    if transfer == 1 or m >= knee:
                        e, rolled = _rolled_off(m, transfer, src_pq, ks, max_lum)
                        if transfer == 1:
                            lm = _hlg_from_pq(e)
                        elif rolled:
                            lm = _pq_light(e)                        # the rolled-off light / L_p
                        else:
                            lm = m
                        k = lm / m if m > 0.0 else 0.0
                        for ch in range(3):
                            if vb[ch] < m:
                                vb[ch] *= k
                    for ch in range(3):
                        code = cm if vb[ch] >= m else _table_code(vb[ch], ib[ch], b0, b1, bt, t0)
                        out[ch, y, x] = np.uint16(code << 6)
                else:
                    for ch in range(3):
                        out[ch, y, x] = np.uint16(_table_code(vb[ch], ib[ch], b0, b1, bt, t0) << 6)


PRIMARIES_OUT = ("bt2020", "bt709")


def hdr_encode_rgb(rgb: np.ndarray, diffuse_white: float, transfer: str = "pq", white_balance=(1.0, 1.0, 1.0),
                   primaries: str = "bt2020", reference_white: float = REFERENCE_WHITE_NITS,
                   exposure_stops: float = 0.0, out: np.ndarray | None = None, peak: float = 0.0,
                   source_peak: float = 0.0) -> np.ndarray:
    """Linear camera RGB (3, H, W; BT.709 primaries) -> BT.2100 10-bit narrow-range R'G'B' codes << 6,
    uint16 (3, H, W).

    Channels times `white_balance`, then (primaries "bt2020") the ITU-R BT.2087 conversion to BT.2020
    primaries (`primaries_matrix`; "bt709": none), then per channel the mapping of `hdr_encode` (the linear
    value `diffuse_white` shown at `reference_white`, PQ or HLG). With `peak` > 0 the BT.2390 roll-off from
    `source_peak` maps the largest channel and scales the others alike (hue kept); a grey pixel gets the codes
    `hdr_encode` gives its value."""
    if primaries not in PRIMARIES_OUT:
        raise ValueError(f"HDR output primaries must be one of {', '.join(PRIMARIES_OUT)}, got {primaries!r}")
    args = _hdr_arguments(transfer, diffuse_white, reference_white, exposure_stops, peak, source_peak)
    v = _rgb_input(rgb)
    gains = _gains(white_balance)
    if out is None:
        out = np.empty(v.shape, np.uint16)
    if out.dtype != np.uint16 or out.shape != v.shape:
        raise ValueError(f"colour HDR output must be uint16 {v.shape}, got {out.dtype} {out.shape}")
    m = primaries_matrix("bt709", primaries) if primaries != "bt709" else np.eye(3)
    d = m - np.eye(3)
    d = np.ascontiguousarray(d[:, :2] + 0.0)      # M - I: column B is -(R + G) (rows of M sum to 1)
    scale, tr, src_pq, ks, max_lum, code_max = args
    tab = _code_table(0, tr, src_pq, ks, max_lum, code_max)
    tabm, knee = tab, _TAB_VMAX
    if src_pq > 0.0:
        tabm = _code_table(1, tr, src_pq, ks, max_lum, code_max)
        knee = float(_code_table(2, tr, src_pq, ks, max_lum, 1)[2][1])    # the smallest m the EETF changes
    _hdr_rgb_kernel(v, gains, d, *args, knee, tab, tabm, out)
    return out
