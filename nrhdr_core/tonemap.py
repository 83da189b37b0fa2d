"""Logarithmic tone mapping for display (paper section 5, Fig. 10 g/h; hdr-references 'Tone mapping').

y = log(1 + q x) / log(1 + q), x = clip(L 2^e / white, 0, 1): the standard logarithmic operator
(HDR Toolbox LogarithmicTMO) with contrast q and exposure e in stops. The normaliser `white` is fixed
(the sensor's largest scaled value, (clip - black) * ND) or smoothed over time (`WhiteTracker`), never a
per-frame min/max: video must not flicker.

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
            for x in range(w):
                b = ubits[x]
                ebuf[x] = np.float32((b >> 23) - 127)
                mbits[x] = (b & 0x7FFFFF) | 0x3F800000
            for x in range(w):
                m = mbuf[x]
                e = ebuf[x]
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
                u = ubuf[x]
                a = u - np.float32(1.0)
                a0 = (values[y, x] * scale)
                a0 = a0 if a0 > np.float32(0.0) else np.float32(0.0)
                a0 = q * (a0 if a0 < np.float32(1.0) else np.float32(1.0))
                l1p = lg * (a0 / a) if a > np.float32(0.0) else a0
                out[y, x] = l1p * inv_den * out_max + np.float32(0.5)


def log_tonemap(values: np.ndarray, white: float, exposure_stops: float = 0.0,
                contrast: float = DEFAULT_CONTRAST, out: np.ndarray | None = None,
                dtype=np.uint8) -> np.ndarray:
    """Map linear values (H, W) to uint8 or uint16 display codes; `out` (filled in place) fixes the type."""
    if not (white > 0 and math.isfinite(white)):
        raise ValueError(f"tone mapping white must be a finite number > 0, got {white}")
    if not (contrast > 0 and math.isfinite(contrast)):
        raise ValueError(f"tone mapping contrast must be > 0, got {contrast}")
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
                if not (v > 0.0):
                    v = 0.0
                if transfer == 1:
                    v = v ** HLG_SYSTEM_GAMMA * (HLG_NOMINAL_PEAK / L_P)
                if v > 1.0:
                    v = 1.0
                ym = v ** M_1
                e1 = ((C_1 + C_2 * ym) / (C_3 * ym + 1.0)) ** M_2 / src_pq
                if e1 >= 1.0:
                    e1 = max_lum
                elif e1 > ks:
                    t = (e1 - ks) / (1.0 - ks)
                    t2 = t * t
                    t3 = t2 * t
                    e1 = ((2.0 * t3 - 3.0 * t2 + 1.0) * ks + (t3 - 2.0 * t2 + t) * (1.0 - ks)
                          + (-2.0 * t3 + 3.0 * t2) * max_lum)
                e = e1 * src_pq
                if transfer == 1:
                    vp = e ** (1.0 / M_2)
                    n = vp - C_1
                    if n < 0.0:
                        n = 0.0
                    v = ((n / (C_2 - C_3 * vp)) ** (1.0 / M_1) * (L_P / HLG_NOMINAL_PEAK)) ** (1.0 / HLG_SYSTEM_GAMMA)
                    if v > 1.0:
                        v = 1.0
                    if v <= 1.0 / 12.0:
                        e = math.sqrt(3.0 * v)
                    else:
                        e = HLG_A * math.log(12.0 * v - HLG_B) + HLG_C
            else:
                if not (v > 0.0):             # NaN and negatives -> black
                    v = 0.0
                elif v > 1.0:
                    v = 1.0
                if transfer == 0:
                    ym = v ** M_1
                    e = ((C_1 + C_2 * ym) / (C_3 * ym + 1.0)) ** M_2
                elif v <= 1.0 / 12.0:
                    e = math.sqrt(3.0 * v)
                else:
                    e = HLG_A * math.log(12.0 * v - HLG_B) + HLG_C
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
    if transfer not in TRANSFERS:
        raise ValueError(f"HDR transfer must be one of {', '.join(TRANSFERS)}, got {transfer!r}")
    if not (diffuse_white > 0 and math.isfinite(diffuse_white)):
        raise ValueError(f"HDR diffuse white must be a finite number > 0, got {diffuse_white}")
    if not (reference_white > 0 and math.isfinite(reference_white)):
        raise ValueError(f"reference white must be > 0 cd/m^2, got {reference_white}")
    if not (0.0 <= peak <= L_P and 0.0 <= source_peak and math.isfinite(source_peak)):
        raise ValueError(f"HDR peak must be in 0..{L_P:g} cd/m^2 and the source peak >= 0, got {peak}, "
                         f"{source_peak}")
    v = np.asarray(values, dtype=np.float32)
    if out is None:
        out = np.empty(v.shape, np.uint16)
    if out.dtype != np.uint16:
        raise ValueError(f"HDR output must be uint16, got {out.dtype}")
    gain = 2.0 ** exposure_stops / diffuse_white
    src_pq, ks, max_lum = _eetf_params(min(source_peak, L_P), peak)
    code_max = 940
    if peak > 0:
        top = (eotf_inverse_ST2084(peak) if transfer == "pq"
               else oetf_HLG((min(peak, HLG_NOMINAL_PEAK) / HLG_NOMINAL_PEAK) ** (1 / HLG_SYSTEM_GAMMA)))
        code_max = min(int(math.floor(64.0 + 876.0 * float(top) + 1e-4)), 940)
    if transfer == "pq":
        _hdr_kernel(v, gain * reference_white / L_P, 0, src_pq, ks, max_lum, code_max, out)
    else:
        _hdr_kernel(v, gain * hlg_reference_E(reference_white), 1, src_pq, ks, max_lum, code_max, out)
    return out
