"""Measurements: PSNR (linear and log domain), SSIM, the SNR of a flat field (paper Eq. 4, Fig. 3/5/9) and
the HDR quality metrics of `nrhdr compare` (log2 PSNR, PU21-PSNR, pixels stops off, per luminance region)."""
from __future__ import annotations

import numpy as np


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
