"""Crosstalk calibration from flat-field exposure sweeps (paper sections 3.2, 4.1, 4.2; docs/CROSSTALK.md).

A sweep is a folder of 16-bit TIFF/PNG frames plus `exposures.csv` (columns `file,exposure_s`), several
frames per exposure, uniform illumination, from dark (exposure 0 recommended) to beyond saturation. It is
what a user captures with the real camera; `simulate_flats` / `nrhdr simulate-flats` writes one from the
sensor model.

`calibrate` is the paper's steps in order, one function each (`read_flats` averages the frames first):
1. `sensor_levels`, `photon_transfer`: black level, clip code, which pixels are clipped; system gain, read
   noise and full well from the temporal noise (EMVA 1288 photon transfer);
2. `reference_curves` (3.2): the attenuated reference (pixels least affected by crosstalk: the paper averages
   attenuated pixels with only attenuated neighbours, fallback one regular neighbour; we also regress, at
   each exposure, every pixel's code on which of its 8 neighbours are of the other kind and take the
   intercept, from all pixels instead of a few, and the 8 slopes: the spill per direction) and the regular
   one; on a regular mask (checkerboard) from the sensor's outer ring;
3. `nd_factor` (3.2, Eq. 1): the ratio of the two references' slopes over exposure; `spill_table`: the
   spill of a source per direction and signal (kernel mode, beyond the paper);
4. `pixel_model`, `pixel_curves`, `pixel_lut`, `clip_points` (3.2, 4.1): each pixel's LUT, its code at every
   exposure where it is not clipped mapped to that exposure's flux, and its clipping point;
5. `effective_nd` (4.1, Eq. 8; Fig. 8a), `valid_pixel_ratio` (4.2, Fig. 8b), `dynamic_range_gain` (4.2: at
   40 % and 20 % known pixels).
The command line is gst_plugins/cli/calibrate.py (`run_calibrate` here is the whole command as a function).
Without a mask, `flats.detect` (through `run_calibrate`'s `find_mask`) finds the ND pixels, the ND and the
defect pixels in the sweep first.
"""
from __future__ import annotations

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


CSV_MAX_BYTES = 16 << 20     # exposures.csv: a line per frame; 16 MiB is over 100000 frames


def read_index(folder, allow_outside: bool = False) -> list[tuple[float, list[Path]]]:
    """Validate `folder/exposures.csv` and return [(exposure_s, [frame paths])] sorted by exposure. The
    frames it names must lie in `folder` unless `allow_outside` (io.resolve_named)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise CalibrationError(f"{folder}: flat-field folder not found")
    csv_path = folder / "exposures.csv"
    if not csv_path.is_file():
        raise CalibrationError(f"{csv_path}: missing (a flat-field folder needs exposures.csv with columns "
                               f"file,exposure_s)")
    try:
        if csv_path.stat().st_size > CSV_MAX_BYTES:
            raise CalibrationError(f"{csv_path}: larger than {CSV_MAX_BYTES} bytes: not a flat-field index")
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
        p = io.resolve_named(csv_path, f"file (line {n})", name, CalibrationError, allow_outside)
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


def _read_frame(p: Path, shape=None, first=None) -> np.ndarray:
    try:
        px = io.read_image(p, np.uint16, shape=shape)
    except io.ImageSizeError as e:
        raise CalibrationError(f"{e}; all frames of a sweep must have one size (that of {first.name})") from None
    except io.ImageFileError as e:
        raise CalibrationError(str(e)) from None
    return px[:, :, 0]


def read_flats(folder, progress: bool = True, allow_outside: bool = False) -> FlatSweep:
    """Read and validate a flat-field folder; per-exposure mean, max and temporal variance per pixel. Every
    frame must have the first frame's size (checked from its header, before decoding)."""
    index = read_index(folder, allow_outside)
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
                fr = _read_frame(p, shape, first)
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


# What simulate_flats writes (outputs.staged_folder: with overwrite, only these are replaced).
FLATS_OUTPUTS = io.owned_by_patterns(r"flat_\d+_\d+\.(tif|png)", r"exposures\.csv", r"mask\.png",
                                     r"truth\.json")


def simulate_flats(out_dir, prof, sensor_model=None, exposures=None, frames_per_exposure: int = 4,
                   seed: int = 0, fmt: str = "tiff", t_sat: float = 0.01, progress: bool = True,
                   overwrite: bool = False, light=None) -> dict:
    """Write a flat-field sweep captured by `prof` (+ `sensor_model`) into `out_dir`: frames, exposures.csv,
    mask.png and truth.json. Flux per second is chosen so that a regular pixel reaches clipping at `t_sat`.
    `light` (r, g, b), colour profiles only (profile.cfa): coloured light, the flux of a photosite is the
    light's channel of its CFA colour x that rate x the exposure (default white, (1, 1, 1)).
    Returns the truth (ND, kernel, light, ...). The folder is written as a whole (outputs.staged_folder: locked,
    nothing left by a stop, a killed run's temporaries removed by the next run): a non-empty `out_dir` is
    refused unless `overwrite`, which replaces only FLATS_OUTPUTS."""
    if frames_per_exposure < 1:
        raise ValueError("frames_per_exposure must be >= 1")
    light = check_light(light, prof)
    ext = {"tiff": ".tif", "tif": ".tif", "png": ".png"}.get(fmt)
    if ext is None:
        raise ValueError(f"format must be tiff or png, got {fmt!r}")
    from . import outputs
    with outputs.staged_folder(out_dir, force=overwrite, owned=FLATS_OUTPUTS) as tmp:
        return _write_flats(tmp, prof, sensor_model, exposures, frames_per_exposure, seed, ext, t_sat,
                            progress, light)


def check_light(light, prof):
    """The light of a simulated sweep as a tuple of 3 floats (None: white); ValueError naming what is wrong
    (not 3 finite values >= 0 with one > 0, or coloured light on a monochrome profile)."""
    from . import cfa as cfas
    if light is None:
        return None
    try:
        v = tuple(float(c) for c in light)
    except (TypeError, ValueError):
        raise ValueError(f"light: need three numbers r, g, b, got {light!r}") from None
    if len(v) != 3 or not all(math.isfinite(c) and c >= 0 for c in v) or max(v) <= 0:
        raise ValueError(f"light: need three finite numbers r, g, b >= 0, not all 0, got {light!r}")
    if not cfas.is_colour(getattr(prof, "cfa", None)) and len(set(v)) > 1:
        raise ValueError(f"light: coloured light {v} needs a colour profile (cfa rggb, bggr, grbg or gbrg), "
                         f"the profile's cfa is {getattr(prof, 'cfa', 'none')!r}")
    return v


def _write_flats(out: Path, prof, sensor_model, exposures, frames_per_exposure, seed, ext, t_sat,
                 progress, light=None) -> dict:
    from tqdm import tqdm
    from . import sensor
    exp = default_exposures(nd=prof.nd, t_sat=t_sat) if exposures is None else np.asarray(exposures, float)
    rate = (prof.clip_code - prof.black_level) / t_sat            # DN per second for a regular pixel
    rng = np.random.default_rng(seed)
    rows = []
    h, w = prof.mask.shape
    share = np.ones((h, w))
    if light is not None:
        from . import cfa as cfas
        share = (np.asarray(light, float)[cfas.channel_index(prof.cfa, h, w)] if cfas.is_colour(prof.cfa)
                 else np.full((h, w), light[0]))
    with tqdm(total=len(exp) * frames_per_exposure, desc="simulating flats", unit="frame",
              disable=not progress, file=sys.stderr) as bar:
        for i, t in enumerate(exp):
            flux = share * (rate * t)
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
    if light is not None or getattr(prof, "cfa", "none") != "none":
        truth["cfa"] = prof.cfa
        truth["light"] = list(light) if light is not None else [1.0, 1.0, 1.0]
    (out / "truth.json").write_text(json.dumps(truth, indent=2) + "\n")
    return truth


# ======================================================================================================
# Calibration: the steps of paper sections 3.2, 4.1 and 4.2, in the order `calibrate` runs them
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


def _trimmed_mean(v):
    """Mean without the 0.5 % largest values (hot pixels); a mean, not a median: the variance of a few
    frames is chi-square skewed."""
    v = v.ravel()
    if v.size == 0:
        return float("nan")
    return float(np.mean(v[v <= np.percentile(v, 99.5)]))


def check_mask(sweep: FlatSweep, mask, mask_name: str = "mask") -> np.ndarray:
    """The ND mask as bool (True = attenuated); CalibrationError unless it fits the frames and holds both
    kinds of pixel."""
    mask = np.asarray(mask, bool)
    H, W = sweep.shape
    if mask.shape != (H, W):
        raise CalibrationError(f"{mask_name}: mask is {mask.shape[1]}x{mask.shape[0]} but the frames in "
                               f"{sweep.folder} are {W}x{H}")
    if mask.all() or not mask.any():
        raise CalibrationError(f"{mask_name}: the mask must contain both attenuated (255) and regular (0) "
                               f"pixels")
    return mask


# ---- step 1: sensor levels (black level, clip code, clipped pixels) -------------------------------------

@dataclasses.dataclass
class SensorLevels:
    """Black and clip levels of the sweep and each pixel's signal above its dark code."""
    black: float                   # black level (DN)
    dark: np.ndarray               # (H, W) per-pixel dark code (DN)
    clip_code: int
    bit_depth: int
    max_code: int
    top: float                     # DN_max of the paper (4.1): clip code above black
    signal: np.ndarray             # (E, H, W) float32 mean code minus the pixel's dark code
    unclipped: np.ndarray          # (E, H, W) not clipped at that exposure (once clipped, stays clipped)
    lit: np.ndarray                # (E,) exposure > 0
    var_reg: np.ndarray            # (E,) temporal variance of the regular pixels (trimmed mean)


def sensor_levels(sweep: FlatSweep, mask: np.ndarray, clip_code: int | None = None,
                  bit_depth: int | None = None) -> SensorLevels:
    """Black level (the dark frame, else the regular pixels extrapolated to zero exposure) and clip code
    (just below the saturated frames, found where the temporal variance collapses; EMVA 1288 style)."""
    where = str(sweep.folder)
    t = sweep.exposures.astype(np.float64)
    mean, maxc, tvar = sweep.mean, sweep.maxcode, sweep.tvar
    reg = ~mask
    max_seen = int(maxc.max())
    if bit_depth is None:
        bit_depth = next(b for b in (8, 10, 12, 14, 16) if (1 << b) - 1 >= max_seen)
    max_code = (1 << bit_depth) - 1
    first_lit = 1 if t[0] == 0 else 0
    hot = np.mean(maxc[0] >= max(max_seen - 3, 1))
    if hot > 0.5 or np.mean(maxc[first_lit] >= max(max_seen - 3, 1)) > 0.9:
        raise CalibrationError(f"{where}: the sweep is saturated everywhere: already at the shortest exposure "
                               f"({t[first_lit]:g} s) most pixels sit at the largest code {max_seen}; the "
                               f"sweep must start dark")
    if t[0] == 0:
        dark = mean[0].astype(np.float64)
        black = float(np.median(dark))
    else:
        m0, m1 = float(np.median(mean[0][reg])), float(np.median(mean[1][reg]))
        black = m0 - t[0] * (m1 - m0) / (t[1] - t[0])
        dark = np.full(sweep.shape, black)
    black = float(max(black, 0.0))
    var_reg = np.array([_trimmed_mean(tvar[i][reg]) for i in range(len(t))])
    if clip_code is None:
        clip_code = _clip_code_from_saturation(sweep, reg, var_reg, max_code)
    clip_code = int(clip_code)
    if not (black + 10 < clip_code <= max_code):
        raise CalibrationError(f"{where}: inconsistent levels: black {black:.1f}, clip code {clip_code}, "
                               f"{bit_depth}-bit data")
    unclipped = np.logical_and.accumulate(maxc < clip_code, axis=0)      # (E, H, W), once clipped stays
    lit = t > 0
    if np.mean(unclipped[np.argmax(lit)][reg]) < 0.5:
        raise CalibrationError(f"{where}: the sweep is saturated everywhere: at the shortest exposure with "
                               f"light ({t[np.argmax(lit)]:g} s) most regular pixels are already clipped")
    signal = mean - dark[None].astype(np.float32)
    return SensorLevels(black, dark, clip_code, bit_depth, max_code, clip_code - black, signal, unclipped,
                        lit, var_reg)


def _clip_code_from_saturation(sweep: FlatSweep, reg, var_reg, max_code) -> int:
    """Clip code: 3 sigma below the 1st percentile of the regular pixels at the longest exposure, which
    must be saturated (their temporal variance has collapsed below a quarter of its peak)."""
    t = sweep.exposures
    if not (var_reg[-1] < 0.25 * var_reg.max()):
        raise CalibrationError(f"{sweep.folder}: the sweep does not reach saturation: the regular pixels' "
                               f"temporal variance at the longest exposure ({t[-1]:g} s) is still "
                               f"{var_reg[-1]:.1f} DN^2 (peak {var_reg.max():.1f}); extend the sweep beyond "
                               f"saturation or pass --clip-code")
    sat = sweep.mean[-1][reg]
    sig = math.sqrt(float(np.median(sweep.tvar[-1][reg])))
    return int(min(max_code - 1, math.floor(np.percentile(sat, 1) - 3 * sig)))


# ---- step 2: photon transfer (EMVA 1288) ----------------------------------------------------------------

@dataclasses.dataclass
class PhotonTransfer:
    gain: float                    # DN per electron
    read_noise: float              # electrons
    full_well: float               # electrons


def photon_transfer(sweep: FlatSweep, mask: np.ndarray, lv: SensorLevels) -> PhotonTransfer:
    """System gain, read noise and full well from the photon transfer curve of the unclipped regular
    pixels (EMVA 1288): temporal variance = gain x signal + (gain x read noise)^2 + 1/12, fitted where the
    signal is below 70 % of DN_max."""
    reg = ~mask
    t = sweep.exposures
    d, unclipped = lv.signal, lv.unclipped
    E = len(t)
    mu = np.array([float(np.median(d[i][reg & unclipped[i]])) if np.any(reg & unclipped[i]) else np.nan
                   for i in range(E)])
    var_unc = np.array([_trimmed_mean(sweep.tvar[i][reg & unclipped[i]]) for i in range(E)])
    ptc = np.isfinite(mu) & (mu < 0.7 * lv.top) & (var_unc > 0)
    gain, read_noise = 4095.0 / 8000.0, 2.0
    if ptc.sum() >= 3:
        k, v0 = np.polyfit(mu[ptc], var_unc[ptc], 1)
        if k > 0 and math.isfinite(k):
            gain = float(k)
            read_noise = math.sqrt(max(float(lv.var_reg[0] if t[0] == 0 else v0) - 1.0 / 12.0, 0.0)) / gain
    # the ADC may clip before the full well: the full well is at least the saturated level (+ margin)
    sat_level = float(np.median(sweep.mean[-1][reg])) - lv.black
    full_well = max(sat_level, lv.top + 3.0 * read_noise * gain + 1.0) / gain
    return PhotonTransfer(gain, read_noise, full_well)


# ---- step 3: reference curves (paper 3.2) ---------------------------------------------------------------

@dataclasses.dataclass
class ReferenceCurves:
    """The two references of paper 3.2 per exposure (signal above dark, NaN where unavailable)."""
    att: np.ndarray                # (E,) attenuated pixel with only attenuated neighbours (regression intercept)
    reg: np.ndarray                # (E,) regular pixel with only regular neighbours (regression intercept)
    spill: np.ndarray              # (E, 8) extra signal of an attenuated pixel per regular neighbour, by direction
    frac_att: np.ndarray           # (E,) share of the attenuated pixels not clipped
    frac_reg: np.ndarray
    paper_att: np.ndarray          # (E,) the paper's literal references: mean of the selected pixels
    paper_reg: np.ndarray
    paper_att_sel: np.ndarray      # (H, W) the paper's attenuated reference pixels
    paper_rule: str
    ind_reg: np.ndarray            # (8, H, W) regular-neighbour indicators (for attenuated targets)
    ind_att: np.ndarray            # (8, H, W) attenuated-neighbour indicators (for regular targets)
    inner: np.ndarray              # (H, W) not on the sensor's outer ring


def reference_curves(lv: SensorLevels, mask: np.ndarray, min_rows: int = 30) -> ReferenceCurves:
    """The attenuated reference (paper 3.2: attenuated pixels with only attenuated neighbours, fallback one
    regular neighbour) and the regular one (regular pixels with at most one attenuated neighbour). Besides
    the paper's averages, at each exposure every pixel's signal is regressed on which of its 8 neighbours
    are of the other kind: the intercept is the reference from all pixels instead of a few, and for the
    attenuated pixels the 8 slopes are the spill of a regular neighbour per direction (kernel mode). On a
    regular mask (every interior pixel of a kind has the same neighbours) that regression cannot separate
    the reference from the spill; there the sensor's outer ring does (_ring_reference)."""
    H, W = mask.shape
    reg = ~mask
    inner = np.zeros((H, W), bool)
    inner[1:-1, 1:-1] = True
    ind_reg = _neighbour_indicators(mask, True)       # for attenuated targets
    ind_att = _neighbour_indicators(mask, False)      # for regular targets
    att_idx, reg_idx = np.nonzero(mask & inner), np.nonzero(reg & inner)
    Xa = np.column_stack([np.ones(att_idx[0].size)] + [ind_reg[k][att_idx] for k in range(8)])
    Xr = np.column_stack([np.ones(reg_idx[0].size)] + [ind_att[k][reg_idx] for k in range(8)])
    n_regnb, n_attnb = ind_reg.sum(0), ind_att.sum(0)
    E = len(lv.lit)
    h0, H0, paper_att, paper_reg = (np.full(E, np.nan) for _ in range(4))
    b = np.full((E, 8), np.nan)
    frac_att, frac_reg = np.zeros(E), np.zeros(E)
    sel0 = mask & inner & (n_regnb == 0)
    only_att = sel0.sum() >= 10
    paper_att_sel = sel0 if only_att else (mask & inner & (n_regnb <= 1))
    paper_reg_sel = reg & inner & (n_attnb <= 1)
    regular_mask = att_idx[0].size > 0 and reg_idx[0].size > 0 and not (np.ptp(Xa, 0).any() or np.ptp(Xr, 0).any())
    for i in range(E):
        if not lv.lit[i]:
            h0[i] = H0[i] = paper_att[i] = paper_reg[i] = 0.0
            b[i] = 0.0
            continue
        d, u = lv.signal[i], lv.unclipped[i]
        ua = u[att_idx]
        frac_att[i] = ua.mean()
        ur = u[reg_idx]
        frac_reg[i] = ur.mean()
        if regular_mask:
            h0[i], b[i] = _ring_reference(d, u, mask, ind_reg, inner, min_rows)
            H0[i] = _ring_reference(d, u, reg, ind_att, inner, min_rows)[0]
        else:
            if ua.sum() >= min_rows:
                h0[i], b[i] = _attenuated_regression(Xa[ua], d[att_idx][ua], b[i])
            if ur.sum() >= min_rows:
                H0[i] = _robust_lstsq(Xr[ur], d[reg_idx][ur])[0]
        for sel, out in ((paper_att_sel, paper_att), (paper_reg_sel, paper_reg)):
            s = sel & u
            if s.sum() >= 3:
                out[i] = float(np.mean(d[s]))
    # tiny sensors: where the regression is impossible, the paper's references
    h0 = np.where(np.isfinite(h0), h0, paper_att)
    H0 = np.where(np.isfinite(H0), H0, paper_reg)
    rule = "only attenuated neighbours" if only_att else "at most one regular neighbour"
    return ReferenceCurves(h0, H0, b, frac_att, frac_reg, paper_att, paper_reg, paper_att_sel, rule,
                           ind_reg, ind_att, inner)


def _attenuated_regression(X, y, spill_nan):
    """(intercept, 8 spills) of y ~ X; with too few pixels per direction, the median of the pixels without
    a regular neighbour (NaN if none) and no spills."""
    if np.all(X[:, 1:].sum(0) >= 5):
        c = _robust_lstsq(X, y)
        return c[0], c[1:]
    alone = X[:, 1:].sum(1) == 0
    return (float(np.median(y[alone])) if np.any(alone) else np.nan), spill_nan


# The four sides of the sensor's outer ring: (name, directions of the neighbours its pixels lack).
_SIDES = (("top", lambda dy, dx: dy == -1), ("bottom", lambda dy, dx: dy == 1),
          ("left", lambda dy, dx: dx == -1), ("right", lambda dy, dx: dx == 1))


def _ring_reference(d, u, kind, ind, inner, min_rows, iters: int = 20):
    """(reference, (8,) spill per direction) at one exposure on a regular mask, from the sensor's outer ring:
    a ring pixel lacks the neighbours beyond the edge, so it gets less crosstalk (or, regular, loses less)
    than the interior pixels of its kind. With d_int(p) = ref + s(p) C inside (C: the crosstalk of the
    full neighbourhood, s(p): its smooth amplitude over the sensor, e.g. glue thickness) a quadratic
    trend P(p) fitted to the interior and extrapolated to the ring gives each side's deficit
    Delta_side = P - d = s_side c_side, and since the sides' missing neighbours add up to the whole
    neighbourhood, sum_side Delta_side (P_c - ref) / (P_side - ref) = P_c - ref (P_c: the interior mean),
    solved for ref by fixed-point iteration. Missing neighbours are taken as of the pixel's own kind (no
    net crosstalk with it, as for a conserving kernel). NaN where too few pixels are unclipped."""
    H, W = kind.shape
    nan = (np.nan, np.full(8, np.nan))
    yy, xx = np.mgrid[0:H, 0:W]
    xn, yn = xx / max(W - 1, 1) - 0.5, yy / max(H - 1, 1) - 0.5
    basis = np.stack([np.ones((H, W)), xn, yn, xn * xn, xn * yn, yn * yn], -1)
    si = kind & inner & u
    if si.sum() < max(min_rows, 12):
        return nan
    P = basis @ _robust_lstsq(basis[si], d[si].astype(np.float64))
    pc = float(np.mean(P[si]))
    other = [k for k in range(8) if ind[k][kind & inner].max() > 0]          # neighbours of the other kind
    corner = ((yy == 0) | (yy == H - 1)) & ((xx == 0) | (xx == W - 1))
    sides = []
    for name, lacks in _SIDES:
        dirs = [k for k in other if lacks(*crosstalk.DIRS[k])]
        ring = {"top": yy == 0, "bottom": yy == H - 1, "left": xx == 0, "right": xx == W - 1}[name]
        sel = ring & ~corner & kind & u
        if dirs and sel.sum() >= 5:
            sides.append((dirs, float(np.mean(P[sel] - d[sel])), float(np.mean(P[sel]))))
    if sorted(k for dirs, _, _ in sides for k in dirs) != sorted(other):      # each neighbour exactly once
        return nan
    ref = pc - sum(delta for _, delta, _ in sides)
    for _ in range(iters):                                                    # amplitude of each side
        rho = [(pc - ref) / (ps - ref) if abs(ps - ref) > 1e-6 * max(abs(pc), 1.0) else 1.0
               for _, _, ps in sides]
        rho = [r if 0.25 < r < 4.0 else 1.0 for r in rho]
        ref = pc - sum(delta * r for (_, delta, _), r in zip(sides, rho))
    spill = np.zeros(8)
    for (dirs, delta, _), r in zip(sides, rho):
        spill[dirs] = delta * r / len(dirs)
    return ref, spill


# ---- step 4: ND factor (paper 3.2, Eq. 1) ---------------------------------------------------------------

@dataclasses.dataclass
class NDFactor:
    nd: float                      # ratio of the two references' slopes over exposure
    nd_paper: float                # the same from the paper's literal references (NaN if unavailable)
    kappa_reg: float               # slope of the regular reference (DN/s): flux = kappa_reg x exposure


def nd_factor(t: np.ndarray, refs: ReferenceCurves, top: float, where: str = "flats") -> NDFactor:
    """ND = slope of the regular reference over exposure / slope of the attenuated one (paper 3.2), each a
    least-squares line through the origin over the exposures where nearly all pixels of its kind are
    unclipped (relaxed step by step for coarse sweeps) and the reference is well above the noise."""
    t = np.asarray(t, np.float64)
    lo_lim = max(20.0, 0.01 * top)
    for need in (0.99, 0.95, 0.8, 0.0):
        ok_r = np.isfinite(refs.reg) & (refs.reg > lo_lim) & (refs.reg < 0.7 * top) & (refs.frac_reg >= need)
        if ok_r.any():
            break
    for need in (0.99, 0.95, 0.8, 0.0):
        ok_a = np.isfinite(refs.att) & (refs.att > lo_lim / 2) & (refs.att < 0.8 * top) & (refs.frac_att >= need)
        if ok_a.any():
            break
    kappa_reg = _slope_through_origin(t, refs.reg, ok_r)
    kappa_att = _slope_through_origin(t, refs.att, ok_a)
    if not (kappa_reg > 0 and kappa_att > 0):
        raise CalibrationError(f"{where}: cannot measure the ND factor: need an exposure where the regular "
                               f"pixels are between {lo_lim:.0f} and {0.7 * top:.0f} DN and one where the "
                               f"attenuated pixels are between {lo_lim / 2:.0f} and {0.8 * top:.0f} DN, all "
                               f"unclipped (found {int(ok_r.sum())} and {int(ok_a.sum())}); use a denser sweep")
    nd = kappa_reg / kappa_att
    pr = np.isfinite(refs.paper_reg) & (refs.paper_reg > lo_lim) & (refs.paper_reg < 0.7 * top)
    pa = np.isfinite(refs.paper_att) & (refs.paper_att > lo_lim / 2) & (refs.paper_att < 0.8 * top)
    nd_paper = _slope_through_origin(t, refs.paper_reg, pr) / _slope_through_origin(t, refs.paper_att, pa)
    if nd < 1:
        raise CalibrationError(f"{where}: measured ND {nd:.3f} < 1: is the mask inverted (255 must mark "
                               f"attenuated pixels)?")
    return NDFactor(nd, nd_paper, kappa_reg)


# ---- step 5: per-direction spill table (kernel mode, beyond the paper) ----------------------------------

def spill_table(flux: np.ndarray, refs: ReferenceCurves, lit: np.ndarray, nd: float):
    """(fe, sigma): sigma[d, j] is the signal a source of flux fe[j] spills into its neighbour in direction
    d. The regression's slope b_d(F) is the spill of a regular source minus that of an attenuated one
    (F / ND), so sigma(F) = b(F) + sigma(F / ND), unrolled from the dimmest exposure; beyond the table it
    continues with the slope of its last quarter (far beyond the knee spill and blooming are linear)."""
    okb = lit & np.all(np.isfinite(refs.spill), axis=1) & (refs.frac_att >= 0.9)
    fe = flux[okb]
    bb = refs.spill[okb]
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
        return np.array([0.0, 1.0]), np.zeros((8, 2))
    # a brighter source never spills less; beyond the table (where the regression would be biased by the
    # pixels that clip first) continue with the slope of its last quarter
    sigma = np.maximum.accumulate(sigma, axis=1)
    kk = max(3, fe.size // 4) if fe.size >= 3 else fe.size
    xs = fe[-kk:] - fe[-kk:].mean()
    slope_end = np.maximum((sigma[:, -kk:] - sigma[:, -kk:].mean(1, keepdims=True)) @ xs
                           / max(float(xs @ xs), 1e-12), 0.0)
    f_far = fe[-1] * 100.0
    fe = np.append(fe, f_far)
    sigma = np.concatenate([sigma, (sigma[:, -1] + slope_end * (f_far - fe[-2]))[:, None]], axis=1)
    return fe, sigma


# ---- step 6: each pixel's curve (paper 3.2: a correction per pixel and code value) -----------------------

@dataclasses.dataclass
class PixelFit:
    gain: np.ndarray               # (H, W) own-signal gain g (PRNU, flat-field non-uniformity)
    alpha: np.ndarray              # (H, W) float32 crosstalk amplitude against the population
    quad: np.ndarray               # (H, W) mild non-linearity c
    model: np.ndarray              # (E, H, W) float32 the fitted curve at every exposure
    chi2: np.ndarray               # (H, W) reduced chi^2 of the fit over the pixel's unclipped exposures
    n_fit: np.ndarray              # (H, W) number of those exposures


def _direct_signal(mask, flux_i, nd):
    """A pixel's own signal without crosstalk (Eq. 2): F for a regular pixel, F / ND for an attenuated one."""
    return np.where(mask, flux_i / nd, flux_i)


def pixel_model(sweep: FlatSweep, mask, lv: SensorLevels, ptc: PhotonTransfer, refs: ReferenceCurves,
                flux, nd, fe, sigma, prior_g=0.02, prior_alpha=0.5, prior_c=0.0002) -> PixelFit:
    """Per pixel: d = g E + alpha Y + c E^2 / DN_max over its unclipped lit exposures, E its direct signal,
    Y the population crosstalk of its neighbourhood from the spill table; weighted by the inverse noise of
    each mean (photon transfer), Gaussian priors g ~ 1 +- prior_g, alpha ~ 1 +- prior_alpha, c ~ 0 +-
    prior_c. In the linear range Y is proportional to E, so the priors split a pixel's excess mostly into
    crosstalk, as it should."""
    E, (H, W) = len(flux), mask.shape
    A, r, Ys = _pixel_normal_equations(sweep, mask, lv, ptc, refs, flux, nd, fe, sigma)
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
    del A, r
    coef = np.where(np.isfinite(coef), coef, np.array([1.0, 1.0, 0.0]))
    gfit, alpha, qfit = coef[..., 0], np.clip(coef[..., 1], 0.0, 5.0), coef[..., 2]
    chi, cnt = np.zeros((H, W)), np.zeros((H, W))
    for i in range(E):
        if not lv.lit[i]:
            continue
        u = lv.unclipped[i]
        Ep = _direct_signal(mask, flux[i], nd)
        fit = gfit * Ep + alpha * Ys[i] + qfit * Ep * Ep / lv.top
        # noise of the mean from the photon transfer curve (a few frames' own variance is too noisy)
        var = (ptc.gain * np.maximum(fit, 0) + (ptc.read_noise * ptc.gain) ** 2 + 1.0 / 12) / sweep.frames[i] + 0.05
        chi += np.where(u, (lv.signal[i] - fit) ** 2 / var, 0)
        cnt += u
        Ys[i] = fit                                     # reuse: the model curve
    return PixelFit(gfit, alpha.astype(np.float32), qfit, Ys, chi / np.maximum(cnt, 1), cnt)


def _pixel_normal_equations(sweep, mask, lv, ptc, refs, flux, nd, fe, sigma):
    """(A (H, W, 3, 3), r (H, W, 3), Y (E, H, W) float32) of pixel_model's weighted least squares; Y is each
    pixel's population crosstalk (spill of its regular neighbours into it, or its own into them)."""
    E, (H, W) = len(flux), mask.shape
    reg = ~mask
    b_model = np.zeros((E, 8))
    for i in range(E):
        if lv.lit[i]:
            b_model[i] = _spill_np(fe, sigma, flux[i]) - _spill_np(fe, sigma, flux[i] / nd)
    A, r = np.zeros((H, W, 3, 3)), np.zeros((H, W, 3))
    Ys = np.zeros((E, H, W), np.float32)
    for i in range(E):
        if not lv.lit[i]:
            continue
        Y = (np.tensordot(b_model[i], refs.ind_reg, axes=1) * mask
             - np.tensordot(b_model[i], refs.ind_att, axes=1) * reg)
        Ys[i] = Y
        Ep = _direct_signal(mask, flux[i], nd)
        wgt = np.where(lv.unclipped[i], sweep.frames[i] / (ptc.gain * np.maximum(Ep, 0)
                                                            + (ptc.read_noise * ptc.gain) ** 2 + 1.0 / 12), 0)
        basis = (Ep, Y, Ep * Ep / lv.top)
        for j in range(3):
            r[:, :, j] += wgt * basis[j] * lv.signal[i]
            for k in range(j, 3):
                A[:, :, j, k] += wgt * basis[j] * basis[k]
    for j in range(3):
        for k in range(j):
            A[:, :, j, k] = A[:, :, k, j]
    return A, r, Ys


def pixel_curves(lv: SensorLevels, fit: PixelFit, smooth_chi2: float = 1.5, smooth_taps: int = 5):
    """(curve (E, H, W) float32, smooth_ok (H, W)): each pixel's signal at every exposure. Where the model
    explains the pixel's unclipped exposures within their noise (reduced chi^2 < smooth_chi2, at least 3)
    the model itself (it averages the flats' noise over all exposures); otherwise the model plus the pixel's
    residual averaged over `smooth_taps` neighbouring exposures (keeps systematic deviations); beyond
    clipping the model (for the clip point)."""
    E = len(lv.lit)
    lit, d, unclipped, Ys = lv.lit, lv.signal, lv.unclipped, fit.model
    smooth_ok = (fit.n_fit >= 3) & (fit.chi2 < smooth_chi2)
    res = np.where(unclipped & lit[:, None, None], d - Ys, 0).astype(np.float32)
    wgt = (unclipped & lit[:, None, None]).astype(np.float32)
    rs = np.zeros_like(res)
    ws = np.zeros_like(wgt)
    for sh in range(-smooth_taps // 2 + 1, smooth_taps // 2 + 1):
        lo, hi = max(0, -sh), min(E, E - sh)
        rs[lo:hi] += res[lo + sh:hi + sh]
        ws[lo:hi] += wgt[lo + sh:hi + sh]
    curve = np.where(smooth_ok[None], Ys, Ys + rs / np.maximum(ws, 1)).astype(np.float32)
    curve = np.where(unclipped, curve, Ys)
    curve[~lit] = d[~lit]
    return curve, smooth_ok


# ---- step 7: per-pixel LUT (paper 3.2) and clipping points (paper 4.1) ---------------------------------

@dataclasses.dataclass
class PixelLUT:
    codes: np.ndarray              # (K, H, W) float32 code above black at each knot, strictly increasing
    knot_flux: np.ndarray          # (K,) flux (regular DN) of each knot
    n_knots: np.ndarray            # (H, W) int32 leading unclipped knots (0: defective, uncalibrated)
    defective: np.ndarray          # (H, W)


def pixel_lut(curve: np.ndarray, lv: SensorLevels, flux: np.ndarray, pixel_gain: np.ndarray) -> PixelLUT:
    """Each pixel's code at every exposure (at most MAX_KNOTS, evenly picked) mapped to that exposure's
    flux: the compensation LUT of paper 3.2, inverted by nrcrosstalk. A synthetic dark knot when the sweep
    has no dark frame; defective pixels (gain g outside 0.25..4: dead, stuck) get no knots."""
    E = len(flux)
    H, W = lv.dark.shape
    idx = np.arange(E)
    if E > MAX_KNOTS:
        idx = np.unique(np.round(np.linspace(0, E - 1, MAX_KNOTS)).astype(int))
    Ek = idx.size
    codes = (curve[idx] + (lv.dark - lv.black)[None]).astype(np.float32)                # code above black
    if lv.lit[0]:                                                          # synthetic dark knot
        codes = np.concatenate([(lv.dark - lv.black)[None].astype(np.float32), codes])
        kflux = np.concatenate([[0.0], flux[idx]])
        unc = np.concatenate([np.ones((1, H, W), bool), lv.unclipped[idx]])
        Ek += 1
    else:
        kflux = flux[idx].copy()
        unc = lv.unclipped[idx].copy()
        unc[0] = True
    n_knots = unc.sum(0).astype(np.int32)                                  # leading unclipped knots
    defective = ~np.isfinite(pixel_gain) | (pixel_gain < 0.25) | (pixel_gain > 4.0)
    n_knots[defective] = 0
    codes = np.maximum.accumulate(codes, axis=0) + (np.arange(Ek, dtype=np.float32) * 1e-3)[:, None, None]
    return PixelLUT(codes, kflux, n_knots, defective)


def clip_points(lut: PixelLUT, sweep: FlatSweep, mask: np.ndarray, lv: SensorLevels, ptc: PhotonTransfer,
                flux: np.ndarray) -> np.ndarray:
    """(H, W) float32 flux at which each pixel reaches DN_max (NaN: never clipped in the sweep, or
    uncalibrated): paper 4.1's clipping point, DN_valid x ND in regular DN. Extrapolated from the last
    knots (a line, or a parabola through the last three where the curve bends up near the neighbours'
    saturation), within the last unclipped and the first clipped exposure; where that first clipped
    exposure is only partly clipped, from its un-censored mean instead."""
    codes, kflux, nk, top = lut.codes, lut.knot_flux, lut.n_knots, lv.top
    Ek = codes.shape[0]
    at = lambda k: np.clip(k, 0, Ek - 1)                                  # noqa: E731
    lastc = np.take_along_axis(codes, at(nk - 1)[None], 0)[0]
    prevc = np.take_along_axis(codes, at(nk - 2)[None], 0)[0]
    pc = np.take_along_axis(codes, at(nk - 3)[None], 0)[0]
    lastf, prevf, nextf, pf = kflux[at(nk - 1)], kflux[at(nk - 2)], kflux[at(nk)], kflux[at(nk - 3)]
    slope = (lastf - prevf) / np.maximum(lastc - prevc, 1e-3)
    est = lastf + (top - lastc) * slope
    # parabola c(F) = lastc + (F - lastf) * (s1 + curv * (F - prevf)) = top, only bending up
    s1 = (lastc - prevc) / np.maximum(lastf - prevf, 1e-9)
    s0 = (prevc - pc) / np.maximum(prevf - pf, 1e-9)
    curv = (s1 - s0) / np.maximum(lastf - pf, 1e-9)          # second divided difference
    curv = np.where(nk >= 3, np.maximum(curv, 0.0), 0.0)
    b_ = s1 + curv * (lastf - prevf)
    c_ = lastc - top
    disc = np.maximum(b_ * b_ - 4 * curv * c_, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        xq = np.where(curv > 1e-15, (-b_ + np.sqrt(disc)) / (2 * curv), -c_ / np.maximum(b_, 1e-9))
    est = np.where(np.isfinite(xq) & (xq >= 0), lastf + xq, est)
    est = np.clip(est, lastf, nextf)
    good = (nk < Ek) & (nk >= 2) & ~lut.defective
    _clip_from_partly_clipped(est, good, lastc, lastf, sweep, mask, lv, ptc, flux)
    clip_flux = np.full(nk.shape, np.nan, np.float32)
    clip_flux[good] = est[good]
    return clip_flux


def _clip_from_partly_clipped(est, good, lastc, lastf, sweep, mask, lv, ptc, flux) -> None:
    """Refine `est` in place where the first clipped exposure is only partly clipped: its mean code is
    the mean of a Gaussian censored at the saturation code; un-censor it (photon-transfer noise) and
    interpolate between the last unclipped knot and that point."""
    E = len(flux)
    jf = np.clip(lv.unclipped.sum(0), 0, E - 1)                            # first clipped exposure
    f_j = flux[jf]
    f_next = flux[np.clip(jf + 1, 0, E - 1)]
    m_j = np.take_along_axis(sweep.mean, jf[None], 0)[0].astype(np.float64) - lv.black
    s_rel = float(np.median(sweep.mean[-1][~mask])) - lv.black
    sig = np.sqrt(ptc.gain * max(s_rel, 1.0) + (ptc.read_noise * ptc.gain) ** 2 + 1.0 / 12)
    partial = good & (m_j < s_rel - 0.05 * sig) & (m_j > lastc)
    if not partial.any():
        return
    mu = _uncensor_mean(m_j[partial], s_rel, sig)
    lc, lf = lastc[partial], lastf[partial]
    with np.errstate(divide="ignore", invalid="ignore"):
        e2 = lf + (lv.top - lc) * (f_j[partial] - lf) / (mu - lc)
    ok2 = np.isfinite(e2) & (mu > lc + 1e-3)
    est_p = est[partial]
    est_p[ok2] = np.clip(e2[ok2], lf[ok2], f_next[partial][ok2])
    est[partial] = est_p


# ---- step 8: effective ND (paper 4.1, Eq. 8), valid-pixel ratio and dynamic-range gain (paper 4.2) ----

def effective_nd(clip_flux: np.ndarray, top: float) -> np.ndarray:
    """ND_eff(m, n) = DN_valid(m, n) x ND / DN_max = DN_scaled(m, n) / DN_max (Eq. 8): a pixel's clipping
    point in regular DN (clip_points) over DN_max. NaN where the pixel never clipped."""
    return clip_flux / top


def valid_pixel_ratio(mask, clip_flux, lmin_flux, flux):
    """(grid, ratio): the share of valid pixels over flux (paper Fig. 8b, 4.2), from each pixel's limits: a
    regular pixel is valid below its clipping point, an attenuated one between the flux where it reaches
    l_min and its clipping point. `grid`: 400 fluxes, log-spaced over the sweep's lit range."""
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


def dynamic_range_gain(grid, ratio, level, top):
    """(stops, DN_scaled) of paper 4.2: the largest flux DN_scaled where the valid ratio is still >= level
    (bright side, log-interpolated), and the gain log2(DN_scaled / DN_max); (None, None) if never reached."""
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


# ---- calibrate: the steps in order ----------------------------------------------------------------------

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
              prior_c: float = 0.0002, defects: np.ndarray | None = None, cfa: str = "none") -> CalibrationResult:
    """Calibrate crosstalk, ND and the sensor's basic parameters from a flat-field sweep: the steps of
    paper 3.2, 4.1 and 4.2 (module doc), each a function of this module. `defects`: a defect map
    (flats.detect) for the profile, where the profile holds one. `cfa`: the profile's CFA (a Bayer sensor's
    white sweep: every photosite sees the same flux; `colour_spill` adds the per-colour amplitudes)."""
    from tqdm import tqdm
    check_options(nd_nominal, l_min, clip_code, bit_depth)
    mask = check_mask(sweep, mask, mask_name)
    where = str(sweep.folder)
    with tqdm(total=6, desc="calibrating", unit="step", disable=not progress, file=sys.stderr) as bar:
        lv = sensor_levels(sweep, mask, clip_code, bit_depth)
        ptc = photon_transfer(sweep, mask, lv)                                      # EMVA 1288
        bar.update(1)
        refs = reference_curves(lv, mask)                                           # paper 3.2
        bar.update(1)
        ndf = nd_factor(sweep.exposures, refs, lv.top, where)                       # paper 3.2, Eq. 1
        flux = ndf.kappa_reg * sweep.exposures.astype(np.float64)                   # (E,) regular DN
        fe, sigma = spill_table(flux, refs, lv.lit, ndf.nd)                         # kernel mode
        bar.update(1)
        fit = pixel_model(sweep, mask, lv, ptc, refs, flux, ndf.nd, fe, sigma, prior_g, prior_alpha, prior_c)
        curve, smooth_ok = pixel_curves(lv, fit, smooth_chi2, smooth_taps)
        bar.update(1)
        lut = pixel_lut(curve, lv, flux, fit.gain)                                  # paper 3.2
        del curve
        clip_flux = clip_points(lut, sweep, mask, lv, ptc, flux)                    # paper 4.1
        bar.update(1)
        prof = _calibrated_profile(mask, lv, ptc, ndf, lut, clip_flux, fe, sigma, fit.alpha, l_min, name, where,
                                   defects, cfa)
        nd_eff_map = effective_nd(clip_flux, lv.top)                                # paper 4.1, Eq. 8
        lmin_flux = _flux_at_code(lut.codes, lut.knot_flux, lut.n_knots, prof.l_min)
        rf, ratio = valid_pixel_ratio(mask, clip_flux, lmin_flux, flux)             # paper 4.2, Fig. 8b
        gains = [dynamic_range_gain(rf, ratio, level, lv.top) for level in (0.4, 0.2)]   # paper 4.2
        bar.update(1)
    examples = _example_pixels(mask, refs, nd_eff_map)
    summary = _summary(sweep, mask, lv, ptc, refs, ndf, lut, nd_eff_map, examples, gains, fe, sigma, prof,
                       nd_nominal, smooth_ok)
    prof.crosstalk.info = {k: summary[k] for k in ("nd", "nd_eff_median", "dr_gain_stops_40",
                                                   "dr_gain_stops_20", "exposures", "frames", "kernel_estimate")}
    # for the plot: the paper's reference (no selection bias until its pixels clip themselves)
    ref_att = np.where(np.isfinite(refs.paper_att), refs.paper_att, refs.att)
    return CalibrationResult(prof, summary, flux, ref_att, refs.reg, nd_eff_map[mask], rf, ratio,
                             _measured_ratio(sweep, prof), examples)


def _calibrated_profile(mask, lv, ptc, ndf, lut, clip_flux, fe, sigma, alpha, l_min, name, where, defects=None,
                        cfa="none"):
    """The camera profile with its crosstalk calibration (crosstalk.CrosstalkCalibration) and, where the
    profile holds one, the defect map."""
    codes_t = np.ascontiguousarray(np.moveaxis(lut.codes, 0, -1))          # (H, W, K)
    q, qs, qo = crosstalk.quantize_codes(codes_t, lv.max_code)
    calib = crosstalk.CrosstalkCalibration(
        codes_q=q, qscale=qs, qoffset=qo, n_knots=lut.n_knots, knot_flux=lut.knot_flux.astype(np.float64),
        clip_flux=clip_flux, nd=float(ndf.nd), black_level=lv.black, clip_code=lv.clip_code,
        sig_e=fe.astype(np.float32), sigma=sigma.astype(np.float32), alpha=alpha, info={})
    try:
        return profiles.make(mask, nd=float(ndf.nd), bit_depth=int(lv.bit_depth), clip_code=int(lv.clip_code),
                             black_level=float(lv.black), gain=float(ptc.gain), read_noise=float(ptc.read_noise),
                             full_well=float(ptc.full_well), l_min=float(min(l_min, 0.5 * lv.top)), name=name,
                             crosstalk=calib, **_defect_field(defects), **({} if cfa == "none" else {"cfa": cfa}))
    except profiles.ProfileError as e:
        raise CalibrationError(f"{where}: calibrated parameters are inconsistent: {e}") from None


def _defect_field(defects) -> dict:
    """{"defects": map} for profiles.make when a map is given, else {}."""
    return {} if defects is None else {"defects": defects}


def _example_pixels(mask, refs, nd_eff_map):
    """Paper Fig. 7's exemplary pixels: two attenuated pixels near the centre with the most regular
    neighbours that clip within the sweep."""
    H, W = mask.shape
    cy, cx = H // 2, W // 2
    score = np.where(mask & refs.inner & np.isfinite(nd_eff_map), refs.ind_reg.sum(0), -1).astype(float)
    yy, xx = np.mgrid[0:H, 0:W]
    score -= 1e-3 * np.hypot(yy - cy, xx - cx) / max(H, W)
    ex = np.argsort(score.ravel())[::-1][:2]
    return [(int(e // W), int(e % W)) for e in ex if score.ravel()[e] >= 0]


def _summary(sweep, mask, lv, ptc, refs, ndf, lut, nd_eff_map, examples, gains, fe, sigma, prof,
             nd_nominal, smooth_ok) -> dict:
    """The calibration's figures (printed by `nrhdr calibrate`, saved in the profile's info)."""
    H, W = mask.shape
    nd, top = ndf.nd, lv.top
    nd_eff = nd_eff_map[mask]
    valid_nd = nd_eff[np.isfinite(nd_eff)]
    (g40, f40), (g20, f20) = gains
    summary = {
        "flats": str(sweep.folder), "width": W, "height": H, "exposures": int(len(sweep.exposures)),
        "frames": int(sweep.frames.sum()), "bit_depth": int(lv.bit_depth), "black_level": round(lv.black, 3),
        "clip_code": int(lv.clip_code), "gain_dn_per_e": round(ptc.gain, 6),
        "read_noise_e": round(ptc.read_noise, 3), "full_well_e": round(ptc.full_well, 1),
        "nd": round(float(nd), 4), "nd_stops": round(math.log2(nd), 3),
        "nd_paper_references": round(float(ndf.nd_paper), 4) if math.isfinite(ndf.nd_paper) else None,
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
        "reference_pixels_paper": int(refs.paper_att_sel.sum()),
        "reference_paper_rule": refs.paper_rule,
        "kernel_estimate": _kernel_estimate(fe, sigma, top),
        "pixels_without_calibration": int(np.sum(lut.n_knots < 2)),
        "defective_pixels": int(lut.defective.sum()),
        "lut_knots": int(lut.codes.shape[0]),
        "lut_smoothed_pct": round(float(np.mean(smooth_ok)) * 100, 2),
    }
    if nd_nominal:
        summary["nd_vs_nominal_pct"] = round(100 * (nd / nd_nominal - 1), 2)
    return summary


# ---- helpers of the steps ----------------------------------------------------------------------------

# ======================================================================================================
# Colour sensors: crosstalk per colour neighbourhood (docs/COLOUR.md "Validity and crosstalk per colour")
# ======================================================================================================

COLOUR_LINEAR = 0.7     # colour sweeps: exposures where 99 % of the pixels are below this share of the range
COLOUR_ITERS = 3        # channel-flux iterations per exposure (`_channel_fluxes`)
COLOUR_OUTER = 3        # rounds of channel fluxes and factors (`colour_spill`)


@dataclasses.dataclass
class ColourSpill:
    """What `colour_spill` measured: colour (3, H, W) each pixel's amplitude for its neighbours of channel
    R, G, B (alpha x its CFA class's factor for that colour; own channel: alpha); gamma (4, 2) the factors
    per CFA class (`_cfa_class`) for its other colours (own + 1, own + 2 mod 3); inliers (H, W) the pixels
    that entered the fit; fluxes [(exposure_s, (F_R, F_G, F_B))] per sweep: the channel fluxes measured at
    each exposure used."""
    colour: np.ndarray
    gamma: np.ndarray
    inliers: np.ndarray
    fluxes: list
    cfa: str

    def summary(self) -> dict:
        """The factor per (CFA class, neighbour colour), e.g. "G(0,1)<-R", and the sweeps' channel fluxes."""
        from . import cfa as cfas
        b = cfas.block(self.cfa)
        fac = {}
        for q in range(4):
            o = int(b[q // 2, q % 2])
            for j in range(2):
                c = (o + 1 + j) % 3
                fac[f"{cfas.CHANNEL_NAMES[o]}({q // 2},{q % 2})<-{cfas.CHANNEL_NAMES[c]}"] = round(
                    float(self.gamma[q, j]), 4)
        return {"factor": fac, "pixels_fitted": int(self.inliers.sum()),
                "sweeps": [[[round(t, 6), [round(float(v), 2) for v in f]] for t, f in sw] for sw in self.fluxes]}


def colour_spill(prof, sweeps, where: str = "colour flats") -> ColourSpill:
    """Per-pixel crosstalk amplitudes per neighbour colour of a Bayer sensor from sweeps under coloured light
    (e.g. red, green, blue), given its white-light calibration `prof` (profile.crosstalk from `calibrate`).

    At each exposure of a sweep in the linear range (99 % of the pixels below COLOUR_LINEAR of the range):
    the channel fluxes F_R, F_G, F_B (`_channel_fluxes`: the regular pixels of each colour through the white
    LUT, their other-colour spill removed); then, per pixel, the code it reads minus the code the white LUT
    gives at its own channel's flux is the spill of its other-colour neighbours beyond what neighbours at its
    flux would send: sum over the other colours c of beta_c x Delta_c, with Delta_c the population spill
    functions (`spill_table`) of its actual neighbours of colour c at F_c minus at F_own (`_colour_deltas`).
    beta_c = alpha x gamma_{q, c}: the pixel's white-light amplitude alpha (the mask's local non-uniformity)
    times a factor per CFA class q (`_cfa_class`) and neighbour colour c (the colour dependence of the
    coupling: longer wavelengths spill more), by weighted least squares (weights: the noise of the mean at
    the predicted code) over every sweep and exposure where the pixel is unclipped and its white LUT covers
    its flux, pooled over the class's pixels (`_class_factors`); the channel fluxes are measured again with
    the factors found, COLOUR_OUTER rounds from factors 1."""
    from . import cfa as cfas
    calib = prof.crosstalk
    if not cfas.is_colour(getattr(prof, "cfa", None)):
        raise CalibrationError(f"{where}: a per-colour calibration needs a colour profile (cfa)")
    if calib is None:
        raise CalibrationError(f"{where}: a per-colour calibration needs the white-light calibration first")
    H, W = prof.mask.shape
    chan = cfas.channel_index(prof.cfa, H, W)
    mask = np.asarray(prof.mask, bool)
    nd = float(prof.nd)
    black = float(prof.black_level)
    top = float(prof.clip_code) - black
    codes = calib.codes()
    kf = calib.knot_flux.astype(np.float64)
    alpha = calib.alpha.astype(np.float64)
    geo = _neighbour_geometry(chan, mask)
    o1, o2 = (chan + 1) % 3, (chan + 2) % 3
    gain, rn = float(prof.gain), float(prof.read_noise)
    for sw in sweeps:
        if sw.shape != (H, W):
            raise CalibrationError(f"{sw.folder}: frames are {sw.shape[1]}x{sw.shape[0]}, the white sweep's "
                                   f"{W}x{H}")
    colour = np.repeat(alpha[None], 3, 0)
    for _ in range(COLOUR_OUTER):     # the channel fluxes depend on the factors: estimate both in turn
        s11, s12, s22, b1, b2 = (np.zeros((H, W)) for _ in range(5))
        npts = np.zeros((H, W), np.int32)
        fluxes = []
        for sw in sweeps:
            used = []
            for k, t in enumerate(sw.exposures):
                m = sw.mean[k].astype(np.float64) - black
                if t <= 0 or np.percentile(m, 99) >= COLOUR_LINEAR * top:
                    continue
                unc = sw.maxcode[k] < prof.clip_code
                F = _channel_fluxes(m, unc, prof, chan, geo, colour)
                if not np.all(np.isfinite(F)):
                    continue
                used.append((float(t), F))
                delta = _colour_deltas(F, chan, geo, calib, nd)
                cw, okw = _white_code(codes, kf, calib.n_knots, F[chan])
                y = m - cw
                u1 = alpha * np.take_along_axis(delta, o1[None].astype(np.intp), 0)[0]
                u2 = alpha * np.take_along_axis(delta, o2[None].astype(np.intp), 0)[0]
                # noise of the mean at the predicted code (the measured one would weight low readings up)
                pred = np.maximum(np.nan_to_num(cw) + u1 + u2, 0.0)
                var = (gain * pred + (gain * rn) ** 2 + 1.0 / 12.0) / max(int(sw.frames[k]), 1)
                wgt = np.where(unc & okw & np.isfinite(y), 1.0 / var, 0.0)
                y = np.nan_to_num(y)
                s11 += wgt * u1 * u1
                s12 += wgt * u1 * u2
                s22 += wgt * u2 * u2
                b1 += wgt * u1 * y
                b2 += wgt * u2 * y
                npts += wgt > 0
            if not used:
                raise CalibrationError(f"{sw.folder}: no lit exposure in the linear range (99 % of the pixels "
                                       f"below {COLOUR_LINEAR * 100:.0f} % of saturation)")
            fluxes.append(used)
        gamma, inliers = _class_factors(chan, s11, s12, s22, b1, b2, npts, where)
        cls = _cfa_class(H, W)
        colour = np.repeat(alpha[None], 3, 0)
        for q in range(4):
            sel = cls == q
            o = int(chan[sel][0])
            for j, c in enumerate(((o + 1) % 3, (o + 2) % 3)):
                colour[c][sel] = alpha[sel] * gamma[q, j]
    return ColourSpill(colour.astype(np.float32), gamma, inliers, fluxes, prof.cfa)


def colour_check(prof, cs: ColourSpill, sweeps) -> dict:
    """Per coloured sweep (named by its folder): the mean relative error (%) per channel R, G, B of the
    attenuated photosites (interior, unclipped) at the brightest exposure `colour_spill` used, against the
    channel fluxes it measured there, after `crosstalk.correct` mode `lut` with the white-light calibration
    (`prof` without colour amplitudes) and with the per-colour amplitudes of `cs`: the bias the per-colour
    calibration removes on the user's own flats."""
    from . import cfa as cfas
    H, W = prof.mask.shape
    chan = cfas.channel_index(prof.cfa, H, W)
    mask = np.asarray(prof.mask, bool)
    white = dataclasses.replace(prof, crosstalk=dataclasses.replace(prof.crosstalk, colour=None))
    colour = dataclasses.replace(prof, crosstalk=dataclasses.replace(prof.crosstalk, colour=cs.colour))
    inner = np.zeros((H, W), bool)
    inner[2:-2, 2:-2] = True
    out = {}
    for sw, used in zip(sweeps, cs.fluxes):
        t, F = used[-1]
        k = int(np.nonzero(sw.exposures == t)[0][0])
        truth = F[chan]
        base = ((sw.mean[k] - float(prof.black_level)) * np.where(mask, float(prof.nd), 1.0)).astype(np.float32)
        sel0 = mask & inner & (sw.maxcode[k] < prof.clip_code) & (truth > 0)
        res = {}
        for name, p in (("white", white), ("colour", colour)):
            v = base.copy()
            st = np.where(mask, np.uint8(crosstalk.ATTENUATED), np.uint8(0)).astype(np.uint8)
            crosstalk.correct(v, st, p, "lut")
            ok = sel0 & ((st & crosstalk.REASON_MASK) == crosstalk.VALID)
            r = (v - truth) / np.where(truth > 0, truth, 1.0)
            res[name] = [round(100 * float(np.mean(r[ok & (chan == c)])), 2) if (ok & (chan == c)).any() else None
                         for c in range(3)]
        out[Path(sw.folder).name] = res
    return out


def _cfa_class(h, w):
    """(h, w) int: the photosite's place in the 2 x 2 CFA block (0..3, row by row): photosites of one class
    have the same colour and the same colours around them."""
    yy, xx = np.mgrid[0:h, 0:w]
    return (yy % 2) * 2 + (xx % 2)


def _class_factors(chan, s11, s12, s22, b1, b2, npts, where):
    """(gamma (4, 2), inliers (H, W)): per CFA class the factors of its two other colours (in the order
    own + 1, own + 2 mod 3) from the per-pixel normal equations pooled over the class's pixels with at least 3
    points whose own solution is within 5 robust sigmas of the class median (defects and outliers out)."""
    H, W = chan.shape
    cls = _cfa_class(H, W)
    det = s11 * s22 - s12 * s12
    ok = (npts >= 3) & (det > 1e-9 * np.maximum(s11 * s22, 1e-300))
    with np.errstate(divide="ignore", invalid="ignore"):
        g1 = (s22 * b1 - s12 * b2) / det
        g2 = (s11 * b2 - s12 * b1) / det
    ok &= np.isfinite(g1) & np.isfinite(g2)
    gamma = np.ones((4, 2))
    inliers = np.zeros((H, W), bool)
    for q in range(4):
        sel = ok & (cls == q)
        if sel.sum() < 8:
            raise CalibrationError(f"{where}: fewer than 8 pixels of CFA class {q} could be fitted (need exposures "
                                   f"in the linear range where they are unclipped)")
        for g in (g1, g2):
            med = np.median(g[sel])
            mad = 1.4826 * np.median(np.abs(g[sel] - med))
            sel &= np.abs(g - med) <= 5 * max(mad, 1e-6)
        a11, a12, a22, r1, r2 = (float(v[sel].sum()) for v in (s11, s12, s22, b1, b2))
        d = a11 * a22 - a12 * a12
        if d > 0:
            gamma[q] = ((a22 * r1 - a12 * r2) / d, (a11 * r2 - a12 * r1) / d)
        inliers |= sel
    return gamma, inliers


def _neighbour_geometry(chan, mask):
    """Per direction d (crosstalk.DIRS): (exists (H, W), neighbour channel (H, W), neighbour attenuated
    (H, W))."""
    out = []
    for dy, dx in crosstalk.DIRS:
        ex = crosstalk._shift(np.ones(chan.shape, bool), int(dy), int(dx))
        ch = crosstalk._shift(chan, int(dy), int(dx))
        at = crosstalk._shift(mask, int(dy), int(dx))
        out.append((ex, ch, at))
    return out


def _colour_deltas(F, chan, geo, calib, nd):
    """(3, H, W): per neighbour colour c, the spill the pixel's neighbours of colour c send at the channel
    fluxes F minus what they would send at the pixel's own channel's flux (population spill functions
    sigma_d of the source signal: F / ND for an attenuated source)."""
    fe = calib.sig_e.astype(np.float64)
    sg = calib.sigma.astype(np.float64)
    # sp[d, c, a]: sigma_d at flux F_c of a regular (a = 0) or attenuated (a = 1) source
    sp = np.array([[[_spill_np(fe, sg, F[c] / (nd if a else 1.0))[d] for a in (0, 1)] for c in range(3)]
                   for d in range(8)])
    out = np.zeros((3,) + chan.shape)
    for d, (ex, ch, at) in enumerate(geo):
        a = at.astype(np.intp)
        diff = np.where(ex, sp[d][ch, a] - sp[d][chan, a], 0.0)
        for c in range(3):
            out[c] += np.where(ch == c, diff, 0.0)
    return out


def _white_code(codes, kf, n_knots, flux):
    """(code, ok): each pixel's code above black at `flux` (H, W) on its white-light LUT (the inverse of
    `crosstalk.lut_eval` between knots); ok False outside its knots."""
    K = kf.size
    j = np.clip(np.searchsorted(kf, flux, side="right") - 1, 0, K - 2)
    c0 = np.take_along_axis(codes, j[..., None], 2)[..., 0].astype(np.float64)
    c1 = np.take_along_axis(codes, (j + 1)[..., None], 2)[..., 0].astype(np.float64)
    t = (flux - kf[j]) / (kf[j + 1] - kf[j])
    ok = (j + 1 < n_knots) & (flux >= kf[0])
    return c0 + t * (c1 - c0), ok


def _channel_fluxes(m, unc, prof, chan, geo, amp):
    """(F_R, F_G, F_B) of a coloured flat (codes above black `m`): the median over the unclipped regular
    pixels of each colour of their white-LUT flux, after removing their other-colour spill (the amplitudes
    `amp` (3, H, W) x `_colour_deltas` at the current fluxes), COLOUR_ITERS times from no correction."""
    calib = prof.crosstalk
    H, W = m.shape
    nd = float(prof.nd)
    reg = ~np.asarray(prof.mask, bool) & unc
    table = crosstalk.lut_record(calib)
    state = np.where(prof.mask, np.uint8(crosstalk.ATTENUATED), np.uint8(0)).astype(np.uint8)
    out = np.empty((H, W), np.float32)
    ok = np.empty((H, W), np.bool_)
    F = np.full(3, np.nan)
    spill = np.zeros((H, W))
    for it in range(COLOUR_ITERS + 1):
        if it:
            spill = (amp * _colour_deltas(F, chan, geo, calib, nd)).sum(0)    # own colour: 0
        vals = ((m - spill) * np.where(prof.mask, nd, 1.0)).astype(np.float32)
        crosstalk._lut_pass(vals, state, table, nd, out, ok)
        for c in range(3):
            sel = reg & ok & (chan == c)
            F[c] = float(np.median(out[sel])) if sel.sum() >= 8 else np.nan
        if not np.all(np.isfinite(F)):
            break
    return F


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


def _measured_ratio(sweep, prof):
    from . import validity
    out = np.zeros(len(sweep.exposures))
    for i in range(len(sweep.exposures)):
        raw = np.clip(np.rint(sweep.mean[i]), 0, prof.max_code).astype(np.uint16)
        raw = np.where(sweep.maxcode[i] >= prof.clip_code, sweep.maxcode[i], raw)
        _, st = validity.classify(raw, prof, mode="threshold")
        out[i] = validity.valid_ratio(st)
    return out


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
# The whole calibration from files (`nrhdr calibrate`, gst_plugins/cli/calibrate.py)
# ======================================================================================================

def check_options(nd_nominal=None, l_min=100.0, clip_code=None, bit_depth=None) -> None:
    """CalibrationError naming the option unless the user's settings are usable: `nd_nominal` None or
    finite in 1..1024, `l_min` finite >= 0, `clip_code` None or an integer in 1..65535, `bit_depth` None or
    an integer in 1..16."""
    def num(v, integer=False):
        if integer:
            return isinstance(v, (int, np.integer)) and not isinstance(v, bool)
        return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool) and math.isfinite(v)
    if nd_nominal is not None and not (num(nd_nominal) and 1 <= nd_nominal <= profiles.ND_MAX):
        raise CalibrationError(f"nd_nominal must be a finite number in 1..{profiles.ND_MAX:g}, got {nd_nominal!r}")
    if not (num(l_min) and l_min >= 0):
        raise CalibrationError(f"l_min must be a finite number >= 0, got {l_min!r}")
    if clip_code is not None and not (num(clip_code, True) and 1 <= clip_code <= 65535):
        raise CalibrationError(f"clip_code must be an integer in 1..65535, got {clip_code!r}")
    if bit_depth is not None and not (num(bit_depth, True) and 1 <= bit_depth <= 16):
        raise CalibrationError(f"bit_depth must be an integer in 1..16, got {bit_depth!r}")


def run_calibrate(flats, mask_path, output, nd_nominal=None, l_min=100.0, clip_code=None, bit_depth=None,
                  plots=True, progress=True, overwrite=False, allow_outside=False, find_mask=None, cfa="none",
                  colour_flats=None):
    """The whole `nrhdr calibrate`: read, calibrate, write profile + plots; returns the summary. Without
    `mask_path` (None) `find_mask(sweep)` finds the mask in the flats (`flats.finder`: a
    `flats.MaskDetection` with the mask, the defect map, `summary()` for the summary's `mask_detection` and
    `write_plot(path)`), or raises CalibrationError. Existing
    outputs (the profile's files, the plots) are refused before any work unless `overwrite`; frames named
    outside the flats folder only with `allow_outside` (read_index). The files are made in a temporary
    folder and moved in together at the end (outputs.staged_files): a stopped or failed run leaves none of
    them (never a mask without its profile), a killed run's temporaries are removed by the next run, and a
    second calibration writing the same profile is refused while this one runs. `cfa`: the sensor's CFA
    (profile.cfa); `colour_flats`: folders of sweeps under coloured light for `colour_spill` (colour only)."""
    from . import cfa as cfas
    from . import outputs
    check_options(nd_nominal, l_min, clip_code, bit_depth)
    try:
        cfa = cfas.check(cfa, "cfa")
    except ValueError as e:
        raise CalibrationError(str(e)) from None
    if colour_flats and cfa == cfas.NONE:
        raise CalibrationError("colour flats: calibrating per colour needs the sensor's CFA (--cfa rggb, bggr, "
                               "grbg or gbrg)")
    out = Path(output)
    with outputs.staged_files(out, out.parent) as tmp:
        return _calibrate_into(tmp, out, flats, mask_path, nd_nominal, l_min, clip_code, bit_depth, plots,
                               progress, overwrite, allow_outside, find_mask, cfa, colour_flats)


def _calibrate_into(tmp: Path, out: Path, flats, mask_path, nd_nominal, l_min, clip_code, bit_depth, plots,
                    progress, overwrite, allow_outside, find_mask=None, cfa="none", colour_flats=None) -> dict:
    if not overwrite:
        plots_made = ("curves", "nd_eff", "valid_ratio") + (("detection",) if mask_path is None else ())
        io.refuse_existing(profiles.written_files(out) + [out.parent / f"{out.stem}_calib_{k}.png" for k in
                                                          plots_made])
    if mask_path is None and find_mask is None:
        raise CalibrationError(f"{flats}: no mask: pass a mask file or a way to find it in the flats")
    if mask_path is not None:
        try:
            mask = io.read_mask(mask_path)
        except io.ImageFileError as e:
            raise CalibrationError(str(e)) from None
    sweep = read_flats(flats, progress=progress, allow_outside=allow_outside)
    det = None
    if mask_path is None:
        det = find_mask(sweep)
        mask = det.mask
    res = calibrate(sweep, mask, nd_nominal=nd_nominal, l_min=l_min, clip_code=clip_code,
                    bit_depth=bit_depth, name=out.stem,
                    mask_name="mask found in the flats" if det is not None else str(mask_path),
                    progress=progress, defects=None if det is None else det.defects, cfa=cfa)
    if colour_flats:
        sweeps = [read_flats(f, progress=progress, allow_outside=allow_outside) for f in colour_flats]
        cs = colour_spill(res.profile, sweeps)
        check = colour_check(res.profile, cs, sweeps)
        res.profile.crosstalk.colour = cs.colour
        res.summary["colour"] = res.profile.crosstalk.info["colour"] = dict(cs.summary(), check=check)
    if det is not None:
        res.summary["mask_detection"] = det.summary()
        res.profile.crosstalk.info["mask_detection"] = res.summary["mask_detection"]
    profiles.save(res.profile, tmp / out.name)
    res.summary["profile"] = str(out)
    if plots:
        made = write_plots(res, tmp / f"{out.stem}_calib")
        if det is not None:
            made.append(det.write_plot(tmp / f"{out.stem}_calib_detection.png"))
        res.summary["plots"] = [str(out.parent / p.name) for p in made]
    return res.summary
