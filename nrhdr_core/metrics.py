"""Measurements: PSNR (linear and log domain), SSIM, the SNR of a flat field (paper Eq. 4, Fig. 3/5/9), the HDR
quality metrics of `nrhdr compare` (log2 PSNR, PU21-PSNR, pixels stops off, per luminance region), TMQI, the
quality of a tone-mapped image (Yeganeh and Wang 2013), and for colour images CIELAB, CIEDE2000 (Sharma, Wu and
Dalal 2005) and false colour (docs/COLOUR.md, "Measured")."""
from __future__ import annotations

import numpy as np
from numba import njit, prange


def psnr(ref: np.ndarray, test: np.ndarray, peak: float | None = None) -> float:
    """PSNR in dB; `peak` defaults to the reference's maximum (255 for 8-bit data should be passed)."""
    ref = np.asarray(ref, np.float64)
    test = np.asarray(test, np.float64)
    peak = float(ref.max()) if peak is None else float(peak)
    mse = float(np.mean((ref - test) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(peak * peak / mse)


def log_psnr(ref: np.ndarray, test: np.ndarray, floor: float | None = None) -> float:
    """PSNR of log2 values (stops) over the reference's log range: the HDR-robust variant
    (hdr-references 'Quality metrics'). `floor` clamps tiny values (default 1e-4 of the max)."""
    ref = np.asarray(ref, np.float64)
    test = np.asarray(test, np.float64)
    floor = float(ref.max()) * 1e-4 if floor is None else floor
    lr = np.log2(np.maximum(ref, floor))
    lt = np.log2(np.maximum(test, floor))
    return psnr(lr - lr.min(), lt - lr.min(), peak=float(lr.max() - lr.min()))


def ssim(ref: np.ndarray, test: np.ndarray, data_range: float | None = None) -> float:
    """Mean SSIM (Wang et al. 2004) with an 11 x 11 Gaussian window, sigma 1.5."""
    from scipy.ndimage import gaussian_filter
    x = np.asarray(ref, np.float64)
    y = np.asarray(test, np.float64)
    L = float(x.max() - x.min()) if data_range is None else float(data_range)
    c1, c2 = (0.01 * L) ** 2, (0.03 * L) ** 2
    f = lambda a: gaussian_filter(a, 1.5, truncate=3.5)
    mx, my = f(x), f(y)
    sxx, syy, sxy = f(x * x) - mx * mx, f(y * y) - my * my, f(x * y) - mx * my
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return float(s.mean())


def snr_db(samples: np.ndarray) -> float:
    """Measured SNR of a flat field, 20 log10(mean / std) (paper Eq. 4)."""
    s = np.asarray(samples, np.float64)
    sd = s.std(ddof=1)
    return float("inf") if sd == 0 else 20.0 * np.log10(s.mean() / sd)


# ---- HDR quality metrics ----------------------------------------------------------------------------

# PU21 encoding, Mantiuk & Azimi, "PU21: A novel perceptually uniform encoding for adapting existing
# quality metrics for HDR", Picture Coding Symposium 2021; parameters of the recommended
# 'banding_glare' variant as published in gfxdisp/pu21 (matlab/pu21_encoder.m, updated 06/02/2020):
#   V = p7 * (((p1 + p2 Y^p4) / (1 + p3 Y^p4))^p5 - p6),  Y in cd/m^2 clamped to [0.005, 10000].
PU21_PARAMS = (0.353487901, 0.3734658629, 8.277049286e-05, 0.9062562627, 0.09150303166, 0.9099517204,
               596.3148142)
PU21_L_MIN = 0.005
PU21_L_MAX = 10000.0


def pu21_encode(lum_nits) -> np.ndarray:
    """PU21 value of absolute luminance (cd/m^2), clamped to [0.005, 10000] as in the reference code;
    0 cd/m^2 -> ~0, 100 cd/m^2 -> ~256 (an sRGB display's code range)."""
    p1, p2, p3, p4, p5, p6, p7 = PU21_PARAMS
    y = np.clip(np.asarray(lum_nits, np.float64), PU21_L_MIN, PU21_L_MAX)
    yp = y ** p4
    return p7 * (((p1 + p2 * yp) / (1.0 + p3 * yp)) ** p5 - p6)


def pu21_psnr(ref, test, white: float | None = None, peak_nits: float = 4000.0) -> float:
    """PU21-PSNR (gfxdisp/pu21 `pu21_metric(..., 'PSNR')`: PSNR of PU21 values with peak 256).
    Linear DN are mapped to absolute luminance with `white` (default: the reference's maximum) shown at
    `peak_nits` cd/m^2 (an HDR display); negative values clamp to the encoder's 0.005 cd/m^2."""
    ref = np.asarray(ref, np.float64)
    test = np.asarray(test, np.float64)
    white = float(ref.max()) if white is None else float(white)
    if not white > 0:
        raise ValueError(f"pu21_psnr: white must be > 0, got {white}")
    k = peak_nits / white
    return psnr(pu21_encode(ref * k), pu21_encode(test * k), peak=256.0)


def log2_psnr(ref, test, floor: float = 1.0, peak_stops: float | None = None) -> float:
    """PSNR of log2 values (errors in stops) with an absolute `floor` (e.g. ~1 DN, the noise floor) and
    peak = the reference's log2 range above the floor (`peak_stops` to fix it, e.g. across frames)."""
    ref = np.asarray(ref, np.float64)
    test = np.asarray(test, np.float64)
    lr = np.log2(np.maximum(ref, floor))
    lt = np.log2(np.maximum(np.nan_to_num(test, nan=floor), floor))
    peak = float(lr.max() - np.log2(floor)) if peak_stops is None else float(peak_stops)
    return psnr(lr, lt, peak=max(peak, 1e-12))


def stops_off(ref, test, floor: float = 1.0) -> np.ndarray:
    """|log2(test) - log2(ref)| per pixel, both floored at `floor` (non-finite test counts as off)."""
    ref = np.asarray(ref, np.float64)
    test = np.asarray(test, np.float64)
    d = np.abs(np.log2(np.maximum(np.nan_to_num(test, nan=floor, posinf=1e300, neginf=floor), floor))
               - np.log2(np.maximum(ref, floor)))
    return d


def regions(truth, dark_level: float, bright_level: float) -> dict:
    """Masks by the truth's level: 'dark' below `dark_level` (l_min x ND: where the paper's threshold
    drops the attenuated pixels), 'bright' at or above `bright_level` (the regular pixels' clip: only
    the ND pixels measure it), 'mid' between, 'all'."""
    t = np.asarray(truth)
    dark = t < dark_level
    bright = t >= bright_level
    return {"dark": dark, "mid": ~dark & ~bright, "bright": bright, "all": np.ones(t.shape, bool)}


def hdr_report(truth, test, dark_level: float, bright_level: float, white: float | None = None,
               floor: float = 1.0, peak_stops: float | None = None) -> dict:
    """Per region ('all', 'dark', 'mid', 'bright'): pixel count, log2 PSNR (peak = the whole truth's
    log2 range unless `peak_stops`), PU21-PSNR (white = `white` or the truth's max), pixels more than 1
    and 3 stops off; plus counts of negative and non-finite test values."""
    truth = np.asarray(truth, np.float64)
    test = np.asarray(test, np.float64)
    if truth.shape != test.shape:
        raise ValueError(f"hdr_report: truth {truth.shape} and test {test.shape} differ in shape")
    white = float(truth.max()) if white is None else float(white)
    peak = float(np.log2(max(truth.max(), floor)) - np.log2(floor)) if peak_stops is None else peak_stops
    off = stops_off(truth, test, floor)
    out = {"negative": int(np.count_nonzero(test < 0)), "nonfinite": int(np.count_nonzero(~np.isfinite(test)))}
    for name, m in regions(truth, dark_level, bright_level).items():
        n = int(m.sum())
        r = {"pixels": n}
        if n:
            r["log2_psnr"] = log2_psnr(truth[m], test[m], floor, peak)
            r["pu21_psnr"] = pu21_psnr(truth[m], test[m], white=white)
            r["off_1stop"] = int(np.count_nonzero(off[m] > 1.0))
            r["off_3stops"] = int(np.count_nonzero(off[m] > 3.0))
        out[name] = r
    return out


REGIONS = ("all", "dark", "mid", "bright")


def clip_report(pairs, dark_level: float, bright_level: float, white: float) -> dict:
    """`hdr_report` over the frames of a clip (`nrhdr compare` and `benchmarks/hdr_quality.py`):
    `pairs` yields (truth, test) linear frames; both are capped at `white` (the ND camera's clip-equivalent
    white, so an unmodified camera's clipped highlights count against it), the log2 peak is log2(white);
    per region the mean over frames of log2 PSNR and PU21-PSNR, and the summed pixel counts and pixels
    more than 1 / 3 stops off; negative and non-finite test values are counted before the cap."""
    acc = {k: {"log2_psnr": [], "pu21_psnr": [], "off_1stop": 0, "off_3stops": 0, "pixels": 0} for k in REGIONS}
    neg = nonfinite = frames = 0
    peak = float(np.log2(white))
    for truth, test in pairs:
        test = np.asarray(test, np.float64)
        neg += int(np.count_nonzero(test < 0))
        nonfinite += int(np.count_nonzero(~np.isfinite(test)))
        r = hdr_report(np.minimum(truth, white), np.minimum(test, white), dark_level, bright_level,
                       white=white, peak_stops=peak)
        frames += 1
        for k in REGIONS:
            if r[k]["pixels"]:
                acc[k]["log2_psnr"].append(r[k]["log2_psnr"])
                acc[k]["pu21_psnr"].append(r[k]["pu21_psnr"])
                for c in ("off_1stop", "off_3stops", "pixels"):
                    acc[k][c] += r[k][c]
    out = {"frames": frames, "negative": neg, "nonfinite": nonfinite}
    for k in REGIONS:
        a = acc[k]
        out[k] = {"log2_psnr": float(np.mean(a["log2_psnr"])) if a["log2_psnr"] else None,
                  "pu21_psnr": float(np.mean(a["pu21_psnr"])) if a["pu21_psnr"] else None,
                  "off_1stop": a["off_1stop"], "off_3stops": a["off_3stops"], "pixels": a["pixels"]}
    return out


# ---- TMQI -------------------------------------------------------------------------------------------------

# Yeganeh and Wang, "Objective Quality Assessment of Tone-Mapped Images", IEEE TIP 22(2) 2013, and the
# authors' TMQI.m v1.0: Q = a S^alpha + (1 - a) N^beta (Eq. 12), S over 5 scales (Eq. 7, weights of
# Wang et al.'s MS-SSIM), N = P_m P_d (Eq. 11: a Gaussian of the mean and a Beta of the mean block std).
TMQI_A, TMQI_ALPHA, TMQI_BETA = 0.8012, 0.3046, 0.7088
TMQI_WEIGHTS = (0.0448, 0.2856, 0.3001, 0.2363, 0.1333)
TMQI_C1, TMQI_C2 = 0.01, 10.0
TMQI_MEAN, TMQI_MEAN_SD = 115.94, 27.99          # brightness model (Eq. 9)
TMQI_CONTRAST_NORM, TMQI_BETA_P, TMQI_BETA_Q = 64.29, 4.4, 10.1   # contrast model (Eq. 10)


def _gauss_window(size: int = 11, sigma: float = 1.5) -> np.ndarray:
    """MATLAB's fspecial('gaussian', 11, 1.5), normalised to sum 1."""
    r = np.arange(size) - (size - 1) / 2.0
    g = np.exp(-(r[:, None] ** 2 + r[None, :] ** 2) / (2 * sigma * sigma))
    return g / g.sum()


@njit(cache=True, nogil=True, parallel=True)
def _local_stats_kernel(a, b, win, s1, s2, s12):
    """'valid' windowed means, then the centred second moments sum w (a - mu_a)(b - mu_b): exact for
    flat windows (0, not the rounding noise of E[a^2] - mu^2)."""
    k = win.shape[0]
    h, w = s1.shape
    for y in prange(h):
        for x in range(w):
            ma = 0.0
            mb = 0.0
            for i in range(k):
                for j in range(k):
                    ma += win[i, j] * a[y + i, x + j]
                    mb += win[i, j] * b[y + i, x + j]
            va = 0.0
            vb = 0.0
            cab = 0.0
            for i in range(k):
                for j in range(k):
                    da = a[y + i, x + j] - ma
                    db = b[y + i, x + j] - mb
                    va += win[i, j] * da * da
                    vb += win[i, j] * db * db
                    cab += win[i, j] * da * db
            s1[y, x] = va
            s2[y, x] = vb
            s12[y, x] = cab


def _local_stats(a, b, win):
    k = win.shape[0]
    shape = (a.shape[0] - k + 1, a.shape[1] - k + 1)
    if min(shape) < 1:
        raise ValueError(f"tmqi: image too small for 5 scales of an {k}x{k} window")
    s1, s2, s12 = (np.empty(shape) for _ in range(3))
    _local_stats_kernel(a, b, win, s1, s2, s12)
    return s1, s2, s12


def _normcdf(x, mu, sd):
    from scipy.special import erfc
    return 0.5 * erfc(-(x - mu) / (sd * np.sqrt(2.0)))


def _tmqi_scale(hdr, ldr, win, sf):
    """Local structural fidelity of one scale (paper Eq. 5-6): the HDR and LDR local std mapped through a
    Gaussian-CDF visibility model centred on the CSF threshold at `sf` cycles/degree."""
    var1, var2, cov = _local_stats(hdr, ldr, win)
    sigma1, sigma2 = np.sqrt(np.maximum(var1, 0.0)), np.sqrt(np.maximum(var2, 0.0))
    csf = 100.0 * 2.6 * (0.0192 + 0.114 * sf) * np.exp(-(0.114 * sf) ** 1.1)   # Mannos-Sakrison
    u = 128.0 / (1.4 * csf)
    p1, p2 = _normcdf(sigma1, u, u / 3.0), _normcdf(sigma2, u, u / 3.0)
    s_map = ((2 * p1 * p2 + TMQI_C1) / (p1 * p1 + p2 * p2 + TMQI_C1)) * ((cov + TMQI_C2) / (sigma1 * sigma2 + TMQI_C2))
    return float(s_map.mean())


def _halve(img):
    """TMQI.m's downsampling: imfilter(ones(2)/4, 'symmetric', 'same') then every other sample."""
    p = np.pad(img, ((0, 1), (0, 1)), mode="symmetric")
    m = 0.25 * (p[:-1, :-1] + p[1:, :-1] + p[:-1, 1:] + p[1:, 1:])
    return m[::2, ::2]


def _block_std_mean(ldr, block: int = 11) -> float:
    """mean2(blkproc(L, [11 11], std)): the sample std of each 11 x 11 block (partial blocks zero-padded,
    as blkproc pads), spread over the block's pixels, averaged over the image."""
    h, w = ldr.shape
    hp, wp = -(-h // block) * block, -(-w // block) * block
    p = np.zeros((hp, wp))
    p[:h, :w] = ldr
    blocks = p.reshape(hp // block, block, wp // block, block)
    sd = blocks.std(axis=(1, 3), ddof=1)
    full = np.repeat(np.repeat(sd, block, axis=0), block, axis=1)[:h, :w]
    return float(full.mean())


def tmqi(hdr, ldr) -> tuple[float, float, float]:
    """TMQI (Yeganeh and Wang 2013, TMQI.m v1.0) of an 8-bit tone-mapped luminance `ldr` (0..255) against its
    HDR luminance `hdr`: (Q, S, N). Q = 0.8012 S^0.3046 + 0.1988 N^0.7088.

    As TMQI.m: the HDR is scaled to 0..2^32-1 by its range, S is the weighted product over 5 scales of the
    mean local fidelity (11 x 11 Gaussian window sigma 1.5, 'valid' region, 2 x 2 mean and decimation
    between scales, CSF at 16, 8, .. 1 cycles/degree), N uses 11 x 11 blocks. The local variances are
    computed centred (exact where the window is flat), where TMQI.m's E[x^2] - mu^2 leaves rounding noise:
    a constant LDR then scores S 0.0126 (Q 0.2174) here, 0.0029 in TMQI.m. A negative per-scale S (an
    inverted LDR, where TMQI.m returns a complex Q) raises ValueError."""
    from scipy.special import betaln
    h = np.asarray(hdr, np.float64)
    l = np.asarray(ldr, np.float64)
    if h.ndim != 2 or h.shape != l.shape:
        raise ValueError(f"tmqi: HDR {h.shape} and LDR {l.shape} must be 2-D luminance of the same shape")
    if not (np.isfinite(h).all() and np.isfinite(l).all()):
        raise ValueError("tmqi: HDR and LDR must be finite")
    lo, hi = float(h.min()), float(h.max())
    h = np.round((2.0 ** 32 - 1) / (hi - lo)) * (h - lo) if hi > lo else np.zeros_like(h)
    win = _gauss_window()
    s_local = []
    a, b, sf = h, l, 16.0
    for _ in TMQI_WEIGHTS:
        s_local.append(_tmqi_scale(a, b, win, sf))
        a, b, sf = _halve(a), _halve(b), sf / 2
    s_local = np.array(s_local)
    if (s_local < 0).any():
        raise ValueError(f"tmqi: negative structural fidelity {s_local.min():.4f} at scale "
                         f"{int(np.argmin(s_local)) + 1}: the LDR's structure runs against the HDR's (inverted?)")
    S = float(np.prod(s_local ** np.array(TMQI_WEIGHTS)))
    # statistical naturalness (Eq. 9-11)
    mu, sig = float(l.mean()), _block_std_mean(l)
    p, q = TMQI_BETA_P, TMQI_BETA_Q

    def beta_pdf(x):
        return np.exp((p - 1) * np.log(x) + (q - 1) * np.log1p(-x) - betaln(p, q)) if 0 < x < 1 else 0.0
    pc = beta_pdf(sig / TMQI_CONTRAST_NORM) / beta_pdf((p - 1) / (p + q - 2))
    pb = np.exp(-0.5 * ((mu - TMQI_MEAN) / TMQI_MEAN_SD) ** 2)
    N = float(pb * pc)
    Q = TMQI_A * S ** TMQI_ALPHA + (1 - TMQI_A) * N ** TMQI_BETA
    return float(Q), S, N


# ---- colour: CIELAB, CIEDE2000, false colour ---------------------------------------------------------------

# Linear RGB with BT.709 / sRGB primaries and a D65 white to CIE XYZ (IEC 61966-2-1, ITU-R BT.709); the white
# (Xn, Yn, Zn) is the image of RGB (1, 1, 1), so equal R, G and B are exactly achromatic (a* = b* = 0).
RGB709_TO_XYZ = np.array([[0.4124, 0.3576, 0.1805],
                          [0.2126, 0.7152, 0.0722],
                          [0.0193, 0.1192, 0.9505]])
D65_WHITE = RGB709_TO_XYZ.sum(axis=1)              # (0.9505, 1.0, 1.089)
LUMA_709 = RGB709_TO_XYZ[1]                        # relative luminance Y of linear BT.709 RGB


def _channels_first(a, axis: int, what: str) -> np.ndarray:
    a = np.asarray(a, np.float64)
    if a.ndim < 1 or a.shape[axis] != 3:
        raise ValueError(f"{what}: need 3 channels on axis {axis}, got shape {a.shape}")
    return np.moveaxis(a, axis, 0)


def luminance(rgb, axis: int = 0) -> np.ndarray:
    """Relative luminance Y (BT.709 weights) of linear RGB; channels on `axis` (planar (3, H, W) by default)."""
    c = _channels_first(rgb, axis, "luminance")
    return LUMA_709[0] * c[0] + LUMA_709[1] * c[1] + LUMA_709[2] * c[2]


def linear_rgb_to_xyz(rgb, axis: int = 0) -> np.ndarray:
    """CIE XYZ (channels first, float64) of linear BT.709 RGB (channels on `axis`)."""
    c = _channels_first(rgb, axis, "linear_rgb_to_xyz")
    return np.tensordot(RGB709_TO_XYZ, c, axes=1)


def xyz_to_lab(xyz, white=D65_WHITE) -> np.ndarray:
    """CIELAB (CIE 15:2004 Eq. 8.1-8.3; L*, a*, b* first) of XYZ (channels first) relative to `white`."""
    xyz = np.asarray(xyz, np.float64)
    d = 6.0 / 29.0

    def f(t):
        return np.where(t > d ** 3, np.cbrt(t), t / (3 * d * d) + 4.0 / 29.0)
    fx, fy, fz = (f(xyz[i] / float(white[i])) for i in range(3))
    return np.stack([116.0 * fy - 16.0, 500.0 * (fx - fy), 200.0 * (fy - fz)])


def linear_rgb_to_lab(rgb, white: float = 1.0, axis: int = 0) -> np.ndarray:
    """CIELAB (channels first) of linear BT.709 RGB whose diffuse white is `white` (R = G = B = white gives
    L* = 100, a* = b* = 0; HDR values above it give L* > 100). Channels on `axis`."""
    if not (float(white) > 0 and np.isfinite(white)):
        raise ValueError(f"linear_rgb_to_lab: white must be a finite number > 0, got {white}")
    return xyz_to_lab(linear_rgb_to_xyz(rgb, axis) / float(white))


def srgb_decode(codes) -> np.ndarray:
    """Linear values of sRGB-encoded values (IEC 61966-2-1 EOTF): uint8 codes are divided by 255, float
    values are taken as 0..1."""
    a = np.asarray(codes)
    v = a / 255.0 if a.dtype == np.uint8 else a.astype(np.float64)
    return np.where(v <= 0.04045, v / 12.92, ((np.maximum(v, 0.04045) + 0.055) / 1.055) ** 2.4)


def srgb_to_lab(codes, axis: int = -1) -> np.ndarray:
    """CIELAB (channels first) of an sRGB display image: uint8 codes or floats 0..1, channels on `axis`
    (interleaved (H, W, 3) by default, what `tonemap` writes for a display)."""
    return linear_rgb_to_lab(srgb_decode(codes), 1.0, axis)


def ciede2000(lab1, lab2, kl: float = 1.0, kc: float = 1.0, kh: float = 1.0) -> np.ndarray:
    """CIEDE2000 colour difference of CIELAB values (channels first: L*, a*, b*), element-wise, after
    Sharma, Wu and Dalal, 'The CIEDE2000 color-difference formula: implementation notes, supplementary
    test data, and mathematical observations', Color Res. Appl. 30(1) 2005, Eq. 1-22 (hue angles in
    degrees, mean hue and hue difference by their notes (i)-(iv))."""
    l1, a1, b1 = np.asarray(lab1, np.float64)
    l2, a2, b2 = np.asarray(lab2, np.float64)
    c1, c2 = np.hypot(a1, b1), np.hypot(a2, b2)
    cm7 = ((c1 + c2) / 2.0) ** 7
    g = 0.5 * (1.0 - np.sqrt(cm7 / (cm7 + 25.0 ** 7)))                       # Eq. 4
    a1p, a2p = (1.0 + g) * a1, (1.0 + g) * a2                                # Eq. 5
    c1p, c2p = np.hypot(a1p, b1), np.hypot(a2p, b2)                         # Eq. 6
    h1p = np.where((a1p == 0) & (b1 == 0), 0.0, np.degrees(np.arctan2(b1, a1p)) % 360.0)   # Eq. 7
    h2p = np.where((a2p == 0) & (b2 == 0), 0.0, np.degrees(np.arctan2(b2, a2p)) % 360.0)
    dlp = l2 - l1                                                            # Eq. 8
    dcp = c2p - c1p                                                          # Eq. 9
    zero = (c1p * c2p) == 0
    dh = h2p - h1p
    dhp = np.where(zero, 0.0, np.where(dh > 180.0, dh - 360.0, np.where(dh < -180.0, dh + 360.0, dh)))  # Eq. 10
    dHp = 2.0 * np.sqrt(c1p * c2p) * np.sin(np.radians(dhp / 2.0))          # Eq. 11
    lpm = (l1 + l2) / 2.0                                                    # Eq. 12
    cpm = (c1p + c2p) / 2.0                                                  # Eq. 13
    hs = h1p + h2p
    hpm = np.where(zero, hs, np.where(np.abs(h1p - h2p) <= 180.0, hs / 2.0,
                                      np.where(hs < 360.0, (hs + 360.0) / 2.0, (hs - 360.0) / 2.0)))   # Eq. 14
    t = (1.0 - 0.17 * np.cos(np.radians(hpm - 30.0)) + 0.24 * np.cos(np.radians(2.0 * hpm))
         + 0.32 * np.cos(np.radians(3.0 * hpm + 6.0)) - 0.20 * np.cos(np.radians(4.0 * hpm - 63.0)))  # Eq. 15
    dtheta = 30.0 * np.exp(-(((hpm - 275.0) / 25.0) ** 2))                   # Eq. 16
    cpm7 = cpm ** 7
    rc = 2.0 * np.sqrt(cpm7 / (cpm7 + 25.0 ** 7))                            # Eq. 17
    l50 = (lpm - 50.0) ** 2
    sl = 1.0 + 0.015 * l50 / np.sqrt(20.0 + l50)                             # Eq. 18
    sc = 1.0 + 0.045 * cpm                                                   # Eq. 19
    sh = 1.0 + 0.015 * cpm * t                                               # Eq. 20
    rt = -np.sin(np.radians(2.0 * dtheta)) * rc                              # Eq. 21
    x, y, z = dlp / (kl * sl), dcp / (kc * sc), dHp / (kh * sh)
    return np.sqrt(x * x + y * y + z * z + rt * y * z)                       # Eq. 22


def mean_ciede2000_srgb(ref_codes, test_codes, mask=None, axis: int = -1) -> float:
    """Mean CIEDE2000 between two sRGB display images (uint8 codes, channels on `axis`), over `mask`
    (bool (H, W)) or every pixel."""
    d = ciede2000(srgb_to_lab(ref_codes, axis), srgb_to_lab(test_codes, axis))
    if mask is not None:
        d = d[np.asarray(mask, bool)]
    return float(d.mean()) if d.size else float("nan")


def chroma_error(truth, test, floor: float = 1.0, axis: int = 0) -> np.ndarray:
    """Per pixel (Delta a*)^2 + (Delta b*)^2 between linear RGB `test` and `truth` (channels on `axis`), both
    scaled by the same factor so that the truth's luminance is the CIELAB white (Y = Yn; the truth's Y
    floored at `floor`). The scaling makes the measure independent of the pixel's level (a fringe counts the
    same in a shadow and in a highlight, as it would under local adaptation) and of the test's luminance
    error: any achromatic test (R = G = B) on an achromatic truth scores 0."""
    t = _channels_first(truth, axis, "chroma_error truth")
    x = _channels_first(test, axis, "chroma_error test")
    if t.shape != x.shape:
        raise ValueError(f"chroma_error: truth {t.shape} and test {x.shape} differ in shape")
    k = 1.0 / np.maximum(luminance(t), floor)
    lt = linear_rgb_to_lab(t * k)
    lx = linear_rgb_to_lab(np.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0).clip(0.0) * k)
    return (lx[1] - lt[1]) ** 2 + (lx[2] - lt[2]) ** 2


def false_colour(truth, test, mask=None, floor: float = 1.0, axis: int = 0) -> float:
    """False colour of a reconstructed colour image: the mean over `mask` (default every pixel) of
    `chroma_error`, the squared CIELAB chroma difference (Delta a*^2 + Delta b*^2; CIE 15:2004 section 8.2.1)
    against the truth at the truth's luminance. 0 for a perfect result. On an achromatic zone plate it is the
    mean squared chroma of the result, the colour aliasing a demosaicker makes of pure luminance detail;
    `false_colour_db` gives it in dB, so '3 dB less' is half the chroma error power."""
    e = chroma_error(truth, test, floor, axis)
    if mask is not None:
        e = e[np.asarray(mask, bool)]
    return float(e.mean()) if e.size else float("nan")


def false_colour_db(truth, test, mask=None, floor: float = 1.0, axis: int = 0) -> float:
    """10 log10(`false_colour`) in dB (-inf for a perfect result)."""
    fc = false_colour(truth, test, mask, floor, axis)
    return float("-inf") if fc == 0 else 10.0 * float(np.log10(fc))


def rgb_clip_report(pairs, dark_level: float, bright_level: float, white: float) -> dict:
    """`clip_report` on the luminance (BT.709 weights, `luminance`) of linear camera RGB frames: `pairs`
    yields (truth, test) planar (3, H, W); regions by the truth's luminance."""
    return clip_report(((luminance(t), luminance(x)) for t, x in pairs), dark_level, bright_level, white)
