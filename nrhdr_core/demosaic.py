"""Joint reconstruction of the missing photosites and the missing colours of a Bayer mosaic under the ND mask
(docs/COLOUR.md "Joint reconstruction").

Green first, then the colour differences (Backes and Froehlich 2020, demosaicing with frequency selective
reconstruction): the green plane is reconstructed over the known green photosites, then the colour
differences d_R = log2(R + c) - log2(G + c) and d_B (the log domain: a hue is a ratio of channels, so an
edge of any brightness leaves the differences smooth) are reconstructed on the red and the blue photosite
lattices (one cell of the lattice per 2 x 2 Bayer block), interpolated bilinearly to every photosite and
turned back into R and B. `method`: "preview" (pull-push for both steps) or "fse" (Frequency Selective
Extrapolation for both, `nrhdr_core.fse`).

Rules of the monochrome chain kept per photosite and its own channel: known = reason VALID; measured
photosites keep their value; a missing photosite's own channel is clamped to its channel's data range and to
its bounds (a CLIPPED photosite at least its lower bound, a DARK one at most its upper bound; the clipped-
neighbour rule of `validity.bounds` among photosites of the same colour); NOISY photosites are fused with
their measurement by `reconstruction.fuse_noisy` among photosites of the same colour.
"""
from __future__ import annotations

import warnings

import numpy as np
from numba import njit, prange

from . import cfa as _cfa
from .states import CLIPPED, DARK, NOISY, REASON_MASK, RECONSTRUCTED, VALID

METHODS = ("preview", "fse")
# offset of the log domain of the colour differences: a share of the mean green level (scale invariant), at
# least OFFSET_NOISE_K noise sigmas of a regular photosite when a noise model is given
OFFSET_SHARE = 2.0 ** -6
OFFSET_NOISE_K = 2.0
_PHASES = ((0, 0), (0, 1), (1, 0), (1, 1))


class DemosaicWarning(UserWarning):
    pass


def _check(values, state, cfa, method, preset, fusion, out):
    from .fse import FSE_PRESETS
    from .reconstruction import FUSIONS
    name = _cfa.check(cfa, "reconstruct_cfa: cfa")
    if name == _cfa.NONE:
        raise ValueError("reconstruct_cfa: cfa 'none' is a monochrome sensor; use reconstruction.reconstruct_frame")
    if method not in METHODS:
        raise ValueError(f"reconstruct_cfa: method must be one of {METHODS}, got {method!r}")
    if method == "fse" and preset not in FSE_PRESETS:
        raise ValueError(f"reconstruct_cfa: preset must be one of {tuple(FSE_PRESETS)}, got {preset!r}")
    if fusion not in FUSIONS:
        raise ValueError(f"reconstruct_cfa: noise fusion setting must be one of {FUSIONS}, got {fusion!r}")
    v = np.asarray(values)
    s = np.asarray(state)
    if v.ndim != 2 or v.size == 0:
        raise ValueError(f"reconstruct_cfa: values must be a non-empty 2-D array (H, W), got shape {v.shape}")
    if not np.issubdtype(v.dtype, np.floating) and not np.issubdtype(v.dtype, np.integer):
        raise ValueError(f"reconstruct_cfa: values must be real numbers, got {v.dtype}")
    if s.shape != v.shape or s.dtype != np.uint8:
        raise ValueError(f"reconstruct_cfa: state must be uint8 of the values' shape {v.shape}, got "
                         f"{s.dtype} {s.shape}")
    if not isinstance(state, np.ndarray) or not state.flags.writeable:
        raise ValueError("reconstruct_cfa: state must be a writeable numpy array (its RECONSTRUCTED bits are set)")
    h, w = v.shape
    if out is not None and (not isinstance(out, np.ndarray) or out.dtype != np.float32 or out.shape != (3, h, w)
                            or not out.flags.c_contiguous or not out.flags.writeable):
        raise ValueError(f"reconstruct_cfa: out must be a writeable C-contiguous float32 array of shape {(3, h, w)}")
    v32 = np.ascontiguousarray(v, np.float32)
    known = (s & REASON_MASK) == VALID
    if not np.isfinite(v32[known]).all():
        raise ValueError("reconstruct_cfa: values contain NaN or Inf at known photosites; reconstruction needs "
                         "finite data")
    return name, v32


def reconstruct_cfa(values, state, cfa, method: str = "preview", preset: str = "fast", use_bounds: bool = True,
                    noise=None, fusion: str = "auto", out=None) -> np.ndarray:
    """Planar RGB float32 (3, H, W) from a Bayer mosaic: `values` float (H, W) (linear DN, one value per
    photosite, of the channel `cfa` gives it: `cfa.channel_index`), `state` uint8 (H, W) (nrhdr_core.states).

    method: "preview" (pull-push, live) or "fse" (FSE, `preset` of `fse.FSE_PRESETS`); use_bounds: clamp
    a CLIPPED photosite's own channel to >= its lower bound and a DARK one's to <= its upper bound;
    noise: the noise model (a CameraProfile) with which NOISY photosites are fused with their measurement
    (`fusion`: one of `reconstruction.FUSIONS`, "auto": "fast" for preview, "accurate" for fse); without it
    they are reconstructed like other missing photosites. out: optional (3, H, W) float32 array written and
    returned. Measured photosites keep their value in their own channel; photosites already RECONSTRUCTED
    keep theirs; the RECONSTRUCTED bit of `state` is set in place where the own channel was filled.
    Output finite. No photosite known: a DemosaicWarning, and the bounds stand in for the measurements."""
    name, v32 = _check(values, state, cfa, method, preset, fusion, out)
    from .reconstruction import fusion_for
    fusion = fusion_for(fusion, method)
    h, w = v32.shape
    if out is None:
        out = np.empty((3, h, w), np.float32)
    idx = _cfa.channel_index(name, h, w)
    st = state
    reason = st & REASON_MASK
    known = reason == VALID
    missing = ~known & ((st & RECONSTRUCTED) == 0)
    lower, upper = _bounds(v32, st, use_bounds)
    if not known.any():
        warnings.warn("reconstruct_cfa: no photosite is known; the bounds stand in for the measurements "
                      "(clipped photosites at their lower bound, too-dark ones at their upper bound)",
                      DemosaicWarning, stacklevel=2)
    pos = _phase_of(name)
    # green plane
    gsrc, gval = _sources(v32, known, idx == _cfa.G, lower, upper, fallback_any=True)
    g = _fill(gval, gsrc, method, preset, None, None)
    c = _offset(g, gsrc, noise)
    out[_cfa.G] = g
    # colour differences on the red and the blue lattices
    for ch in (_cfa.R, _cfa.B):
        py, px = pos[ch]
        src, val = _sources(v32, known, idx == ch, lower, upper, fallback_any=False)
        ssrc = np.ascontiguousarray(src[py::2, px::2])
        if ssrc.size == 0 or not ssrc.any():
            d = np.zeros((max(ssrc.shape[0], 1), max(ssrc.shape[1], 1)), np.float32)
        else:
            d = _log_diff(np.ascontiguousarray(val[py::2, px::2]), np.ascontiguousarray(g[py::2, px::2]), ssrc, c)
            d = _fill(d, ssrc, method, preset, None, None, diff=True)
        _from_diff(g, d, py, px, np.float32(c), out[ch])
    _finish(out, v32, st, idx, known, missing, lower, upper)
    if noise is not None:
        _fuse(out, v32, st, idx, known, missing, noise, fusion)
    st |= (missing * RECONSTRUCTED).astype(np.uint8)
    return out


def _phase_of(name):
    """{channel: (row, column)} of R and B in the 2 x 2 block (G: its first photosite)."""
    b = _cfa.block(name)
    pos = {}
    for py, px in _PHASES:
        pos.setdefault(int(b[py, px]), (py, px))
    return pos


def _bounds(v32, st, use_bounds):
    """(lower, upper) float32 (H, W), NaN = no bound: `validity.bounds` applied to each of the four Bayer
    phases apart, so that the clipped-neighbour rule compares photosites of one colour."""
    h, w = v32.shape
    lower = np.full((h, w), np.nan, np.float32)
    upper = np.full((h, w), np.nan, np.float32)
    if not use_bounds:
        return lower, upper
    from .validity import bounds
    for py, px in _PHASES:
        sv = np.ascontiguousarray(v32[py::2, px::2])
        if sv.size == 0:
            continue
        lo, hi = bounds(sv, np.ascontiguousarray(st[py::2, px::2]))
        lower[py::2, px::2] = lo
        upper[py::2, px::2] = hi
    # a non-finite measurement is no bound
    lower[~np.isfinite(lower)] = np.nan
    upper[~np.isfinite(upper)] = np.nan
    return lower, upper


def _sources(v32, known, chan, lower, upper, fallback_any):
    """(source mask, values) of a channel's reconstruction: its known photosites; with none, its photosites
    with a bound (value: the bound); with none either and `fallback_any`, the known photosites of any
    channel, then the bounded ones. Values outside the sources are 0."""
    src = known & chan
    val = v32
    if not src.any():
        bnd = np.where(np.isnan(lower), upper, lower)
        has = ~np.isnan(bnd)
        src = has & chan
        val = bnd
        if not src.any() and fallback_any:
            src = known if known.any() else has
            val = v32 if known.any() else bnd
    return src, np.where(src, val, np.float32(0.0)).astype(np.float32)


def _fill(vals, src, method, preset, lower, upper, diff=False):
    """A channel's plane: `reconstruction.reconstruct` of `vals` at the pixels not in `src`."""
    from .reconstruction import reconstruct
    if not src.any():
        return np.zeros(vals.shape, np.float32)
    if method == "fse":
        kw = dict(domain="linear") if diff else {}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            return reconstruct(vals, src, method="fse", preset=preset, lower=lower, upper=upper, **kw)
    return reconstruct(vals, src, method="preview", lower=lower, upper=upper)


def _offset(g, src, noise):
    """c of the log domain log2(max(x, 0) + c): OFFSET_SHARE x the mean green source level, at least
    OFFSET_NOISE_K regular-photosite noise sigmas (`noise`), 1 when both are 0."""
    m = float(np.mean(np.maximum(g[src], 0.0))) if src.any() else 0.0
    c = OFFSET_SHARE * m
    if noise is not None:
        gain = float(noise.gain)
        c = max(c, OFFSET_NOISE_K * float(np.sqrt(gain * gain * float(noise.read_noise) ** 2 + 1.0 / 12.0)))
    return c if c > 0.0 else 1.0


def _log_diff(vals, g, src, c):
    """log2(max(x, 0) + c) - log2(max(G, 0) + c) at the sources, 0 elsewhere (float32)."""
    c = np.float32(c)
    d = np.log2(np.maximum(vals, 0) + c) - np.log2(np.maximum(g, 0) + c)
    return np.where(src, d, np.float32(0.0)).astype(np.float32)


@njit(cache=True, nogil=True, parallel=True)
def _from_diff(g, d, py, px, c, dst):
    """dst = (max(G, 0) + c) 2^d - c, d interpolated bilinearly from its lattice (photosites (py + 2 i,
    px + 2 j)) at every pixel (edge lattice values replicated)."""
    h, w = g.shape
    hs, ws = d.shape
    half = np.float32(0.5)
    for y in prange(h):
        t = y - py
        i0 = 0 if t < 0 else min(t // 2, hs - 1)
        i1 = min(i0 + 1, hs - 1)
        a = half if (t >= 0 and t % 2 == 1) else np.float32(0.0)
        for x in range(w):
            u = x - px
            j0 = 0 if u < 0 else min(u // 2, ws - 1)
            j1 = min(j0 + 1, ws - 1)
            b = half if (u >= 0 and u % 2 == 1) else np.float32(0.0)
            top = d[i0, j0] + b * (d[i0, j1] - d[i0, j0])
            bot = d[i1, j0] + b * (d[i1, j1] - d[i1, j0])
            dv = top + a * (bot - top)
            gv = g[y, x]
            gv = gv if gv > 0 else np.float32(0.0)
            dst[y, x] = (gv + c) * np.exp2(dv) - c


def _finish(out, v32, st, idx, known, missing, lower, upper):
    """Own channel: measured value at known photosites, the value kept at already-RECONSTRUCTED ones;
    missing ones clamped to the channel's data range [min(known min, 0), max(known max, lower bound)] and
    to their bounds. Other channels: within the channel's data range; every value finite."""
    for ch in range(3):
        plane = out[ch]
        own = idx == ch
        kc = known & own
        if kc.any():
            lo = min(float(v32[kc].min()), 0.0)
            hi = float(v32[kc].max())
        else:
            lo, hi = 0.0, 0.0
        lb = lower[own]
        lb = lb[~np.isnan(lb)]
        ub = upper[own]
        ub = ub[~np.isnan(ub)]
        top = max([hi] + ([float(lb.max())] if lb.size else []))
        if not kc.any() and ub.size and not lb.size:
            top = max(top, float(ub.max()))
        bad = ~np.isfinite(plane)
        plane[bad] = 0.0
        np.clip(plane, lo, top, out=plane)
        m = missing & own
        lo_m = np.where(m & ~np.isnan(lower), lower, -np.inf)
        hi_m = np.where(m & ~np.isnan(upper), upper, np.inf)
        np.maximum(plane, lo_m, out=plane)
        np.minimum(plane, hi_m, out=plane)
        keep = own & ~missing
        plane[keep] = v32[keep]
        # not finite kept values (an already-RECONSTRUCTED NaN): 0
        plane[~np.isfinite(plane)] = 0.0


def _fuse(out, v32, st, idx, known, missing, noise, fusion):
    """NOISY photosites: their own channel fused with the measurement (`reconstruction.fuse_noisy`) on
    each Bayer phase apart (neighbours of the same colour)."""
    from .reconstruction import fuse_noisy
    noisy = missing & ((st & REASON_MASK) == NOISY) & np.isfinite(v32)
    if not noisy.any():
        return
    for py, px in _PHASES:
        nz = np.ascontiguousarray(noisy[py::2, px::2])
        if nz.size == 0 or not nz.any():
            continue
        ch = int(idx[py, px])
        est = np.ascontiguousarray(out[ch][py::2, px::2])
        fuse_noisy(est, np.ascontiguousarray(v32[py::2, px::2]), np.ascontiguousarray(known[py::2, px::2]), nz,
                   noise, setting=fusion)
        sub = out[ch][py::2, px::2]
        sub[nz] = est[nz]


def warmup() -> None:
    """Compile (or load from numba's cache) the kernels of both methods on a tiny synthetic mosaic."""
    from .validity import default_noise
    rng = np.random.default_rng(0)
    h, w = 16, 20
    vals = rng.uniform(10.0, 1000.0, (h, w)).astype(np.float32)
    st = np.where(rng.random((h, w)) < 0.3, np.uint8(NOISY), np.uint8(VALID)).astype(np.uint8)
    st[0, :3] = CLIPPED
    st[1, :3] = DARK
    for method in METHODS:
        reconstruct_cfa(vals, st.copy(), "rggb", method=method, preset="fast", noise=default_noise())
