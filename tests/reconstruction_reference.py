"""Independent numpy references for the reconstruction tests: the preview's pull-push (paper 2.4; Gortler et
al. 1996, "The Lumigraph", pull-push with 0/1 weights), the data-range clamp and the bounds of
`reconstruction.reconstruct`, and the per-frame contract of `reconstruction.reconstruct_frame`. Written with
whole-array numpy operations in the summation order the product's contract fixes, so the product must
match them bit for bit."""
from __future__ import annotations

import numpy as np

from nrhdr_core import reconstruction, validity
from nrhdr_core.states import RECONSTRUCTED

F32 = np.float32


def _pull(v, c):
    """One pull step: each coarse pixel is the sum of its (up to) 2 x 2 children, values and weights,
    children summed row by row; a weight above 1 is normalised to 1 (the value divided by it)."""
    h, w = v.shape
    h1, w1 = (h + 1) // 2, (w + 1) // 2
    pv = np.zeros((2 * h1, 2 * w1), F32)
    pw = np.zeros((2 * h1, 2 * w1), F32)
    pv[:h, :w] = v
    pw[:h, :w] = c
    s = pv[0::2, 0::2] + pv[0::2, 1::2] + pv[1::2, 0::2] + pv[1::2, 1::2]
    n = pw[0::2, 0::2] + pw[0::2, 1::2] + pw[1::2, 0::2] + pw[1::2, 1::2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(n > 1, s / n, s).astype(F32)
    return s, np.minimum(n, F32(1.0)).astype(F32)


def _mean3x3(v0, k0):
    """Weighted mean of the known 8-neighbours (edge neighbours weigh 2, corners 1), summed in row-major
    neighbour order; NaN where none is known."""
    h, w = v0.shape
    pv = np.zeros((h + 2, w + 2), F32)
    pk = np.zeros((h + 2, w + 2), F32)
    pv[1:-1, 1:-1] = v0
    pk[1:-1, 1:-1] = k0
    acc = np.zeros((h, w), F32)
    ws = np.zeros((h, w), F32)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy == 0 and dx == 0:
                continue
            wt = F32(1.0 if dy and dx else 2.0)
            acc = acc + wt * pv[1 + dy:h + 1 + dy, 1 + dx:w + 1 + dx]
            ws = ws + wt * pk[1 + dy:h + 1 + dy, 1 + dx:w + 1 + dx]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(ws > 0, acc / ws, np.nan).astype(F32)


def pull_push(values, known):
    """The preview fill: known pixels keep their value; a missing pixel gets the weighted mean of its known
    8-neighbours, else the value of its level-1 cell of the pull-push pyramid (levels to 1 x 1, empty cells
    pushed down from their parent). Values under missing pixels are never read."""
    known = np.asarray(known, bool)
    v0 = np.where(known, np.asarray(values, F32), F32(0.0)).astype(F32)
    k0 = known.astype(F32)
    h, w = v0.shape
    levels = int(np.ceil(np.log2(max(h, w, 2))))
    pyr = [(v0, k0)]
    for _ in range(levels):
        pyr.append(_pull(*pyr[-1]))
    for lv in range(levels - 1, 0, -1):                    # push down to level 1
        pv, pw = pyr[lv]
        cv, cw = pyr[lv + 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            parent = np.where(cw > 0, cv / cw, F32(0.0)).astype(F32)
        parent = np.repeat(np.repeat(parent, 2, 0), 2, 1)[:pv.shape[0], :pv.shape[1]]
        pyr[lv] = (np.where(pw < 1, parent, pv).astype(F32), np.ones_like(pw))
    lvl1 = np.repeat(np.repeat(pyr[1][0], 2, 0), 2, 1)[:h, :w]
    near = _mean3x3(v0, k0)
    fill = np.where(np.isnan(near), lvl1, near)
    return np.where(known, v0, fill).astype(F32)


def clamp_to_data(out, values, known, lower=None):
    """Missing pixels within [min(known min, 0), max(known max, their lower bound)] (NaN bound: none);
    non-finite ones left as they are."""
    out = np.array(out, F32)
    kv = np.asarray(values, F32)[known]
    lo = min(F32(kv.min()), F32(0.0))
    top = np.full(out.shape, kv.max(), F32)
    if lower is not None:
        top = np.where(lower > top, lower, top).astype(F32)
    m = ~known & np.isfinite(out)
    out[m] = np.minimum(np.maximum(out[m], lo), top[m])
    return out


def apply_bounds(out, known, lower=None, upper=None):
    """Missing pixels raised to `lower`, then lowered to `upper` (NaN: no bound)."""
    out = np.array(out, F32)
    if lower is not None:
        out = np.where(~known & (lower > out), lower, out).astype(F32)
    if upper is not None:
        out = np.where(~known & (upper < out), upper, out).astype(F32)
    return out


def preview(values, known, lower=None, upper=None):
    """`reconstruct(values, known, method="preview", lower=, upper=)`: pull-push, data-range clamp, bounds."""
    known = np.asarray(known, bool)
    res = clamp_to_data(pull_push(values, known), values, known, lower)
    return apply_bounds(res, known, lower, upper)


def frame(values, state, method="preview", use_bounds=True, noise=None, fusion="auto", preset="balanced"):
    """`reconstruct_frame`'s contract from public parts: the missing pixels (`validity.missing_mask`) get
    `reconstruct(values, known, ...)` with the state's bounds (`validity.bounds`) and, with `noise`, the
    NOISY pixels fused; they get the RECONSTRUCTED bit. Returns (pixels filled, values, state), copies."""
    v, s = np.array(values, F32), np.array(state, np.uint8)
    miss = validity.missing_mask(s)
    if not miss.any():
        return 0, v, s
    known = validity.known_mask(s)
    lower, upper = validity.bounds(v, s) if use_bounds else (None, None)
    noisy = validity.noisy_mask(s) if noise is not None else None
    out = reconstruction.reconstruct(v, known, method=method, preset=preset, lower=lower, upper=upper,
                                     noisy=noisy, noise=noise, fusion=fusion)
    np.copyto(v, out, where=miss)
    s[miss] |= np.uint8(RECONSTRUCTED)
    return int(miss.sum()), v, s
