"""Reconstruction of missing pixels (paper section 2.2, 2.4, 5): one entry point, several methods.

Methods, from fastest to most accurate:
- ``preview``: pull-push normalised averaging on an image pyramid (numba); live preview.
- ``nearest``: nearest known pixel (`nrhdr_core.fill`: exact Euclidean nearest, one tie rule).
- ``linear``: Delaunay triangulation of the known pixels and linear interpolation on it (scipy), the
  paper's "triangular interpolation" of Fig. 10g.
- ``fse``: Frequency Selective Extrapolation (ref. 9; `nrhdr_core.fse`), the paper's method of Fig. 10h.

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
from .fill import nearest  # the nearest fill (method "nearest", outside the hull, non-finite repair)
from .pullpush import fill_row, pull_push, pull_push_levels, pull_row, pyramid  # the preview's pull-push
from .scratch import interleaved, planes
from .states import ATTENUATED, CLIPPED, DARK, NOISY, REASON_MASK, RECONSTRUCTED, VALID
from .validity import clip_lower_row  # the clip rule, for the fused preview pass

METHODS = ("fse", "linear", "nearest", "preview")   # `reconstruct(method=)`
FUSION_SETTINGS = ("fast", "accurate")             # `fuse_noisy(setting=)`
FUSIONS = ("auto",) + FUSION_SETTINGS              # `reconstruct(fusion=)`: "auto" = `fusion_for`


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
    variance (`fuse_noisy`; `fusion`: one of FUSIONS, "auto" = `fusion_for`). noisy_joint > 0 (method
    fse, opt-in): FSE fits its model to the NOISY measurements too, weighted
    `noisy_weights(..., noisy_joint)`, ahead of the fusion (joint estimation; measured no better than the
    default, docs/BENCHMARKS.md "Joint FSE with noisy samples").
    noisy_skip (method fse, fusion "accurate", no noisy_joint): FSE leaves the NOISY pixels alone (the
    accurate fusion re-estimates them from their measured 3 x 3 neighbours; FSE's value there would only
    set the noise level) and they get the mean of their non-NOISY 3 x 3 neighbours as that level
    (`_noisy_level`); None: `NOISY_SKIP` (docs/FSE.md "Skipping NOISY pixels").
    out: optional float32 C-contiguous (H, W) array to write the result into (may be `values` itself:
    in place, e.g. mapped frame memory), returned.
    Missing pixels are returned finite, within [min(known min, 0), max(known max, lower bound)] (no
    blow-up, no negative value from non-negative data) and within their bounds.
    With no known pixel the result is the bounds (lower where there is one, else upper, else 0) and a
    ReconstructionWarning saying so is issued."""
    if method not in METHODS:
        raise ValueError(f"reconstruction method must be one of {METHODS}, got {method!r}")
    if fusion not in FUSIONS:
        raise ValueError(f"noise fusion setting must be one of {FUSIONS}, got {fusion!r}")
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
        # in place: FSE writes only the missing pixels of `out` (no copy back)
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
            res = pull_push(out, k, out)
        elif method == "nearest":
            res = nearest(out, k, out)
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


def _meas_copy(v):
    """float32 copy of `v` into the calling thread's plane (no frame-sized allocation per call)."""
    buf = planes("reconstruction.measurements", v.shape, lambda: np.empty(v.shape, np.float32))
    np.copyto(buf, v, casting="same_kind")
    return buf


# FSE skips the NOISY pixels when the accurate fusion follows (the default); NRHDR_FSE_NOISY_SKIP=0 makes
# FSE estimate them too (benchmarks/stages.py times both)
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


def fusion_for(fusion: str, method: str) -> str:
    """The noise-fusion setting a method runs with: "auto" is "fast" for the live preview (pull-push; its
    frame budget) and "accurate" for the others; an explicit setting is kept."""
    if fusion == "auto":
        return "fast" if method == "preview" else "accurate"
    return fusion


_FUSE_ROWS = 64            # rows per parallel chunk of `_fuse_kernel` (its window sums slide down a chunk)


def fuse_noisy(out, values, known, noisy, noise, texture: float = 1.0, size: int = 5,
               setting: str = "accurate"):
    """Inverse-variance fusion of an estimate e with the noisy measurement m at `noisy` pixels (beyond
    the paper): e + w (m - e), w = var_e / (var_e + var_m), var_m the sensor's noise at level g
    (the reconstruction) for an attenuated pixel (`validity.measurement_variance`, Eq. 4-7). Both
    settings add to var_e `texture` x the variance of the known pixels of the size x size window in
    excess of their noise: in flat areas the estimate wins, at edges and fine detail the measurement.
    "fast": e = g, var_e = the regular-pixel noise at g over the ~4 neighbours it is interpolated from.
    "accurate" (default): e = the inverse-variance weighted mean of the measured 3 x 3 neighbours,
    known pixels weighted 1 / (regular noise at g), the other NOISY pixels 1 / var_m (the noisy
    ND samples are measurements for their neighbours too, not only for their own pixel); var_e =
    1 / (sum of the weights); it reaches the inverse-variance bound of those samples on flat fields
    (docs/BENCHMARKS.md "Dark regions": +0.38 dB at the dark ND pixels of the
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
    chunk; rows without a noisy pixel cost the slide only). Per row the column sums slide in branch-free
    loops (they vectorise), the row's noisy pixels are listed without branches (random masks) and each is
    fused from the column sums around it. `nt`: the thread count the chunks are interleaved over (passed in: calling get_num_threads inside
    would stop numba caching the kernel)."""
    h, w = out.shape
    nch = (h + rows - 1) // rows
    per = (nch + nt - 1) // nt
    for i in prange(per * nt):
        ci = interleaved(i, per, nt)        # dark areas at one end of the frame shared by the threads
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
    """No known pixel: each pixel at its lower bound, else its upper bound, else 0 (a
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
    reconstruction exceeds what the data and its bounds imply; NaN/Inf (never expected) are
    replaced by the nearest known value."""
    v32 = np.ascontiguousarray(v, np.float32)
    kk = np.ascontiguousarray(k)
    lo_arr = np.zeros((1, 1), np.float32) if lower is None else np.ascontiguousarray(lower, np.float32)
    nbad = _clamp_kernel(out, v32, kk, lo_arr, lower is not None)
    if nbad:
        bad = ~np.isfinite(out) & ~kk
        out[bad] = nearest(v32, kk)[bad]
        _clamp_kernel(out, v32, kk, lo_arr, lower is not None)
    return out


@njit(cache=True, nogil=True, parallel=True)
def _clamp_kernel(out, v, k, lower, use_lower):
    """The clamp of `_clamp_to_data` in two parallel row passes (min/max per row, reduced in row order:
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
    # back to float32 (`_f32_key` is an involution); no known pixel: +inf / -inf
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
        return nearest(out, k)
    pts = np.column_stack([ky, kx]).astype(np.float64)
    pts += np.random.default_rng(0).uniform(-1e-6, 1e-6, pts.shape)
    try:
        tri = Delaunay(pts)
    except QhullError:  # all known pixels collinear: no triangle exists
        return nearest(out, k)
    res = out.astype(np.float32, copy=True)
    filled = np.zeros(out.shape, bool)
    _raster_triangles(tri.simplices.astype(np.int64), ky.astype(np.int64), kx.astype(np.int64),
                      out[ky, kx].astype(np.float64), k, res, filled)
    hole = ~k & ~filled
    if hole.any():
        near = nearest(out, k)
        res[hole] = near[hole]
    return res


def _linear_1d(out, k):
    flat, kf = out.ravel(), k.ravel()
    x = np.arange(flat.size)
    return np.interp(x, x[kf], flat[kf]).astype(np.float32).reshape(out.shape)


# ---- whole-frame entry point for elements: no per-frame allocation -----------------------------------------

def _frame_scratch(h, w):
    """The general frame path's planes (known, lower, upper, result), the calling thread's."""
    return planes("reconstruction.frame", (h, w), lambda: (
        np.empty((h, w), np.bool_), np.empty((h, w), np.float32), np.empty((h, w), np.float32),
        np.empty((h, w), np.float32)))


def reconstruct_frame(values: np.ndarray, state: np.ndarray, method="fse", preset: str = "balanced",
                      use_bounds: bool = True, noise=None, fusion: str = "auto", **params) -> int:
    """Reconstruct an HDR frame in place (docs/ARCHITECTURE.md layout): the missing pixels
    (`validity.missing_mask`) of `values` get `reconstruct(values, known, ...)`'s result and the
    RECONSTRUCTED bit in `state`; measured pixels are untouched. Known mask and bounds come from one
    fused pass into per-thread scratch reused frame after frame; `preview` and `nearest` write straight
    into `values`. `noise`: the noise model (a CameraProfile) with which NOISY pixels (dark policy
    "weighted") are fused (`fusion`: one of FUSIONS, `fuse_noisy`'s setting); without it they are
    reconstructed like other missing pixels. `method` may be a callable
    `f(missing_share) -> (method, preset)`, called once the frame's missing share is known (only when
    something is missing): how `nrreconstruct method=auto` picks per frame.
    This is the one per-frame path of nrreconstruct and of `chain.process_frame` (batch), so both give
    the same bits. Returns the number of pixels filled (0: nothing to do, nothing touched).
    The preview (fixed, or chosen by a callable `method`) runs in three fused passes over the frame
    (`_preview_frame`, the same bits as `reconstruct`)."""
    if (method == "preview" or callable(method)) and not params and values.ndim == 2 \
            and values.dtype == np.float32 and values.flags.c_contiguous and values.flags.writeable \
            and isinstance(state, np.ndarray) and state.dtype == np.uint8 and state.shape == values.shape \
            and state.flags.c_contiguous and state.flags.writeable:
        if fusion not in FUSIONS:
            raise ValueError(f"noise fusion setting must be one of {FUSIONS}, got {fusion!r}")
        r = _preview_frame(values, state, method, use_bounds, noise, fusion)
        if isinstance(r, int):
            return r
        if isinstance(r, tuple):
            method, preset = r
    return _reconstruct_frame_general(values, state, method, preset, use_bounds, noise, fusion, **params)


def _reconstruct_frame_general(values, state, method, preset, use_bounds, noise, fusion="auto",
                               **params) -> int:
    """`reconstruct_frame` for every method: prepare, `reconstruct`, write-back."""
    from . import validity
    h, w = values.shape
    known, lower, upper, res = _frame_scratch(h, w)
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


# ---- the preview frame path in three fused passes -------------------------------------------------------
# `reconstruct_frame(method="preview")` gives exactly the bits of the general path (prepare, `reconstruct`
# with its data-range clamp, noise fusion and bounds, write-back), in three passes over the frame instead
# of about ten and without a frame-sized temporary:
#   1. `_frame_pull`: known / NOISY masks, the clip bounds (neighbour rule only in rows with a clipped
#      regular pixel), counts, range of the known values, and the pyramid's level 1 (`pull_row`), straight
#      from the values and states;
#   2. the pyramid levels (`pull_push_levels`, as `pull_push`);
#   3. `_frame_fill`: per row with a missing pixel the fill (`fill_row`), clamp to the data range,
#      bounds, written into the frame with the RECONSTRUCTED bit.
# NOISY pixels go through `fuse_noisy` from a scratch plane, then `_frame_put_noisy`. A frame with a
# non-finite value or no known pixel takes the general path (its errors and warnings).

def _preview_scratch(h, w):
    """The fused path's planes (known, noisy, lower bound, fill, per row pair stats), the calling thread's."""
    h1 = (h + 1) // 2
    return planes("reconstruction.preview_frame", (h, w), lambda: (
        np.empty((h, w), np.bool_), np.empty((h, w), np.bool_), np.empty((h, w), np.float32),
        np.empty((h, w), np.float32), np.empty((h1, 4), np.int64), np.empty((h1, 2), np.int32)))


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _frame_pull(values, state, known, noisy, lower, pv, pw, o1, h1, w1, cnt, rng, use_bounds):
    """Pass 1 (per pair of rows): known = reason VALID; noisy = NOISY and not RECONSTRUCTED; lower =
    the CLIPPED pixels' lower bound (`validity.bounds`, with `use_bounds`; other entries are scratch);
    cnt[y1] = (missing, not VALID, noisy, non-finite values); rng[y1] = keys (`_f32_key`) of the min and
    max known value; the pyramid's level 1 (`pull_row`). The per-pixel loops are branch-free (they
    vectorise)."""
    h, w = values.shape
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
                r = st & REASON_MASK
                k = r == VALID
                known[yy, x] = k
                nz = (st & (REASON_MASK | RECONSTRUCTED)) == NOISY
                noisy[yy, x] = nz
                cu += np.int64(~k)
                cm += np.int64(~k & ((st & RECONSTRUCTED) == 0))
                cn += np.int64(nz)
                ccl += np.int64(r == CLIPPED)
                ccr += np.int64((st & (ATTENUATED | REASON_MASK)) == CLIPPED)
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
                    b = m if (((st & ATTENUATED) == 0) & (m == m) & (m > v) & (ccr > 0)) else v
                    lower[yy, x] = b if (st & REASON_MASK) == CLIPPED else m
        cnt[y1, 0] = cm
        cnt[y1, 1] = cu
        cnt[y1, 2] = cn
        cnt[y1, 3] = cb
        rng[y1, 0] = lo
        rng[y1, 1] = hi
        pull_row(values, known, pv, pw, o1, w1, y1)


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _frame_fill(values, state, known, noisy, lower, pv, o1, w1, flo, top0, use_bounds, fuse, g, cnt):
    """Pass 3, per row with a missing pixel: g = the fill (`fill_row`), then for the missing pixels the
    data range [flo, top0 or the lower bound] (`_clamp_kernel`) and the bounds (`_clamp_missing2`),
    written into the frame with RECONSTRUCTED; with `fuse`, NOISY pixels keep their measurement and their
    estimate stays in g for the fusion. A non-finite estimate is not written (noisy cleared too) and
    counted (the general path then finishes the frame). The fill reads values only at known pixels, so
    it works in place."""
    h, w = values.shape
    zero = np.float32(0.0)
    ninf = np.float32(-np.inf)
    pinf = np.float32(np.inf)
    flag = np.uint8(RECONSTRUCTED)
    nbad = 0
    for y in prange(h):
        if cnt[y // 2, 0] == 0:
            continue
        fill_row(values, known, pv, o1, w1, y, g[y], False)
        nb = 0
        for x in range(w):
            st = state[y, x]
            r = st & REASON_MASK
            m = (r != VALID) & ((st & RECONSTRUCTED) == 0)
            a = g[y, x]
            fin = a - a == zero
            lb = lower[y, x]
            v = values[y, x]
            bb = lb if (use_bounds & (r == CLIPPED)) else ninf
            top = bb if bb > top0 else top0
            a = flo if a < flo else a
            a = top if a > top else a
            isn = fuse & (r == NOISY)
            if use_bounds:
                a = bb if bb > a else a
                u = v if r == DARK else pinf
                a = u if u < a else a
            wr = m & fin & ~isn
            g[y, x] = a
            values[y, x] = a if wr else v
            state[y, x] = (st | flag) if wr else st
            noisy[y, x] = noisy[y, x] & fin
            nb += np.int64(m & ~fin)
        nbad += nb
    return nbad


@njit(cache=True, nogil=True, parallel=True)
def _frame_put_noisy(values, state, noisy, g, cnt):
    """The fused NOISY pixels into the frame with RECONSTRUCTED (rows without one skipped)."""
    h, w = values.shape
    flag = np.uint8(RECONSTRUCTED)
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
    h, w = values.shape
    known, noisy, lower, g, cnt, rng = _preview_scratch(h, w)
    pv, pw, hs, ws, off = pyramid(h, w)
    _frame_pull(values, state, known, noisy, lower, pv, pw, off[1], hs[1], ws[1], cnt, rng, bool(use_bounds))
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
    pull_push_levels(pv, pw, hs, ws, off)
    keys = np.array([rng[:, 0].min(), rng[:, 1].max()], np.int32)
    lo, hi = (keys ^ ((keys >> 31) & 0x7FFFFFFF)).view(np.float32)     # `_f32_key` undone
    lo = np.float32(min(lo, np.float32(0.0)))
    fuse = noise is not None and n_noisy > 0
    nbad = _frame_fill(values, state, known, noisy, lower, pv, off[1], ws[1], lo, hi, bool(use_bounds), fuse,
                       g, cnt)
    if fuse:
        fuse_noisy(g, values, known, noisy, noise, setting=fusion_for(fusion, "preview"))
        _frame_put_noisy(values, state, noisy, g, cnt)
    n = n_miss - nbad
    if nbad:
        # a fill that overflows float32: the general path fills what is left, as it would
        n += _reconstruct_frame_general(values, state, "preview", "balanced", use_bounds, noise, fusion)
    return n
