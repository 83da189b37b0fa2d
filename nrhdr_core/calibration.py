"""Crosstalk calibration from flat-field exposure sweeps (paper sections 3.2, 4.1, 4.2; docs/CROSSTALK.md).

A sweep is a folder of 16-bit TIFF/PNG frames plus `exposures.csv` (columns `file,exposure_s`), several
frames per exposure, uniform illumination, from dark (exposure 0 recommended) to beyond saturation. It is
what a user captures with the real camera; `simulate_flats` / `nrhdr simulate-flats` writes one from the
sensor model.

`calibrate` follows the paper:
1. average the frames of each exposure (temporal noise from the frame-to-frame variance, EMVA 1288 style:
   system gain, read noise, full well, black level, clip code);
2. the reference curve from the attenuated pixels least affected by crosstalk. The paper averages the
   attenuated pixels with only attenuated neighbours (fallback: one regular neighbour); we also fit, at each
   exposure, every attenuated pixel's code against which of its 8 neighbours are regular and take the
   intercept (= an attenuated pixel with only attenuated neighbours, from all pixels instead of a few) and the
   8 coefficients (the spill of a regular neighbour in each direction, used by the kernel mode);
3. the ND factor from a second reference, the regular pixels (paper: at most one attenuated neighbour; here
   the same regression's intercept), as the ratio of the two references' slopes over exposure;
4. each pixel's LUT: its mean code at every exposure where it is not clipped, mapped to the flux of that
   exposure (the reference), plus its clipping point;
5. the effective ND per attenuated pixel (Eq. 8) and its histogram (Fig. 8a), the ratio of valid pixels over
   flux (Fig. 8b) and the dynamic-range gain at 40 % and 20 % known pixels (section 4.2).
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import math
import sys
from pathlib import Path

import numpy as np

from . import crosstalk, io
from . import profile as profiles

IMAGE_EXTS = (".tif", ".tiff", ".png")
MAX_KNOTS = 64


class CalibrationError(ValueError):
    """Bad or unusable calibration input; the message names the file or folder and what is wrong."""


# ======================================================================================================
# Flat-field folders
# ======================================================================================================

@dataclasses.dataclass
class FlatSweep:
    folder: Path
    exposures: np.ndarray          # (E,) seconds, increasing
    mean: np.ndarray               # (E, H, W) float32 mean code per pixel
    maxcode: np.ndarray            # (E, H, W) uint16 largest code over the exposure's frames
    tvar: np.ndarray               # (E, H, W) float32 temporal variance (frame to frame, ddof=1)
    frames: np.ndarray             # (E,) frames per exposure

    @property
    def shape(self):
        return self.mean.shape[1:]


def read_index(folder) -> list[tuple[float, list[Path]]]:
    """Validate `folder/exposures.csv` and return [(exposure_s, [frame paths])] sorted by exposure."""
    folder = Path(folder)
    if not folder.is_dir():
        raise CalibrationError(f"{folder}: flat-field folder not found")
    csv_path = folder / "exposures.csv"
    if not csv_path.is_file():
        raise CalibrationError(f"{csv_path}: missing (a flat-field folder needs exposures.csv with columns "
                               f"file,exposure_s)")
    try:
        with open(csv_path, newline="", encoding="utf-8-sig") as f:     # tolerate a BOM (spreadsheets)
            rd = csv.DictReader(f)
            rows = list(rd)
            fields = [c.strip() for c in (rd.fieldnames or [])]
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise CalibrationError(f"{csv_path}: unreadable: {e}") from None
    if "file" not in fields or "exposure_s" not in fields:
        raise CalibrationError(f"{csv_path}: header must contain columns 'file' and 'exposure_s', "
                               f"got {fields}")
    groups: dict[float, list[Path]] = {}
    seen = set()
    for n, row in enumerate(rows, start=2):
        if None in row:     # csv.DictReader puts surplus cells under the key None (as a list)
            raise CalibrationError(f"{csv_path}: line {n}: {len(fields) + len(row[None])} columns, but the "
                                   f"header has {len(fields)} ({','.join(fields)}); extra cells "
                                   f"{row[None]!r}")
        row = {(k or "").strip(): (v or "").strip() for k, v in row.items()}
        name = row.get("file", "")
        if not name:
            raise CalibrationError(f"{csv_path}: line {n}: empty 'file'")
        if name in seen:
            raise CalibrationError(f"{csv_path}: line {n}: file {name} listed twice")
        seen.add(name)
        try:
            t = float(row.get("exposure_s", ""))
        except ValueError:
            raise CalibrationError(f"{csv_path}: line {n}: exposure_s {row.get('exposure_s')!r} is not a "
                                   f"number") from None
        if not (math.isfinite(t) and t >= 0):
            raise CalibrationError(f"{csv_path}: line {n}: exposure_s must be finite and >= 0, got {t}")
        p = folder / name
        try:
            found = p.is_file()
        except (OSError, ValueError):     # e.g. a NUL byte or a name too long for the file system
            found = False
        if not found:
            raise CalibrationError(f"{csv_path}: line {n}: frame {p} not found")
        groups.setdefault(t, []).append(p)
    if not groups:
        raise CalibrationError(f"{csv_path}: lists no frames")
    listed = {p.resolve() for g in groups.values() for p in g}
    unlisted = sorted(p.name for p in folder.iterdir()
                      if p.suffix.lower() in IMAGE_EXTS and p.resolve() not in listed
                      and not p.name.startswith(".") and "mask" not in p.stem.lower())
    if unlisted:
        raise CalibrationError(f"{csv_path}: rows missing: {len(unlisted)} frame(s) in {folder} are not listed "
                               f"(e.g. {', '.join(unlisted[:3])}); list every frame with its exposure_s")
    few = [(t, g) for t, g in sorted(groups.items()) if len(g) < 2]
    if few:
        t, g = few[0]
        raise CalibrationError(f"{csv_path}: exposure {t:g} s has {len(g)} frame ({g[0].name}); at least two "
                               f"frames per exposure are needed (temporal noise); {len(few)} exposure(s) "
                               f"affected")
    if len(groups) < 3:
        raise CalibrationError(f"{csv_path}: only {len(groups)} distinct exposures; a sweep needs at least 3 "
                               f"(dark to beyond saturation)")
    return sorted(groups.items())


def _read_frame(p: Path) -> np.ndarray:
    try:
        px = io.read_image(p, np.uint16)
    except io.ImageFileError as e:
        raise CalibrationError(str(e)) from None
    return px[:, :, 0]


def read_flats(folder, progress: bool = True) -> FlatSweep:
    """Read and validate a flat-field folder; per-exposure mean, max and temporal variance per pixel."""
    index = read_index(folder)
    from tqdm import tqdm
    total = sum(len(g) for _, g in index)
    shape = None
    first = None
    E = len(index)
    bar = tqdm(total=total, desc="reading flats", unit="frame", disable=not progress, file=sys.stderr)
    try:
        for i, (t, paths) in enumerate(index):
            s = s2 = mx = None
            for p in paths:
                fr = _read_frame(p)
                if shape is None:
                    shape, first = fr.shape, p
                    mean = np.empty((E,) + shape, np.float32)
                    maxc = np.empty((E,) + shape, np.uint16)
                    tvar = np.empty((E,) + shape, np.float32)
                elif fr.shape != shape:
                    raise CalibrationError(f"{p}: frame is {fr.shape[1]}x{fr.shape[0]} but {first.name} is "
                                           f"{shape[1]}x{shape[0]}; all frames of a sweep must have one size")
                f64 = fr.astype(np.float64)
                if s is None:
                    s, s2, mx = f64.copy(), f64 * f64, fr.copy()
                else:
                    s += f64
                    s2 += f64 * f64
                    np.maximum(mx, fr, out=mx)
                bar.update(1)
            n = len(paths)
            m = s / n
            mean[i] = m
            maxc[i] = mx
            tvar[i] = np.maximum(s2 - n * m * m, 0.0) / (n - 1)
    finally:
        bar.close()
    return FlatSweep(Path(folder), np.array([t for t, _ in index]), mean, maxc, tvar,
                     np.array([len(g) for _, g in index]))


def default_exposures(n: int = 40, t_sat: float = 0.01, nd: float = 6.35, over: float = 1.6) -> np.ndarray:
    """Exposure times (s) for a sweep: 0 (dark), then geometric up to the regular pixels' saturation at
    `t_sat`, then denser up to `over` x ND x t_sat (all attenuated pixels clipped)."""
    if n < 6:
        raise ValueError(f"a sweep needs at least 6 exposures, got {n}")
    n_hi = max(3, int(round(0.6 * (n - 1))))
    n_lo = n - 1 - n_hi
    lo = np.geomspace(t_sat * 0.002, t_sat, n_lo, endpoint=False)
    hi = np.geomspace(t_sat, t_sat * nd * over, n_hi)
    return np.concatenate([[0.0], lo, hi])


# What simulate_flats writes (io.staged_folder: with overwrite, only these are replaced).
FLATS_OUTPUTS = io.owned_by_patterns(r"flat_\d+_\d+\.(tif|png)", r"exposures\.csv", r"mask\.png",
                                     r"truth\.json")


def simulate_flats(out_dir, prof, sensor_model=None, exposures=None, frames_per_exposure: int = 4,
                   seed: int = 0, fmt: str = "tiff", t_sat: float = 0.01, progress: bool = True,
                   overwrite: bool = False) -> dict:
    """Write a flat-field sweep captured by `prof` (+ `sensor_model`) into `out_dir`: frames, exposures.csv,
    mask.png and truth.json. Flux per second is chosen so that a regular pixel reaches clipping at `t_sat`.
    Returns the truth (ND, kernel, ...). The folder is written as a whole (io.staged_folder): a non-empty
    `out_dir` is refused unless `overwrite`, which replaces only FLATS_OUTPUTS."""
    if frames_per_exposure < 1:
        raise ValueError("frames_per_exposure must be >= 1")
    ext = {"tiff": ".tif", "tif": ".tif", "png": ".png"}.get(fmt)
    if ext is None:
        raise ValueError(f"format must be tiff or png, got {fmt!r}")
    with io.staged_folder(out_dir, force=overwrite, owned=FLATS_OUTPUTS) as tmp:
        return _write_flats(tmp, prof, sensor_model, exposures, frames_per_exposure, seed, ext, t_sat,
                            progress)


def _write_flats(out: Path, prof, sensor_model, exposures, frames_per_exposure, seed, ext, t_sat,
                 progress) -> dict:
    from tqdm import tqdm
    from . import sensor
    exp = default_exposures(nd=prof.nd, t_sat=t_sat) if exposures is None else np.asarray(exposures, float)
    rate = (prof.clip_code - prof.black_level) / t_sat            # DN per second for a regular pixel
    rng = np.random.default_rng(seed)
    rows = []
    h, w = prof.mask.shape
    with tqdm(total=len(exp) * frames_per_exposure, desc="simulating flats", unit="frame",
              disable=not progress, file=sys.stderr) as bar:
        for i, t in enumerate(exp):
            flux = np.full((h, w), rate * t)
            for j in range(frames_per_exposure):
                raw = sensor.capture(flux, prof, rng, sensor_model=sensor_model)
                name = f"flat_{i:03d}_{j:02d}{ext}"
                io.write_image(out / name, raw, np.uint16)
                rows.append((name, float(t)))
                bar.update(1)
    tmp = out / ".exposures.csv.tmp"
    with open(tmp, "w", newline="") as f:
        wr = csv.writer(f)
        wr.writerow(["file", "exposure_s"])
        for r in rows:
            wr.writerow([r[0], repr(r[1])])
    tmp.replace(out / "exposures.csv")
    io.write_mask(out / "mask.png", prof.mask)
    truth = {"nd": prof.nd, "rate_dn_per_s": rate, "black_level": prof.black_level, "clip_code": prof.clip_code,
             "gain": prof.gain, "read_noise": prof.read_noise, "full_well": prof.full_well,
             "sensor_model": None if sensor_model is None else sensor_model.truth()}
    (out / "truth.json").write_text(json.dumps(truth, indent=2) + "\n")
    return truth


# ======================================================================================================
# Calibration math
# ======================================================================================================

def _neighbour_indicators(mask: np.ndarray, want_regular: bool) -> np.ndarray:
    """(8, H, W) float32: 1 where neighbour d exists and is regular (want_regular) / attenuated."""
    h, w = mask.shape
    out = np.zeros((8, h, w), np.float32)
    for d, (dy, dx) in enumerate(crosstalk.DIRS):
        nb = crosstalk._shift(mask.astype(np.float32), int(dy), int(dx))
        inside = crosstalk._shift(np.ones((h, w), np.float32), int(dy), int(dx))
        out[d] = (inside - nb) if want_regular else nb
    return out


def _lstsq(X, y):
    try:
        return np.linalg.solve(X.T @ X, X.T @ y)           # normal equations: fast for tall X
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(X, y, rcond=None)[0]


def _robust_lstsq(X: np.ndarray, y: np.ndarray, reject: float = 8.0):
    """Least squares with one pass of rejecting gross outliers (hot/dead pixels) beyond `reject` MADs."""
    coef = _lstsq(X, y)
    r = y - X @ coef
    mad = 1.4826 * np.median(np.abs(r - np.median(r)))
    if mad > 0:
        keep = np.abs(r) < reject * mad
        if keep.sum() > X.shape[1] * 3 and not keep.all():
            coef = _lstsq(X[keep], y[keep])
    return coef


def _slope_through_origin(t, y, ok):
    t, y = t[ok], y[ok]
    if t.size < 1 or not np.any(t > 0):
        return float("nan")
    return float(np.sum(t * y) / np.sum(t * t))


@dataclasses.dataclass
class CalibrationResult:
    profile: profiles.CameraProfile
    summary: dict
    flux: np.ndarray               # (E,) flux of each exposure (regular DN)
    ref_att: np.ndarray            # (E,) attenuated reference (code above dark), NaN where unavailable
    ref_reg: np.ndarray
    nd_eff: np.ndarray             # (N_att,) effective ND of the attenuated pixels (NaN: never clipped)
    ratio_flux: np.ndarray
    ratio: np.ndarray
    ratio_measured: np.ndarray     # (E,) valid ratio of the sweep's mean frames
    examples: list


def calibrate(sweep: FlatSweep, mask: np.ndarray, nd_nominal: float | None = None, l_min: float = 100.0,
              clip_code: int | None = None, bit_depth: int | None = None, name: str = "calibrated",
              mask_name: str = "mask", progress: bool = True, smooth_chi2: float = 1.5,
              smooth_taps: int = 5, prior_g: float = 0.02, prior_alpha: float = 0.5,
              prior_c: float = 0.0002) -> CalibrationResult:
    """Calibrate crosstalk, ND and the sensor's basic parameters from a flat-field sweep."""
    from tqdm import tqdm
    mask = np.asarray(mask, bool)
    E = len(sweep.exposures)
    H, W = sweep.shape
    where = str(sweep.folder)
    if mask.shape != (H, W):
        raise CalibrationError(f"{mask_name}: mask is {mask.shape[1]}x{mask.shape[0]} but the frames in "
                               f"{where} are {W}x{H}")
    if mask.all() or not mask.any():
        raise CalibrationError(f"{mask_name}: the mask must contain both attenuated (255) and regular (0) "
                               f"pixels")
    steps = tqdm(total=7, desc="calibrating", unit="step", disable=not progress, file=sys.stderr)
    t = sweep.exposures.astype(np.float64)
    mean, maxc, tvar = sweep.mean, sweep.maxcode, sweep.tvar
    reg = ~mask
    max_seen = int(maxc.max())
    if bit_depth is None:
        bit_depth = next(b for b in (8, 10, 12, 14, 16) if (1 << b) - 1 >= max_seen)
    max_code = (1 << bit_depth) - 1

    # ---- saturated everywhere? ------------------------------------------------------------------
    first_lit = 1 if t[0] == 0 else 0
    hot = np.mean(maxc[0] >= max(max_seen - 3, 1))
    if hot > 0.5 or np.mean(maxc[first_lit] >= max(max_seen - 3, 1)) > 0.9:
        raise CalibrationError(f"{where}: the sweep is saturated everywhere: already at the shortest exposure "
                               f"({t[first_lit]:g} s) most pixels sit at the largest code {max_seen}; the "
                               f"sweep must start dark")

    # ---- black level, dark per pixel ------------------------------------------------------------
    if t[0] == 0:
        dark = mean[0].astype(np.float64)
        black = float(np.median(dark))
    else:
        m0, m1 = float(np.median(mean[0][reg])), float(np.median(mean[1][reg]))
        black = m0 - t[0] * (m1 - m0) / (t[1] - t[0])
        dark = np.full((H, W), black)
    black = float(max(black, 0.0))

    # ---- saturation, clip code ------------------------------------------------------------------
    # mean (not median: the variance of a few frames is chi-square skewed) over the regular pixels,
    # without the 0.5 % most extreme (hot pixels)
    def _tmean(v):
        v = v.ravel()
        if v.size == 0:
            return float("nan")
        return float(np.mean(v[v <= np.percentile(v, 99.5)]))
    var_reg = np.array([_tmean(tvar[i][reg]) for i in range(E)])
    if clip_code is None:
        if not (var_reg[-1] < 0.25 * var_reg.max()):
            raise CalibrationError(f"{where}: the sweep does not reach saturation: the regular pixels' temporal "
                                   f"variance at the longest exposure ({t[-1]:g} s) is still "
                                   f"{var_reg[-1]:.1f} DN^2 (peak {var_reg.max():.1f}); extend the sweep beyond "
                                   f"saturation or pass --clip-code")
        sat = mean[-1][reg]
        sig = math.sqrt(float(np.median(tvar[-1][reg])))
        clip_code = int(min(max_code - 1, math.floor(np.percentile(sat, 1) - 3 * sig)))
    clip_code = int(clip_code)
    if not (black + 10 < clip_code <= max_code):
        raise CalibrationError(f"{where}: inconsistent levels: black {black:.1f}, clip code {clip_code}, "
                               f"{bit_depth}-bit data")
    top = clip_code - black
    unclipped = np.logical_and.accumulate(maxc < clip_code, axis=0)      # (E, H, W), once clipped stays
    lit = t > 0
    if np.mean(unclipped[np.argmax(lit)][reg]) < 0.5:
        raise CalibrationError(f"{where}: the sweep is saturated everywhere: at the shortest exposure with "
                               f"light ({t[np.argmax(lit)]:g} s) most regular pixels are already clipped")
    steps.update(1)

    # ---- photon transfer (EMVA 1288): gain, read noise, full well -------------------------------
    d = mean - dark[None].astype(np.float32)                             # (E, H, W) dark-subtracted
    mu = np.array([float(np.median(d[i][reg & unclipped[i]])) if np.any(reg & unclipped[i]) else np.nan
                   for i in range(E)])
    var_unc = np.array([_tmean(tvar[i][reg & unclipped[i]]) for i in range(E)])
    ptc = np.isfinite(mu) & (mu < 0.7 * top) & (var_unc > 0)
    gain, read_noise = 4095.0 / 8000.0, 2.0
    if ptc.sum() >= 3:
        k, v0 = np.polyfit(mu[ptc], var_unc[ptc], 1)
        if k > 0 and math.isfinite(k):
            gain = float(k)
            read_noise = math.sqrt(max(float(var_reg[0] if t[0] == 0 else v0) - 1.0 / 12.0, 0.0)) / gain
    # the ADC may clip before the full well: the full well is at least the saturated level (+ margin)
    sat_level = float(np.median(mean[-1][reg])) - black
    full_well = max(sat_level, top + 3.0 * read_noise * gain + 1.0) / gain
    steps.update(1)

    # ---- references: regression on neighbour configuration ---------------------------------------
    border = np.zeros((H, W), bool)
    border[1:-1, 1:-1] = True
    ind_reg = _neighbour_indicators(mask, True)       # for attenuated targets
    ind_att = _neighbour_indicators(mask, False)      # for regular targets
    att_idx = np.nonzero(mask & border)
    reg_idx = np.nonzero(reg & border)
    Xa = np.column_stack([np.ones(att_idx[0].size)] + [ind_reg[k][att_idx] for k in range(8)])
    Xr = np.column_stack([np.ones(reg_idx[0].size)] + [ind_att[k][reg_idx] for k in range(8)])
    n_regnb = ind_reg.sum(0)
    n_attnb = ind_att.sum(0)
    h0 = np.full(E, np.nan)
    H0 = np.full(E, np.nan)
    b = np.full((E, 8), np.nan)
    frac_att = np.zeros(E)
    frac_reg = np.zeros(E)
    paper_att = np.full(E, np.nan)
    paper_reg = np.full(E, np.nan)
    sel0 = mask & border & (n_regnb == 0)
    paper_att_sel = sel0 if sel0.sum() >= 10 else (mask & border & (n_regnb <= 1))
    paper_reg_sel = reg & border & (n_attnb <= 1)
    min_rows = 30
    for i in range(E):
        if not lit[i]:
            h0[i] = H0[i] = paper_att[i] = paper_reg[i] = 0.0
            b[i] = 0.0
            continue
        ua = unclipped[i][att_idx]
        frac_att[i] = ua.mean()
        if ua.sum() >= min_rows:
            ya = d[i][att_idx][ua]
            Xs = Xa[ua]
            if np.all(Xs[:, 1:].sum(0) >= 5):
                c = _robust_lstsq(Xs, ya)
                h0[i], b[i] = c[0], c[1:]
            else:
                h0[i] = float(np.median(ya[Xs[:, 1:].sum(1) == 0])) if np.any(Xs[:, 1:].sum(1) == 0) else np.nan
        ur = unclipped[i][reg_idx]
        frac_reg[i] = ur.mean()
        if ur.sum() >= min_rows:
            H0[i] = _robust_lstsq(Xr[ur], d[i][reg_idx][ur])[0]
        s = paper_att_sel & unclipped[i]
        if s.sum() >= 3:
            paper_att[i] = float(np.mean(d[i][s]))
        s = paper_reg_sel & unclipped[i]
        if s.sum() >= 3:
            paper_reg[i] = float(np.mean(d[i][s]))
    # tiny sensors: where the regression is impossible, the paper's references
    h0 = np.where(np.isfinite(h0), h0, paper_att)
    H0 = np.where(np.isfinite(H0), H0, paper_reg)
    steps.update(1)

    # ---- ND from the two references' slopes over exposure -----------------------------------------
    lo_lim = max(20.0, 0.01 * top)
    # (only where nearly all pixels of the kind are unclipped: the clipped ones would bias the regression)
    # (progressively relaxed for sweeps too coarse to have such exposures)
    for need in (0.99, 0.95, 0.8, 0.0):
        ok_r = np.isfinite(H0) & (H0 > lo_lim) & (H0 < 0.7 * top) & (frac_reg >= need)
        if ok_r.any():
            break
    for need in (0.99, 0.95, 0.8, 0.0):
        ok_a = np.isfinite(h0) & (h0 > lo_lim / 2) & (h0 < 0.8 * top) & (frac_att >= need)
        if ok_a.any():
            break
    kappa_reg = _slope_through_origin(t, H0, ok_r)
    kappa_att = _slope_through_origin(t, h0, ok_a)
    if not (kappa_reg > 0 and kappa_att > 0):
        raise CalibrationError(f"{where}: cannot measure the ND factor: need an exposure where the regular "
                               f"pixels are between {lo_lim:.0f} and {0.7 * top:.0f} DN and one where the "
                               f"attenuated pixels are between {lo_lim / 2:.0f} and {0.8 * top:.0f} DN, all "
                               f"unclipped (found {int(ok_r.sum())} and {int(ok_a.sum())}); use a denser sweep")
    nd = kappa_reg / kappa_att
    pr = np.isfinite(paper_reg) & (paper_reg > lo_lim) & (paper_reg < 0.7 * top)
    pa = np.isfinite(paper_att) & (paper_att > lo_lim / 2) & (paper_att < 0.8 * top)
    nd_paper = _slope_through_origin(t, paper_reg, pr) / _slope_through_origin(t, paper_att, pa)
    if nd < 1:
        raise CalibrationError(f"{where}: measured ND {nd:.3f} < 1: is the mask inverted (255 must mark "
                               f"attenuated pixels)?")
    flux = kappa_reg * t                                                  # (E,) regular DN
    steps.update(1)

    # ---- kernel mode: per-direction spill sigma_d(e), per-pixel amplitude alpha ---------------------
    okb = lit & np.all(np.isfinite(b), axis=1) & (frac_att >= 0.9)
    fe = flux[okb]
    bb = b[okb]
    order = np.argsort(fe)
    fe, bb = fe[order], bb[order]
    sigma = np.zeros((8, fe.size))
    for j in range(fe.size):
        lowf = fe[j] / nd
        if j == 0 or lowf <= fe[0]:
            base = bb[0] * nd / (nd - 1) if nd > 1.0001 else bb[0]
            prev = base * (lowf / fe[0]) if fe.size else 0.0
            sigma[:, j] = bb[j] + prev if j > 0 else base
        else:
            prev = np.array([np.interp(lowf, fe[:j], sigma[k, :j]) for k in range(8)])
            sigma[:, j] = bb[j] + prev
    if fe.size < 2:
        fe = np.array([0.0, 1.0])
        sigma = np.zeros((8, 2))
    else:
        # a brighter source never spills less; beyond the table (where the regression would be biased by
        # the pixels that clip first) continue with the slope of its last quarter (optical spill and
        # blooming are both linear in the source signal far above the knee)
        sigma = np.maximum.accumulate(sigma, axis=1)
        kk = max(3, fe.size // 4) if fe.size >= 3 else fe.size
        xs = fe[-kk:] - fe[-kk:].mean()
        slope_end = np.maximum((sigma[:, -kk:] - sigma[:, -kk:].mean(1, keepdims=True)) @ xs
                               / max(float(xs @ xs), 1e-12), 0.0)
        f_far = fe[-1] * 100.0
        fe = np.append(fe, f_far)
        sigma = np.concatenate([sigma, (sigma[:, -1] + slope_end * (f_far - fe[-2]))[:, None]], axis=1)
    # population model of every pixel's curve: b_d at every exposure from the spill table
    b_model = np.zeros((E, 8))
    for i in range(E):
        if lit[i]:
            b_model[i] = _spill_np(fe, sigma, flux[i]) - _spill_np(fe, sigma, flux[i] / nd)
    # per pixel: d_p = g * E_p + alpha * Y_p over its unclipped lit exposures (ridge towards alpha = 1);
    # g absorbs PRNU, alpha the pixel's crosstalk amplitude (non-uniform mask)
    # basis per pixel: E_p (own signal), Y_p (population crosstalk for its neighbourhood), E_p^2 / top
    # (mild per-pixel non-linearity). Weighted by the inverse noise of each mean (photon transfer curve),
    # with Gaussian priors: gain g ~ 1 +- prior_g (PRNU, flat-field non-uniformity), alpha ~ 1 +- prior_alpha
    # (a glued mask varies a lot), c ~ 0 +- prior_c. In the linear range Y is proportional to E, so the prior
    # decides how a pixel's excess splits between PRNU and crosstalk: mostly crosstalk, as it should.
    A = np.zeros((H, W, 3, 3))
    r = np.zeros((H, W, 3))
    Ys = np.zeros((E, H, W), np.float32)
    for i in range(E):
        if not lit[i]:
            continue
        u = unclipped[i]
        Y = np.tensordot(b_model[i], ind_reg, axes=1) * mask - np.tensordot(b_model[i], ind_att, axes=1) * reg
        Ys[i] = Y
        Ep = np.where(mask, flux[i] / nd, flux[i])
        wgt = np.where(u, sweep.frames[i] / (gain * np.maximum(Ep, 0) + (read_noise * gain) ** 2 + 1.0 / 12), 0)
        basis = (Ep, Y, Ep * Ep / top)
        for j in range(3):
            r[:, :, j] += wgt * basis[j] * d[i]
            for k in range(j, 3):
                A[:, :, j, k] += wgt * basis[j] * basis[k]
    for j in range(3):
        for k in range(j):
            A[:, :, j, k] = A[:, :, k, j]
    # priors, in units of the parameters: the data term is in DN^2 / variance
    A[:, :, 0, 0] += 1.0 / prior_g ** 2
    r[:, :, 0] += 1.0 / prior_g ** 2
    A[:, :, 1, 1] += 1.0 / prior_alpha ** 2
    r[:, :, 1] += 1.0 / prior_alpha ** 2
    A[:, :, 2, 2] += 1.0 / prior_c ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        try:
            coef = np.linalg.solve(A, r[..., None])[..., 0]
        except np.linalg.LinAlgError:
            coef = np.stack([np.ones((H, W)), np.ones((H, W)), np.zeros((H, W))], -1)
    coef = np.where(np.isfinite(coef), coef, np.array([1.0, 1.0, 0.0]))
    gfit, alpha, qfit = coef[..., 0], np.clip(coef[..., 1], 0.0, 5.0), coef[..., 2]
    del A, r
    # smoothed curves: where the 3-parameter model explains a pixel's knots within the measurement noise,
    # its LUT uses the model (averages the flats' noise over all exposures); otherwise the raw means
    chi = np.zeros((H, W))
    cnt = np.zeros((H, W))
    for i in range(E):
        if not lit[i]:
            continue
        u = unclipped[i]
        Ep = np.where(mask, flux[i] / nd, flux[i])
        fit = gfit * Ep + alpha * Ys[i] + qfit * Ep * Ep / top
        # noise of the mean from the photon transfer curve (a few frames' own variance is too noisy)
        var = (gain * np.maximum(fit, 0) + (read_noise * gain) ** 2 + 1.0 / 12) / sweep.frames[i] + 0.05
        chi += np.where(u, (d[i] - fit) ** 2 / var, 0)
        cnt += u
        Ys[i] = fit                                     # reuse: the model curve
    smooth_ok = (cnt >= 3) & (chi / np.maximum(cnt, 1) < smooth_chi2)
    alpha = alpha.astype(np.float32)
    # the model plus the pixel's residual averaged over neighbouring exposures (5 taps, valid knots only):
    # keeps systematic deviations from the model, averages the flats' noise
    res = np.where(unclipped & lit[:, None, None], d - Ys, 0).astype(np.float32)
    wgt = (unclipped & lit[:, None, None]).astype(np.float32)
    rs = np.zeros_like(res)
    ws = np.zeros_like(wgt)
    for sh in range(-smooth_taps // 2 + 1, smooth_taps // 2 + 1):
        lo, hi = max(0, -sh), min(E, E - sh)
        rs[lo:hi] += res[lo + sh:hi + sh]
        ws[lo:hi] += wgt[lo + sh:hi + sh]
    curve = np.where(smooth_ok[None], Ys, Ys + rs / np.maximum(ws, 1)).astype(np.float32)
    curve = np.where(unclipped, curve, Ys)          # beyond clipping: the model (for the clip point)
    curve[~lit] = d[~lit]
    del res, wgt, rs, ws
    del Ys
    steps.update(1)

    # ---- per-pixel LUT knots ------------------------------------------------------------------------
    idx = np.arange(E)
    if E > MAX_KNOTS:
        keep = np.unique(np.round(np.linspace(0, E - 1, MAX_KNOTS)).astype(int))
        idx = keep
    Ek = idx.size
    codes = (curve[idx] + (dark - black)[None]).astype(np.float32)                        # code above black
    if t[0] != 0:                                                          # synthetic dark knot
        codes = np.concatenate([(dark - black)[None].astype(np.float32), codes])
        kflux = np.concatenate([[0.0], flux[idx]])
        unc = np.concatenate([np.ones((1, H, W), bool), unclipped[idx]])
        Ek += 1
    else:
        kflux = flux[idx].copy()
        unc = unclipped[idx].copy()
        unc[0] = True
    n_knots = unc.sum(0).astype(np.int32)                                  # leading unclipped knots
    # defective pixels (dead, stuck, or a response far from their kind's): no calibration -> UNCALIBRATED
    defective = ~np.isfinite(gfit) | (gfit < 0.25) | (gfit > 4.0)
    n_knots[defective] = 0
    # strictly increasing codes
    codes = np.maximum.accumulate(codes, axis=0) + (np.arange(Ek, dtype=np.float32) * 1e-3)[:, None, None]
    # clipping point: extrapolate the last knots (straight line, or a parabola through the last three where
    # the curve bends up), bounded by the last unclipped and the first clipped exposure
    clip_flux = np.full((H, W), np.nan, np.float32)
    ncl = n_knots < Ek
    nk = n_knots
    lastc = np.take_along_axis(codes, np.clip(nk - 1, 0, Ek - 1)[None], 0)[0]
    prevc = np.take_along_axis(codes, np.clip(nk - 2, 0, Ek - 1)[None], 0)[0]
    lastf = kflux[np.clip(nk - 1, 0, Ek - 1)]
    prevf = kflux[np.clip(nk - 2, 0, Ek - 1)]
    nextf = kflux[np.clip(nk, 0, Ek - 1)]
    slope = (lastf - prevf) / np.maximum(lastc - prevc, 1e-3)
    est = lastf + (top - lastc) * slope
    # parabola through the last three knots (the curve bends up near the neighbours' saturation)
    pc = np.take_along_axis(codes, np.clip(nk - 3, 0, Ek - 1)[None], 0)[0]
    pf = kflux[np.clip(nk - 3, 0, Ek - 1)]
    s1 = (lastc - prevc) / np.maximum(lastf - prevf, 1e-9)
    s0 = (prevc - pc) / np.maximum(prevf - pf, 1e-9)
    curv = (s1 - s0) / np.maximum(lastf - pf, 1e-9)          # second divided difference
    curv = np.where(nk >= 3, np.maximum(curv, 0.0), 0.0)     # only bending up; else linear
    # c(F) = lastc + (F - lastf) * (s1 + curv * (F - prevf)) = top
    a_ = curv
    b_ = s1 + curv * (lastf - prevf)
    c_ = lastc - top
    disc = np.maximum(b_ * b_ - 4 * a_ * c_, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        xq = np.where(a_ > 1e-15, (-b_ + np.sqrt(disc)) / (2 * a_), -c_ / np.maximum(b_, 1e-9))
    est = np.where(np.isfinite(xq) & (xq >= 0), lastf + xq, est)
    est = np.clip(est, lastf, nextf)
    # better, where the first clipped exposure is only partly clipped: its mean code is the mean of a
    # Gaussian censored at the saturation code S; un-censor it (photon-transfer noise) and interpolate
    # between the last unclipped knot and that point
    jf = np.clip(unclipped.sum(0), 0, E - 1)                               # first clipped exposure
    f_j = flux[jf]
    f_next = flux[np.clip(jf + 1, 0, E - 1)]
    m_j = np.take_along_axis(mean, jf[None], 0)[0].astype(np.float64) - black
    s_rel = float(np.median(mean[-1][reg])) - black
    sig = np.sqrt(gain * max(s_rel, 1.0) + (read_noise * gain) ** 2 + 1.0 / 12)
    partial = ncl & (nk >= 2) & ~defective & (m_j < s_rel - 0.05 * sig) & (m_j > lastc)
    if partial.any():
        mu = _uncensor_mean(m_j[partial], s_rel, sig)
        lc, lf = lastc[partial], lastf[partial]
        with np.errstate(divide="ignore", invalid="ignore"):
            e2 = lf + (top - lc) * (f_j[partial] - lf) / (mu - lc)
        ok2 = np.isfinite(e2) & (mu > lc + 1e-3)
        est_p = est[partial]
        est_p[ok2] = np.clip(e2[ok2], lf[ok2], f_next[partial][ok2])
        est[partial] = est_p
    good = ncl & (nk >= 2) & ~defective
    clip_flux[good] = est[good]
    codes_t = np.ascontiguousarray(np.moveaxis(codes, 0, -1))              # (H, W, K)
    q, qs, qo = crosstalk.quantize_codes(codes_t, max_code)
    steps.update(1)
    steps.close()

    calib = crosstalk.CrosstalkCalibration(
        codes_q=q, qscale=qs, qoffset=qo, n_knots=n_knots, knot_flux=kflux.astype(np.float64),
        clip_flux=clip_flux, nd=float(nd), black_level=black, clip_code=clip_code,
        sig_e=fe.astype(np.float32), sigma=sigma.astype(np.float32), alpha=alpha, info={})
    try:
        prof = profiles.make(mask, nd=float(nd), bit_depth=int(bit_depth), clip_code=int(clip_code),
                             black_level=float(black), gain=float(gain), read_noise=float(read_noise),
                             full_well=float(full_well), l_min=float(min(l_min, 0.5 * top)), name=name,
                             crosstalk=calib)
    except profiles.ProfileError as e:
        raise CalibrationError(f"{where}: calibrated parameters are inconsistent: {e}") from None

    # ---- effective ND (Eq. 8), valid ratio (Fig. 8b), DR gain (4.2) ---------------------------------
    nd_eff_map = clip_flux / top
    nd_eff = nd_eff_map[mask]
    valid_nd = nd_eff[np.isfinite(nd_eff)]
    lmin_flux = _flux_at_code(codes, kflux, n_knots, prof.l_min)
    rf, ratio = _valid_ratio_curve(mask, clip_flux, lmin_flux, flux)
    meas = _measured_ratio(sweep, prof)
    g40, f40 = _dr_gain(rf, ratio, 0.4, top)
    g20, f20 = _dr_gain(rf, ratio, 0.2, top)
    # example pixels: attenuated pixels near the centre with the most regular neighbours
    cy, cx = H // 2, W // 2
    score = np.where(mask & border & np.isfinite(nd_eff_map), n_regnb, -1).astype(float)
    yy, xx = np.mgrid[0:H, 0:W]
    score -= 1e-3 * np.hypot(yy - cy, xx - cx) / max(H, W)
    ex = np.argsort(score.ravel())[::-1][:2]
    examples = [(int(e // W), int(e % W)) for e in ex if score.ravel()[e] >= 0]
    k_eff = _kernel_estimate(fe, sigma, top)
    uncal = int(np.sum(n_knots < 2))
    summary = {
        "flats": str(sweep.folder), "width": W, "height": H, "exposures": int(E),
        "frames": int(sweep.frames.sum()), "bit_depth": int(bit_depth), "black_level": round(black, 3),
        "clip_code": int(clip_code), "gain_dn_per_e": round(gain, 6), "read_noise_e": round(read_noise, 3),
        "full_well_e": round(full_well, 1),
        "nd": round(float(nd), 4), "nd_stops": round(math.log2(nd), 3),
        "nd_paper_references": round(float(nd_paper), 4) if math.isfinite(nd_paper) else None,
        "nd_nominal": nd_nominal,
        "nd_eff_median": round(float(np.median(valid_nd)), 4) if valid_nd.size else None,
        "nd_eff_p5": round(float(np.percentile(valid_nd, 5)), 4) if valid_nd.size else None,
        "nd_eff_p95": round(float(np.percentile(valid_nd, 95)), 4) if valid_nd.size else None,
        "nd_eff_min": round(float(valid_nd.min()), 4) if valid_nd.size else None,
        "nd_eff_example": [round(float(nd_eff_map[e]), 4) for e in examples],
        "example_pixels": examples,
        "attenuated_never_clipped": int(np.sum(~np.isfinite(nd_eff))),
        "dr_gain_stops_40": round(g40, 3) if g40 is not None else None,
        "dr_gain_stops_20": round(g20, 3) if g20 is not None else None,
        "dn_scaled_40": round(f40, 1) if f40 is not None else None,
        "dn_scaled_20": round(f20, 1) if f20 is not None else None,
        "dn_max": round(top, 2), "l_min": prof.l_min,
        "reference_pixels_paper": int(paper_att_sel.sum()),
        "reference_paper_rule": "only attenuated neighbours" if sel0.sum() >= 10 else "at most one regular neighbour",
        "kernel_estimate": k_eff,
        "pixels_without_calibration": uncal,
        "defective_pixels": int(defective.sum()),
        "lut_knots": int(Ek),
        "lut_smoothed_pct": round(float(np.mean(smooth_ok)) * 100, 2),
    }
    if nd_nominal:
        summary["nd_vs_nominal_pct"] = round(100 * (nd / nd_nominal - 1), 2)
    calib.info = {k: summary[k] for k in ("nd", "nd_eff_median", "dr_gain_stops_40", "dr_gain_stops_20",
                                          "exposures", "frames", "kernel_estimate")}
    # for the plot: the paper's reference (pixels with only attenuated neighbours: no selection bias until
    # they clip themselves)
    ref_att = np.where(np.isfinite(paper_att), paper_att, h0)
    return CalibrationResult(prof, summary, flux, ref_att, H0, nd_eff, rf, ratio, meas, examples)


def _uncensor_mean(m, s, sig, iters: int = 40):
    """Mean mu of a Gaussian (sd `sig`) whose samples are clipped at `s`, from the clipped samples' mean `m`
    (E[min(X, s)] = mu Phi(z) - sig phi(z) + s (1 - Phi(z)), z = (s - mu) / sig; monotonic in mu)."""
    from math import sqrt
    from scipy.special import ndtr

    def cmean(mu):
        z = (s - mu) / sig
        return mu * ndtr(z) - sig * np.exp(-0.5 * z * z) / sqrt(2 * np.pi) + s * (1 - ndtr(z))
    lo = np.asarray(m, float) - 1.0
    hi = np.full_like(lo, s + 6 * sig)
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        below = cmean(mid) < m
        lo = np.where(below, mid, lo)
        hi = np.where(below, hi, mid)
    return 0.5 * (lo + hi)


def _spill_np(fe, sigma, e):
    """sigma_d(e) for the 8 directions, as crosstalk._spill (linear through 0 below, last slope above)."""
    e = float(e)
    if fe.size < 2 or e <= 0:
        return np.zeros(8)
    if e <= fe[0]:
        return sigma[:, 0] * (e / fe[0]) if fe[0] > 0 else np.zeros(8)
    if e >= fe[-1]:
        sl = (sigma[:, -1] - sigma[:, -2]) / max(fe[-1] - fe[-2], 1e-9)
        return sigma[:, -1] + (e - fe[-1]) * sl
    return np.array([np.interp(e, fe, sigma[k]) for k in range(8)])


def _flux_at_code(codes, kflux, n_knots, level):
    """Per pixel: flux at which the pixel's code first reaches `level` (NaN if never)."""
    Ek, H, W = codes.shape
    out = np.full((H, W), np.nan)
    done = np.zeros((H, W), bool)
    for k in range(1, Ek):
        valid = (k < n_knots) & ~done
        hit = valid & (codes[k] >= level)
        if hit.any():
            c0, c1 = codes[k - 1][hit], codes[k][hit]
            f = kflux[k - 1] + (level - c0) * (kflux[k] - kflux[k - 1]) / np.maximum(c1 - c0, 1e-3)
            out[hit] = np.clip(f, kflux[k - 1], kflux[k])
            done |= hit
    return out


def _valid_ratio_curve(mask, clip_flux, lmin_flux, flux):
    fmax = float(np.nanmax(flux))
    lit = flux[flux > 0]
    grid = np.geomspace(max(float(lit.min()), 1e-3), fmax, 400)
    cf = np.where(np.isfinite(clip_flux), clip_flux, np.inf)
    reg_clip = np.sort(cf[~mask])
    att_clip = np.sort(cf[mask])
    att_lmin = np.sort(np.where(np.isfinite(lmin_flux), lmin_flux, np.inf)[mask])
    n = mask.size
    valid = (reg_clip.size - np.searchsorted(reg_clip, grid, side="right")) \
        + np.searchsorted(att_lmin, grid, side="right") - np.searchsorted(att_clip, grid, side="right")
    return grid, valid / n


def _measured_ratio(sweep, prof):
    from . import validity
    out = np.zeros(len(sweep.exposures))
    for i in range(len(sweep.exposures)):
        raw = np.clip(np.rint(sweep.mean[i]), 0, prof.max_code).astype(np.uint16)
        raw = np.where(sweep.maxcode[i] >= prof.clip_code, sweep.maxcode[i], raw)
        _, st = validity.classify(raw, prof, mode="threshold")
        out[i] = validity.valid_ratio(st)
    return out


def _dr_gain(grid, ratio, level, top):
    """Largest flux where the valid ratio is still >= level (on the bright side), in f-stops over DN_max."""
    above = np.nonzero(ratio >= level)[0]
    if above.size == 0:
        return None, None
    j = above[-1]
    if j + 1 >= grid.size:
        return None, None
    r0, r1 = ratio[j], ratio[j + 1]
    f0, f1 = math.log(grid[j]), math.log(grid[j + 1])
    f = math.exp(f0 + (f1 - f0) * (r0 - level) / max(r0 - r1, 1e-12))
    return math.log2(f / top), f


def _kernel_estimate(fe, sigma, top):
    """3 x 3 kernel (%) from the spill table at ~25 % of the regular range (linear regime)."""
    k = np.zeros((3, 3))
    if fe.size < 2:
        return k.tolist()
    f = 0.25 * top
    for dd, (dy, dx) in enumerate(crosstalk.DIRS):
        k[1 + dy, 1 + dx] = float(np.interp(f, fe, sigma[dd])) / f * 100
    return np.round(k, 4).tolist()


# ======================================================================================================
# Plots
# ======================================================================================================

def write_plots(res: CalibrationResult, prefix) -> list[Path]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    prefix = Path(prefix)
    prefix.parent.mkdir(parents=True, exist_ok=True)
    s = res.summary
    top = s["dn_max"]
    out = []
    calib = res.profile.crosstalk
    codes = calib.codes()
    fig, ax = plt.subplots(figsize=(6, 4), dpi=90)
    phi = res.flux / top
    ok = np.isfinite(res.ref_att)
    ax.plot(phi[ok], res.ref_att[ok], "k-", lw=2, label="reference (attenuated pixels, attenuated nb.)")
    for n, (y, x) in enumerate(res.examples):
        kk = int(calib.n_knots[y, x])
        kf = calib.knot_flux[:kk] / top
        ax.plot(kf, codes[y, x, :kk], "r.-", lw=1, label=f"pixel {n + 1} ({y},{x})")
        ra = np.interp(calib.knot_flux[:kk], res.flux[ok], res.ref_att[ok])
        ax.plot(kf, codes[y, x, :kk] - ra, "g--", lw=1, label=f"correction {n + 1}")
    ax.set_xlabel("normalised flux Φ' (regular DN / DN_max)")
    ax.set_ylabel("code value above black (DN)")
    ax.set_xlim(0, s["nd"] * 1.1)
    ax.set_ylim(0, top * 1.05)
    ax.legend(fontsize=7)
    ax.set_title("Crosstalk calibration (paper Fig. 7)")
    fig.tight_layout()
    p = Path(f"{prefix}_curves.png")
    fig.savefig(p)
    plt.close(fig)
    out.append(p)

    fig, ax = plt.subplots(figsize=(6, 4), dpi=90)
    v = res.nd_eff[np.isfinite(res.nd_eff)]
    ax.hist(v, bins=60, color="tab:blue")
    ax.axvline(s["nd"], color="k", ls="--", label=f"ND {s['nd']:.2f}")
    if s["nd_eff_median"]:
        ax.axvline(s["nd_eff_median"], color="r", ls=":", label=f"median ND_eff {s['nd_eff_median']:.2f}")
    ax.set_xlabel("effective ND factor (Eq. 8)")
    ax.set_ylabel("attenuated pixels")
    ax.legend()
    ax.set_title("Effective ND (paper Fig. 8a)")
    fig.tight_layout()
    p = Path(f"{prefix}_nd_eff.png")
    fig.savefig(p)
    plt.close(fig)
    out.append(p)

    fig, ax = plt.subplots(figsize=(6, 4), dpi=90)
    ax.semilogx(res.ratio_flux / top, res.ratio * 100, "b-", label="calibrated per-pixel limits")
    lit = res.flux > 0
    ax.semilogx(res.flux[lit] / top, res.ratio_measured[lit] * 100, "ko", ms=3, label="sweep (mean frames)")
    for lvl, key in ((40, "dn_scaled_40"), (20, "dn_scaled_20")):
        if s[key]:
            ax.axvline(s[key] / top, color="gray", ls=":")
            ax.text(s[key] / top, lvl + 3, f"{lvl} %: {math.log2(s[key] / top):.2f} stops", fontsize=7)
    ax.set_xlabel("normalised flux Φ' (regular DN / DN_max)")
    ax.set_ylabel("known pixels (%)")
    ax.set_ylim(0, 105)
    ax.legend(fontsize=8)
    ax.set_title("Ratio of known pixels (paper Fig. 8b)")
    fig.tight_layout()
    p = Path(f"{prefix}_valid_ratio.png")
    fig.savefig(p)
    plt.close(fig)
    out.append(p)
    return out


# ======================================================================================================
# CLI
# ======================================================================================================

def run_calibrate(flats, mask_path, output, nd_nominal=None, l_min=100.0, clip_code=None, bit_depth=None,
                  plots=True, progress=True, overwrite=False):
    """The whole `nrhdr calibrate`: read, calibrate, write profile + plots; returns the summary. Existing
    outputs (the profile's files, the plots) are refused before any work unless `overwrite`."""
    out = Path(output)
    if not overwrite:
        io.refuse_existing(profiles.written_files(out) + [out.parent / f"{out.stem}_calib_{k}.png" for k in
                                                          ("curves", "nd_eff", "valid_ratio")])
    try:
        mask = io.read_mask(mask_path)
    except io.ImageFileError as e:
        raise CalibrationError(str(e)) from None
    sweep = read_flats(flats, progress=progress)
    res = calibrate(sweep, mask, nd_nominal=nd_nominal, l_min=l_min, clip_code=clip_code,
                    bit_depth=bit_depth, name=out.stem, mask_name=str(mask_path), progress=progress)
    profiles.save(res.profile, out)
    res.summary["profile"] = str(out)
    if plots:
        res.summary["plots"] = [str(p) for p in write_plots(res, out.parent / f"{out.stem}_calib")]
    return res.summary


def _cmd_calibrate(a) -> int:
    try:
        s = run_calibrate(a.flats, a.mask, a.output, nd_nominal=a.nd_nominal, l_min=a.l_min,
                          clip_code=a.clip_code, bit_depth=a.bit_depth, plots=not a.no_plots,
                          progress=not a.quiet, overwrite=a.force)
    except (CalibrationError, io.OutputExistsError) as e:
        print(f"nrhdr calibrate: error: {e}", file=sys.stderr)
        return 2
    if a.json:
        print(json.dumps(s, indent=2))
    else:
        print(f"wrote {s['profile']}: ND {s['nd']:.3f} ({s['nd_stops']:.2f} stops)"
              + (f", nominal {s['nd_nominal']} ({s['nd_vs_nominal_pct']:+.1f} %)" if s.get("nd_nominal") else ""))
        print(f"  black {s['black_level']:.1f}, clip code {s['clip_code']}, gain {s['gain_dn_per_e']:.4f} DN/e-, "
              f"read noise {s['read_noise_e']:.2f} e-, full well {s['full_well_e']:.0f} e-")
        print(f"  effective ND (Eq. 8): median {s['nd_eff_median']}, 5-95 % {s['nd_eff_p5']} .. {s['nd_eff_p95']}")
        print(f"  dynamic-range gain: {s['dr_gain_stops_40']} stops at 40 % known, {s['dr_gain_stops_20']} "
              f"stops at 20 % known (paper: 2.1 / 2.4)")
        for p in s.get("plots", []):
            print(f"  plot {p}")
    return 0


def _cmd_simulate_flats(a) -> int:
    try:
        if a.profile:
            prof = profiles.load(a.profile)
        else:
            prof = profiles.default(a.height, a.width, seed=a.mask_seed, nd=a.nd)
        model = crosstalk.sensor_model_preset(a.sensor_model, prof.height, prof.width, seed=a.sensor_seed)
    except (ValueError, profiles.ProfileError) as e:
        print(f"nrhdr simulate-flats: error: {e}", file=sys.stderr)
        return 2
    try:
        exp = default_exposures(a.exposures, nd=prof.nd)
        truth = simulate_flats(a.output, prof, model, exposures=exp, frames_per_exposure=a.frames,
                               seed=a.seed, fmt=a.format, progress=not a.quiet, overwrite=a.force)
    except (ValueError, io.OutputExistsError) as e:
        print(f"nrhdr simulate-flats: error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {len(exp) * a.frames} flat frames ({len(exp)} exposures x {a.frames}) to {a.output}/ "
          f"with exposures.csv, mask.png and truth.json (ND {truth['nd']}, sensor model {a.sensor_model})")
    print(f"calibrate: nrhdr calibrate {a.output} --mask {Path(a.output) / 'mask.png'} -o camera.json")
    return 0


def register_cli(sub) -> None:
    p = sub.add_parser("calibrate", help="crosstalk/ND calibration from a flat-field sweep (paper 3.2, 4)",
                       description="Calibrate ND, crosstalk LUT and neighbour kernel from a folder of flat "
                                   "frames + exposures.csv (file,exposure_s); writes a camera profile, plots "
                                   "and a summary.")
    p.add_argument("flats", help="folder with 16-bit TIFF/PNG frames and exposures.csv")
    p.add_argument("--mask", required=True, help="ND mask PNG (255 = attenuated)")
    p.add_argument("-o", "--output", required=True, help="camera profile JSON to write")
    p.add_argument("--nd-nominal", type=float, help="nominal ND factor (reported against the measured one)")
    p.add_argument("--l-min", type=float, default=100.0, help="l_min for the profile and the valid ratio")
    p.add_argument("--clip-code", type=int, help="override the clip code (default: from the saturated frames)")
    p.add_argument("--bit-depth", type=int, help="ADC bits (default: from the largest code)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--no-plots", action="store_true")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.add_argument("--force", action="store_true",
                   help="replace an existing profile (and its mask, calibration, plots) at --output")
    p.set_defaults(func=_cmd_calibrate)

    p = sub.add_parser("simulate-flats", help="write a simulated flat-field sweep (for calibrate)")
    p.add_argument("output", help="folder to write")
    p.add_argument("--profile", help="camera profile to simulate (default: the paper-like default)")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--nd", type=float, default=6.35)
    p.add_argument("--mask-seed", type=int, default=0)
    p.add_argument("--sensor-model", default="prototype", help=f"one of {crosstalk.PRESETS}")
    p.add_argument("--exposures", type=int, default=40, help="number of exposures (incl. dark)")
    p.add_argument("--frames", type=int, default=4, help="frames per exposure")
    p.add_argument("--format", choices=("tiff", "png"), default="tiff")
    p.add_argument("--seed", type=int, default=0, help="noise seed")
    p.add_argument("--sensor-seed", type=int, default=0,
                   help="seed of the sensor's pixel-to-pixel variation: use the same value with "
                        "'nrhdr simulate --sensor-seed' to calibrate the sensor that recorded a clip")
    p.add_argument("-q", "--quiet", action="store_true")
    p.add_argument("--force", action="store_true",
                   help="replace the sweep files in an existing folder (other files there are kept)")
    p.set_defaults(func=_cmd_simulate_flats)
