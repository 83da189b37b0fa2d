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

import warnings

import numpy as np
from numba import njit

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
    vk = v[k]
    if vk.size and not np.isfinite(vk).all():
        raise ValueError("values contain NaN or Inf at known pixels; reconstruction needs finite data")
    out = []
    for name, b in (("lower", lower), ("upper", upper)):
        if b is None:
            out.append(None)
            continue
        b = np.asarray(b, dtype=np.float32)
        if b.shape != v.shape:
            raise ValueError(f"{name} bound shape {b.shape} differs from values shape {v.shape}")
        if np.isinf(b).any():
            raise ValueError(f"{name} bound contains Inf; use NaN for 'no bound'")
        out.append(b)
    return v, k, out[0], out[1]


def reconstruct(values, known, method: str = "fse", preset: str = "balanced", lower=None, upper=None,
                noisy=None, noise=None, **params) -> np.ndarray:
    """Fill the pixels where `known` is False; returns float32 (H, W), known pixels bit-exact.

    values: float (H, W) in any scale (8-bit data or linear HDR); known: bool (H, W);
    lower/upper: optional float (H, W) bounds for missing pixels, NaN = no bound;
    preset/params: FSE parameter set (`fse.FSE_PRESETS`) and overrides; ignored by other methods.
    noisy/noise: optional bool (H, W) of missing pixels whose value is a noisy measurement (state NOISY,
    dark policy "weighted") and the noise model (anything with gain, read_noise, nd: a CameraProfile);
    they are reconstructed like the other missing pixels, then fused with their measurement by inverse
    variance (`fuse_noisy`, issue 8).
    Missing pixels are returned finite, within [min(known min, 0), max(known max, lower bound)] (no
    blow-up, no negative value from non-negative data; issue 8) and within their bounds.
    With no known pixel the result is the bounds (lower where there is one, else upper, else 0) and a
    ReconstructionWarning saying so is issued."""
    if method not in METHODS:
        raise ValueError(f"reconstruction method must be one of {METHODS}, got {method!r}")
    v, k, lower, upper = _validate(values, known, lower, upper)
    if noisy is not None:
        if noise is None:
            raise ValueError("noisy pixels need a noise model (noise=: gain, read_noise, nd, e.g. the profile)")
        if np.shape(noisy) != v.shape:
            raise ValueError(f"noisy mask shape {np.shape(noisy)} differs from values shape {v.shape}")
    out = np.array(v, dtype=np.float32, copy=True)
    miss = ~k
    if not miss.any():
        return out
    if not k.any():
        warnings.warn("no pixel is known: the output is filled from the bounds (clipped pixels at their "
                      "lower bound, too-dark ones at their upper bound, 0 where there is none)",
                      ReconstructionWarning, stacklevel=2)
        return _fill_from_bounds(out, lower, upper)
    if method == "fse":
        from .fse import fse_reconstruct
        out = fse_reconstruct(out, k, lower=lower, upper=upper, preset=preset, **params)
    else:
        if params:
            raise ValueError(f"method {method!r} takes no parameters, got {sorted(params)}")
        if method == "preview":
            out = _preview(out, k)
        elif method == "nearest":
            out = _nearest(out, k)
        else:
            out = _linear(out, k)
    out = np.asarray(out, dtype=np.float32)
    out[k] = np.asarray(v, dtype=np.float32)[k]
    out = _clamp_to_data(out, v, k, miss, lower)
    if noisy is not None:
        nz = np.asarray(noisy, bool) & miss
        if nz.any():
            out = fuse_noisy(out, np.asarray(v, np.float32), k, nz, noise)
    return _apply_bounds(out, miss, lower, upper)


def fuse_noisy(out, values, known, noisy, noise, texture: float = 1.0, size: int = 5):
    """Inverse-variance fusion of the reconstruction g with a noisy measurement m at `noisy` pixels
    (issue 8, beyond the paper): g + w (m - g), w = var_g / (var_g + var_m). var_m: the sensor's noise
    at level g for an attenuated pixel (`validity.measurement_variance`, Eq. 4-7); var_g: the
    reconstruction's own error, modelled as the regular-pixel noise at g over the ~4 neighbours it is
    interpolated from plus `texture` x the known neighbours' variance in excess of their noise (size x
    size window): in flat areas the estimate wins, at edges and fine detail the measurement. In place
    on `out` (numba, only the noisy pixels cost anything)."""
    g = float(noise.gain)
    floor = g * g * float(noise.read_noise) ** 2 + 1.0 / 12.0
    _fuse_kernel(out, np.ascontiguousarray(values, np.float32), np.ascontiguousarray(known),
                 np.ascontiguousarray(noisy), np.float32(g), np.float32(floor), np.float32(noise.nd),
                 np.float32(texture), int(size) // 2)
    return out


from numba import prange  # noqa: E402  (fuse_noisy kernel; kept beside it to keep merges local)


@njit(cache=True, nogil=True)
def _known_integrals(values, known):
    """Integral images (count, sum, sum of squares) of the known pixels, float64, (h+1, w+1)."""
    h, w = values.shape
    c = np.zeros((h + 1, w + 1), np.float64)
    s1 = np.zeros((h + 1, w + 1), np.float64)
    s2 = np.zeros((h + 1, w + 1), np.float64)
    for y in range(h):
        rc = 0.0
        r1 = 0.0
        r2 = 0.0
        for x in range(w):
            if known[y, x]:
                a = np.float64(values[y, x])
                rc += 1.0
                r1 += a
                r2 += a * a
            c[y + 1, x + 1] = c[y, x + 1] + rc
            s1[y + 1, x + 1] = s1[y, x + 1] + r1
            s2[y + 1, x + 1] = s2[y, x + 1] + r2
    return c, s1, s2


@njit(cache=True, nogil=True, parallel=True)
def _fuse_kernel(out, values, known, noisy, gain, floor, nd, texture, r):
    h, w = out.shape
    c, s1, s2 = _known_integrals(values, known)
    for y in prange(h):
        y0 = max(y - r, 0)
        y1 = min(y + r + 1, h)
        for x in range(w):
            if not noisy[y, x]:
                continue
            x0 = max(x - r, 0)
            x1 = min(x + r + 1, w)
            n = c[y1, x1] - c[y0, x1] - c[y1, x0] + c[y0, x0]
            excess = 0.0
            if n > 0.5:
                mean = (s1[y1, x1] - s1[y0, x1] - s1[y1, x0] + s1[y0, x0]) / n
                var = (s2[y1, x1] - s2[y0, x1] - s2[y1, x0] + s2[y0, x0]) / n - mean * mean
                excess = var - (gain * max(mean, 0.0) + floor)
                if excess < 0.0:
                    excess = 0.0
            gv = np.float64(out[y, x])
            gp = max(gv, 0.0)
            var_g = (gain * gp + floor) / 4.0 + texture * excess
            var_m = nd * gain * gp + nd * nd * floor
            wgt = var_g / (var_g + var_m)
            f = gv + wgt * (np.float64(values[y, x]) - gv)
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


@njit(cache=True, nogil=True)
def _clamp_kernel(out, v, k, lower, use_lower):
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
    if lower is not None:
        m = miss & ~np.isnan(lower)
        out[m] = np.maximum(out[m], lower[m])
    if upper is not None:
        m = miss & ~np.isnan(upper)
        out[m] = np.minimum(out[m], upper[m])
    return out


def _nearest(out, k):
    from scipy import ndimage
    idx = ndimage.distance_transform_edt(~k, return_distances=False, return_indices=True)
    return out[idx[0], idx[1]]


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
            acc = np.float32(0.0)
            wsum = np.float32(0.0)
            for dy in range(-1, 2):
                yy = y + dy
                if yy < 0 or yy >= h:
                    continue
                for dx in range(-1, 2):
                    xx = x + dx
                    if xx < 0 or xx >= w or not known[yy, xx]:
                        continue
                    wt = np.float32(1.0) if (dy != 0 and dx != 0) else np.float32(2.0)
                    acc += wt * vals[yy, xx]
                    wsum += wt
            out[y, x] = acc / wsum if wsum > 0 else coarse[y, x]


def _preview(out, k):
    h, w = out.shape
    levels = int(np.ceil(np.log2(max(h, w, 2))))
    coarse = np.where(k, out, np.float32(0.0)).astype(np.float32)   # NaN/Inf at missing pixels: weight 0 * NaN
    _pull_push(coarse, k.astype(np.float32), levels)
    res = np.empty_like(coarse)
    _fill_3x3(out.astype(np.float32), k, coarse, res)
    return res


def warmup(method: str | None = None) -> None:
    """Compile the numba code of `method` (all methods when None) on a tiny image; called from element
    start, never at import. numba's on-disk cache makes later processes load instead of compile."""
    v = np.zeros((4, 4), np.float32)
    k = np.ones((4, 4), bool)
    k[1, 1] = False
    if method in (None, "preview"):
        reconstruct(v, k, method="preview")
    # the dispatcher's own kernels (every method): data-range clamp, noise fusion (issue 8)
    from types import SimpleNamespace
    _clamp_to_data(v.copy(), v, k, ~k, np.full(v.shape, np.nan, np.float32))
    fuse_noisy(v.copy(), v, k, ~k, SimpleNamespace(gain=0.55, read_noise=2.0, nd=6.35))
    if method in (None, "fse"):
        from . import fse
        fse.warmup()
