"""FSE of a frame: :func:`fse_reconstruct`, the steps in order.

1. parameters (``params``) and the data statistics (``domain.stats``); degenerate frames (all known, none
   known, constant) are answered without a model (``fallback``);
2. working domain and bounds (``domain``, ``bounds``): working image, states, bounds, data scale;
3. block plan (``plan``): quadtree leaves and rounds (Genser et al.);
4. the block kernel on every leaf (``parallel``, ``kernel``; Seiler & Kaup, SPL 2010);
5. back to the data domain (``domain.finish``); pixels no block could fill take the nearest value
   (``fallback.fill_left``).
"""
from __future__ import annotations

import warnings

import numpy as np
from numba import get_num_threads, njit, prange, set_num_threads

from . import bounds as B
from . import domain as D
from .fallback import fill_bounded, fill_left, fill_without_data
from .kernel import Frame, Params
from .parallel import run
from .params import KNOWN, NOISY, SKIP, density_params, resolve_params, tables
from .plan import block_plan

__all__ = ["fse_reconstruct", "extrapolate_frame"]


def fse_reconstruct(values, known, lower=None, upper=None, preset: str = "balanced", weights=None, skip=None,
                    inplace: bool = False, **params):
    """Reconstruct the pixels where ``known`` is False with FSE; returns float32 (H, W).

    ``values``: finite float (H, W), any scale; ``known``: bool (H, W); known pixels are returned
    bit-exact. ``lower``/``upper``: optional float arrays (NaN = no bound): a missing pixel's
    reconstruction is clamped to ``[lower, upper]`` (clipped pixels: >= clip level; dark pixels:
    <= threshold). ``preset`` selects one of :data:`FSE_PRESETS`, ``**params`` override entries.
    The output does not depend on the number of threads (each round's blocks read only pixels
    finalised in earlier rounds).

    ``weights``: optional float (H, W); where a pixel is not known and its weight is > 0 its value is a
    noisy measurement that enters the model's fit with that weight (known pixels weigh 1; joint
    estimation, docs/FSE.md "Noisy samples") and is replaced by the model there; None or no such pixel:
    the plain path, same bits. ``skip``: optional bool (H, W) of missing pixels left alone (weight 0, not
    reconstructed, not a fallback source; they keep their value of ``values``; docs/FSE.md "Skipped
    pixels"). ``inplace``: write the missing pixels into ``values`` itself when it is a C-contiguous
    float32 array, and return it.
    """
    p = resolve_params(preset, **params)
    v = np.asarray(values)
    k = np.asarray(known, dtype=bool)
    if v.ndim != 2 or k.shape != v.shape:
        raise ValueError(f"fse_reconstruct: values {v.shape} and known {k.shape} must be 2-D arrays of the "
                         "same shape")
    v32 = np.ascontiguousarray(v, dtype=np.float32)
    k = np.ascontiguousarray(k)
    out = v32 if (inplace and v32 is v) else v32.copy()
    noisy = wts = None
    if weights is not None:
        wts = np.asarray(weights, np.float32)
        if wts.shape != v.shape:
            raise ValueError(f"fse_reconstruct: weights shape {wts.shape} differs from values shape {v.shape}")
        noisy = (wts > 0) & ~k
        if not noisy.any():
            noisy = None
    nk, kmin, kmax, minpos = D.stats(v32, k)
    if nk == v32.size:
        return out
    if nk == 0:
        warnings.warn("fse_reconstruct: no known pixel; output is filled from the bounds or 0",
                      RuntimeWarning, stacklevel=2)
        return fill_without_data(out, ~k, lower, upper)
    p = density_params(p, nk / v32.size)
    if kmin == kmax:
        # constant known data: the constant is the only model (exact), within the bounds
        out[~k] = np.float32(kmin)
        return fill_bounded(out, ~k, lower if p["use_bounds"] else None, upper if p["use_bounds"] else None)
    domain, c = D.working_domain(p, v32, k, lower, kmin, kmax)
    logd = domain == "log"
    work, state, lo, hi, use_lo, use_hi, scale, floor = _prepare(v32, k, lower, upper, p, (logd, c),
                                                                 (kmin, kmax, minpos))
    if skip is not None:
        _mark_skip(state, skip)
    nz = None
    if noisy is not None:
        # noisy measurements: NOISY state, their value in the working domain, their weight (kernel.gather)
        state[noisy] = NOISY
        mv = v32[noisy]
        if logd:
            mv = np.log2(np.maximum(mv + np.float32(c), np.float32(floor)))
        work[noisy] = mv
        nz = (np.where(noisy, np.minimum(wts, np.float32(1.0)), np.float32(0.0)).astype(np.float32),
              np.zeros_like(work))
    extrapolate_frame(Frame(work, state, lo, hi), p, scale, use_lo, use_hi, nz)
    cf = np.float32(c if logd else 0.0)
    with_c = bool(cf > 0)
    nleft = D.finish_c(out, work, state, cf) if with_c else D.finish(out, work, state, logd)
    if nleft:
        # blocks whose support held no usable pixel: nearest known, reconstructed or noisy-measurement value
        # (skipped pixels hold no value in `work`); only these pixels are finished again
        ys, xs = fill_left(work, state)
        D.finish_at(out, work, ys, xs, cf, with_c, logd)
    if nz is not None:
        # the model at the noisy measurements
        me = nz[1][noisy]
        if logd:
            me = (2.0 ** me.astype(np.float64)).astype(np.float32)
            if with_c:
                me -= cf
        out[noisy] = me
    return out


def _prepare(v32, k, lower, upper, p, dom, st):
    """Step 2: (work, state, lo, hi, use_lo, use_hi, scale, floor) in the working domain ``dom`` = (log
    domain?, c) for the known values' statistics ``st`` = (kmin, kmax, smallest positive) (docs/FSE.md
    "Domain and bounds"): the log domain log2(max(x + c, floor)) with its log-range scale and, with
    ``local_bound``, the local bound merged with the data's bounds; or the linear domain with the known
    values' range as scale."""
    logd, c = dom
    kmin, kmax, minpos = st
    if logd:
        floor = D.log_floor(c, minpos)
        scale = D.log_scale(p, c, kmin, kmax, floor)
        if int(p["local_bound"]):
            work, state, lo, hi = B.log_local_prep(v32, k, lower, upper, p, c, floor)
            return work, state, lo, hi, True, True, scale, floor
        lo, hi, use_lo, use_hi = B.data_bounds(lower, upper, v32.shape, p["use_bounds"])
        # log2(max(x, 0) + c): well conditioned down to the offset (no blow-up at black pixels)
        src = v32 + np.float32(c) if c > 0.0 else v32
        lo, hi = B.log_bounds(lo, hi, use_lo, use_hi, c, floor)
        work, state = D.prep(src, k, True, np.float32(floor))
        return work, state, lo, hi, use_lo, use_hi, scale, floor
    lo, hi, use_lo, use_hi = B.data_bounds(lower, upper, v32.shape, p["use_bounds"])
    rng = float(kmax - kmin)
    work, state = D.prep(v32, k, False, np.float32(0.0))
    return work, state, lo, hi, use_lo, use_hi, (rng if rng > 0 else 1.0), 0.0


def extrapolate_frame(frame, p, scale, use_lo, use_hi, noisy=None):
    """Steps 3-4: the block plan of the working image ``frame`` (``kernel.Frame``) and the block kernel on
    every leaf, in place (MISSING pixels that a block reconstructs become RECONSTRUCTED). ``p``: resolved
    parameters; ``scale``: the data scale of sigma; ``noisy``: None or (wp, mest) (joint estimation)."""
    tab = tables(p)
    n = int(p["window"])
    plan = block_plan(frame.img, frame.state, p, tab, scale)
    par = Params(float(p["delta"]), float(p["gamma"]), float(p["iter_c"]), int(p["iter_min"]),
                 int(p["iter_max"]), float(scale), bool(use_lo), bool(use_hi))
    nthreads = int(get_num_threads())
    # small jobs run on the calling thread only: fork/join per round would cost more than it gains
    # (the result is the same for any thread count)
    if plan.leaf_y.shape[0] * n * n < 400_000:
        nthreads = 1
    old = get_num_threads()
    set_num_threads(nthreads)
    try:
        run(frame, plan, tab, par, noisy, nthreads)
    finally:
        set_num_threads(old)


@njit(cache=True, nogil=True, parallel=True)
def _mark_skip(state, skip):
    """state = SKIP at the ``skip`` pixels that are not known."""
    h, w = state.shape
    for y in prange(h):
        for x in range(w):
            if skip[y, x] and state[y, x] != KNOWN:
                state[y, x] = SKIP
