"""Plain-Python statements of the crosstalk correction's LUT rules (paper 3.2, docs/CROSSTALK.md), for the
tests to check the numba kernels against: the per-pixel curve by binary search, the `lut` mode pixel by
pixel, and the compact LUT's error against the full table."""
from __future__ import annotations

import numpy as np

from nrhdr_core import crosstalk
from nrhdr_core.states import ATTENUATED, CLIPPED, DARK, FLAG_MASK, REASON_MASK, UNCALIBRATED, VALID


def lut_eval(codes, n, knot_flux, clip_rel, cflux, m):
    """Flux of code m on one pixel's curve (codes: its knot codes, float32 above black), in float32 like the
    kernel; (flux, ok). Below the dark knot the chord from (black, 0), never negative; the knot by binary
    search; above the last knot towards the clip flux up to the clip code; else not ok."""
    f32 = np.float32
    if n < 2:
        return f32(0.0), False
    c0 = codes[0]
    if m <= c0:
        f0 = max(f32(knot_flux[0]), f32(0.0))
        return (f0 * (max(m, f32(0.0)) / c0) if c0 > 0 else f0), True
    last_c = codes[n - 1]
    if m <= last_c:
        lo, hi = 1, n - 1
        while lo < hi:
            mid = (lo + hi) // 2
            if codes[mid] >= m:
                hi = mid
            else:
                lo = mid + 1
        c, pc = codes[lo], codes[lo - 1]
        f, pf = f32(knot_flux[lo]), f32(knot_flux[lo - 1])
        return pf + (m - pc) * (f - pf) / max(c - pc, f32(1e-3)), True
    prev_f = f32(knot_flux[n - 1])
    if cflux == cflux and clip_rel > last_c and m <= clip_rel:
        return prev_f + (m - last_c) * (cflux - prev_f) / (clip_rel - last_c), True
    return f32(0.0), False


def lut_correct(values, state, calib, nd):
    """`crosstalk.correct(mode="lut", lut="full")` pixel by pixel: VALID pixels take their curve's flux
    (UNCALIBRATED when out of range), DARK pixels their bound's flux when positive, CLIPPED pixels at most
    their clipping flux; other states untouched. Returns new (values, state)."""
    v_ref, s_ref = values.copy(), state.copy()
    cq = calib.codes_q.astype(np.float32) * np.float32(calib.qscale) - np.float32(calib.qoffset)
    clip_rel = np.float32(float(calib.clip_code) - float(calib.black_level))
    h, w = values.shape
    for y in range(h):
        for x in range(w):
            st = state[y, x]
            r = st & REASON_MASK
            sc = np.float32(nd) if st & ATTENUATED else np.float32(1.0)
            cf = calib.clip_flux[y, x]
            if r in (VALID, DARK):
                f, ok = lut_eval(cq[y, x], calib.n_knots[y, x], calib.knot_flux, clip_rel, cf, values[y, x] / sc)
                if r == VALID and ok:
                    v_ref[y, x] = f
                elif r == VALID:
                    s_ref[y, x] = (st & FLAG_MASK) | UNCALIBRATED
                elif ok and f > 0:
                    v_ref[y, x] = f
            elif r == CLIPPED and cf == cf and cf < values[y, x]:
                v_ref[y, x] = cf
    return v_ref, s_ref


def compact_error(profile, codes_per_pixel: int = 4, seed: int = 0) -> dict:
    """Error of the compact LUT (`lut="compact"`) against the full table (`lut="full"`) of a calibrated
    profile at random VALID codes inside every pixel's range (uniform in code): absolute error in DN and
    relative to the full table's flux (median, 99th percentile), the peak signal-to-error ratio in dB
    against the sensor's white (largest clip flux) and the share of pixels whose states differ."""
    calib = profile.crosstalk
    h, w = calib.shape
    rng = np.random.default_rng(seed)
    clip_rel = float(calib.clip_code) - float(calib.black_level)
    st = np.where(np.asarray(profile.mask, bool), np.uint8(ATTENUATED), np.uint8(0))
    s = np.where(st != 0, np.float32(profile.nd), np.float32(1.0))
    errs, rels, fulls = [], [], []
    n_state = n_all = 0
    for _ in range(codes_per_pixel):
        v1 = (rng.random((h, w)) * clip_rel).astype(np.float32) * s
        s1 = st.copy()
        v2, s2 = v1.copy(), st.copy()
        crosstalk.correct(v1, s1, profile, mode="lut", lut="full")
        crosstalk.correct(v2, s2, profile, mode="lut", lut="compact")
        both = ((s1 & REASON_MASK) == VALID) & ((s2 & REASON_MASK) == VALID)
        e = np.abs(v2[both].astype(np.float64) - v1[both])
        errs.append(e)
        rels.append(e / np.maximum(np.abs(v1[both]), 1.0))
        fulls.append(v1[both])
        n_state += int(np.sum((s1 & REASON_MASK) != (s2 & REASON_MASK)))
        n_all += int(s1.size)
    e, r = np.concatenate(errs), np.concatenate(rels)
    white = float(np.nanmax(calib.clip_flux)) if np.any(np.isfinite(calib.clip_flux)) else float(
        np.max(np.concatenate(fulls)))
    rms = float(np.sqrt(np.mean(e * e)))
    return {"abs_dn_median": float(np.median(e)), "abs_dn_p99": float(np.percentile(e, 99)),
            "abs_dn_max": float(e.max()), "rel_pct_median": 100 * float(np.median(r)),
            "rel_pct_p99": 100 * float(np.percentile(r, 99)), "rms_dn": rms,
            "psnr_db": float(20 * np.log10(white / max(rms, 1e-12))),
            "state_differs_pct": 100.0 * n_state / max(n_all, 1)}
