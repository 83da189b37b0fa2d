"""Reconstruction of missing pixels (paper section 2.2, 2.4, 5): one entry point, several methods.

Methods, from fastest to most accurate:
- ``preview``: pull-push normalised averaging on an image pyramid (numba); live preview.
- ``nearest``: nearest known pixel (scipy's exact Euclidean distance transform).
- ``linear``: Delaunay triangulation of the known pixels and linear interpolation on it (scipy), the
  paper's "triangular interpolation" of Fig. 10g.
- ``fse``: Frequency Selective Extrapolation (ref. 9; `fse.py`), the paper's method of Fig. 10h.

All methods leave known pixels bit-exact, honour optional bounds (a clipped pixel is at least `lower`, a
too-dark pixel at most `upper`), and cost nothing when no pixel is missing.
"""
from __future__ import annotations

import os
import warnings

import numpy as np
from numba import get_num_threads, njit, prange

from .fse import f32_key as _f32_key  # order-preserving int32 keys of float32 bits (min/max that vectorise)
from .fse import f32_unkey as _unkey
from .scratch import ThreadScratch  # scratch per OS thread (issue 7)
from .validity import clip_lower_row  # the clip rule, for the fused preview pass

METHODS = ("fse", "linear", "nearest", "preview")


class ReconstructionWarning(UserWarning):
    pass


def _validate(values, known, lower, upper):
    v = np.asarray(values)
    k = np.asarray(known)
    if v.ndim != 2:
        raise ValueError(f"values must be a 2-D array (H, W), got shape {v.shape}")
    if k.shape != v.shape:
        raise ValueError(f"known mask shape {k.shape} differs from values shape {v.shape}")
    if k.dtype != bool:
        raise ValueError(f"known must be a boolean array, got {k.dtype}")
    if not np.issubdtype(v.dtype, np.number) or np.iscomplexobj(v):
        raise ValueError(f"values must be real numbers, got {v.dtype}")
    if _nonfinite_known(v, k):
        raise ValueError("values contain NaN or Inf at known pixels; reconstruction needs finite data")
    out = []
    for name, b in (("lower", lower), ("upper", upper)):
        if b is None:
            out.append(None)
            continue
        b = np.asarray(b, dtype=np.float32)
        if b.shape != v.shape:
            raise ValueError(f"{name} bound shape {b.shape} differs from values shape {v.shape}")
        if _any_inf(b):
            raise ValueError(f"{name} bound contains Inf; use NaN for 'no bound'")
        out.append(b)
    return v, k, out[0], out[1]


def reconstruct(values, known, method: str = "fse", preset: str = "balanced", lower=None, upper=None,
                noisy=None, noise=None, out=None, noisy_joint: float = 0.0, fusion: str = "auto",
                noisy_skip=None, **params) -> np.ndarray:
    """Fill the pixels where `known` is False; returns float32 (H, W), known pixels bit-exact.

    values: float (H, W) in any scale (8-bit data or linear HDR); known: bool (H, W);
    lower/upper: optional float (H, W) bounds for missing pixels, NaN = no bound;
    preset/params: FSE parameter set (`fse.FSE_PRESETS`) and overrides; ignored by other methods.
    noisy/noise: optional bool (H, W) of missing pixels whose value is a noisy measurement (state NOISY,
    dark policy "weighted") and the noise model (anything with gain, read_noise, nd: a CameraProfile);
    they are reconstructed like the other missing pixels, then fused with their measurement by inverse
    variance (`fuse_noisy`, issue 8; `fusion`: its setting, "accurate", "fast" or "auto" = `fusion_for`). noisy_joint > 0 (method fse, opt-in): FSE fits its model to the
    NOISY measurements too, weighted `noisy_weights(..., noisy_joint)`, before the fusion (joint
    estimation; measured no better than the default, docs/BENCHMARKS.md "Joint FSE with noisy samples").
    noisy_skip (method fse, fusion "accurate", no noisy_joint): FSE leaves the NOISY pixels alone (issue 7:
    the accurate fusion re-estimates them from their measured 3 x 3 neighbours; FSE's value there only
    set the noise level) and they get the mean of their non-NOISY 3 x 3 neighbours as that level
    (`_noisy_level`); None: `NOISY_SKIP` (docs/FSE.md "Skipping NOISY pixels").
    out: optional float32 C-contiguous (H, W) array to write the result into (may be `values` itself:
    in place, e.g. mapped frame memory), returned.
    Missing pixels are returned finite, within [min(known min, 0), max(known max, lower bound)] (no
    blow-up, no negative value from non-negative data; issue 8) and within their bounds.
    With no known pixel the result is the bounds (lower where there is one, else upper, else 0) and a
    ReconstructionWarning saying so is issued."""
    if method not in METHODS:
        raise ValueError(f"reconstruction method must be one of {METHODS}, got {method!r}")
    if fusion not in FUSION_CHOICES:
        raise ValueError(f"noise fusion setting must be one of {FUSION_CHOICES}, got {fusion!r}")
    fusion = fusion_for(fusion, method)
    v, k, lower, upper = _validate(values, known, lower, upper)
    if noisy is not None:
        if noise is None:
            raise ValueError("noisy pixels need a noise model (noise=: gain, read_noise, nd, e.g. the profile)")
        if np.shape(noisy) != v.shape:
            raise ValueError(f"noisy mask shape {np.shape(noisy)} differs from values shape {v.shape}")
        noisy = np.asarray(noisy, bool)
        if not noisy.any():
            noisy = None
    v_meas = v
    if noisy is not None and out is not None and np.shares_memory(out, v):
        # in place: keep the noisy measurements for the fusion (a per-thread plane reused frame after frame)
        v_meas = _meas_copy(v)
    out = _output_array(v, out)
    nk = _count_true(k)
    if nk == k.size:
        return out
    miss = ~k
    if nk == 0:
        warnings.warn("no pixel is known: the output is filled from the bounds (clipped pixels at their "
                      "lower bound, too-dark ones at their upper bound, 0 where there is none)",
                      ReconstructionWarning, stacklevel=2)
        return _fill_from_bounds(out, lower, upper)
    if method == "fse":
        from .fse import fse_reconstruct
        # in place: FSE writes only the missing pixels of `out` (issue 7 item 3: no copy back)
        wts = skip = None
        if noisy is not None and noisy_joint > 0:
            wts = noisy_weights(v_meas, noisy & ~k, noise, noisy_joint)
        elif noisy is not None and fusion == "accurate" and (NOISY_SKIP if noisy_skip is None else noisy_skip):
            skip = np.ascontiguousarray(noisy)
        res = fse_reconstruct(out, k, lower, upper, preset, weights=wts, skip=skip, inplace=True, **params)
        if skip is not None:
            # the fusion's noise level at the skipped pixels (they still hold their measurement)
            _noisy_level(res, k, skip)
    else:
        if params:
            raise ValueError(f"method {method!r} takes no parameters, got {sorted(params)}")
        if method == "preview":
            res = _preview(out, k, out)
        elif method == "nearest":
            res = _nearest(out, k, out)
        else:
            res = _linear(out, k)
    if res is not out:
        # known pixels of `out` already hold the float32 input: take only the missing ones
        _copy_missing(np.ascontiguousarray(res, dtype=np.float32), k, out)
    out = _clamp_to_data(out, v_meas, k, miss, lower)
    if noisy is not None:
        nz = noisy & miss
        if nz.any():
            out = fuse_noisy(out, np.asarray(v_meas, np.float32), k, nz, noise, setting=fusion)
    return _apply_bounds(out, miss, lower, upper)


_MEAS = ThreadScratch()


def _meas_copy(v):
    """float32 copy of `v` into a per-thread plane kept between calls (no 8 MB allocation and its page
    faults per 1080p frame; issue 7)."""
    buf = getattr(_MEAS, "buf", None)
    if buf is None or buf.shape != v.shape:
        buf = _MEAS.buf = np.empty(v.shape, np.float32)
    np.copyto(buf, v, casting="same_kind")
    return buf


# issue 7 (helper fsenoisy): FSE skips the NOISY pixels when the accurate fusion follows (the default);
# NRHDR_FSE_NOISY_SKIP=0 restores the FSE estimate there (the before/after switch of the benchmarks)
NOISY_SKIP = os.environ.get("NRHDR_FSE_NOISY_SKIP", "1") != "0"


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _noisy_level(out, known, skip):
    """Each `skip` pixel that is not known: the mean of its 3 x 3 neighbours that are not skipped (known
    or reconstructed), else its own measurement (clipped at 0): the level `fuse_noisy` sets the noise
    variances from, and its estimate where no neighbour is measured. Reads only non-skipped pixels, so
    the order of the writes does not matter; branch-free 3-row column sums per row and a branch-free
    write (a select; random masks)."""
    h, w = out.shape
    nch = min(h, 64)
    for ch in prange(nch):
        cs = np.empty(w + 2, np.float64)     # column sums of the usable pixels, one column of margin
        cn = np.empty(w + 2, np.float64)
        for y in range(ch * h // nch, (ch + 1) * h // nch):
            cs[:] = 0.0
            cn[:] = 0.0
            for yy in range(max(y - 1, 0), min(y + 2, h)):
                for x in range(w):
                    ok = known[yy, x] | (not skip[yy, x])
                    # (a select, not a product: a skipped pixel's value, written by another row, is never used)
                    cs[x + 1] += np.float64(out[yy, x]) if ok else 0.0
                    cn[x + 1] += 1.0 if ok else 0.0
            for x in range(w):
                c = cn[x] + cn[x + 1] + cn[x + 2]
                a = out[y, x]
                lv = np.float32((cs[x] + cs[x + 1] + cs[x + 2]) / c) if c > 0.5 else max(a, np.float32(0.0))
                # every pixel written (a select, no branch): the others get their own value back
                out[y, x] = lv if skip[y, x] & (not known[y, x]) else a


def noisy_weights(values, noisy, noise, factor: float = 2.0) -> np.ndarray:
    """FSE sample weights of NOISY measurements for joint estimation (`fse.fse_reconstruct(weights=)`):
    factor x var_regular(m) / var_ND(m) at `noisy` pixels (known pixels weigh 1 in FSE), 0 elsewhere,
    at the measured level m (Eq. 4-7 as `validity.measurement_variance`; the ratio is the same in
    FSE's log2(x + c) domain, both variances scale with the same derivative). Between 1 / ND^2
    (read-noise limited) and 1 / ND (shot-noise limited) times `factor`, capped at 1."""
    g = float(noise.gain)
    floor = g * g * float(noise.read_noise) ** 2 + 1.0 / 12.0
    nd = float(noise.nd)
    m = np.maximum(np.asarray(values, np.float64), 0.0)
    r = float(factor) * (g * m + floor) / (nd * g * m + nd * nd * floor)
    return np.where(np.asarray(noisy, bool), np.minimum(r, 1.0), 0.0).astype(np.float32)


FUSION_SETTINGS = ("fast", "accurate")
FUSION_CHOICES = ("auto",) + FUSION_SETTINGS   # "auto": fast for the preview method, accurate otherwise


def fusion_for(fusion: str, method: str) -> str:
    """The noise-fusion setting a method runs with: "auto" is "fast" for the live preview (pull-push; its
    frame budget, issue 7) and "accurate" for the others; an explicit setting is kept."""
    if fusion == "auto":
        return "fast" if method == "preview" else "accurate"
    return fusion
_FUSE_ROWS = 64            # rows per parallel chunk of `_fuse_kernel` (its window sums slide down a chunk)


def fuse_noisy(out, values, known, noisy, noise, texture: float = 1.0, size: int = 5,
               setting: str = "accurate"):
    """Inverse-variance fusion of an estimate e with the noisy measurement m at `noisy` pixels (issue 8,
    beyond the paper): e + w (m - e), w = var_e / (var_e + var_m), var_m the sensor's noise at level g
    (the reconstruction) for an attenuated pixel (`validity.measurement_variance`, Eq. 4-7). Both
    settings add to var_e `texture` x the variance of the known pixels of the size x size window in
    excess of their noise: in flat areas the estimate wins, at edges and fine detail the measurement.
    "fast": e = g, var_e = the regular-pixel noise at g over the ~4 neighbours it is interpolated from.
    "accurate" (default): e = the inverse-variance weighted mean of the measured 3 x 3 neighbours,
    known pixels weighted 1 / (regular noise at g), the other NOISY pixels 1 / var_m (the noisy
    ND samples are measurements for their neighbours too, not only for their own pixel); var_e =
    1 / (sum of the weights); it reaches the inverse-variance bound of those samples on flat fields
    (docs/BENCHMARKS.md "Dark regions (issue 8, helper dark)": +0.38 dB at the dark ND pixels of the
    shared scenes for about +19 % of the fast setting's time). `size`: the texture window. In place on
    `out`; numba, window sums slide down chunks of rows."""
    if setting not in FUSION_SETTINGS:
        raise ValueError(f"noise fusion setting must be one of {FUSION_SETTINGS}, got {setting!r}")
    g = float(noise.gain)
    floor = g * g * float(noise.read_noise) ** 2 + 1.0 / 12.0
    _fuse_kernel(out, np.ascontiguousarray(values, np.float32), np.ascontiguousarray(known),
                 np.ascontiguousarray(noisy), np.float32(g), np.float32(floor), np.float32(noise.nd),
                 np.float32(texture), int(size) // 2, setting == "accurate", _FUSE_ROWS, get_num_threads())
    return out


@njit(cache=True, nogil=True, inline="always")
def _fuse_add_row(values, known, noisy, yy, sgn, c, est):
    """Add (sgn = 1) or remove (-1) row yy to the column sums c: the texture window's known count, sum
    and sum of squares (rows 0-2), or, `est`, the estimate window's known count and sum and NOISY count
    and sum (rows 3-6). Branchless loops (the masks are random), one per case so both vectorise."""
    w = values.shape[1]
    if est:
        for x in range(w):
            kf = np.float64(known[yy, x])
            zf = np.float64(noisy[yy, x]) * (1.0 - kf)
            a = np.float64(values[yy, x])
            c[3, x] += sgn * kf
            c[4, x] += sgn * kf * a
            c[5, x] += sgn * zf
            c[6, x] += sgn * zf * a
    else:
        for x in range(w):
            kf = np.float64(known[yy, x])
            ka = kf * np.float64(values[yy, x])
            c[0, x] += sgn * kf
            c[1, x] += sgn * ka
            c[2, x] += sgn * ka * np.float64(values[yy, x])


@njit(cache=True, nogil=True, inline="always")
def _fuse_slide(values, known, noisy, y, ya, r, h, c, est):
    """Column sums of the rows y - r .. y + r: built at the chunk's first row ya, then slid by one row."""
    if y == ya:
        for yy in range(max(ya - r, 0), min(ya + r + 1, h)):
            _fuse_add_row(values, known, noisy, yy, 1.0, c, est)
    else:
        if y + r < h:
            _fuse_add_row(values, known, noisy, y + r, 1.0, c, est)
        if y - r - 1 >= 0:
            _fuse_add_row(values, known, noisy, y - r - 1, -1.0, c, est)


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _fuse_kernel(out, values, known, noisy, gain, floor, nd, texture, r, joint, rows, nt):
    """`fuse_noisy`'s pass: (2r+1)^2 window sums of the known pixels (count, sum, sum of squares) and,
    `joint`, 3 x 3 window sums of the known and the NOISY pixels (count, sum) at every noisy pixel,
    from column sums that slide down each chunk of `rows` rows (parallel over chunks, one scratch per
    chunk; rows without a noisy pixel cost the slide only). Per row the window sums and the fusion are
    computed for every pixel in branch-free loops over zero-margined column sums (they vectorise; the
    sums keep the order of the per-pixel loops they replaced) and stored at the noisy pixels only.
    `nt`: the thread count the chunks are interleaved over (passed in: calling get_num_threads inside
    would stop numba caching the kernel)."""
    h, w = out.shape
    nch = (h + rows - 1) // rows
    per = (nch + nt - 1) // nt
    for i in prange(per * nt):
        # prange hands each thread one contiguous run of i: interleave the chunks over the threads
        # (thread t gets chunks t, t + nt, ...) so dark areas at one end of the frame are shared
        ci = (i % per) * nt + i // per
        if ci >= nch:
            continue
        ya = ci * rows
        yb = min(ya + rows, h)
        c = np.zeros((7, w), np.float64)
        idx = np.empty(w, np.int64)
        for y in range(ya, yb):
            _fuse_slide(values, known, noisy, y, ya, r, h, c, False)
            if joint:
                _fuse_slide(values, known, noisy, y, ya, 1, h, c, True)
            k = 0
            for x in range(w):          # the row's noisy pixels, compacted without branches
                idx[k] = x
                k += 1 if noisy[y, x] else 0
            for q in range(k):
                x = idx[q]
                n = 0.0
                t1 = 0.0
                t2 = 0.0
                for xx in range(max(x - r, 0), min(x + r + 1, w)):
                    n += c[0, xx]
                    t1 += c[1, xx]
                    t2 += c[2, xx]
                mv = np.float64(values[y, x])
                gv = np.float64(out[y, x])
                gp = max(gv, 0.0)
                var_r = gain * gp + floor
                var_m = nd * gain * gp + nd * nd * floor
                excess = 0.0
                if n > 0.5:
                    mean = t1 / n
                    excess = max(t2 / n - mean * mean - (gain * max(mean, 0.0) + floor), 0.0)
                e = gv
                var_e = var_r / 4.0 + texture * excess
                if joint:
                    kn = 0.0
                    ks = 0.0
                    zn = 0.0
                    zs = 0.0
                    for xx in range(max(x - 1, 0), min(x + 2, w)):
                        kn += c[3, xx]
                        ks += c[4, xx]
                        zn += c[5, xx]
                        zs += c[6, xx]
                    if not known[y, x]:     # the pixel's own measurement enters below, not its estimate
                        zn -= 1.0
                        zs -= mv
                    sw = kn / var_r + zn / var_m
                    if sw > 0.5 / var_m:
                        e = (ks / var_r + zs / var_m) / sw
                        var_e = 1.0 / sw + texture * excess
                wgt = var_e / (var_e + var_m)
                f = e + wgt * (mv - e)
                out[y, x] = np.float32(f if f > 0.0 else 0.0)


def _fill_from_bounds(out, lower, upper):
    """No known pixel: each pixel at its lower bound, else its upper bound, else 0 (issue 9 item 5: a
    saturated frame is a uniform area at the clip bound, not the mask pattern)."""
    out[:] = 0.0
    if upper is not None:
        m = ~np.isnan(upper)
        out[m] = upper[m]
    if lower is not None:
        m = ~np.isnan(lower)
        out[m] = lower[m]
    return out


def _clamp_to_data(out, v, k, miss, lower):
    """Missing pixels finite and within [min(known min, 0), max(known max, their lower bound)]: no
    reconstruction exceeds what the data and its bounds imply (issue 8); NaN/Inf (never expected) are
    replaced by the nearest known value."""
    v32 = np.ascontiguousarray(v, np.float32)
    kk = np.ascontiguousarray(k)
    lo_arr = np.zeros((1, 1), np.float32) if lower is None else np.ascontiguousarray(lower, np.float32)
    nbad = _clamp_kernel(out, v32, kk, lo_arr, lower is not None)
    if nbad:
        bad = ~np.isfinite(out) & ~kk
        out[bad] = _nearest(v32, kk)[bad]
        _clamp_kernel(out, v32, kk, lo_arr, lower is not None)
    return out


@njit(cache=True, nogil=True, parallel=True)
def _clamp_kernel(out, v, k, lower, use_lower):
    """`_clamp_kernel_reference` in two parallel row passes (min/max per row, reduced in row order:
    exact, independent of the thread count); the number of non-finite missing pixels (left as they are).
    Branch-free (a random mask defeats branch prediction): the known range as order-preserving integer
    keys (`_f32_key`: integer min/max vectorise), the clamp as selects written back to every pixel."""
    h, w = out.shape
    r_lo = np.empty(h, np.int32)
    r_hi = np.empty(h, np.int32)
    vi = v.view(np.int32)
    kmax = np.int32(0x7FFFFFFF)
    kmin = np.int32(-0x7FFFFFFF - 1)
    for y in prange(h):
        lo = kmax
        hi = kmin
        for x in range(w):
            kk = k[y, x]
            key = _f32_key(vi[y, x])
            lo = min(lo, key if kk else kmax)
            hi = max(hi, key if kk else kmin)
        r_lo[y] = lo
        r_hi[y] = hi
    lo = kmax
    hi = kmin
    for y in range(h):
        lo = min(lo, r_lo[y])
        hi = max(hi, r_hi[y])
    # back to float32 (`_f32_key` is an involution); no known pixel: +inf / -inf as the reference
    flo = np.float32(np.inf) if lo == kmax else np.float32(_unkey(lo))
    fhi = np.float32(-np.inf) if hi == kmin else np.float32(_unkey(hi))
    flo = min(flo, np.float32(0.0))
    nbad = 0
    for y in prange(h):
        nb = 0
        for x in range(w):
            miss = not k[y, x]
            a = out[y, x]
            fin = a - a == np.float32(0.0)
            top = fhi
            if use_lower:
                b = lower[y, x]
                top = b if (b == b) & (b > top) else top
            c = flo if a < flo else a
            c = top if c > top else c
            out[y, x] = c if miss & fin else a
            nb += np.int64(miss & (not fin))
        nbad += nb
    return nbad


@njit(cache=True, nogil=True)
def _clamp_kernel_reference(out, v, k, lower, use_lower):
    """The serial clamp (before issue 7 item 3); tests compare."""
    h, w = out.shape
    lo = np.inf
    hi = -np.inf
    for y in range(h):
        for x in range(w):
            if k[y, x]:
                a = v[y, x]
                lo = min(lo, a)
                hi = max(hi, a)
    lo = min(lo, 0.0)
    flo = np.float32(lo)
    nbad = 0
    for y in range(h):
        for x in range(w):
            if k[y, x]:
                continue
            a = out[y, x]
            if not np.isfinite(a):
                nbad += 1
                continue
            top = np.float32(hi)
            if use_lower:
                b = lower[y, x]
                if b == b and b > top:
                    top = b
            if a < flo:
                a = flo
            if a > top:
                a = top
            out[y, x] = a
    return nbad


def _apply_bounds(out, miss, lower, upper):
    if lower is not None and upper is not None:
        _clamp_missing2(out, miss, np.ascontiguousarray(lower, dtype=np.float32),
                        np.ascontiguousarray(upper, dtype=np.float32))
    elif lower is not None:
        _clamp_missing(out, miss, np.ascontiguousarray(lower, dtype=np.float32), True)
    elif upper is not None:
        _clamp_missing(out, miss, np.ascontiguousarray(upper, dtype=np.float32), False)
    return out


# ---- per-frame passes of the dispatcher as parallel numba loops (no fancy-indexing temporaries) ----------

def _output_array(v, out):
    """`out` (checked) holding `v` as float32, or a new float32 copy of `v`."""
    if out is None:
        return np.array(v, dtype=np.float32, copy=True, order="C")
    if not isinstance(out, np.ndarray) or out.dtype != np.float32 or out.shape != v.shape \
            or not out.flags.c_contiguous or not out.flags.writeable:
        raise ValueError(f"out must be a writeable C-contiguous float32 array of shape {v.shape}")
    if not (out.__array_interface__["data"][0] == v.__array_interface__["data"][0] and v.dtype == out.dtype
            and v.strides == out.strides):
        np.copyto(out, v, casting="unsafe")
    return out


@njit(cache=True, nogil=True, parallel=True)
def _count_true_kernel(k):
    h, w = k.shape
    n = 0
    for y in prange(h):
        c = 0
        for x in range(w):
            c += 1 if k[y, x] else 0
        n += c
    return n


def _count_true(k) -> int:
    return int(_count_true_kernel(k.reshape(1, -1) if k.ndim != 2 else k))


@njit(cache=True, nogil=True, parallel=True)
def _nonfinite_known_kernel(v, k):
    h, w = v.shape
    n = 0
    for y in prange(h):
        c = 0
        for x in range(w):
            a = v[y, x]
            c += 1 if (k[y, x] and not (a - a == 0)) else 0
        n += c
    return n


def _nonfinite_known(v, k) -> bool:
    """True if a known pixel is NaN or Inf."""
    if v.dtype.kind in "iub":
        return False
    if v.dtype in (np.float32, np.float64):
        return bool(_nonfinite_known_kernel(v, k))
    vk = v[k]
    return bool(vk.size and not np.isfinite(vk).all())


@njit(cache=True, nogil=True, parallel=True)
def _any_inf_kernel(b):
    h, w = b.shape
    n = 0
    for y in prange(h):
        c = 0
        for x in range(w):
            a = b[y, x]
            c += 1 if (a - a != a - a and a == a) else 0
        n += c
    return n


def _any_inf(b) -> bool:
    if b.ndim == 2:
        return bool(_any_inf_kernel(b))
    return bool(np.isinf(b).any())


@njit(cache=True, nogil=True, parallel=True)
def _copy_missing(res, k, out):
    h, w = out.shape
    for y in prange(h):
        for x in range(w):
            out[y, x] = out[y, x] if k[y, x] else res[y, x]


@njit(cache=True, nogil=True, parallel=True)
def _clamp_missing2(out, miss, lo, hi):
    """`_clamp_missing` with both bounds in one pass (lower first, then upper)."""
    h, w = out.shape
    for y in prange(h):
        for x in range(w):
            r = out[y, x]
            m = miss[y, x]
            a = lo[y, x]
            r = a if (m and a > r) else r
            b = hi[y, x]
            r = b if (m and b < r) else r
            out[y, x] = r


@njit(cache=True, nogil=True, parallel=True)
def _clamp_missing(out, miss, b, is_lower):
    """out = max(out, b) (is_lower) or min(out, b) where miss and b is not NaN (NaN out stays NaN)."""
    h, w = out.shape
    for y in prange(h):
        for x in range(w):
            r = out[y, x]
            bb = b[y, x]
            if is_lower:
                r = bb if (miss[y, x] and bb > r) else r
            else:
                r = bb if (miss[y, x] and bb < r) else r
            out[y, x] = r


def _nearest(out, k, dst=None):
    """Value of the nearest known pixel (exact Euclidean distance; ties may pick another pixel at the
    same distance than scipy), by a separable distance transform with argmin tracking (Felzenszwalb &
    Huttenlocher 2012): nearest known row per column, then the lower envelope of parabolas per row.
    Written into `dst` (may be `out`: known pixels are only read) or a new array."""
    vals = np.ascontiguousarray(out, dtype=np.float32)
    k = np.ascontiguousarray(k)
    if dst is None:
        dst = vals.copy()
    h, w = vals.shape
    row = _nn_scratch(h, w)
    _nn_columns(k, row)
    _nn_rows(vals, k, row, dst)
    return dst


_NN = ThreadScratch()


def _nn_scratch(h, w):
    cache = getattr(_NN, "cache", None)
    if cache is None or cache.shape != (h, w):
        cache = _NN.cache = np.empty((h, w), np.int32)
    return cache


@njit(cache=True, nogil=True, parallel=True)
def _nn_columns(known, row):
    """row[y, x] = row of the nearest known pixel in column x (-1: the column has none); column blocks
    of 64 in parallel, rows in memory order."""
    h, w = known.shape
    nb = (w + 63) // 64
    for b in prange(nb):
        x0 = b * 64
        x1 = min(w, x0 + 64)
        below = np.empty(x1 - x0, np.int32)
        for x in range(x0, x1):
            row[0, x] = 0 if known[0, x] else -1
        for y in range(1, h):
            for x in range(x0, x1):
                row[y, x] = y if known[y, x] else row[y - 1, x]
        for x in range(x0, x1):
            below[x - x0] = -1
        for y in range(h - 1, -1, -1):
            for x in range(x0, x1):
                if known[y, x]:
                    below[x - x0] = y
                bl = below[x - x0]
                up = row[y, x]
                if bl >= 0 and (up < 0 or bl - y < y - up):
                    row[y, x] = bl


@njit(cache=True, nogil=True, parallel=True)
def _nn_rows(vals, known, row, out):
    """Per row: lower envelope of the parabolas (x - q)^2 + (y - row[y, q])^2 over the columns q that
    have a known pixel; each missing pixel takes the value at its minimiser."""
    h, w = vals.shape
    nch = min(h, 64)
    for c in prange(nch):
        v = np.empty(w, np.int64)
        z = np.empty(w + 1, np.float64)
        f = np.empty(w, np.float64)
        for y in range((c * h) // nch, ((c + 1) * h) // nch):
            kk = -1
            for q in range(w):
                r = row[y, q]
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
                continue
            j = 0
            for x in range(w):
                while z[j + 1] < x:
                    j += 1
                if not known[y, x]:
                    p = v[j]
                    out[y, x] = vals[row[y, p], p]


@njit(cache=True, nogil=True)
def _raster_triangles(tris, py, px, pv, known, res, filled):
    """Scan-convert each triangle (integer vertex coordinates) and write the barycentric interpolation
    of its vertex values into the missing pixels it covers; O(total triangle area)."""
    h, w = res.shape
    eps = -1e-9
    for t in range(tris.shape[0]):
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        y0, x0, y1, x1, y2, x2 = py[a], px[a], py[b], px[b], py[c], px[c]
        det = (y1 - y0) * (x2 - x0) - (x1 - x0) * (y2 - y0)
        if det == 0:
            continue  # degenerate in integer coordinates: its pixels lie on neighbouring triangles
        inv = 1.0 / det
        ylo, yhi = min(y0, y1, y2), max(y0, y1, y2)
        xlo, xhi = min(x0, x1, x2), max(x0, x1, x2)
        for y in range(max(ylo, 0), min(yhi, h - 1) + 1):
            for x in range(max(xlo, 0), min(xhi, w - 1) + 1):
                if known[y, x] or filled[y, x]:
                    continue
                l1 = ((y - y0) * (x2 - x0) - (x - x0) * (y2 - y0)) * inv
                l2 = ((y1 - y0) * (x - x0) - (x1 - x0) * (y - y0)) * inv
                l0 = 1.0 - l1 - l2
                if l0 >= eps and l1 >= eps and l2 >= eps:
                    res[y, x] = np.float32(l0 * pv[a] + l1 * pv[b] + l2 * pv[c])
                    filled[y, x] = True


def _linear(out, k):
    """Delaunay-linear on the known pixels (the paper's "triangular interpolation", Fig. 10g); outside
    their convex hull, nearest known pixel. Only known pixels within 2 px of a missing one are
    triangulated (triangles of the full triangulation that cover a hole stay Delaunay in the subset); a
    fixed 1e-6 px jitter breaks the lattice's co-circular degeneracy (Qhull ~2x faster); the triangles are
    then scan-converted in numba instead of located point by point."""
    from scipy import ndimage
    from scipy.spatial import Delaunay, QhullError
    if min(out.shape) == 1:
        return _linear_1d(out, k)
    band = k & ndimage.binary_dilation(~k, np.ones((5, 5), bool))
    ky, kx = np.nonzero(band)
    if ky.size < 3:
        return _nearest(out, k)
    pts = np.column_stack([ky, kx]).astype(np.float64)
    pts += np.random.default_rng(0).uniform(-1e-6, 1e-6, pts.shape)
    try:
        tri = Delaunay(pts)
    except QhullError:  # all known pixels collinear: no triangle exists
        return _nearest(out, k)
    res = out.astype(np.float32, copy=True)
    filled = np.zeros(out.shape, bool)
    _raster_triangles(tri.simplices.astype(np.int64), ky.astype(np.int64), kx.astype(np.int64),
                      out[ky, kx].astype(np.float64), k, res, filled)
    hole = ~k & ~filled
    if hole.any():
        near = _nearest(out, k)
        res[hole] = near[hole]
    return res


def _linear_1d(out, k):
    flat, kf = out.ravel(), k.ravel()
    x = np.arange(flat.size)
    return np.interp(x, x[kf], flat[kf]).astype(np.float32).reshape(out.shape)


@njit(cache=True, nogil=True)
def _pull_push(vals, wts, levels):
    """Pull-push (Gortler et al. 1996): sum values and weights down a 2x pyramid, then fill each
    level's empty pixels from the coarser level (bilinear-ish 2x2 box). In place on level 0."""
    h, w = vals.shape
    # pyramid storage: concatenated levels, offsets computed on the fly
    hs = np.empty(levels + 1, np.int64)
    ws = np.empty(levels + 1, np.int64)
    off = np.empty(levels + 2, np.int64)
    hs[0], ws[0], off[0] = h, w, 0
    for l in range(levels):
        hs[l + 1] = (hs[l] + 1) // 2
        ws[l + 1] = (ws[l] + 1) // 2
    for l in range(levels + 1):
        off[l + 1] = off[l] + hs[l] * ws[l]
    pv = np.zeros(off[levels + 1], np.float32)
    pw = np.zeros(off[levels + 1], np.float32)
    for y in range(h):
        for x in range(w):
            pw[y * w + x] = wts[y, x]
            pv[y * w + x] = vals[y, x] * wts[y, x]
    for l in range(levels):  # pull
        h0, w0, o0 = hs[l], ws[l], off[l]
        h1, w1, o1 = hs[l + 1], ws[l + 1], off[l + 1]
        for y in range(h0):
            for x in range(w0):
                i1 = o1 + (y // 2) * w1 + x // 2
                pv[i1] += pv[o0 + y * w0 + x]
                pw[i1] += pw[o0 + y * w0 + x]
        for i in range(h1 * w1):  # cap weights at 1 (normalise full cells)
            if pw[o1 + i] > 1.0:
                pv[o1 + i] /= pw[o1 + i]
                pw[o1 + i] = 1.0
    for l in range(levels - 1, -1, -1):  # push
        h0, w0, o0 = hs[l], ws[l], off[l]
        w1, o1 = ws[l + 1], off[l + 1]
        for y in range(h0):
            for x in range(w0):
                i0 = o0 + y * w0 + x
                wt = pw[i0]
                if wt < 1.0:
                    i1 = o1 + (y // 2) * w1 + x // 2
                    c = pv[i1] / pw[i1] if pw[i1] > 0 else np.float32(0.0)
                    # blend: own normalised average weighted by its weight, coarse fills the rest
                    own = pv[i0] / wt if wt > 0 else np.float32(0.0)
                    v = wt * own + (np.float32(1.0) - wt) * c
                    pv[i0] = v
                    pw[i0] = 1.0
                else:
                    pv[i0] = pv[i0] / wt
                    pw[i0] = 1.0
    for y in range(h):
        for x in range(w):
            vals[y, x] = pv[y * w + x]


@njit(cache=True, nogil=True, inline="always")
def _mean3x3(vals, mask, y, x):
    """(weighted sum, weight) of the 8-neighbours of (y, x) where `mask` is non-zero: edges weigh 2,
    corners 1 (the pull-push level-0 fill; one source for `_fill_3x3`, `_pp_fill_px`, `_pvf_fill_px`)."""
    h, w = vals.shape
    acc = np.float32(0.0)
    wsum = np.float32(0.0)
    for dy in range(-1, 2):
        yy = y + dy
        if yy < 0 or yy >= h:
            continue
        for dx in range(-1, 2):
            xx = x + dx
            if xx < 0 or xx >= w or mask[yy, xx] == 0:
                continue
            wt = np.float32(1.0) if (dy != 0 and dx != 0) else np.float32(2.0)
            acc += wt * vals[yy, xx]
            wsum += wt
    return acc, wsum


@njit(cache=True, nogil=True)
def _fill_3x3(vals, known, coarse, out):
    """Missing pixels with known 8-neighbours get their weighted mean (edges 2, corners 1); the rest
    take the pull-push value `coarse`."""
    h, w = vals.shape
    for y in range(h):
        for x in range(w):
            if known[y, x]:
                out[y, x] = vals[y, x]
                continue
            acc, wsum = _mean3x3(vals, known, y, x)
            out[y, x] = acc / wsum if wsum > 0 else coarse[y, x]


def _preview_reference(out, k):
    """The serial pull-push of the previous release (reference for the tests of `_preview`)."""
    h, w = out.shape
    levels = int(np.ceil(np.log2(max(h, w, 2))))
    coarse = np.where(k, out, np.float32(0.0)).astype(np.float32)   # NaN/Inf at missing pixels: weight 0 * NaN
    _pull_push(coarse, k.astype(np.float32), levels)
    res = np.empty_like(coarse)
    _fill_3x3(out.astype(np.float32), k, coarse, res)
    return res


# ---- pull-push at memory speed (issue 7 item 3) ---------------------------------------------------------
# Same arithmetic as `_pull_push` + `_fill_3x3` (kept as the reference; tests compare bit for bit), but
# parallel over rows, float32, level 0 never copied (pulled straight from the values and the known mask,
# filled straight into the output, in place when out is values), and the coarse levels in a pyramid
# allocated once per frame shape and thread. With 0/1 input weights every level's capped weight is 0 or 1,
# so a push only fills empty cells with their parent's value.

_PYR = ThreadScratch()


def _pyramid(h: int, w: int):
    """(pv, pw, hs, ws, off, zv, kf): flat float32 value/weight storage of levels 1..L (level l at
    off[l]) and level 0 as zero-filled values and 0/1 weights (H, W), cached per shape in thread-local
    storage (reused frame after frame, never shared between threads)."""
    key = (h, w)
    cache = getattr(_PYR, "cache", None)
    if cache is None:
        cache = _PYR.cache = {}
    p = cache.get(key)
    if p is None:
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
        p = (np.zeros(n, np.float32), np.zeros(n, np.float32), hs, ws, off,
             np.zeros((h, w), np.float32), np.zeros((h, w), np.float32))
        if len(cache) > 4:
            cache.clear()
        cache[key] = p
    return p


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _pp_pull0(vals, known, zv, kf, pv, pw, o1, h1, w1):
    """Level 0 as zero-filled values zv and 0/1 weights kf; level 1 = capped 2 x 2 sums of them
    (summation order of `_pull_push`)."""
    h, w = vals.shape
    one = np.float32(1.0)
    zero = np.float32(0.0)
    for y1 in prange(h1):
        y = 2 * y1
        for yy in range(y, min(y + 2, h)):
            for x in range(w):
                kk = known[yy, x]
                zv[yy, x] = vals[yy, x] if kk else zero
                kf[yy, x] = one if kk else zero
        base = o1 + y1 * w1
        if y + 1 < h:
            for x1 in range(w // 2):
                x = 2 * x1
                s = zero + zv[y, x]
                s = s + zv[y, x + 1]
                s = s + zv[y + 1, x]
                s = s + zv[y + 1, x + 1]
                c = zero + kf[y, x]
                c = c + kf[y, x + 1]
                c = c + kf[y + 1, x]
                c = c + kf[y + 1, x + 1]
                d = c if c > one else one
                pv[base + x1] = s / d
                pw[base + x1] = c if c < one else one
            if w % 2:
                x = w - 1
                s = zero + zv[y, x] + zv[y + 1, x]
                c = zero + kf[y, x] + kf[y + 1, x]
                pv[base + w // 2] = s / c if c > one else s
                pw[base + w // 2] = c if c < one else one
        else:
            for x1 in range(w1):
                s = zero
                c = zero
                for x in range(2 * x1, min(2 * x1 + 2, w)):
                    s += zv[y, x]
                    c += kf[y, x]
                if c > one:
                    s = s / c
                    c = one
                pv[base + x1] = s
                pw[base + x1] = c


@njit(cache=True, nogil=True, inline="always")
def _pp_pull_at(pv, pw, o0, h0, w0, o1, w1, y1, x1):
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
def _pp_push_at(pv, pw, o0, w0, o1, w1, y, x):
    """One fine pixel of the push: an under-weighted pixel takes its parent's normalised value."""
    one = np.float32(1.0)
    i0 = o0 + y * w0 + x
    if pw[i0] < one:
        i1 = o1 + (y // 2) * w1 + x // 2
        pv[i0] = pv[i1] / pw[i1] if pw[i1] > 0 else np.float32(0.0)
    pw[i0] = one


@njit(cache=True, nogil=True, parallel=True)
def _pp_pull(pv, pw, o0, h0, w0, o1, h1, w1):
    for y1 in prange(h1):
        for x1 in range(w1):
            _pp_pull_at(pv, pw, o0, h0, w0, o1, w1, y1, x1)


@njit(cache=True, nogil=True, parallel=True)
def _pp_push(pv, pw, o0, h0, w0, o1, w1):
    for y in prange(h0):
        for x in range(w0):
            _pp_push_at(pv, pw, o0, w0, o1, w1, y, x)


@njit(cache=True, nogil=True)
def _pp_fill_px(zv, kf, pv, o1, w1, y, x, out):
    """One pixel of `_pp_fill` with bounds checks (image border, no known neighbour)."""
    if kf[y, x] > 0:
        out[y, x] = zv[y, x]
        return
    acc, wsum = _mean3x3(zv, kf, y, x)
    out[y, x] = acc / wsum if wsum > 0 else pv[o1 + (y // 2) * w1 + x // 2]


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _pp_fill(zv, kf, pv, o1, w1, out):
    """Missing pixels: weighted mean of the known 8-neighbours (edges 2, corners 1; order of
    `_fill_3x3`), else the level-1 value; known pixels copied. Reads only zv/kf, so `out` may be the
    input values. The interior loop is branch-free (vectorises); pixels without a known neighbour
    come out NaN (0/0) there and are redone by `_pp_fill_px`."""
    h, w = zv.shape
    two = np.float32(2.0)
    zero = np.float32(0.0)
    for y in prange(h):
        if y == 0 or y == h - 1 or w < 3:
            for x in range(w):
                _pp_fill_px(zv, kf, pv, o1, w1, y, x, out)
            continue
        for x in range(1, w - 1):
            acc = zero + zv[y - 1, x - 1]
            acc = acc + two * zv[y - 1, x]
            acc = acc + zv[y - 1, x + 1]
            acc = acc + two * zv[y, x - 1]
            acc = acc + two * zv[y, x + 1]
            acc = acc + zv[y + 1, x - 1]
            acc = acc + two * zv[y + 1, x]
            acc = acc + zv[y + 1, x + 1]
            ws = zero + kf[y - 1, x - 1]
            ws = ws + two * kf[y - 1, x]
            ws = ws + kf[y - 1, x + 1]
            ws = ws + two * kf[y, x - 1]
            ws = ws + two * kf[y, x + 1]
            ws = ws + kf[y + 1, x - 1]
            ws = ws + two * kf[y + 1, x]
            ws = ws + kf[y + 1, x + 1]
            r = acc / ws
            out[y, x] = zv[y, x] if kf[y, x] > zero else r
        nan = 0
        for x in range(1, w - 1):
            nan += 1 if out[y, x] != out[y, x] else 0
        if nan:
            for x in range(1, w - 1):
                if out[y, x] != out[y, x]:
                    _pp_fill_px(zv, kf, pv, o1, w1, y, x, out)
        _pp_fill_px(zv, kf, pv, o1, w1, y, 0, out)
        _pp_fill_px(zv, kf, pv, o1, w1, y, w - 1, out)


def _preview(vals, k, out=None):
    """Pull-push preview of float32 `vals` (H, W) with bool `known`, written into `out` (new array when
    None; may be `vals` itself); same result as `_preview_reference`, bit for bit."""
    vals = np.ascontiguousarray(vals, dtype=np.float32)
    k = np.ascontiguousarray(k)
    if out is None:
        out = np.empty_like(vals)
    h, w = vals.shape
    pv, pw, hs, ws, off, zv, kf = _pyramid(h, w)
    levels = hs.shape[0] - 1
    _pp_pull0(vals, k, zv, kf, pv, pw, off[1], hs[1], ws[1])
    _pp_levels(pv, pw, hs, ws, off, levels)
    _pp_fill(zv, kf, pv, off[1], ws[1], out)
    return out


def _pp_levels(pv, pw, hs, ws, off, levels):
    """Pull levels 1 -> `levels`, then push back to level 1 (level 1 already pulled from the frame): big
    levels in parallel regions, the small ones (< _PP_SERIAL pixels) in one serial call (a parallel
    region per tiny level costs more than its work, and much more when the cores are busy)."""
    small = 1
    while small < levels and hs[small] * ws[small] >= _PP_SERIAL:
        small += 1
    for lv in range(1, small):
        _pp_pull(pv, pw, off[lv], hs[lv], ws[lv], off[lv + 1], hs[lv + 1], ws[lv + 1])
    _pp_small_levels(pv, pw, hs, ws, off, small, levels)
    for lv in range(small - 1, 0, -1):
        _pp_push(pv, pw, off[lv], hs[lv], ws[lv], off[lv + 1], ws[lv + 1])


_PP_SERIAL = 1 << 16


@njit(cache=True, nogil=True)
def _pp_small_levels(pv, pw, hs, ws, off, first, levels):
    """Pull from level `first` to the top and push back down to `first`, serially (same arithmetic as
    `_pp_pull` / `_pp_push`)."""
    for lv in range(first, levels):
        o0, h0, w0 = off[lv], hs[lv], ws[lv]
        o1, h1, w1 = off[lv + 1], hs[lv + 1], ws[lv + 1]
        for y1 in range(h1):
            for x1 in range(w1):
                _pp_pull_at(pv, pw, o0, h0, w0, o1, w1, y1, x1)
    for lv in range(levels - 1, first - 1, -1):
        o0, h0, w0 = off[lv], hs[lv], ws[lv]
        o1, w1 = off[lv + 1], ws[lv + 1]
        for y in range(h0):
            for x in range(w0):
                _pp_push_at(pv, pw, o0, w0, o1, w1, y, x)


def warmup(method: str | None = None) -> None:
    """Compile the numba code of `method` (all methods when None) on a tiny image; called from element
    start, never at import. numba's on-disk cache makes later processes load instead of compile."""
    v = np.zeros((4, 4), np.float32)
    k = np.ones((4, 4), bool)
    k[1, 1] = False
    if method in (None, "preview"):
        reconstruct(v, k, method="preview")
        # the parallel pyramid levels (used from 512 x 512 on) and the element's frame path with bounds
        pv = np.zeros(8, np.float32)
        _pp_pull(pv, pv.copy(), 0, 2, 2, 4, 1, 1)
        _pp_push(pv, pv.copy(), 0, 2, 2, 4, 1)
    if method in (None, "nearest"):
        reconstruct(v, k, method="nearest")
    # the dispatcher's own kernels (every method): data-range clamp, noise fusion (issue 8)
    from types import SimpleNamespace
    _clamp_to_data(v.copy(), v, k, ~k, np.full(v.shape, np.nan, np.float32))
    fuse_noisy(v.copy(), v, k, ~k, SimpleNamespace(gain=0.55, read_noise=2.0, nd=6.35))
    _noisy_level(v.copy(), k, ~k)
    if method in (None, "fse"):
        from . import fse
        fse.warmup()
    if method is not None:
        from . import validity
        state = np.zeros((4, 4), np.uint8)
        state[1, 1] = validity.CLIPPED
        state[2, 2] = validity.DARK
        reconstruct_frame(v.copy(), state, method=method, preset="preview", use_bounds=True)
        reconstruct_frame(v.copy(), state.copy(), method=method, preset="preview", use_bounds=False)
        # the element's frame with NOISY pixels fused (nrvalidity dark-policy=weighted, issue 8)
        state = np.full((4, 4), validity.ATTENUATED | validity.CLIPPED, np.uint8)
        state[0, :] = validity.VALID
        state[1, 1] = validity.CLIPPED
        state[2, 2] = validity.ATTENUATED | validity.NOISY
        reconstruct_frame(v.copy() + 1, state, method=method, preset="preview", use_bounds=True,
                          noise=SimpleNamespace(gain=0.55, read_noise=2.0, nd=6.35))


# ---- whole-frame entry point for elements (issue 7 item 3): no per-frame allocation --------------------

_FRAME = ThreadScratch()


def _frame_scratch(h, w, with_bounds):
    s = getattr(_FRAME, "s", None)
    if s is None or s[0].shape != (h, w):
        s = _FRAME.s = (np.empty((h, w), np.bool_), np.empty((h, w), np.float32),
                        np.empty((h, w), np.float32), np.empty((h, w), np.float32))
    return s


def reconstruct_frame(values: np.ndarray, state: np.ndarray, method="fse", preset: str = "balanced",
                      use_bounds: bool = True, noise=None, fusion: str = "auto", **params) -> int:
    """Reconstruct an HDR frame in place (docs/ARCHITECTURE.md layout): the missing pixels
    (`validity.missing_mask`) of `values` get `reconstruct(values, known, ...)`'s result and the
    RECONSTRUCTED bit in `state`; measured pixels are untouched. Known mask and bounds come from one
    fused pass into per-thread scratch reused frame after frame; `preview` and `nearest` write straight
    into `values`. `noise`: the noise model (a CameraProfile) with which NOISY pixels (dark policy
    "weighted", issue 8) are fused (`fusion`: `fuse_noisy`'s setting, "accurate" or "fast"); without it
    they are reconstructed like other missing pixels. `method` may be a callable `f(missing_share) -> (method, preset)`, called once the frame's missing
    share is known (only when something is missing): how `nrreconstruct method=auto` picks per frame.
    This is the one per-frame path of nrreconstruct and of `chain.process_frame` (batch), so both give
    the same bits. Returns the number of pixels filled (0: nothing to do, nothing touched).
    The preview (fixed, or chosen by a callable `method`) runs in three fused passes over the frame
    (`_preview_frame`, same bits as the general path)."""
    if (method == "preview" or callable(method)) and not params and values.ndim == 2 \
            and values.dtype == np.float32 and values.flags.c_contiguous and values.flags.writeable \
            and isinstance(state, np.ndarray) and state.dtype == np.uint8 and state.shape == values.shape \
            and state.flags.c_contiguous and state.flags.writeable:
        if fusion not in FUSION_CHOICES:
            raise ValueError(f"noise fusion setting must be one of {FUSION_CHOICES}, got {fusion!r}")
        r = _preview_frame(values, state, method, use_bounds, noise, fusion)
        if isinstance(r, int):
            return r
        if isinstance(r, tuple):
            method, preset = r
    return _reconstruct_frame_general(values, state, method, preset, use_bounds, noise, fusion, **params)


def _reconstruct_frame_general(values, state, method, preset, use_bounds, noise, fusion="auto",
                               **params) -> int:
    """`reconstruct_frame` for every method: prepare, `reconstruct`, write-back (the reference of the
    fused preview path)."""
    from . import validity
    h, w = values.shape
    known, lower, upper, res = _frame_scratch(h, w, use_bounds)
    n_miss, n_unknown, known, lower, upper = validity._prepare(
        values, state, known, lower if use_bounds else None, upper if use_bounds else None, use_bounds)
    if n_miss == 0:
        return 0
    if callable(method):
        method, preset = method(n_miss / float(h * w))
    noisy = None
    if noise is not None:
        noisy = validity.noisy_mask(state)
        if not noisy.any():
            noisy = None
    # in place only when every unknown pixel is to be filled (no earlier RECONSTRUCTED pixel to keep)
    target = values if (n_miss == n_unknown and values.dtype == np.float32 and values.flags.c_contiguous) \
        else res
    out = reconstruct(values, known, method=method, preset=preset, lower=lower, upper=upper, out=target,
                      noisy=noisy, noise=noise if noisy is not None else None, fusion=fusion, **params)
    return validity.write_back(values, state, out)


# ---- the element's preview frame path in three fused passes (issue 7 item 3) ----------------------------
# `reconstruct_frame(method="preview")` gives exactly the bits of the general path (prepare, `reconstruct`
# with its data-range clamp, noise fusion and bounds, write-back), in three passes over the frame instead
# of about ten and without a frame-sized temporary:
#   1. `_pvf_pull0`: known / NOISY masks, the clip bounds (neighbour rule only in rows with a clipped
#      regular pixel), counts, range of the known values, and the pyramid's level 1, straight from the
#      values and states (no level-0 copy);
#   2. the pyramid levels (`_pp_pull`, `_pp_small_levels`, `_pp_push`, as `_preview`);
#   3. `_pvf_fill`: per missing pixel the 3 x 3 fill (else the level-1 value), clamp to the data range,
#      bounds, written into the frame with the RECONSTRUCTED bit; rows with nothing missing are skipped.
# NOISY pixels go through `fuse_noisy` (issue 8) from a scratch plane, then `_pvf_put_noisy`. A frame with
# a non-finite value or no known pixel takes the general path (its errors and warnings).

def _pvf_scratch(h, w):
    """Per-thread planes reused frame after frame: known, noisy, lower bound, fusion scratch, row stats."""
    s = getattr(_FRAME, "pv", None)
    if s is None or s[0].shape != (h, w):
        h1 = (h + 1) // 2
        s = _FRAME.pv = (np.empty((h, w), np.bool_), np.empty((h, w), np.bool_), np.empty((h, w), np.float32),
                         np.empty((h, w), np.float32), np.empty((h1, 4), np.int64), np.empty((h1, 2), np.int32))
    return s


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _pvf_pull0(values, state, known, noisy, lower, pv, pw, o1, h1, w1, cnt, rng, use_bounds):
    """Pass 1 (per pair of rows): known = reason VALID; noisy = NOISY and not RECONSTRUCTED; lower =
    the CLIPPED pixels' lower bound (`validity.bounds`, with `use_bounds`; other entries are scratch); cnt[y1] = (missing,
    not VALID, noisy, non-finite values); rng[y1] = keys (`_f32_key`) of the min and max known value;
    level 1 of the pull-push pyramid = `_pp_pull0`'s capped 2 x 2 sums (same summation order). The
    per-pixel loops are branch-free (they vectorise)."""
    h, w = values.shape
    one = np.float32(1.0)
    zero = np.float32(0.0)
    vi = values.view(np.int32)
    kmax = np.int32(0x7FFFFFFF)
    kmin = np.int32(-0x7FFFFFFF - 1)
    for y1 in prange(h1):
        y = 2 * y1
        cm = 0
        cu = 0
        cn = 0
        cb = 0
        lo = kmax
        hi = kmin
        for yy in range(y, min(y + 2, h)):
            ccl = 0
            ccr = 0
            for x in range(w):
                st = state[yy, x]
                r = st & 0x0F
                k = r == 0
                known[yy, x] = k
                nz = (st & 0x4F) == 5
                noisy[yy, x] = nz
                cu += np.int64(~k)
                cm += np.int64(~k & ((st & 0x40) == 0))
                cn += np.int64(nz)
                ccl += np.int64(r == 1)
                ccr += np.int64((st & 0x8F) == 1)
                i = vi[yy, x]
                cb += np.int64((i & 0x7F800000) == 0x7F800000)
                key = _f32_key(i)
                lo = min(lo, key if k else kmax)
                hi = max(hi, key if k else kmin)
            if ccl and use_bounds:
                if ccr:
                    clip_lower_row(values, state, yy, lower[yy])
                for x in range(w):   # branch-free: clipped pixels get max(value, rule), others scratch
                    st = state[yy, x]
                    v = values[yy, x]
                    m = lower[yy, x]
                    b = m if (((st & 0x80) == 0) & (m == m) & (m > v) & (ccr > 0)) else v
                    lower[yy, x] = b if (st & 0x0F) == 1 else m
        cnt[y1, 0] = cm
        cnt[y1, 1] = cu
        cnt[y1, 2] = cn
        cnt[y1, 3] = cb
        rng[y1, 0] = lo
        rng[y1, 1] = hi
        base = o1 + y1 * w1
        if y + 1 < h:
            for x1 in range(w // 2):
                x = 2 * x1
                k00 = one if known[y, x] else zero
                k01 = one if known[y, x + 1] else zero
                k10 = one if known[y + 1, x] else zero
                k11 = one if known[y + 1, x + 1] else zero
                s = zero + values[y, x] * k00
                s = s + values[y, x + 1] * k01
                s = s + values[y + 1, x] * k10
                s = s + values[y + 1, x + 1] * k11
                c = zero + k00
                c = c + k01
                c = c + k10
                c = c + k11
                d = c if c > one else one
                pv[base + x1] = s / d
                pw[base + x1] = c if c < one else one
            if w % 2:
                x = w - 1
                k00 = one if known[y, x] else zero
                k10 = one if known[y + 1, x] else zero
                s = zero + values[y, x] * k00 + values[y + 1, x] * k10
                c = zero + k00 + k10
                pv[base + w // 2] = s / c if c > one else s
                pw[base + w // 2] = c if c < one else one
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


@njit(cache=True, nogil=True)
def _pvf_fill_px(values, known, pv, o1, w1, y, x):
    """`_pp_fill_px` for a missing pixel: weighted mean of its known 8-neighbours, else level 1."""
    acc, wsum = _mean3x3(values, known, y, x)
    return acc / wsum if wsum > 0 else pv[o1 + (y // 2) * w1 + x // 2]


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _pvf_fill(values, state, known, noisy, lower, pv, o1, w1, flo, top0, use_bounds, fuse, g, cnt, flag):
    """Pass 3, per row with a missing pixel: g = `_pp_fill`'s value (3 x 3 weighted mean of the known
    neighbours, else level 1; the interior branch-free as `_pp_fill`, known values times 0/1 weights),
    then for the missing pixels `_clamp_kernel`'s data range [flo, top0 or the lower bound] and
    `_clamp_missing2`'s bounds, written into the frame with `flag`; with `fuse`, NOISY pixels keep their
    measurement and their estimate stays in g for the fusion. A non-finite estimate is not written
    (noisy cleared too) and counted (the general path then finishes the frame). Reads the values only
    at known pixels and at the pixel itself (the others times weight 0), so it works in place."""
    h, w = values.shape
    two = np.float32(2.0)
    one = np.float32(1.0)
    zero = np.float32(0.0)
    ninf = np.float32(-np.inf)
    pinf = np.float32(np.inf)
    nbad = 0
    for y in prange(h):
        if cnt[y // 2, 0] == 0:
            continue
        if y == 0 or y == h - 1 or w < 3:
            for x in range(w):
                g[y, x] = _pvf_fill_px(values, known, pv, o1, w1, y, x)
        else:
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
                g[y, x] = acc / ws
            for x in range(1, w - 1):
                if ws_zero(g[y, x]):
                    g[y, x] = pv[o1 + (y // 2) * w1 + x // 2]
            g[y, 0] = _pvf_fill_px(values, known, pv, o1, w1, y, 0)
            g[y, w - 1] = _pvf_fill_px(values, known, pv, o1, w1, y, w - 1)
        nb = 0
        for x in range(w):
            st = state[y, x]
            r = st & 0x0F
            m = (r != 0) & ((st & 0x40) == 0)
            a = g[y, x]
            fin = a - a == zero
            lb = lower[y, x]
            v = values[y, x]
            bb = lb if (use_bounds & (r == 1)) else ninf
            top = bb if bb > top0 else top0
            a = flo if a < flo else a
            a = top if a > top else a
            isn = fuse & (r == 5)
            if use_bounds:
                a = bb if bb > a else a
                u = v if r == 2 else pinf
                a = u if u < a else a
            wr = m & fin & ~isn
            g[y, x] = a
            values[y, x] = a if wr else v
            state[y, x] = (st | flag) if wr else st
            noisy[y, x] = noisy[y, x] & fin
            nb += np.int64(m & ~fin)
        nbad += nb
    return nbad


@njit(cache=True, nogil=True, inline="always")
def ws_zero(a):
    """The interior fill's 0/0 (no known neighbour): NaN."""
    return a != a


@njit(cache=True, nogil=True, parallel=True)
def _pvf_put_noisy(values, state, noisy, g, cnt, flag):
    """The fused NOISY pixels into the frame with `flag` (rows without one skipped)."""
    h, w = values.shape
    for y in prange(h):
        if cnt[y // 2, 2] == 0:
            continue
        for x in range(w):
            if noisy[y, x]:
                values[y, x] = g[y, x]
                state[y, x] = state[y, x] | flag


def _preview_frame(values, state, method, use_bounds, noise, fusion="auto"):
    """`reconstruct_frame` for the preview (fused passes above). Returns the pixels filled, or
    (method, preset) when a callable `method` chose something else, or None when the general path must
    do the frame (non-finite values, no known pixel); nothing is written then."""
    from . import validity
    h, w = values.shape
    known, noisy, lower, g, cnt, rng = _pvf_scratch(h, w)
    pv, pw, hs, ws, off, _, _ = _pyramid(h, w)
    levels = hs.shape[0] - 1
    _pvf_pull0(values, state, known, noisy, lower, pv, pw, off[1], hs[1], ws[1], cnt, rng, bool(use_bounds))
    tot = cnt.sum(axis=0)
    n_miss, n_unknown, n_noisy, n_bad = (int(t) for t in tot)
    if n_miss == 0:
        return 0
    if n_bad or n_unknown == h * w:
        return None
    if callable(method):
        method, preset = method(n_miss / float(h * w))
        if method != "preview":
            return method, preset
    _pp_levels(pv, pw, hs, ws, off, levels)
    keys = np.array([rng[:, 0].min(), rng[:, 1].max()], np.int32)
    lo, hi = (keys ^ ((keys >> 31) & 0x7FFFFFFF)).view(np.float32)     # `_f32_key` undone
    lo = np.float32(min(lo, np.float32(0.0)))
    fuse = noise is not None and n_noisy > 0
    flag = np.uint8(validity.RECONSTRUCTED)
    nbad = _pvf_fill(values, state, known, noisy, lower, pv, off[1], ws[1], lo, hi, bool(use_bounds), fuse,
                     g, cnt, flag)
    if fuse:
        fuse_noisy(g, values, known, noisy, noise, setting=fusion_for(fusion, "preview"))
        _pvf_put_noisy(values, state, noisy, g, cnt, flag)
    n = n_miss - nbad
    if nbad:
        # never seen (a fill that overflows float32): the general path fills what is left, as it would
        n += _reconstruct_frame_general(values, state, "preview", "balanced", use_bounds, noise, fusion)
    return n
