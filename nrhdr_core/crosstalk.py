"""Crosstalk (paper section 3): a realistic sensor model and the calibrated correction (docs/CROSSTALK.md).

Sensor model (`SensorModel`, used by `sensor.capture`): every pixel receives a share of the charge/light of
its 8 neighbours through a 3 x 3 kernel (edge terms, corner terms, row/column anisotropy) that varies from
pixel to pixel (a glued-on mask is not uniform: a smooth field times a random factor); the coupling grows
with the source's signal, and a source approaching full well blooms into its neighbours (non-linear, paper
3.2); the spilled charge leaves the source (the centre term is 1 - outgoing share). Photo-response (PRNU) and
dark-signal (DSNU) non-uniformity follow.

Correction (`correct`, element `nrcrosstalk`), from a `CrosstalkCalibration` made by `calibration.py` out of
flat-field sweeps:
- ``lut`` (paper 3.2): each pixel's code-to-flux curve measured on the flats (one knot per calibrated
  exposure plus the pixel's clipping point); codes are interpolated between knots, and codes above the
  pixel's calibrated range become UNCALIBRATED (missing), never extrapolated. The paper's assumption: the
  neighbours are as bright as the pixel.
- ``kernel`` (beyond the paper): the LUT applied after removing the difference between the crosstalk the
  pixel's *actual* neighbours send and what flat neighbours would have sent: per-direction spill functions
  sigma_d(e) of the source signal e (calibrated from the flats, non-linear near saturation), scaled by the
  pixel's own crosstalk amplitude alpha. On flats it equals ``lut``; at edges it follows the neighbours.
  A pixel that got more spill from clipped neighbours (whose flux is only estimated) than its own signal
  becomes UNCALIBRATED (`CLIP_SHARE`).
- ``off``: identity.

Colour sensors (profile.cfa a Bayer phase; docs/COLOUR.md "Validity and crosstalk per colour"): under
coloured light a photosite's neighbours of other colours are not as bright as it is, which the white-light
LUT assumes. A calibration with per-colour amplitudes (`CrosstalkCalibration.colour`, from sweeps under
coloured light: `calibration.colour_spill`) corrects that in both modes (`_correct_kernel`): ``lut`` removes
the spill of the other-colour neighbours beyond what neighbours at the pixel's flux would send, with the
pixel's amplitude for that colour, before the LUT (same-colour neighbours keep the LUT's assumption);
``kernel`` does so for every neighbour, with the pixel's amplitude for the neighbour's colour. ``lut`` with
the compact LUT does the former in one pass (`_colour_compact_correct`, docs/CROSSTALK.md section 4b).

Values are linear DN (attenuated pixels scaled by ND, docs/ARCHITECTURE.md); the correction returns flux in
the same units. Clipped pixels keep their state; their lower bound is lowered to the pixel's calibrated
clipping flux (the nominal bound (clip - black) * ND overstates it under crosstalk). Dark pixels keep their
state; their upper bound is mapped through the LUT.
"""
from __future__ import annotations

import dataclasses
import math
import os
import tempfile
import threading
import zipfile
from collections import namedtuple
from pathlib import Path

import numpy as np
from numba import get_num_threads, njit, prange

from .scratch import interleaved
from .states import ATTENUATED, CLIPPED, DARK, FLAG_MASK, NOISY, REASON_MASK, UNCALIBRATED, VALID

MODES = ("lut", "kernel", "off")
# kernel mode: a pixel that received more spill from clipped neighbours (whose flux is only estimated) than
# its own signal (CLIP_SHARE x its corrected code) is unreliable and becomes UNCALIBRATED (value: the kernel
# estimate); None disables it. See docs/CROSSTALK.md for the trade-off.
CLIP_SHARE = 1.0
CALIB_FORMAT = "nrhdr-crosstalk"
CALIB_VERSION = 1

# the 8 neighbour directions (dy, dx), source = target + (dy, dx); index d is used everywhere
DIRS = np.array([(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)], dtype=np.int64)



# ======================================================================================================
# Sensor model
# ======================================================================================================

def _shift(a: np.ndarray, dy: int, dx: int) -> np.ndarray:
    """out[y, x] = a[y + dy, x + dx], zero outside."""
    h, w = a.shape
    out = np.zeros_like(a)
    ys, yd = (slice(dy, h), slice(0, h - dy)) if dy >= 0 else (slice(0, h + dy), slice(-dy, h))
    xs, xd = (slice(dx, w), slice(0, w - dx)) if dx >= 0 else (slice(0, w + dx), slice(-dx, w))
    out[yd, xd] = a[ys, xs]
    return out


def _soft_hinge(t: np.ndarray, width: float) -> np.ndarray:
    """0 for t <= 0, t^2 / (2 width) up to width, then t - width / 2 (C1-smooth)."""
    t = np.maximum(t, 0.0)
    return np.where(t < width, t * t / (2.0 * width), t - 0.5 * width)


@dataclasses.dataclass
class SensorModel:
    """Crosstalk + PRNU + DSNU acting on mean electrons (before shot noise), see module doc.

    kernel[1 + dy, 1 + dx]: share of the source at (y + dy, x + dx) that lands in (y, x) (centre ignored),
    at half full well; `spread` (H, W) multiplies the kernel of each target pixel; `gamma` makes the coupling
    signal dependent: k * (1 + gamma * (min(e / FW, 1) - 0.5)); `bloom[1 + dy, 1 + dx]` is the share of the
    source's charge above `knee` * FW that overflows into the target (smooth hinge of width `knee_width`);
    `prnu` (H, W) gains and `dsnu` (H, W) dark electrons are applied last. `colour_coupling` (r, g, b), on a
    colour profile (profile.cfa): the coupling of a source photosite of that colour relative to the kernel
    (crosstalk grows with wavelength: red light is absorbed deeper, its carriers diffuse further); None: 1.
    """
    kernel: np.ndarray
    spread: np.ndarray | None = None
    gamma: float = 0.0
    bloom: np.ndarray | None = None
    knee: float = 0.9
    knee_width: float = 0.2
    prnu: np.ndarray | None = None
    dsnu: np.ndarray | None = None
    name: str = "custom"
    colour_coupling: tuple | None = None

    def apply(self, electrons_mean: np.ndarray, profile, rng=None) -> np.ndarray:
        e = np.asarray(electrons_mean, dtype=np.float64)
        h, w = e.shape
        fw = float(profile.full_well)
        spread = np.ones((h, w)) if self.spread is None else np.asarray(self.spread, np.float64)
        if spread.shape != e.shape:
            raise ValueError(f"sensor model is {spread.shape[1]}x{spread.shape[0]} but the frame is {w}x{h}")
        u = np.minimum(e / fw, 1.0)
        lin = e * (1.0 + self.gamma * (u - 0.5))              # signal-dependent coupling
        if self.colour_coupling is not None and getattr(profile, "cfa", "none") != "none":
            from . import cfa as cfas
            lin = lin * np.asarray(self.colour_coupling, np.float64)[cfas.channel_index(profile.cfa, h, w)]
        bl = None
        if self.bloom is not None and np.any(self.bloom):
            bl = fw * _soft_hinge(e / fw - self.knee, self.knee_width)
        out = e.copy()
        for dy, dx in DIRS:
            k = float(self.kernel[1 + dy, 1 + dx])
            if k != 0.0:
                out += spread * k * _shift(lin, dy, dx)             # received from the source p + d
                out -= _shift(spread, -dy, -dx) * k * lin           # sent to the target p - d
            if bl is not None:
                b = float(self.bloom[1 + dy, 1 + dx])
                if b != 0.0:
                    out += spread * b * _shift(bl, dy, dx)
        if self.prnu is not None:
            out *= self.prnu
        if self.dsnu is not None:
            out += self.dsnu
        return np.maximum(out, 0.0)

    def truth(self) -> dict:
        """Summary of the known model (for validation reports)."""
        k = np.asarray(self.kernel, float)
        return {"name": self.name, "kernel": k.tolist(), "gamma": self.gamma,
                "bloom": None if self.bloom is None else np.asarray(self.bloom, float).tolist(),
                "knee": self.knee,
                "spread_mean": None if self.spread is None else float(np.mean(self.spread)),
                "spread_std": None if self.spread is None else float(np.std(self.spread)),
                "prnu_std": None if self.prnu is None else float(np.std(self.prnu)),
                "dsnu_mean_e": None if self.dsnu is None else float(np.mean(self.dsnu)),
                **({} if self.colour_coupling is None else {"colour_coupling": list(self.colour_coupling)})}


def make_kernel(edge_h: float, edge_v: float, corner: float) -> np.ndarray:
    """3 x 3 kernel: left/right neighbours edge_h, up/down edge_v, diagonals corner; centre 0."""
    return np.array([[corner, edge_v, corner], [edge_h, 0.0, edge_h], [corner, edge_v, corner]], float)


PRESETS = ("none", "prototype", "linear", "mild")


def sensor_model_preset(name: str, height: int, width: int, seed: int = 0) -> SensorModel | None:
    """Named sensor models.

    - ``none``: no crosstalk (None).
    - ``prototype``: like the paper's glued-mask CCD prototype: ~1 % edge spill (1.2 % along columns),
      0.3 % corners, coupling rising with signal, blooming of saturated sources (mostly along columns),
      a non-uniform mask (smooth field x log-normal factor, ~35 % rms), 0.8 % PRNU, DSNU ~3 +- 1.5 e-.
      With ND 6.35 it reproduces the paper's effective-ND spread (docs/CROSSTALK.md).
    - ``linear``: uniform, linear 1 % / 0.25 % kernel, nothing else (for tests and textbook comparisons).
    - ``mild``: the prototype's structure at a third of its strength.
    """
    if name in (None, "", "none"):
        return None
    if name not in PRESETS:
        raise ValueError(f"sensor model preset must be one of {PRESETS}, got {name!r}")
    if height < 1 or width < 1:
        raise ValueError(f"sensor size must be positive, got {width}x{height}")
    if name == "linear":
        return SensorModel(kernel=make_kernel(0.01, 0.01, 0.0025), name="linear")
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0xC0557A1C]))
    yy, xx = np.mgrid[0:height, 0:width]
    yn, xn = yy / max(height - 1, 1) - 0.5, xx / max(width - 1, 1) - 0.5
    # glue thickness: a tilt and a bowl over the sensor, plus a random per-pixel factor
    smooth = 1.0 + 0.25 * xn - 0.15 * yn + 0.3 * (xn * xn + yn * yn - 1.0 / 6.0)
    spread = smooth * rng.lognormal(mean=-0.5 * 0.35 ** 2, sigma=0.35, size=(height, width))
    prnu = 1.0 + 0.008 * rng.standard_normal((height, width))
    dsnu = np.maximum(3.0 + 1.5 * rng.standard_normal((height, width)), 0.0)
    s = 1.0 if name == "prototype" else 1.0 / 3.0
    return SensorModel(kernel=s * make_kernel(0.010, 0.012, 0.003), spread=spread, gamma=0.7,
                       bloom=s * make_kernel(0.004, 0.012, 0.001), knee=0.9, knee_width=0.2,
                       prnu=prnu, dsnu=dsnu, name=name)


# ======================================================================================================
# Calibration container, storage
# ======================================================================================================

@dataclasses.dataclass(eq=False)
class CrosstalkCalibration:
    """Per-pixel LUT and neighbour model measured from flat-field sweeps (see calibration.py).

    codes_q (H, W, K) uint16: the pixel's mean code above black at knot k (`code = q * qscale - qoffset`);
    knots k < n_knots[y, x] are valid and strictly increasing; knot k maps to flux `knot_flux[k]` (linear DN
    of a regular pixel; knot 0 is the dark level, flux 0). clip_flux (H, W): flux at which the pixel reaches
    `clip_code` (NaN if it never did within the sweep: its range ends at its last knot). Kernel mode:
    sigma (8, J) spill from a source in direction d at source signal sig_e (J,), alpha (H, W) the pixel's
    crosstalk amplitude relative to the sensor average. Colour sensors: colour (3, H, W) float32 (or None),
    the pixel's amplitude for its neighbours of channel R, G, B (`calibration.colour_spill`).
    """
    codes_q: np.ndarray
    qscale: float
    qoffset: float
    n_knots: np.ndarray
    knot_flux: np.ndarray
    clip_flux: np.ndarray
    nd: float
    black_level: float
    clip_code: int
    sig_e: np.ndarray
    sigma: np.ndarray
    alpha: np.ndarray
    info: dict = dataclasses.field(default_factory=dict)
    colour: np.ndarray | None = None

    @property
    def shape(self):
        return self.codes_q.shape[:2]

    def __getstate__(self):
        # the compact LUT derived from this table (`compact_for`) is not shipped: derived again where used
        d = dict(self.__dict__)
        d.pop("_compact", None)
        d.pop("_spill_basis", None)
        d.pop("_colour_pairs", None)
        return d

    def codes(self) -> np.ndarray:
        """(H, W, K) float32 codes above black (invalid knots included)."""
        return self.codes_q.astype(np.float32) * np.float32(self.qscale) - np.float32(self.qoffset)


def quantize_codes(codes: np.ndarray, max_code: int):
    """float codes above black -> (uint16, qscale, qoffset) with ~1/16 DN resolution for 12-bit data."""
    qscale = (max_code + 512.0) / 65535.0
    qoffset = round(256.0 / qscale) * qscale          # code 0 is represented exactly
    q = np.rint((np.nan_to_num(codes, nan=0.0) + qoffset) / qscale)
    return np.clip(q, 0, 65535).astype(np.uint16), float(qscale), float(qoffset)


_ARRAYS = ("codes_q", "n_knots", "knot_flux", "clip_flux", "sig_e", "sigma", "alpha")
_OPTIONAL = ("colour",)          # per-colour amplitudes (3, H, W) of a colour calibration


def save_calibration(calib: CrosstalkCalibration, path) -> dict:
    """Write the calibration as a compressed .npz (atomic); return the profile's JSON entry."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix="." + path.stem + ".", suffix=".npz", dir=path.parent)
    os.close(fd)
    try:
        np.savez_compressed(tmp, codes_q=calib.codes_q, n_knots=calib.n_knots.astype(np.uint8),
                            knot_flux=calib.knot_flux.astype(np.float64),
                            clip_flux=calib.clip_flux.astype(np.float32),
                            sig_e=calib.sig_e.astype(np.float64), sigma=calib.sigma.astype(np.float64),
                            alpha=calib.alpha.astype(np.float16),
                            **({} if calib.colour is None else {"colour": calib.colour.astype(np.float32)}))
        os.replace(tmp, path)
    finally:
        Path(tmp).unlink(missing_ok=True)
    h, w = calib.shape
    return {"format": CALIB_FORMAT, "version": CALIB_VERSION, "file": path.name, "width": int(w),
            "height": int(h), "knots": int(calib.codes_q.shape[2]), "qscale": calib.qscale,
            "qoffset": calib.qoffset, "nd": float(calib.nd), "black_level": float(calib.black_level),
            "clip_code": int(calib.clip_code), "info": calib.info}


def _entry_number(entry: dict, key: str, lo: float, hi: float, integer: bool = False, lo_open: bool = False):
    """entry[key] as a finite number within [lo, hi] ((lo, hi] with lo_open); ValueError naming the field."""
    v = entry[key]
    ok = isinstance(v, int) if integer else isinstance(v, (int, float))
    if not ok or isinstance(v, bool) or not math.isfinite(v) or v < lo or v > hi or (lo_open and v == lo):
        kind = "an integer" if integer else "a finite number"
        raise ValueError(f"field '{key}' must be {kind} in {'(' if lo_open else '['}{lo:g}, {hi:g}], got {v!r}")
    return int(v) if integer else float(v)


MAX_SPILL_SIGNALS = 4096     # the spill table's signal count (a calibration writes one per exposure)


def _check_npz_shapes(path: Path, h: int, w: int) -> None:
    """ValueError unless every array of the calibration `path` declares (in its .npy header, read without
    decompressing the data) a shape that fits an (h, w) sensor: (h, w, K <= 255) for codes_q, (h, w) for the
    per-pixel maps, (K,) knot fluxes, (8, J) and (J,) spill table with J <= MAX_SPILL_SIGNALS. Bounds the
    memory a received calibration can make us allocate."""
    shapes, dtypes = {}, {}
    try:
        with zipfile.ZipFile(path) as zf:
            members = set(zf.namelist())
            for k in _ARRAYS + _OPTIONAL:
                if k + ".npy" not in members:
                    continue                 # reported by the reader below, naming the array
                with zf.open(k + ".npy") as f:
                    version = np.lib.format.read_magic(f)
                    if version == (1, 0):
                        shp, _, dt = np.lib.format.read_array_header_1_0(f)
                    elif version == (2, 0):
                        shp, _, dt = np.lib.format.read_array_header_2_0(f)
                    else:
                        raise ValueError(f"array {k}: .npy format version {version} is not read here")
                shapes[k] = tuple(int(n) for n in shp)
                dtypes[k] = np.dtype(dt)
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, RuntimeError, NotImplementedError) as e:
        raise ValueError(f"{path}: not a readable crosstalk calibration (.npz): {e}") from None
    cq = shapes.get("codes_q")
    k = cq[2] if cq is not None and len(cq) == 3 else None
    j = shapes.get("sig_e", (0,))[0] if len(shapes.get("sig_e", (0,))) == 1 else None
    want = {"codes_q": ((h, w, k), f"uint16 ({h}, {w}, K)"), "n_knots": ((h, w), f"({h}, {w})"),
            "clip_flux": ((h, w), f"({h}, {w})"), "alpha": ((h, w), f"({h}, {w})"), "knot_flux": ((k,), "(K,)"),
            "sig_e": ((j,), "(J,)"), "sigma": ((8, j), "(8, J)"), "colour": ((3, h, w), f"(3, {h}, {w})")}
    for name, shp in shapes.items():
        if shp != want[name][0] or (name == "codes_q" and not (1 <= k <= 255 and dtypes[name] == np.uint16)) \
                or (name == "sig_e" and not 2 <= j <= MAX_SPILL_SIGNALS):
            raise ValueError(f"{path}: array {name} is {dtypes[name]} {shp}, expected {want[name][1]} for the "
                             f"profile's {w}x{h} mask (1..255 knots K, 2..{MAX_SPILL_SIGNALS} spill signals J)")


def load_calibration(entry: dict, base_dir, shape, source=None, allow_outside: bool = False) -> CrosstalkCalibration:
    """Read the calibration named by a profile's 'crosstalk' entry; ValueError on any inconsistency.

    `source`: the JSON file holding the entry (default: a file in `base_dir`); the .npz it names must lie in
    its folder unless `allow_outside` (io.resolve_named). Every value is checked before use: the entry's
    numbers finite and in range, every array of the sensor's `shape` (H, W), knot fluxes finite and strictly
    increasing, each pixel's knot codes non-decreasing, spill table finite."""
    from . import io
    if not isinstance(entry, dict):
        raise ValueError(f"crosstalk entry must be an object, got {type(entry).__name__}")
    if entry.get("format") != CALIB_FORMAT:
        raise ValueError(f"crosstalk entry: field 'format' must be '{CALIB_FORMAT}'")
    if entry.get("version") != CALIB_VERSION or isinstance(entry.get("version"), bool):
        raise ValueError(f"crosstalk entry: this nrhdr reads version {CALIB_VERSION}, got "
                         f"{entry.get('version')!r}")
    for k in ("file", "qscale", "qoffset", "nd", "black_level", "clip_code"):
        if k not in entry:
            raise ValueError(f"crosstalk entry: missing field '{k}'")
    try:
        qscale = _entry_number(entry, "qscale", 0.0, 16.0, lo_open=True)
        qoffset = _entry_number(entry, "qoffset", 0.0, 65535.0 * 16.0)
        nd = _entry_number(entry, "nd", 1.0, 1e6)
        black_level = _entry_number(entry, "black_level", 0.0, 65535.0)
        clip_code = _entry_number(entry, "clip_code", 1, 65535, integer=True)
    except ValueError as e:
        raise ValueError(f"crosstalk entry: {e}") from None
    source = Path(source) if source is not None else Path(base_dir) / "profile.json"
    path = io.resolve_named(source, "crosstalk.file", entry["file"], ValueError, allow_outside)
    if not path.is_file():
        raise ValueError(f"{path}: crosstalk calibration file not found")
    h, w = int(shape[0]), int(shape[1])
    _check_npz_shapes(path, h, w)               # from the array headers, before anything is decompressed
    try:
        with np.load(path, allow_pickle=False) as z:
            arr = {}
            for k in _ARRAYS:
                arr[k] = z[k]
            colour = z["colour"] if "colour" in z.files else None
    except KeyError as e:
        raise ValueError(f"{path}: crosstalk calibration lacks array {e}") from None
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, RuntimeError, NotImplementedError) as e:
        raise ValueError(f"{path}: not a readable crosstalk calibration (.npz): {e}") from None
    for name in _ARRAYS:
        if arr[name].dtype.kind not in "uif":
            raise ValueError(f"{path}: array {name} has type {arr[name].dtype}, expected numbers")
    cq = arr["codes_q"]
    if cq.ndim != 3 or cq.shape[:2] != (h, w) or cq.dtype != np.uint16:
        raise ValueError(f"{path}: LUT is {cq.shape} {cq.dtype}, expected uint16 ({h}, {w}, K) for the "
                         f"profile's {w}x{h} mask")
    k = cq.shape[2]
    for name, want in (("knot_flux", (k,)), ("n_knots", (h, w)), ("clip_flux", (h, w)), ("alpha", (h, w))):
        if arr[name].shape != want:
            raise ValueError(f"{path}: array {name} has shape {arr[name].shape}, expected {want} (a calibration "
                             f"of this {w}x{h} sensor with {k} knots)")
    if arr["sigma"].ndim != 2 or arr["sigma"].shape[0] != 8 or arr["sig_e"].ndim != 1 \
            or arr["sigma"].shape[1] != arr["sig_e"].shape[0]:
        raise ValueError(f"{path}: neighbour spill table has shape {arr['sigma'].shape} for signals "
                         f"{arr['sig_e'].shape}, expected (8, J) and (J,)")
    if k < 1 or k > 255:
        raise ValueError(f"{path}: the LUT holds {k} knots per pixel, expected 1..255")
    nk = arr["n_knots"]
    if nk.dtype.kind == "f" and not np.array_equal(nk, np.floor(nk)) or nk.min(initial=0) < 0 \
            or nk.max(initial=0) > k:
        raise ValueError(f"{path}: knot counts must be integers in 0..{k} (corrupt calibration)")
    nk = nk.astype(np.int32)
    kf = arr["knot_flux"].astype(np.float64)
    if not np.all(np.isfinite(kf)) or np.any(kf < 0) or np.any(np.diff(kf) <= 0):
        raise ValueError(f"{path}: knot fluxes must be finite, >= 0 and strictly increasing")
    down = (cq[:, :, 1:] < cq[:, :, :-1]) & (np.arange(1, k) < nk[:, :, None])
    if down.any():
        bad = np.argwhere(down)
        y, x = int(bad[0][0]), int(bad[0][1])
        raise ValueError(f"{path}: the knot codes of {len(np.unique(bad[:, :2], axis=0))} pixels decrease "
                         f"(first at y={y}, x={x}): a pixel's codes must not decrease with flux")
    cf = arr["clip_flux"].astype(np.float32)
    if np.any(np.isinf(cf)) or np.any(cf <= 0):
        raise ValueError(f"{path}: clip fluxes must be positive (NaN: never clipped), found "
                         f"{int(np.sum(np.isinf(cf) | (cf <= 0)))} others")
    al = arr["alpha"].astype(np.float32)
    if not np.all(np.isfinite(al)):
        raise ValueError(f"{path}: crosstalk amplitudes (alpha) must be finite")
    se, sg = arr["sig_e"].astype(np.float64), arr["sigma"].astype(np.float64)
    if not np.all(np.isfinite(sg)) or not np.all(np.isfinite(se)):
        raise ValueError(f"{path}: neighbour spill table contains non-finite values")
    # what the numba kernels index without bounds checks must be well-formed
    if se.shape[0] < 2 or np.any(np.diff(se) < 0):
        raise ValueError(f"{path}: neighbour spill table signals must be an increasing 1-D array of at least "
                         f"2 values, got shape {se.shape}")
    if not np.all(np.isfinite(se.astype(np.float32))) or not np.all(np.isfinite(sg.astype(np.float32))):
        raise ValueError(f"{path}: neighbour spill table values overflow float32")
    if colour is not None:
        if colour.dtype.kind != "f" or not np.all(np.isfinite(colour)):
            raise ValueError(f"{path}: per-colour crosstalk amplitudes (colour) must be finite numbers")
        colour = np.ascontiguousarray(colour.astype(np.float32))
    info = entry.get("info") or {}
    if not isinstance(info, dict):
        raise ValueError(f"crosstalk entry: field 'info' must be an object, got {type(info).__name__}")
    return CrosstalkCalibration(
        codes_q=np.ascontiguousarray(cq), qscale=qscale, qoffset=qoffset,
        n_knots=nk, knot_flux=kf, clip_flux=cf, nd=nd, black_level=black_level,
        clip_code=clip_code, sig_e=se.astype(np.float32),
        sigma=np.ascontiguousarray(sg.astype(np.float32)),
        alpha=al, info=dict(info), colour=colour)


# ======================================================================================================
# Correction kernels (numba)
# ======================================================================================================

# The full table as the kernels take it (`lut_record`): codes_q (H, W, K) uint16, n_knots (H, W), knot_flux
# (K,) float64, clip_flux (H, W) float32 and its scalars `LutScale`. A kernel unpacks it before its pixel
# loop: an array read out of a tuple inside the loop costs a reference count per pixel.
Lut = namedtuple("Lut", "codes_q n_knots knot_flux clip_flux scale")
# float32 quantisation of the knot codes (code = q * qs - qo, `quantize_codes`); clip_rel: clip code - black
LutScale = namedtuple("LutScale", "qs qo clip_rel")
# the `kernel` mode's neighbour model: the 8 directions (DIRS), the spill table sigma (8, J) at the source
# signals sig_e (J,) and the per-pixel crosstalk amplitude alpha (H, W) (`CrosstalkCalibration`)
Spill = namedtuple("Spill", "dirs sig_e sigma alpha")
# the `kernel` mode's scalars: ND, iterations per pass, the clipped-spill share (`correct`)
KernelParams = namedtuple("KernelParams", "nd iters clip_share")
# `_correct_kernel`'s colour arguments on a monochrome sensor (unused)
_NO_COLOUR = np.ones((3, 1, 1), np.float32)
_NO_CHANNELS = np.zeros((1, 1), np.uint8)


def lut_record(calib: CrosstalkCalibration) -> Lut:
    """The kernels' view of a calibration's full table (no copy)."""
    return Lut(calib.codes_q, calib.n_knots, calib.knot_flux, calib.clip_flux,
               LutScale(np.float32(calib.qscale), np.float32(calib.qoffset),
                        np.float32(float(calib.clip_code) - float(calib.black_level))))


@njit(cache=True, nogil=True, inline="always")
def code_threshold(m, qs, qo):
    """The smallest quantised code Q with Q * qs - qo >= m (`quantize_codes`): that float32 map is monotone
    in Q, so a knot's code is >= m exactly when its quantised code is >= Q."""
    qe = int(math.ceil((np.float64(m) + np.float64(qo)) / np.float64(qs)))
    qe = min(max(qe, 0), 65536)
    while qe <= 65535 and np.float32(qe) * qs - qo < m:
        qe += 1
    while qe > 0 and np.float32(qe - 1) * qs - qo >= m:
        qe -= 1
    return qe


@njit(cache=True, nogil=True, inline="always")
def lut_eval(codes_q, knot_flux, scale, y, x, n, cflux, m, qe=-1):
    """Flux of code `m` (above black) on pixel (y, x)'s calibrated code-to-flux curve (paper 3.2): the one
    evaluator of the full table (`Lut`'s arrays, `scale` its `LutScale`), used by the `lut` and `kernel`
    modes and by `compact_lut`. Returns (flux, ok); ok is False above the calibrated range, without a range
    (n < 2) or for NaN.

    Piecewise linear through the pixel's n knots (code_k = codes_q * qs - qo, flux knot_flux[k]); below the
    dark knot c0 the chord from (black level, flux 0), never negative; above the last knot up to the clip
    code (`clip_rel`) towards the pixel's clipping flux `cflux` when it was measured. Inside the range the
    knot is found without a data-dependent branch per step: 1 + the count of knots 1..n-1 whose quantised
    code is below `code_threshold(m)` (the knots increase), the same bracket as a binary search. `qe`: that
    threshold when the caller has it (one code for many pixels), else -1."""
    qs, qo, clip_rel = scale
    if n < 2:
        return np.float32(0.0), False
    c0 = np.float32(codes_q[y, x, 0]) * qs - qo
    if m <= c0:
        f0 = max(np.float32(knot_flux[0]), np.float32(0.0))
        if c0 > 0:
            return f0 * (max(m, np.float32(0.0)) / c0), True
        return f0, True
    last_c = np.float32(codes_q[y, x, n - 1]) * qs - qo
    if m <= last_c:
        if qe < 0:
            qe = code_threshold(m, qs, qo)
        cnt = 0
        for k in range(1, n):
            cnt += 1 if np.int32(codes_q[y, x, k]) < qe else 0
        lo = 1 + cnt
        c = np.float32(codes_q[y, x, lo]) * qs - qo
        pc = np.float32(codes_q[y, x, lo - 1]) * qs - qo
        f = np.float32(knot_flux[lo])
        pf = np.float32(knot_flux[lo - 1])
        return pf + (m - pc) * (f - pf) / max(c - pc, np.float32(1e-3)), True
    prev_f = np.float32(knot_flux[n - 1])
    # between the last knot and the clipping point (measured: the pixel clipped before the next knot)
    if cflux == cflux and clip_rel > last_c and m <= clip_rel:
        return prev_f + (m - last_c) * (cflux - prev_f) / (clip_rel - last_c), True
    return np.float32(0.0), False


@njit(cache=True, nogil=True, parallel=True)
def _lut_kernel(values, state, lut, nd):
    """`lut` mode in place with the full table: VALID pixels take their LUT flux (UNCALIBRATED outside the
    range), DARK pixels their bound's flux when positive, CLIPPED pixels at most their clipping flux."""
    h, w = values.shape
    ndf = np.float32(nd)
    codes_q, n_knots, knot_flux, clip_flux, table_scale = lut
    qs, qo, clip_rel = table_scale
    for y in prange(h):
        scale = LutScale(qs, qo, clip_rel)      # a tuple captured by a parfor does not lower
        for x in range(w):
            st = state[y, x]
            reason = st & REASON_MASK
            if reason == CLIPPED:
                cf = clip_flux[y, x]
                if cf == cf and cf < values[y, x]:
                    values[y, x] = cf
                continue
            if reason != VALID and reason != DARK:
                continue
            att = (st & ATTENUATED) != 0
            s = ndf if att else np.float32(1.0)
            f, ok = lut_eval(codes_q, knot_flux, scale, y, x, n_knots[y, x], clip_flux[y, x], values[y, x] / s)
            if reason == VALID:
                if ok:
                    values[y, x] = f
                else:
                    state[y, x] = (st & FLAG_MASK) | UNCALIBRATED
            elif ok and f > 0:
                values[y, x] = f


# ---- compact LUT: the `lut` mode's fast setting (docs/CROSSTALK.md "Compact LUT") ------------------------
# The full table holds K uint16 knot codes per pixel (K = 40: 166 MB at 1080p) and searches them for every
# pixel of every frame (~30 ms per 1080p frame on one core). The compact form is derived from it at load
# time: each pixel's correction D(m) = F(m) / s - m (flux in code units minus the code, s = ND or 1) sampled
# at COMPACT_POINTS codes m_j = top * (j / G)^2 (dense at low codes, where the curves bend at the dark
# level), stored as int16 (one scale per pixel group) in a 32-byte record with the pixel's dark knot and the
# top of its range. Evaluating it is a square root, two reads and a lerp: no search. Error against the full
# table: docs/CROSSTALK.md "Compact LUT" (a low-rank model of the same curves, rank 8 of the pixels x grid
# matrix, has about the same error and costs 4x more per pixel).

COMPACT_POINTS = 14                 # grid points per pixel (G = 13 segments); + c0 + top = 16 int16 = 32 bytes
LUT_FORMS = ("full", "compact")
# record[14], [15]: the raw uint16 knot codes (codes_q) of the pixel's dark knot and of the top of its range,
# so that both decode to exactly the full table's floats; [15] may instead be one of (never a knot below clip):
_TOP_IS_CLIP = 65535                # the range ends at the clip code (the usual case)
_NO_RANGE = 65534                   # fewer than 2 knots: every code UNCALIBRATED


@dataclasses.dataclass(eq=False)
class CompactLut:
    """Compact form of a `CrosstalkCalibration`'s LUT (`compact_lut`). rec (H, W, 16) int16: the pixel's
    correction at the grid codes in units of dscale[group] (group 0 regular, 1 attenuated), then the raw
    uint16 knot codes of its dark knot and of its range's top (or _TOP_IS_CLIP / _NO_RANGE), decoded as
    `q * qscale - qoffset` like the full table's. f0: flux of the dark knot; clip_rel: clip code - black."""
    rec: np.ndarray
    dscale: np.ndarray
    clip_rel: float
    qscale: float
    qoffset: float
    f0: float
    nd: float
    info: dict = dataclasses.field(default_factory=dict)

    def record(self) -> CompactRecord:
        """The kernels' view of this LUT (float32 scalars, no copy)."""
        return CompactRecord(self.rec, self.dscale, np.float32(self.clip_rel), np.float32(self.qscale),
                             np.float32(self.qoffset), np.float32(self.f0), self.nd)


# `CompactLut` as `_lut_kernel_compact` takes it
CompactRecord = namedtuple("CompactRecord", "rec dscale clip_rel qs qo f0 nd")


@njit(cache=True, nogil=True, parallel=True)
def _grid_residual(lut, ys, xs, s_px, gcodes, out, rng_out):
    """out[i, j] = F(m_j) / s - m_j for pixel (ys[i], xs[i]) at the grid codes m_j = gcodes[j] from its full
    LUT `lut` (`Lut`); below the pixel's dark knot c0 the chord from (c0, 0) to the first grid code above it
    is continued, above its range its last segment (the compact form's lerp then follows it up to the
    range's top). rng_out[i] = (c0, top)."""
    n_pix, g = out.shape
    codes_q, n_knots, knot_flux, clip_flux, table_scale = lut
    qs, qo, clip_rel = table_scale
    gq = np.empty(g, np.int64)
    for j in range(g):
        gq[j] = code_threshold(gcodes[j], qs, qo)
    for i in prange(n_pix):
        scale = LutScale(qs, qo, clip_rel)      # a tuple captured by a parfor does not lower
        y = ys[i]
        x = xs[i]
        n = n_knots[y, x]
        s = s_px[i]
        cf = clip_flux[y, x]
        if n < 2:
            for j in range(g):
                out[i, j] = np.float32(0.0)
            rng_out[i, 0] = np.float32(0.0)
            rng_out[i, 1] = np.float32(-1.0)     # empty range: every code is out of range
            continue
        c0 = np.float32(codes_q[y, x, 0]) * qs - qo
        last_c = np.float32(codes_q[y, x, n - 1]) * qs - qo
        top = clip_rel if (cf == cf and clip_rel > last_c) else last_c
        rng_out[i, 0] = c0
        rng_out[i, 1] = top
        first = -1
        last = -1
        for j in range(g):
            m = gcodes[j]
            if m > c0 and m <= top:
                f, ok = lut_eval(codes_q, knot_flux, scale, y, x, n, cf, m, gq[j])
                out[i, j] = f / s - m
                if first < 0:
                    first = j
                last = j
        if first < 0:      # range narrower than a grid step: evaluate at its top
            f, ok = lut_eval(codes_q, knot_flux, scale, y, x, n, cf, top)
            for j in range(g):
                out[i, j] = f / s - top
            continue
        mf = gcodes[first]
        slope = (out[i, first] + mf) / max(mf - c0, np.float32(1e-3))   # F/s per code from (c0, 0)
        for j in range(first):
            m = gcodes[j]
            out[i, j] = (m - c0) * slope - m
        # above the range (a pixel without clipping point ends at its last knot): its last segment continued,
        # so that the lerp between the grid codes around its top follows that segment
        pc = np.float32(codes_q[y, x, n - 2]) * qs - qo
        pf = np.float32(knot_flux[n - 2])
        sl = (np.float32(knot_flux[n - 1]) - pf) / max(last_c - pc, np.float32(1e-3))
        for j in range(last + 1, g):
            m = gcodes[j]
            out[i, j] = (np.float32(knot_flux[n - 1]) + (m - last_c) * sl) / s - m


def compact_lut(calib: CrosstalkCalibration, mask: np.ndarray, nd: float, chunk: int = 262144) -> CompactLut:
    """Derive the compact LUT from the full table (load time, about a second at 1080p)."""
    h, w = calib.shape
    mask = np.asarray(mask, bool)
    if mask.shape != (h, w):
        raise ValueError(f"mask is {mask.shape[1]}x{mask.shape[0]} but the calibration is {w}x{h}")
    g = COMPACT_POINTS - 1
    clip_rel = np.float32(float(calib.clip_code) - float(calib.black_level))
    gcodes = (clip_rel * (np.arange(COMPACT_POINTS) / g) ** 2).astype(np.float32)
    lut = lut_record(calib)
    d_all = np.empty((h * w, COMPACT_POINTS), np.float32)
    rng_all = np.empty((h * w, 2), np.float32)
    ys, xs = np.divmod(np.arange(h * w, dtype=np.int64), w)
    s_px = np.where(mask.reshape(-1), np.float32(nd), np.float32(1.0))
    for a in range(0, h * w, chunk):
        b = min(a + chunk, h * w)
        _grid_residual(lut, ys[a:b], xs[a:b], s_px[a:b], gcodes, d_all[a:b], rng_all[a:b])
    att = mask.reshape(-1)
    dscale = np.ones(2, np.float32)
    for grp in (0, 1):
        sel = att == bool(grp)
        if np.any(sel):
            dscale[grp] = max(float(np.max(np.abs(d_all[sel]))), 1e-3) / 32000.0
    rec = np.empty((h * w, 16), np.int16)
    rec[:, :COMPACT_POINTS] = np.rint(d_all / dscale[att.astype(np.int64)][:, None]).astype(np.int16)
    n = calib.n_knots.reshape(-1).astype(np.int64)
    cq = calib.codes_q.reshape(h * w, -1)
    q_last = cq[np.arange(h * w), np.clip(n - 1, 0, cq.shape[1] - 1)].astype(np.int64)
    top_q = np.where(n < 2, _NO_RANGE, np.where(rng_all[:, 1] >= clip_rel, _TOP_IS_CLIP, q_last))
    rec[:, 14] = cq[:, 0].view(np.int16)
    rec[:, 15] = top_q.astype(np.uint16).view(np.int16)
    return CompactLut(rec=rec.reshape(h, w, 16), dscale=dscale, clip_rel=float(clip_rel),
                      qscale=float(calib.qscale), qoffset=float(calib.qoffset),
                      f0=max(float(calib.knot_flux[0]), 0.0), nd=float(nd),
                      info={"points": COMPACT_POINTS, "no_range_pixels": int(np.sum(n < 2))})


@njit(cache=True, nogil=True, inline="always")
def _compact_fetch(rec, y, x, m, inv_step, g, clip_rel, qs, qo):
    """The reads of code `m` on pixel (y, x)'s compact record `rec` (`CompactLut`): (c0, top, a, b), its
    dark knot's code, its range's top (-inf without a range) and the grid values around m
    (`_compact_line`, `_compact_at` evaluate them; split so that the arithmetic runs without gathers)."""
    c0 = np.float32(np.int64(rec[y, x, 14]) & 0xFFFF) * qs - qo
    tq = np.int64(rec[y, x, 15]) & 0xFFFF
    top = clip_rel if tq == _TOP_IS_CLIP else np.float32(tq) * qs - qo
    top = -np.inf if tq == _NO_RANGE else top
    mm = max(min(max(m, c0), top), np.float32(0.0))
    j = min(np.int32(np.sqrt(mm * inv_step)), np.int32(g - 1))
    return c0, top, np.float32(rec[y, x, j]), np.float32(rec[y, x, j + 1])


@njit(cache=True, nogil=True, inline="always")
def _compact_line(m, c0, top, a, b, dsc, inv_step, g):
    """The compact LUT's correction around code m as a line in u = sqrt(code x inv_step): (d0, du) with
    correction(m') = d0 + du u' for every m' of m's grid segment (a, b: `_compact_fetch`'s grid values,
    dsc: the pixel's group's scale)."""
    mm = max(min(max(m, c0), top), np.float32(0.0))
    j = min(np.int32(np.sqrt(mm * inv_step)), np.int32(g - 1))
    du = (b - a) * dsc
    return a * dsc - np.float32(j) * du, du


@njit(cache=True, nogil=True, inline="always")
def _compact_at(m, c0, d0, du, s, inv_step, f0):
    """Flux of code m (at most the range's top) on the compact LUT's segment (d0, du) (`_compact_line`): a
    square root and a multiply-add, s: ND or 1; below the dark knot c0 between (black, f0) and the knot, as
    `lut_eval`; exact on the segment, the segment continued beyond it. The colour passes keep the segment as
    this line so that `_colour_value` evaluates it at a second code; `_lut_kernel_compact` evaluates it once,
    as a lerp at the code (a + t (b - a), rounded differently)."""
    zero = np.float32(0.0)
    mm = max(max(m, c0), zero)
    f = max((mm + d0 + du * np.sqrt(mm * inv_step)) * s, zero)
    fb = f0 / c0 * max(m, zero) if c0 > zero else f0
    return fb if m <= c0 else f


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _lut_kernel_compact(values, state, c, clip_flux):
    """`lut` mode in place with the compact LUT `c` (`CompactRecord`) and the table's clipping fluxes: the
    same state handling as `_lut_kernel`, written without data-dependent branches (attenuated and regular
    pixels alternate at random in the mask)."""
    h, w = values.shape
    rec, dscale, clip_rel, qs, qo, f0, nd = c.rec, c.dscale, c.clip_rel, c.qs, c.qo, c.f0, c.nd
    g = rec.shape[2] - 3
    inv_step = np.float32(g * g) / clip_rel
    ndf = np.float32(nd)
    sc = np.empty(2, np.float32)
    sc[0] = 1.0
    sc[1] = ndf
    inv = np.empty(2, np.float32)
    inv[0] = 1.0
    inv[1] = np.float32(1.0) / ndf
    zero = np.float32(0.0)
    for y in prange(h):
        for x in range(w):
            st = state[y, x]
            v = values[y, x]
            grp = np.int64((st & ATTENUATED) != 0)    # group 1: attenuated
            s = sc[grp]
            m = v * inv[grp]
            c0 = np.float32(np.int64(rec[y, x, 14]) & 0xFFFF) * qs - qo
            tq = np.int64(rec[y, x, 15]) & 0xFFFF
            top = clip_rel if tq == _TOP_IS_CLIP else np.float32(tq) * qs - qo
            mm = max(min(max(m, c0), top), zero)
            u = np.sqrt(mm * inv_step)
            j = min(np.int64(u), g - 1)
            t = u - np.float32(j)
            a = np.float32(rec[y, x, j])
            d = (a + t * (np.float32(rec[y, x, j + 1]) - a)) * dscale[grp]
            f = max((mm + d) * s, zero)
            # below the dark knot: between (black, f0) and the knot, as `lut_eval`
            fb = f0 * (max(m, zero) / c0) if c0 > zero else f0
            f = fb if m <= c0 else f
            # bitwise & |, not `and`: short-circuits compile to branches (2x slower on a random mask)
            ok = (m <= top) & (tq != _NO_RANGE)
            reason = st & REASON_MASK
            cf = clip_flux[y, x]
            nv = v
            nv = f if ((reason == VALID) & ok) | ((reason == DARK) & ok & (f > zero)) else nv
            nv = cf if ((reason == CLIPPED) & (cf < v)) else nv     # NaN clip flux: no change
            values[y, x] = nv
            # (reason VALID is 0: st | UNCALIBRATED is (st & FLAG_MASK) | UNCALIBRATED; arithmetic, not a
            # select: 2x faster)
            state[y, x] = st | (np.uint8(UNCALIBRATED) * np.uint8((reason == VALID) & (not ok)))


@njit(cache=True, nogil=True)
def _spill_vec(sig_e, sigma, e, out):
    """out[d] = sigma_d(e) for the 8 directions with a single table search: piecewise linear in the table,
    linear through 0 below it, its last slope above it."""
    j = sig_e.shape[0]
    if e <= sig_e[0]:
        r = e / sig_e[0] if sig_e[0] > 0 else np.float32(0.0)
        for d in range(8):
            out[d] = sigma[d, 0] * r
        return
    if e >= sig_e[j - 1]:
        dx = max(sig_e[j - 1] - sig_e[j - 2], np.float32(1e-6))
        for d in range(8):
            out[d] = sigma[d, j - 1] + (e - sig_e[j - 1]) * (sigma[d, j - 1] - sigma[d, j - 2]) / dx
        return
    lo = 0
    hi = j - 1
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if sig_e[mid] <= e:
            lo = mid
        else:
            hi = mid
    t = (e - sig_e[lo]) / (sig_e[hi] - sig_e[lo])
    for d in range(8):
        out[d] = sigma[d, lo] + t * (sigma[d, hi] - sigma[d, lo])


@njit(cache=True, nogil=True, parallel=True)
def _source_spill(est, state, nd, sig_e, sigma, out):
    """out[d, y, x] = sigma_d(signal of (y, x) as a source): what it sends to the target at -d."""
    h, w = est.shape
    for y in prange(h):
        buf = np.empty(8, np.float32)
        for x in range(w):
            t = np.float32(1.0) / np.float32(nd) if (state[y, x] & ATTENUATED) != 0 else np.float32(1.0)
            _spill_vec(sig_e, sigma, est[y, x] * t, buf)
            for d in range(8):
                out[d, y, x] = buf[d]


@njit(cache=True, nogil=True, parallel=True)
def _lut_pass(values, state, lut, nd, lut_out, ok_out):
    """lut_out = flux of every pixel's value in the full table `lut` (`Lut`) (for VALID pixels; others keep
    their bound)."""
    h, w = values.shape
    codes_q, n_knots, knot_flux, clip_flux, table_scale = lut
    qs, qo, clip_rel = table_scale
    for y in prange(h):
        scale = LutScale(qs, qo, clip_rel)      # a tuple captured by a parfor does not lower
        for x in range(w):
            st = state[y, x]
            s = np.float32(nd) if (st & ATTENUATED) != 0 else np.float32(1.0)
            v = values[y, x]
            lut_out[y, x] = v
            ok_out[y, x] = False
            if (st & REASON_MASK) == VALID:
                f, ok = lut_eval(codes_q, knot_flux, scale, y, x, n_knots[y, x], clip_flux[y, x], v / s)
                if ok:
                    lut_out[y, x] = f
                    ok_out[y, x] = True


@njit(cache=True, nogil=True, parallel=True)
def _correct_kernel(values, state, src, est, src_spill, lut, spill, par, colour, chan, every, coloured):
    """`kernel` mode: each VALID pixel's flux in the full table `lut` (`Lut`) after removing the difference
    between the spill its actual neighbours send (`src_spill`) and what flat neighbours at its flux would
    send (`spill`: `Spill`), scaled by the pixel's amplitude alpha, `par.iters` times (`par`:
    `KernelParams`); CLIPPED and DARK/NOISY pixels as in `_lut_kernel`. `coloured` (a Bayer mosaic, `chan`
    its channel plane): the amplitude is the pixel's for the neighbour's colour (`colour` (3, H, W), alpha
    for its own colour); `every` False (`lut` mode on a colour profile) skips the same-colour neighbours
    (the LUT assumes them as bright as the pixel) and the clipped-spill rule. Monochrome: `colour` and
    `chan` are unused placeholders, `every` True."""
    h, w = values.shape
    codes_q, n_knots, knot_flux, clip_flux, table_scale = lut
    dirs, sig_e, sigma, alpha = spill.dirs, spill.sig_e, spill.sigma, spill.alpha
    nd, iters, clip_share = par.nd, par.iters, par.clip_share
    qs, qo, clip_rel = table_scale
    ndf = np.float32(nd)
    for y in prange(h):
        scale = LutScale(qs, qo, clip_rel)      # a tuple captured by a parfor does not lower
        flat_att = np.empty(8, np.float32)
        flat_reg = np.empty(8, np.float32)
        acc = np.empty(3, np.float32)           # spill difference per neighbour colour (monochrome: [0])
        clp = np.empty(3, np.float32)           # spill from clipped neighbours per colour
        amp = np.empty(3, np.float32)
        for x in range(w):
            st = state[y, x]
            reason = st & REASON_MASK
            att = (st & ATTENUATED) != 0
            s = ndf if att else np.float32(1.0)
            n = n_knots[y, x]
            cf = clip_flux[y, x]
            if reason == VALID:
                m = src[y, x] / s
                f, ok = lut_eval(codes_q, knot_flux, scale, y, x, n, cf, m)
                if not ok:
                    state[y, x] = (st & FLAG_MASK) | UNCALIBRATED
                    continue
                a = alpha[y, x]
                own = chan[y, x] if coloured else np.uint8(0)
                if coloured:
                    for c in range(3):
                        amp[c] = a if c == own else colour[c, y, x]
                from_clipped = np.float32(0.0)
                for _ in range(iters):
                    # what flat neighbours at this pixel's flux would send (the LUT's assumption)
                    _spill_vec(sig_e, sigma, f / ndf, flat_att)
                    _spill_vec(sig_e, sigma, f, flat_reg)
                    for c in range(3):
                        acc[c] = 0.0
                        clp[c] = 0.0
                    for d in range(8):
                        yy = y + dirs[d, 0]
                        xx = x + dirs[d, 1]
                        if yy < 0 or yy >= h or xx < 0 or xx >= w:
                            continue
                        c = chan[yy, xx] if coloured else np.uint8(0)
                        if coloured and c == own and not every:
                            continue
                        stn = state[yy, xx]
                        if (stn & REASON_MASK) == DARK and est[yy, xx] > f:
                            continue        # an upper bound only: assume no brighter than this pixel
                        flat = flat_att[d] if (stn & ATTENUATED) != 0 else flat_reg[d]
                        acc[c] += src_spill[d, yy, xx] - flat
                        if (stn & REASON_MASK) == CLIPPED:
                            clp[c] += src_spill[d, yy, xx]
                    if coloured:
                        delta = amp[0] * acc[0] + amp[1] * acc[1] + amp[2] * acc[2]
                        from_clipped = amp[0] * clp[0] + amp[1] * clp[1] + amp[2] * clp[2]
                    else:
                        delta = a * acc[0]
                        from_clipped = a * clp[0]
                    f2, ok2 = lut_eval(codes_q, knot_flux, scale, y, x, n, cf, m - delta)
                    if not ok2:
                        break
                    f = f2
                if f < 0:
                    f = np.float32(0.0)
                if every and from_clipped > clip_share * max(f / s, np.float32(1.0)):
                    # more spill from clipped neighbours than own signal: their flux is only an
                    # estimate (>= their bound), so this pixel is unreliable; leave it to reconstruction
                    values[y, x] = f
                    state[y, x] = (st & FLAG_MASK) | UNCALIBRATED
                    continue
                values[y, x] = f
            elif reason == CLIPPED:
                # the true flux is at least the flux at which this pixel clips
                if cf == cf and cf < values[y, x]:
                    values[y, x] = cf
            elif reason == DARK or reason == NOISY:
                f, ok = lut_eval(codes_q, knot_flux, scale, y, x, n, cf, src[y, x] / s)
                if ok and f > 0:
                    values[y, x] = f


@njit(cache=True, nogil=True, parallel=True)
def _neighbour_estimate(values, state, lut, ok, dirs, est, chan, step):
    """Flux estimate of every pixel as a crosstalk source: LUT flux where known; a clipped pixel is at
    least its bound and at least as bright as its brightest known neighbour; others their value. `step`
    1: every neighbour; 2 (a Bayer mosaic, `chan` its channel plane): same-colour neighbours only, in the
    colour plane's 3 x 3 and 5 x 5 (the other colours say nothing of this one's flux)."""
    h, w = values.shape
    for y in prange(h):
        for x in range(w):
            reason = state[y, x] & REASON_MASK
            v = lut[y, x]
            if reason == CLIPPED:
                # a clipped neighbour's bound (e.g. an attenuated pixel's clipping flux) is a lower bound
                # for this pixel too: the region is at least that bright
                for dy in range(-step, step + 1):
                    for dx in range(-step, step + 1):
                        yy = y + dy
                        xx = x + dx
                        if 0 <= yy < h and 0 <= xx < w and (state[yy, xx] & REASON_MASK) == CLIPPED \
                                and lut[yy, xx] > v and (step == 1 or chan[yy, xx] == chan[y, x]):
                            v = lut[yy, xx]
                acc = np.float32(0.0)
                n = 0
                for dy in range(-2 * step, 2 * step + 1):
                    for dx in range(-2 * step, 2 * step + 1):
                        yy = y + dy
                        xx = x + dx
                        if 0 <= yy < h and 0 <= xx < w and ok[yy, xx] and lut[yy, xx] > v \
                                and (step == 1 or chan[yy, xx] == chan[y, x]):
                            acc += lut[yy, xx]
                            n += 1
                if n > 0:
                    v = acc / n
            est[y, x] = v


# ---- colour compact: the `lut` mode's fast setting on a colour calibration (docs/CROSSTALK.md 4b) ---------
# The compact LUT per pixel plus the per-colour correction of `_correct_kernel` (every=False), one iteration,
# in three passes: `_colour_compact_planes` evaluates each pixel's compact LUT once into planes (its spill as a
# source, its LUT segment as a target), `_colour_compact_clipped` estimates the clipped pixels' flux from their
# colour's photosites, `_colour_compact_correct` subtracts the other-colour spill difference in a loop without
# gathers (it vectorises) and reads the compact record again only where the corrected code left its segment.

# the spill table as the colour compact kernels read it: sigma_d(e) resampled at the signals e_i = i / inv_de,
# i < SPILL_GRID, up to the table's last signal, in its rank-2 form sigma_d(e) ~ sum_k weight[d, k] basis_k(e)
# (SVD; `spill_basis`): a source's spill to all 8 neighbours is 2 numbers, the plane pass computes them once
SpillBasis = namedtuple("SpillBasis", "basis weight inv_de")
SPILL_GRID = 2048
SPILL_RANK = 2


def spill_basis(calib: CrosstalkCalibration) -> SpillBasis:
    """`SpillBasis` of a calibration's spill table (sig_e, sigma): `_spill_vec`'s function (linear through 0
    below the table, its last slope above it: the last cell's lerp continued) at SPILL_GRID uniform signals,
    reduced to its best rank-SPILL_RANK approximation (exact for a spill that is one signal curve per
    mechanism, coupling and blooming, times a 3 x 3 shape each: `SensorModel`); a component below 1e-6 of
    the first is dropped (it would be denormal in float32). Derived once per calibration and kept on it."""
    hit = calib.__dict__.get("_spill_basis")
    if hit is not None and hit[0] is calib.sigma and hit[1] is calib.sig_e:
        return hit[2]
    sig_e = np.asarray(calib.sig_e, np.float64)
    sigma = np.asarray(calib.sigma, np.float64)
    top = float(sig_e[-1]) if sig_e[-1] > 0 else 1.0
    e = np.linspace(0.0, top, SPILL_GRID)
    if sig_e[0] > 0:
        xs, ys = np.concatenate([[0.0], sig_e]), np.concatenate([np.zeros((8, 1)), sigma], 1)
    else:
        xs, ys = sig_e, sigma
    table = np.stack([np.interp(e, xs, ys[d]) for d in range(8)], 1)          # (G, 8)
    u, sv, vt = np.linalg.svd(table, full_matrices=False)
    keep = sv[:SPILL_RANK] > 1e-6 * max(sv[0], 1e-30)    # a component at rounding level would be denormal
    basis = np.where(keep, u[:, :SPILL_RANK] * sv[:SPILL_RANK], 0.0)             # (G, R)
    weight = np.where(keep, vt[:SPILL_RANK].T, 0.0)                              # (8, R)
    sb = SpillBasis(np.ascontiguousarray(basis, np.float32), np.ascontiguousarray(weight, np.float32),
                    np.float32((SPILL_GRID - 1) / top))
    calib.__dict__["_spill_basis"] = (calib.sigma, calib.sig_e, sb)
    return sb


@njit(cache=True, nogil=True, inline="always")
def _basis_at(basis, k, q):
    """basis_k at grid coordinate q = e * inv_de (`SpillBasis`): a lerp, the last cell continued above, the
    first cell continued below and for q >= 9.2e18 or NaN. The cell index is an int32 conversion (one
    instruction for 8 lanes with AVX2; int64 is converted lane by lane)."""
    qq = q if q < np.float32(9.2e18) else np.float32(-1.0)
    i = min(max(np.int32(min(qq, np.float32(1e9))), np.int32(0)), np.int32(basis.shape[0] - 2))
    t = q - np.float32(i)
    a = basis[i, k]
    return a + t * (basis[i + 1, k] - a)


def colour_pairs(calib: CrosstalkCalibration, cfa: str) -> np.ndarray:
    """(2, H, W) float32: the per-colour amplitudes (`CrosstalkCalibration.colour`) a photosite of the Bayer
    mosaic `cfa` applies to its other-colour neighbours: [0] for its left/right neighbours' colour, [1] for
    its diagonal neighbours' colour (red, blue photosites: their up/down neighbours are green
    like the left/right ones) or its up/down neighbours' colour (green photosites: their diagonals are
    green).
    Derived once per calibration and mosaic and kept on the calibration."""
    from . import cfa as cfas
    hit = calib.__dict__.get("_colour_pairs")
    if hit is not None and hit[0] is calib.colour and hit[1] == cfa:
        return hit[2]
    blk = cfas.block(cfa).astype(np.int64)
    h, w = calib.shape
    out = np.empty((2, h, w), np.float32)
    for py in range(2):
        for px in range(2):
            own, c_h, c_v, c_d = blk[py, px], blk[py, 1 - px], blk[1 - py, px], blk[1 - py, 1 - px]
            out[0, py::2, px::2] = calib.colour[c_h, py::2, px::2]
            out[1, py::2, px::2] = calib.colour[c_v if c_d == own else c_d, py::2, px::2]
    calib.__dict__["_colour_pairs"] = (calib.colour, cfa, out)
    return out


@njit(cache=True, nogil=True, inline="always")
def _pick(k, a, b):
    """a where k (float32) is 1, b where it is 0: exact for finite a, b, and no branch (the mask's groups
    alternate at random)."""
    return k * a + (np.float32(1.0) - k) * b


# the colour compact kernels' working planes, float32 (K, H, W), per pixel:
# src (as a neighbour): basis values b0, b1 (`SpillBasis`) of its signal (its flux est, / ND if attenuated);
#     its bound if DARK (left out as a neighbour brighter than the target) else -inf
# tgt (as the corrected pixel): est (its compact-LUT flux if VALID and in range, else its value); its compact
#     LUT around its code: dark knot c0, segment d0, du (`_compact_line`), room = the range's top - code; the
#     basis values o0, o1 of a source at est of the other group (regular if it is attenuated, else attenuated)
_SRC_B0, _SRC_B1, _SRC_DARK = 0, 1, 2
_TGT_F, _TGT_C0, _TGT_D0, _TGT_DU, _TGT_ROOM, _TGT_O0, _TGT_O1 = 0, 1, 2, 3, 4, 5, 6
SRC_PLANES, TGT_PLANES = 3, 7


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _colour_compact_planes(values, state, c, basis, inv_de, src, tgt, n_clipped):
    """The planes `src`, `tgt` of every pixel (see _SRC_B0) from its compact LUT `c`: a VALID pixel in range
    is a source at its flux, others at their value (as `_lut_pass`). The target side of `lut` mode too: a
    VALID pixel out of range becomes UNCALIBRATED (value kept), a DARK/NOISY bound is mapped through the
    compact LUT when positive (as `_lut_kernel_compact`); n_clipped[y] = the CLIPPED pixels of row y
    (`_colour_compact_clipped` and the clip-flux bound visit only those rows). Branch-free per pixel."""
    h, w = values.shape
    rec, dscale, clip_rel, qs, qo, f0, nd = c.rec, c.dscale, c.clip_rel, c.qs, c.qo, c.f0, c.nd
    g = rec.shape[2] - 3
    inv_step = np.float32(g * g) / clip_rel
    ndf = np.float32(nd)
    invnd = np.float32(1.0) / ndf
    one = np.float32(1.0)
    zero = np.float32(0.0)
    dsc0 = dscale[0]
    dsc1 = dscale[1]
    # the planes indexed [y, x] from whole-plane views: LLVM does not vectorise a loop that gathers (the record
    # and spill table reads) and stores through row views made inside the prange body
    b0p, b1p, dkp = src[_SRC_B0], src[_SRC_B1], src[_SRC_DARK]
    fp, c0p, d0p, dup, rmp = tgt[_TGT_F], tgt[_TGT_C0], tgt[_TGT_D0], tgt[_TGT_DU], tgt[_TGT_ROOM]
    o0p, o1p = tgt[_TGT_O0], tgt[_TGT_O1]
    for y in prange(h):
        # the record reads (gathers) and the compact LUT's arithmetic in one vectorised loop, as
        # `_lut_kernel_compact`
        for x in range(w):
            st = state[y, x]
            v = values[y, x]
            attf = np.float32((st & ATTENUATED) != 0)
            m = v * _pick(attf, invnd, one)
            c0, top, a, b = _compact_fetch(rec, y, x, m, inv_step, g, clip_rel, qs, qo)
            d0, du = _compact_line(m, c0, top, a, b, _pick(attf, dsc1, dsc0), inv_step, g)
            f = _compact_at(m, c0, d0, du, _pick(attf, ndf, one), inv_step, f0)
            ok = m <= top
            reason = st & REASON_MASK
            valid = (reason == VALID) & ok
            fp[y, x] = f if valid else v
            c0p[y, x] = c0
            d0p[y, x] = d0
            dup[y, x] = du
            rmp[y, x] = top - m
            dkp[y, x] = v if reason == DARK else -np.inf
            values[y, x] = f if ((reason == DARK) | (reason == NOISY)) & ok & (f > zero) else v
            # (VALID is 0: st | UNCALIBRATED is (st & FLAG_MASK) | UNCALIBRATED)
            state[y, x] = st | (np.uint8(UNCALIBRATED) * np.uint8((reason == VALID) & (not ok)))
        # the spill table lookups (gathers) at the flux, in a second vectorised loop (one loop with both sets
        # of gathers vectorises narrower)
        n = 0
        for x in range(w):
            st = state[y, x]
            n += np.int64((st & REASON_MASK) == CLIPPED)
            attf = np.float32((st & ATTENUATED) != 0)
            q = fp[y, x] * inv_de
            q_own = q * _pick(attf, invnd, one)
            q_other = q * _pick(attf, one, invnd)
            b0p[y, x] = _basis_at(basis, 0, q_own)
            b1p[y, x] = _basis_at(basis, 1, q_own)
            o0p[y, x] = _basis_at(basis, 0, q_other)
            o1p[y, x] = _basis_at(basis, 1, q_other)
        n_clipped[y] = n


# the rows of `_colour_compact_clipped`'s work unit (a thread's share) and the columns of its skip test
_CLIP_ROWS = 16
_CLIP_TILE = 64
_CLIP_PAD = 4         # -inf columns each side of `_clip_span`'s VALID flux rows (its 9 x 9 window)


@njit(cache=True, nogil=True, inline="always")
def _span_offset(y, yy, dx, a, b, w, block):
    """For `_clip_span`: the pixels x in [lo, hi) of the span [a, b) of row y whose neighbour (yy, x + dx) is
    in the frame, and whether it has their colour when x is even (f0), odd (f1)."""
    f0 = block[yy & 1, dx & 1] == block[y & 1, 0]
    f1 = block[yy & 1, (dx + 1) & 1] == block[y & 1, 1]
    return max(a, -dx), min(b, w - dx), f0, f1


@njit(cache=True, nogil=True, error_model="numpy")
def _clip_span(y, a, b, r0, cvb, veb, pz, block, mr, ar, cr):
    """`_colour_compact_clipped`'s estimate for the pixels x in [a, b) of row y, into mr (the largest
    CLIPPED value, itself included, of its colour's photosites in its 5 x 5), ar and cr (sum and count of its
    colour's VALID fluxes above mr in its 9 x 9), at x - a. cvb, veb: rows r0.. of the CLIPPED values and
    VALID fluxes (-inf elsewhere; veb with _CLIP_PAD columns of -inf each side); pz[p, x]: 0 where x & 1 == p,
    -inf elsewhere (p = 0, 1), 0 (p = 2). One pass per window row over the span, its offsets dx left to right
    in one loop (the sum's order: window rows top to bottom, columns left to right); the maximum of a span
    within 2 columns of the frame's sides one pass per offset (dy, dx). Loops without branches (they
    vectorise): an offset that reaches the pixel's colour from one column parity only is masked by pz (a -inf
    candidate, a +inf threshold); one outside the frame adds 0."""
    h = r0 + cvb.shape[0]
    w = cvb.shape[1]
    n = b - a
    zero = np.float32(0.0)
    m = mr[:n]
    c = cvb[y - r0, a:b]
    for i in range(n):
        m[i] = c[i]
    for dy in range(-2, 3):
        yy = y + dy
        if yy < r0 or yy >= h:
            continue
        if a >= 2 and b + 2 <= w:
            # away from the frame's sides: the row's offsets in one loop (dx left to right)
            _, _, e0, e1 = _span_offset(y, yy, 0, a, b, w, block)
            _, _, o0, o1 = _span_offset(y, yy, 1, a, b, w, block)
            _max_row(m, cvb[yy - r0, a - 2:b + 2], pz[_pz_row(e0, e1), a:b], pz[_pz_row(o0, o1), a:b], n,
                     e0 or e1, o0 or o1, dy == 0)
            continue
        for dx in range(-2, 3):
            lo, hi, f0, f1 = _span_offset(y, yy, dx, a, b, w, block)
            if (dy == 0 and dx == 0) or not (f0 or f1) or hi <= lo:
                continue
            c = cvb[yy - r0, lo + dx:hi + dx]
            mm = mr[lo - a:hi - a]
            z = pz[0 if f0 else 1, lo:hi]
            # (+ 0: an unconditional store; `if ci > mi: mm[i] = ci` does not vectorise)
            if f0 and f1:
                for i in range(hi - lo):
                    ci = c[i]
                    mi = mm[i]
                    mm[i] = (ci if ci > mi else mi) + zero
            else:
                for i in range(hi - lo):
                    ci = c[i] + z[i]
                    mi = mm[i]
                    mm[i] = (ci if ci > mi else mi) + zero
    acc = ar[:n]
    cnt = cr[:n]
    for i in range(n):
        acc[i] = zero
        cnt[i] = zero
    for dy in range(-4, 5):
        yy = y + dy
        if yy < r0 or yy >= h:
            continue
        # whether an even (e.) / odd (o.) dx reaches the pixel's colour from an even (.0) / odd (.1) x
        _, _, e0, e1 = _span_offset(y, yy, 0, a, b, w, block)
        _, _, o0, o1 = _span_offset(y, yy, 1, a, b, w, block)
        ev = e0 or e1
        od = o0 or o1
        if not (ev or od):
            continue
        e = veb[yy - r0, a:b + 2 * _CLIP_PAD]            # e[i + _CLIP_PAD + dx]: the flux at x + dx
        ze = pz[_pz_row(e0, e1), a:b]
        zo = pz[_pz_row(o0, o1), a:b]
        if ev and od:
            for i in range(n):
                te = mr[i] - ze[i]
                to = mr[i] - zo[i]
                sv, cv = _above(e[i], te, acc[i], cnt[i])
                sv, cv = _above(e[i + 1], to, sv, cv)
                sv, cv = _above(e[i + 2], te, sv, cv)
                sv, cv = _above(e[i + 3], to, sv, cv)
                sv, cv = _above(e[i + 4], te, sv, cv)
                sv, cv = _above(e[i + 5], to, sv, cv)
                sv, cv = _above(e[i + 6], te, sv, cv)
                sv, cv = _above(e[i + 7], to, sv, cv)
                acc[i], cnt[i] = _above(e[i + 8], te, sv, cv)
        elif ev:
            for i in range(n):
                te = mr[i] - ze[i]
                sv, cv = _above(e[i], te, acc[i], cnt[i])
                sv, cv = _above(e[i + 2], te, sv, cv)
                sv, cv = _above(e[i + 4], te, sv, cv)
                sv, cv = _above(e[i + 6], te, sv, cv)
                acc[i], cnt[i] = _above(e[i + 8], te, sv, cv)
        else:
            for i in range(n):
                to = mr[i] - zo[i]
                sv, cv = _above(e[i + 1], to, acc[i], cnt[i])
                sv, cv = _above(e[i + 3], to, sv, cv)
                sv, cv = _above(e[i + 5], to, sv, cv)
                acc[i], cnt[i] = _above(e[i + 7], to, sv, cv)


@njit(cache=True, nogil=True, inline="always")
def _max_row(m, c, ze, zo, n, ev, od, centre):
    """`_clip_span`'s largest CLIPPED values m[:n] with one window row's offsets dx = -2..2 (c[i + 2 + dx]:
    the value at x + dx) taken in, left to right: those of even (ev) / odd (od) dx, masked by ze / zo; the
    centre (dx = 0) left out where `centre`."""
    if ev and od and centre:
        for i in range(n):
            te, to = ze[i], zo[i]
            mi = _larger(c[i] + te, m[i])
            mi = _larger(c[i + 1] + to, mi)
            mi = _larger(c[i + 3] + to, mi)
            m[i] = _larger(c[i + 4] + te, mi)
    elif ev and od:
        for i in range(n):
            te, to = ze[i], zo[i]
            mi = _larger(c[i] + te, m[i])
            mi = _larger(c[i + 1] + to, mi)
            mi = _larger(c[i + 2] + te, mi)
            mi = _larger(c[i + 3] + to, mi)
            m[i] = _larger(c[i + 4] + te, mi)
    elif ev and centre:
        for i in range(n):
            te = ze[i]
            mi = _larger(c[i] + te, m[i])
            m[i] = _larger(c[i + 4] + te, mi)
    elif ev:
        for i in range(n):
            te = ze[i]
            mi = _larger(c[i] + te, m[i])
            mi = _larger(c[i + 2] + te, mi)
            m[i] = _larger(c[i + 4] + te, mi)
    elif od:
        for i in range(n):
            to = zo[i]
            mi = _larger(c[i + 1] + to, m[i])
            m[i] = _larger(c[i + 3] + to, mi)


@njit(cache=True, nogil=True, inline="always")
def _larger(ci, mi):
    """ci where it is larger than mi, else mi, plus 0 (`_clip_span`'s maximum step)."""
    return (ci if ci > mi else mi) + np.float32(0.0)


@njit(cache=True, nogil=True, inline="always")
def _pz_row(f0, f1):
    """The row of `_clip_span`'s pz masking an offset that reaches the pixel's colour from even x only (f0),
    odd x only (f1), both (the row of zeros)."""
    return 2 if f0 and f1 else (0 if f0 else 1)


@njit(cache=True, nogil=True, inline="always")
def _above(e, t, s, c):
    """`_clip_span`'s sum s and count c with the flux e added where e > t."""
    k = e > t
    return s + (e if k else np.float32(0.0)), c + (np.float32(1.0) if k else np.float32(0.0))


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _colour_compact_clipped(values, state, src, tgt, basis, inv_de, nd, block, n_clipped, nt):
    """A CLIPPED pixel's source flux as `_neighbour_estimate` with step 2 (same-colour photosites only): at
    least the largest bound of the clipped ones in the colour plane's 3 x 3, then the mean of the VALID
    ones brighter than that in its 5 x 5 (their `_colour_compact_planes` flux); its `src` basis values
    updated. Visits the rows with CLIPPED pixels (n_clipped), in each the runs of _CLIP_TILE columns with
    CLIPPED pixels (`_clip_span`); the row groups interleaved over `nt` threads (`scratch.interleaved`)."""
    h, w = values.shape
    inv_att = np.float32(1.0) / np.float32(nd)
    ninf = np.float32(-np.inf)
    pz = np.empty((3, w), np.float32)
    for x in range(w):
        pz[x & 1, x] = np.float32(0.0)
        pz[1 - (x & 1), x] = ninf
        pz[2, x] = np.float32(0.0)
    ng = (h + _CLIP_ROWS - 1) // _CLIP_ROWS
    groups = np.empty(ng, np.int64)
    k = 0
    for g in range(ng):
        # (a scalar loop: an array expression here, as `.sum()` of a slice, is a parallel region of its own
        # per group, each a wake-up of the threads)
        n = 0
        for y in range(g * _CLIP_ROWS, min(g * _CLIP_ROWS + _CLIP_ROWS, h)):
            n += n_clipped[y]
        if n > 0:
            groups[k] = g
            k += 1
    ntile = (w + _CLIP_TILE - 1) // _CLIP_TILE
    per = (k + nt - 1) // nt
    for i in prange(per * nt):
        gi = interleaved(i, per, nt)          # highlights at one end of the frame shared by the threads
        if gi >= k:
            continue
        y0 = groups[gi] * _CLIP_ROWS
        y1 = min(y0 + _CLIP_ROWS, h)
        r0 = max(y0 - 4, 0)
        r1 = min(y1 + 4, h)
        cvb = np.empty((r1 - r0, w), np.float32)
        veb = np.empty((r1 - r0, w + 2 * _CLIP_PAD), np.float32)
        for r in range(r0, r1):
            sr, vr, fr = state[r], values[r], tgt[_TGT_F, r]
            cr_, vb = cvb[r - r0], veb[r - r0, _CLIP_PAD:_CLIP_PAD + w]
            for x in range(w):
                reason = sr[x] & REASON_MASK
                cr_[x] = vr[x] if reason == CLIPPED else ninf
                vb[x] = fr[x] if reason == VALID else ninf
            for x in range(_CLIP_PAD):
                veb[r - r0, x] = ninf
                veb[r - r0, _CLIP_PAD + w + x] = ninf
        mr = np.empty(w, np.float32)
        ar = np.empty(w, np.float32)
        cn = np.empty(w, np.float32)
        cx = np.empty(w, np.int64)
        vf = np.empty(w, np.float64)
        for y in range(y0, y1):
            if n_clipped[y] == 0:
                continue
            crow = cvb[y - r0]
            t = 0
            while t < ntile:
                a = t * _CLIP_TILE
                b = a
                while t < ntile:                   # the run of tiles with CLIPPED pixels from tile t
                    hit = False
                    for x in range(t * _CLIP_TILE, min(t * _CLIP_TILE + _CLIP_TILE, w)):
                        if crow[x] != ninf:
                            hit = True
                            break
                    if not hit:
                        break
                    t += 1
                    b = min(t * _CLIP_TILE, w)
                if b == a:
                    t += 1
                    continue
                _clip_span(y, a, b, r0, cvb, veb, pz, block, mr, ar, cn)
                # the estimate of every pixel of the span (the mean where there are VALID fluxes above the
                # maximum, else the maximum), then the span's CLIPPED pixels listed and their source basis
                # values: loops without branches
                for u in range(b - a):
                    n = np.int64(cn[u])
                    d = ar[u] / max(n, np.int64(1))
                    vf[u] = d if n > 0 else np.float64(mr[u])
                sr, b0r, b1r = state[y], src[_SRC_B0, y], src[_SRC_B1, y]
                nc = 0
                for x in range(a, b):
                    cx[nc] = x
                    nc += np.int64((sr[x] & REASON_MASK) == CLIPPED)
                for j in range(nc):
                    x = cx[j]
                    st = sr[x]
                    q = vf[x - a] * inv_de * (inv_att if (st & ATTENUATED) != 0 else np.float32(1.0))
                    b0r[x] = _basis_at(basis, 0, q)
                    b1r[x] = _basis_at(basis, 1, q)


@njit(cache=True, nogil=True, inline="always")
def _spill_term(w0, w1, b0, b1, stn, dark, f, fr0, fr1, da0, da1):
    """sigma_d of a neighbour (state stn, `src` entries b0, b1, dark) minus sigma_d of a flat neighbour at
    flux f (basis values fr. of a regular one, + da. for an attenuated one), w0, w1 direction d's weights
    (`SpillBasis`); 0 for a DARK neighbour brighter than f (its value is an upper bound only). Arithmetic,
    no branch."""
    att = np.float32((stn & ATTENUATED) != 0)
    t = w0 * (b0 - fr0 - att * da0) + w1 * (b1 - fr1 - att * da1)
    return t * np.float32(dark <= f)


@njit(cache=True, nogil=True, inline="always")
def _neighbour_spill(w0, w1, state, src, yy, xx, h, w, f, fr0, fr1, da0, da1):
    """`_spill_term` of the neighbour at (yy, xx); 0 outside the frame."""
    inb = (yy >= 0) & (yy < h) & (xx >= 0) & (xx < w)
    y2 = min(max(yy, 0), h - 1)
    x2 = min(max(xx, 0), w - 1)
    t = _spill_term(w0, w1, src[_SRC_B0, y2, x2], src[_SRC_B1, y2, x2], state[y2, x2],
                    src[_SRC_DARK, y2, x2], f, fr0, fr1, da0, da1)
    return t * np.float32(inb)


@njit(cache=True, nogil=True, inline="always")
def _flat_spill(f, o0, o1, own0, own1, st):
    """(fr0, fr1, da0, da1) of a pixel in state st (`_spill_term`) from its own basis values (`src`) and
    the other group's (`tgt`) at its flux f: a regular source's values and what an attenuated one adds."""
    attf = np.float32((st & ATTENUATED) != 0)
    fr0 = _pick(attf, o0, own0)
    fr1 = _pick(attf, o1, own1)
    return fr0, fr1, _pick(attf, own0, o0) - fr0, _pick(attf, own1, o1) - fr1


@njit(cache=True, nogil=True, inline="always")
def _colour_value(v, st, t, kd, p, q, sd, sv, sh, ndf, invnd, inv_step, g, f0):
    """A pixel's corrected value (`_colour_compact_correct`) and the code to evaluate again (NaN: none):
    v its value, st its state, t = (est, c0, d0, du, room) its `tgt` entries; p, q: its amplitudes
    (`colour_pairs`); sd, sv, sh: the summed spill differences of its diagonal, up/down and left/right
    neighbours; kd 1 where its diagonal neighbours have another colour (red, blue photosites), 0 where they
    are green like it. VALID: its compact LUT at its code m less the other-colour spill delta (est where
    m - delta lies above its range), at least 0, on m's grid segment (`_compact_at`); m - delta is
    returned where it lies on another segment; others v."""
    f, c0, d0, du, room = t
    one = np.float32(1.0)
    zero = np.float32(0.0)
    attf = np.float32((st & ATTENUATED) != 0)
    delta = kd * q * sd + _pick(kd, p, q) * sv + p * sh
    m = v * _pick(attf, invnd, one)
    m2 = m - delta
    f2 = _compact_at(m2, c0, d0, du, _pick(attf, ndf, one), inv_step, f0)
    valid = (st & REASON_MASK) == VALID
    inside = delta >= -room
    nv = max(f2 if inside else f, zero)
    # the grid segments of m and m - delta (as `_compact_line`); below c0 the LUT is one line
    j = min(np.int32(np.sqrt(max(min(max(m, c0), m + room), zero) * inv_step)), np.int32(g - 1))
    j2 = min(np.int32(np.sqrt(max(m2, c0, zero) * inv_step)), np.int32(g - 1))
    again = valid & inside & (m2 > c0) & (j2 != j)
    return (nv if valid else v), (m2 if again else np.float32(np.nan))


@njit(cache=True, nogil=True, inline="always")
def _compact_again(rec, y, x, m, st, ndf, invnd, dsc0, dsc1, inv_step, g, clip_rel, qs, qo, f0):
    """The compact LUT's flux at code m (in its range) on pixel (y, x) in state st, at least 0."""
    one = np.float32(1.0)
    attf = np.float32((st & ATTENUATED) != 0)
    c0, top, a, b = _compact_fetch(rec, y, x, m, inv_step, g, clip_rel, qs, qo)
    d0, du = _compact_line(m, c0, top, a, b, _pick(attf, dsc1, dsc0), inv_step, g)
    return max(_compact_at(m, c0, d0, du, _pick(attf, ndf, one), inv_step, f0), np.float32(0.0))


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _colour_compact_correct(values, state, c, clip_flux, src, tgt, wt, pairs, block, n_clipped):
    """`lut` mode in place on a Bayer mosaic (`block`: its 2 x 2 channels) with the per-colour amplitudes
    `pairs` (`colour_pairs`), after `_colour_compact_planes` and `_colour_compact_clipped` (the planes
    `src`, `tgt`): a VALID pixel's code, less the spill of its other-colour neighbours beyond what
    neighbours at its flux would send, times its amplitude for that colour, through its compact LUT `c`
    (its segment at the code, `_colour_value`; one iteration of `_correct_kernel` with every=False; wt: the
    `SpillBasis` weights); a
    DARK neighbour brighter than the pixel is left out; CLIPPED values at most the clipping flux (rows with
    CLIPPED pixels: n_clipped). The interior is one branch-free loop per row over contiguous rows (y - 1,
    y, y + 1 of each plane: no gathers, so it vectorises); the border rows and columns clamp their
    neighbours."""
    h, w = values.shape
    rec, dscale, clip_rel, qs, qo, f0, nd = c.rec, c.dscale, c.clip_rel, c.qs, c.qo, c.f0, c.nd
    g = rec.shape[2] - 3
    inv_step = np.float32(g * g) / clip_rel
    ndf = np.float32(nd)
    invnd = np.float32(1.0) / ndf
    dsc0 = dscale[0]
    dsc1 = dscale[1]
    # directions in DIRS order: (-1,-1) (-1,0) (-1,1) (0,-1) (0,1) (1,-1) (1,0) (1,1)
    w00, w01, w10, w11, w20, w21, w30, w31 = wt[0, 0], wt[0, 1], wt[1, 0], wt[1, 1], wt[2, 0], wt[2, 1], \
        wt[3, 0], wt[3, 1]
    w40, w41, w50, w51, w60, w61, w70, w71 = wt[4, 0], wt[4, 1], wt[5, 0], wt[5, 1], wt[6, 0], wt[6, 1], \
        wt[7, 0], wt[7, 1]
    for y in prange(h):
        yi = np.int64(y)                     # (a parfor index is unsigned: y - 1 would be float)
        py = yi & 1
        qy = (yi + 1) & 1
        # 1 where the pixel's diagonal neighbours have another colour, by its column parity (even e, odd o)
        kd_e = np.float32(block[qy, 1] != block[py, 0])
        kd_o = np.float32(block[qy, 0] != block[py, 1])
        border = (yi == 0) | (yi == h - 1) | (w < 3)
        for k in range(w if border else 2):
            xi = np.int64(k) if border else np.int64(k) * (w - 1)      # a border row, or columns 0 and w - 1
            f = tgt[_TGT_F, yi, xi]
            st = state[yi, xi]
            fr0, fr1, da0, da1 = _flat_spill(f, tgt[_TGT_O0, yi, xi], tgt[_TGT_O1, yi, xi], src[_SRC_B0, yi, xi],
                                             src[_SRC_B1, yi, xi], st)
            sd = _neighbour_spill(w00, w01, state, src, yi - 1, xi - 1, h, w, f, fr0, fr1, da0, da1)
            sd += _neighbour_spill(w20, w21, state, src, yi - 1, xi + 1, h, w, f, fr0, fr1, da0, da1)
            sd += _neighbour_spill(w50, w51, state, src, yi + 1, xi - 1, h, w, f, fr0, fr1, da0, da1)
            sd += _neighbour_spill(w70, w71, state, src, yi + 1, xi + 1, h, w, f, fr0, fr1, da0, da1)
            sv = _neighbour_spill(w10, w11, state, src, yi - 1, xi, h, w, f, fr0, fr1, da0, da1)
            sv += _neighbour_spill(w60, w61, state, src, yi + 1, xi, h, w, f, fr0, fr1, da0, da1)
            sh = _neighbour_spill(w30, w31, state, src, yi, xi - 1, h, w, f, fr0, fr1, da0, da1)
            sh += _neighbour_spill(w40, w41, state, src, yi, xi + 1, h, w, f, fr0, fr1, da0, da1)
            t = (f, tgt[_TGT_C0, yi, xi], tgt[_TGT_D0, yi, xi], tgt[_TGT_DU, yi, xi], tgt[_TGT_ROOM, yi, xi])
            values[yi, xi], tgt[_TGT_O0, yi, xi] = _colour_value(
                values[yi, xi], st, t, _pick(np.float32(xi & 1), kd_o, kd_e), pairs[0, yi, xi], pairs[1, yi, xi], sd,
                sv, sh, ndf, invnd, inv_step, g, f0)
        if not border:
            # interior: the target is x + 1, its neighbours x, x + 1, x + 2 of the rows above (u), at (c)
            # and below (d) of each plane: non-negative indices only
            b0u, b0c, b0d = src[_SRC_B0, yi - 1], src[_SRC_B0, yi], src[_SRC_B0, yi + 1]
            b1u, b1c, b1d = src[_SRC_B1, yi - 1], src[_SRC_B1, yi], src[_SRC_B1, yi + 1]
            su, sc, sdn = state[yi - 1], state[yi], state[yi + 1]
            dku, dkc, dkd = src[_SRC_DARK, yi - 1], src[_SRC_DARK, yi], src[_SRC_DARK, yi + 1]
            fr, c0r, d0r, dur, rmr = tgt[_TGT_F, yi], tgt[_TGT_C0, yi], tgt[_TGT_D0, yi], tgt[_TGT_DU, yi], \
                tgt[_TGT_ROOM, yi]
            o0r, o1r = tgt[_TGT_O0, yi], tgt[_TGT_O1, yi]
            vr, pr, qr = values[yi], pairs[0, yi], pairs[1, yi]
            for x in range(w - 2):
                xc = x + 1
                f = fr[xc]
                st = sc[xc]
                fr0, fr1, da0, da1 = _flat_spill(f, o0r[xc], o1r[xc], b0c[xc], b1c[xc], st)
                sd = _spill_term(w00, w01, b0u[x], b1u[x], su[x], dku[x], f, fr0, fr1, da0, da1)
                sd += _spill_term(w20, w21, b0u[x + 2], b1u[x + 2], su[x + 2], dku[x + 2], f, fr0, fr1, da0, da1)
                sd += _spill_term(w50, w51, b0d[x], b1d[x], sdn[x], dkd[x], f, fr0, fr1, da0, da1)
                sd += _spill_term(w70, w71, b0d[x + 2], b1d[x + 2], sdn[x + 2], dkd[x + 2], f, fr0, fr1, da0, da1)
                sv = _spill_term(w10, w11, b0u[xc], b1u[xc], su[xc], dku[xc], f, fr0, fr1, da0, da1)
                sv += _spill_term(w60, w61, b0d[xc], b1d[xc], sdn[xc], dkd[xc], f, fr0, fr1, da0, da1)
                sh = _spill_term(w30, w31, b0c[x], b1c[x], sc[x], dkc[x], f, fr0, fr1, da0, da1)
                sh += _spill_term(w40, w41, b0c[x + 2], b1c[x + 2], sc[x + 2], dkc[x + 2], f, fr0, fr1, da0, da1)
                # the new value into the c0 row (read above), copied to the values row after the loop (a
                # masked store otherwise, as in `_colour_compact_planes`)
                c0r[xc], o0r[xc] = _colour_value(vr[xc], st, (f, c0r[xc], d0r[xc], dur[xc], rmr[xc]),
                                                 _pick(np.float32(xc & 1), kd_o, kd_e), pr[xc], qr[xc], sd, sv, sh,
                                                 ndf, invnd, inv_step, g, f0)
            vr[1:w - 1] = c0r[1:w - 1]
        # the pixels whose corrected code lies on another grid segment: the compact LUT read there (tgt's o0
        # row holds that code)
        for x in range(w):
            m2 = tgt[_TGT_O0, yi, x]
            if m2 == m2:
                values[yi, x] = _compact_again(rec, yi, x, m2, state[yi, x], ndf, invnd, dsc0, dsc1, inv_step, g,
                                               clip_rel, qs, qo, f0)
        if n_clipped[yi] > 0:
            for x in range(w):
                cf = clip_flux[yi, x]
                if (state[yi, x] & REASON_MASK) == CLIPPED and cf < values[yi, x]:    # NaN: no change
                    values[yi, x] = cf

_compact_lock = threading.Lock()


def compact_for(profile) -> CompactLut:
    """The compact LUT of a profile's calibration, derived once and kept on the calibration object (the
    elements call this when they start, so the first frame does not pay for it); for a colour profile
    whose calibration has per-colour amplitudes also its `spill_basis` and `colour_pairs`."""
    calib = profile.crosstalk
    if calib is None:
        raise ValueError("the profile has no crosstalk calibration")
    mask, nd = profile.mask, float(profile.nd)
    hit = calib.__dict__.get("_compact")            # (mask object, nd, CompactLut): an O(1) check per frame
    if hit is not None and hit[0] is mask and hit[1] == nd:
        return hit[2]
    with _compact_lock:
        hit = calib.__dict__.get("_compact")
        if hit is None or hit[0] is not mask or hit[1] != nd:
            hit = (mask, nd, compact_lut(calib, mask, nd))
            cfa = getattr(profile, "cfa", "none")
            if calib.colour is not None and cfa != "none":
                spill_basis(calib)
                colour_pairs(calib, cfa)
            calib.__dict__["_compact"] = hit
    return hit[2]


def correct(values: np.ndarray, state: np.ndarray, profile, mode: str = "lut", iterations: int = 2,
            passes: int = 2, clip_share: float | None = CLIP_SHARE, lut: str = "full"):
    """Correct crosstalk in place (paper 3.2). `values` float32 linear DN (attenuated pixels scaled by ND),
    `state` uint8 (docs/ARCHITECTURE.md); `profile`: a camera profile (or anything with its `crosstalk`,
    `nd` and `mask`). Identity without a calibration or with mode 'off'. VALID pixels
    whose code lies outside their calibrated range become UNCALIBRATED (value left as measured).
    `lut` (mode 'lut' only): 'full' = the calibration's per-pixel table (accurate), 'compact' = its
    compact form (`compact_for`, fast; error: docs/CROSSTALK.md "Compact LUT"). A colour profile whose
    calibration has per-colour amplitudes (`CrosstalkCalibration.colour`) takes `_correct_kernel` with them
    in both modes with the full table (two passes, `iterations` each), and with lut 'compact' in mode 'lut'
    the one-pass `_colour_compact_correct` (docs/CROSSTALK.md section 4b). Returns (values, state)."""
    if mode not in MODES:
        raise ValueError(f"crosstalk mode must be one of {MODES}, got {mode!r}")
    if lut not in LUT_FORMS:
        raise ValueError(f"crosstalk lut form must be one of {LUT_FORMS}, got {lut!r}")
    calib = getattr(profile, "crosstalk", None)
    if mode == "off" or calib is None:
        return values, state
    if values.dtype != np.float32 or state.dtype != np.uint8 or values.shape != state.shape \
            or values.ndim != 2:
        raise ValueError(f"values must be float32 and state uint8 of the same 2-D shape, got "
                         f"{values.dtype} {values.shape} and {state.dtype} {state.shape}")
    if values.shape != tuple(calib.shape):
        raise ValueError(f"frame is {values.shape[1]}x{values.shape[0]} but the crosstalk calibration is "
                         f"{calib.shape[1]}x{calib.shape[0]}")
    nd = float(profile.nd)
    table = lut_record(calib)
    cfa = getattr(profile, "cfa", "none")
    coloured = calib.colour is not None and cfa != "none"
    if mode == "lut" and not coloured:
        # per pixel, in place (no copy of the frame)
        if lut == "compact":
            c = compact_for(profile)
            _lut_kernel_compact(values, state, c.record(), calib.clip_flux)
        else:
            _lut_kernel(values, state, table, nd)
        return values, state
    if coloured and mode == "lut" and lut == "compact":
        from . import cfa as cfas
        from . import scratch
        c = compact_for(profile)
        h, w = values.shape
        src, tgt, n_clipped = scratch.planes(
            "crosstalk_colour", values.shape,
            lambda: (np.empty((SRC_PLANES, h, w), np.float32), np.empty((TGT_PLANES, h, w), np.float32),
                     np.empty(h, np.int64)))
        sb = spill_basis(calib)
        _colour_compact_planes(values, state, c.record(), sb.basis, sb.inv_de, src, tgt, n_clipped)
        blk = cfas.block(cfa)
        _colour_compact_clipped(values, state, src, tgt, sb.basis, sb.inv_de, nd, blk, n_clipped, get_num_threads())
        _colour_compact_correct(values, state, c.record(), calib.clip_flux, src, tgt, sb.weight,
                                colour_pairs(calib, cfa), blk, n_clipped)
        return values, state
    if coloured:
        from . import cfa as cfas
        colour, chan = calib.colour, cfas.channel_index(cfa, *values.shape)
    else:
        colour, chan = _NO_COLOUR, _NO_CHANNELS
    src = values.copy()
    # kernel mode (and lut on a colour profile): neighbour fluxes first from the LUT, then (second pass) from
    # the first pass's result
    state0 = state.copy()
    lut = np.empty_like(values)
    ok = np.empty(values.shape, np.bool_)
    est = np.empty_like(values)
    spill = np.empty((8,) + values.shape, np.float32)
    _lut_pass(src, state0, table, nd, lut, ok)
    spill_model = Spill(DIRS, calib.sig_e, calib.sigma, calib.alpha)
    par = KernelParams(nd, int(iterations), np.float32(clip_share if clip_share is not None else np.inf))
    for p in range(max(1, int(passes))):
        _neighbour_estimate(src, state0, lut, ok, DIRS, est, chan, 2 if coloured else 1)
        _source_spill(est, state0, nd, calib.sig_e, calib.sigma, spill)
        if p > 0:
            state[:] = state0
        values[:] = src
        _correct_kernel(values, state, src, est, spill, table, spill_model, par, colour, chan, mode == "kernel",
                        coloured)
        lut[:] = values
        ok[:] = (state & REASON_MASK) == VALID
    return values, state


def identity_calibration(mask: np.ndarray, nd: float = 6.35, black_level: float = 0.0,
                         clip_code: int = 4094, colour: bool = False) -> CrosstalkCalibration:
    """A calibration that maps every code to code * s (zero crosstalk); for `chain.warmup` and tests.
    `colour`: with per-colour amplitudes (all 1), as a colour camera's calibration has them, so that a
    colour profile takes (and warms) the colour kernels of `correct`."""
    mask = np.asarray(mask, bool)
    h, w = mask.shape
    top = float(clip_code) - black_level
    codes = np.zeros((h, w, 3), np.float32)
    codes[:, :, 1] = np.where(mask, top / nd, top)
    codes[:, :, 2] = np.where(mask, top, top + 1.0)
    q, qs, qo = quantize_codes(codes, int(clip_code) + 1)
    return CrosstalkCalibration(
        codes_q=q, qscale=qs, qoffset=qo, n_knots=np.where(mask, 3, 2).astype(np.int32),
        knot_flux=np.array([0.0, top, top * nd], np.float64),
        clip_flux=np.full((h, w), np.nan, np.float32), nd=nd, black_level=black_level,
        clip_code=clip_code, sig_e=np.array([0.0, 1.0], np.float32), sigma=np.zeros((8, 2), np.float32),
        alpha=np.ones((h, w), np.float32), info={"identity": True},
        colour=np.ones((3, h, w), np.float32) if colour else None)
